"""`BatchSource`: training batches, drawn one step ahead on a background thread where that is safe.

Drawing a batch (sampling rays, casting them against the exact BLAS for ground truth) is ~17% of
an `hq` step on the CPU (docs/lsnif.md, "Training throughput"). Embree and our numba kernels
release the GIL, so batch k+1 can be drawn while the network runs step k. Only ray distributions
that declare ``model_independent = True`` are drawn ahead: their batches depend on their own
generator and state, never on the model (N-BVH's do: they follow the BVH cut the model refines).
The distribution is called in exactly the same order as without the thread, so a seed gives the
same batches; callers pass ``ahead=False`` before a checkpoint, so the saved distribution state
is never one batch ahead of the saved step. A ``prepare`` function (the model's
``prepare_training_batch``: for LSNIF the voxel walk and the network rays, which depend on the
batch alone) runs on the same thread right after the batch is drawn.

The drawing thread runs at idle priority (Linux ``SCHED_IDLE``) where the OS has it: on a machine
with few cores, a drawing thread of normal priority took cores from the step's parallel regions
(torch's GEMMs, the numba encoder), whose threads then waited for each other a scheduler slice at a
time; at idle priority it runs only in the step's serial gaps (bunny `hq`, 2 cores: 17-20 ms ->
~16 ms a step, docs/lsnif.md). An idle thread starves when other processes keep every core busy: if
the step then waits for its batches (more than `STARVED_SHARE` of the time in `STARVED_WINDOWS`
windows of steps in a row), the later batches are drawn by a fresh thread of normal priority. One
window is not enough: an idle 2-core machine waits up to ~8% of a window, and a single 10.1% window
once sent a whole run to normal priority (456k vs ~500k rays/s, docs/lsnif.md); a starved thread
waits ~90%.

Whether drawing ahead pays depends on the machine: where the step's parallel regions leave cores
idle it hides the drawing (a 16-core host, session 34: 1.39x the rays/s of drawing in turn), where
they do not, the drawing thread slows them more than it saves (the 2-core Zen 5, session 40: 0.89x;
the step's forward took 6.4 instead of 3.2 ms beside it). So by default (``overlap=None``) the
loop measures both on its own steps (`_OverlapTrial`): after `TRIAL_START` steps, windows of
`TRIAL_WINDOW` steps drawn in turn and drawn ahead alternate, `TRIAL_ROUNDS` of each, and the
faster is kept. A machine's load changes during a run, and a trial can fall on a slow phase: every
`RECHECK_EVERY` steps after it, one more window of the other mode and one of the kept mode run,
and the mode is chosen again from the last `TRIAL_ROUNDS` windows of each (the other mode where
it is `RECHECK_MARGIN` faster). The batches are the same either way, so the choice changes the
speed alone. Drawing in turn ends the drawing thread: the OpenMP team its first parallel region
started would stay, and with more OpenMP threads than cores libgomp spins ~100 iterations instead
of `GOMP_SPINCOUNT` before sleeping, so every parallel region of the step would wake sleeping
threads (steps 1.15x slower on 2 cores; docs/lsnif.md, session 40).
"""

from __future__ import annotations

import os
import statistics
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

from ..fork_guard import numba_regions_thread_safe

__all__ = ["BatchSource"]

IDLE_PRIORITY = hasattr(os, "SCHED_IDLE")  # Linux; elsewhere the thread keeps its normal priority
STARVED_SHARE = 0.1  # waiting for batches over this share of the loop's time ...
STARVED_WINDOWS = 3  # ... in this many windows in a row: give up idle priority
_WINDOW = 20  # steps per check of that share
TRIAL_START = 10  # steps drawn ahead before the trial (compilation, thread pools, caches)
# Short windows, many rounds: a machine's slow phases last tens of steps, and with windows of 10
# steps, 3 of each mode, one could fall on one mode's windows alone: on the 2-core Zen 4 (drawing
# ahead 0.87x the rays/s there) that trial chose drawing ahead in 7 of 16 bunny `hq` runs, windows
# of 4 steps, 8 of each, in 1 of 16 (docs/lsnif.md, session 42).
TRIAL_WINDOW = 4  # steps per trial window; its first step, a change of mode, is not timed
TRIAL_ROUNDS = 8  # windows of each mode
# After the trial, a window of each mode every this many steps (the other mode first): a wrong
# choice costs 10-13% of the rest of a run (drawing ahead 0.87-0.90x on the Zen 4), rechecks ~0.5%.
RECHECK_EVERY = 100
# A recheck changes the mode only where the other one's median step is this much shorter: with none,
# noise made rechecks pick drawing ahead for 100-900 steps at a time in 5 of 16 traced bunny runs; replayed on
# 2,000 steps of alternating windows, 2% left no wrong pick and undid a wrong trial within 1-5
# rechecks (docs/lsnif.md, session 43).
RECHECK_MARGIN = 0.02


class _OverlapTrial:
    """Which steps draw ahead, and the faster mode: each timed step's wall time (from one call of
    `BatchSource.next` to the next) kept per mode, the last `TRIAL_ROUNDS` windows' worth; the
    trial's windows drawn in turn first, then every `RECHECK_EVERY` steps a window of the other
    mode and one of the chosen mode; after each, the mode of the lower median is chosen (a median:
    a step the machine interrupts does not decide; after a recheck with `RECHECK_MARGIN`)."""

    def __init__(self):
        self.steps = 0  # calls of `mode` so far
        kept = TRIAL_ROUNDS * (TRIAL_WINDOW - 1)  # (a window's first step is not timed)
        self.seconds: dict[bool, deque[float]] = {False: deque(maxlen=kept), True: deque(maxlen=kept)}
        self.last: tuple[float, bool] | None = None  # the previous step's start and mode, where it is timed
        self.choice: bool | None = None  # drawing ahead was faster; None while the first trial runs

    def mode(self, now: float) -> bool:
        """Whether the step that starts at ``now`` (`time.perf_counter`) draws the next batch ahead."""
        if self.last is not None:
            self.seconds[self.last[1]].append(now - self.last[0])
        self.last = None
        k, self.steps = self.steps - TRIAL_START, self.steps + 1
        trial = 2 * TRIAL_ROUNDS * TRIAL_WINDOW
        if k < 0:
            return True
        if k < trial:
            position = k  # in the trial's windows
            ahead = k // TRIAL_WINDOW % 2 == 1
        else:
            since = (k - trial) % RECHECK_EVERY
            if since == 0:  # the trial or a recheck just ended
                self.choice = self._faster()
            position = since - (RECHECK_EVERY - 2 * TRIAL_WINDOW)  # in the recheck's two windows, which end the period
            if position < 0:
                return self.choice
            ahead = self.choice != (position < TRIAL_WINDOW)  # the other mode first, then the chosen one
        if position % TRIAL_WINDOW > 0:  # (a window's first step changes mode: not timed)
            self.last = (now, ahead)
        return ahead

    def _faster(self) -> bool:
        """Whether drawing ahead is the faster mode: the lower median after the trial; after a
        recheck the other mode only where it is `RECHECK_MARGIN` faster."""
        ahead, in_turn = statistics.median(self.seconds[True]), statistics.median(self.seconds[False])
        if self.choice is None:
            return ahead < in_turn
        kept, other = (ahead, in_turn) if self.choice else (in_turn, ahead)
        return self.choice != (other < kept * (1 - RECHECK_MARGIN))


class BatchSource:
    """``next(ahead)`` returns the next batch of ``batch_size`` rays from ``sampler`` and what
    ``prepare`` made of its rays (None without ``prepare``) as ``(batch, prepared)``; with
    ``ahead=True`` it may also start drawing the one after it on a background thread: always with
    ``overlap=True``, never with False, and with None (the default) as the trial of drawing in
    turn against drawing ahead decides (module docstring; `draws_ahead` tells its choice); never
    where numba's parallel regions may not run on two threads at once (its workqueue layer)."""

    def __init__(self, sampler, batch_size: int, *, overlap: bool | None = None, prepare: Callable | None = None,
                 idle_priority: bool | None = None):
        self.sampler, self.batch_size, self.prepare = sampler, batch_size, prepare
        self.overlap = (overlap is not False and bool(getattr(sampler, "model_independent", False))
                        and numba_regions_thread_safe())  # (numba's workqueue layer aborted the process)
        self._trial = _OverlapTrial() if self.overlap and overlap is None else None
        self.idle_priority = IDLE_PRIORITY if idle_priority is None else idle_priority and IDLE_PRIORITY
        self._executor: ThreadPoolExecutor | None = None
        self._pending: Future | None = None
        self._since = time.perf_counter()  # start of the current window of steps
        self._waited, self._steps = 0.0, 0
        self._starved_windows = 0  # windows in a row over STARVED_SHARE

    @property
    def draws_ahead(self) -> bool | None:
        """Whether batches are drawn ahead (None while the trial has not decided)."""
        if self._trial is not None:
            return self._trial.choice
        return self.overlap

    def next(self, ahead: bool):
        in_turn = self._trial is not None and not self._trial.mode(time.perf_counter())
        if self._pending is not None:
            start = time.perf_counter()
            drawn, self._pending = self._pending.result(), None  # re-raises the thread's exception here
            self._count_wait(time.perf_counter() - start)
        else:
            drawn = self._draw()
        if in_turn:
            self._stop_thread()
        elif ahead and self.overlap:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix="neuralrt-batches",
                                                    initializer=_lower_priority if self.idle_priority else None)
            self._pending = self._executor.submit(self._draw)
        return drawn

    def _count_wait(self, waited: float) -> None:
        """Over each window of steps, the share of time spent waiting for batches; an idle thread
        starved for STARVED_WINDOWS windows in a row is replaced by one of normal priority (the
        threads the loop makes inherit its own)."""
        self._waited, self._steps = self._waited + waited, self._steps + 1
        if self._steps < _WINDOW:
            return
        now = time.perf_counter()
        starved = self._waited > STARVED_SHARE * (now - self._since)
        self._starved_windows = self._starved_windows + 1 if starved else 0
        if self.idle_priority and self._starved_windows >= STARVED_WINDOWS:
            self.idle_priority = False
            self._executor.shutdown(wait=False)  # idle: nothing is pending
            self._executor = None
        self._since, self._waited, self._steps = now, 0.0, 0

    def _draw(self) -> tuple:
        batch = self.sampler.sample(self.batch_size)
        return batch, (None if self.prepare is None else self.prepare(batch.rays))

    def close(self) -> None:
        """Waits for a batch still being drawn (so the sampler is left quiet) and stops the thread."""
        if self._pending is not None:
            self._pending.exception()  # wait; an error of a batch nobody will use is dropped
            self._pending = None
        self._stop_thread()

    def _stop_thread(self) -> None:
        """Ends the drawing thread (nothing is pending), and with it the OpenMP threads its parallel
        regions started (module docstring)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None


def _lower_priority() -> None:
    """The calling thread to idle priority (Linux: ``sched_setscheduler`` of pid 0 is this thread)."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except OSError:  # not permitted here (a container's seccomp policy): keep normal priority
        pass

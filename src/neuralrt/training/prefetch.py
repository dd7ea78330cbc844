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
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

__all__ = ["BatchSource"]

IDLE_PRIORITY = hasattr(os, "SCHED_IDLE")  # Linux; elsewhere the thread keeps its normal priority
STARVED_SHARE = 0.1  # waiting for batches over this share of the loop's time ...
STARVED_WINDOWS = 3  # ... in this many windows in a row: give up idle priority
_WINDOW = 20  # steps per check of that share


class BatchSource:
    """``next(ahead)`` returns the next batch of ``batch_size`` rays from ``sampler`` and what
    ``prepare`` made of its rays (None without ``prepare``) as ``(batch, prepared)``; with
    ``ahead=True`` it also starts drawing the one after it on a background thread."""

    def __init__(self, sampler, batch_size: int, *, overlap: bool = True, prepare: Callable | None = None,
                 idle_priority: bool | None = None):
        self.sampler, self.batch_size, self.prepare = sampler, batch_size, prepare
        self.overlap = overlap and bool(getattr(sampler, "model_independent", False))
        self.idle_priority = IDLE_PRIORITY if idle_priority is None else idle_priority and IDLE_PRIORITY
        self._executor: ThreadPoolExecutor | None = None
        self._pending: Future | None = None
        self._since = time.perf_counter()  # start of the current window of steps
        self._waited, self._steps = 0.0, 0
        self._starved_windows = 0  # windows in a row over STARVED_SHARE

    def next(self, ahead: bool):
        if self._pending is not None:
            start = time.perf_counter()
            drawn, self._pending = self._pending.result(), None  # re-raises the thread's exception here
            self._count_wait(time.perf_counter() - start)
        else:
            drawn = self._draw()
        if ahead and self.overlap:
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
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None


def _lower_priority() -> None:
    """The calling thread to idle priority (Linux: ``sched_setscheduler`` of pid 0 is this thread)."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except OSError:  # not permitted here (a container's seccomp policy): keep normal priority
        pass

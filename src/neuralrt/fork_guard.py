"""Refusing queries in a process forked after this one's OpenMP threads had run neuralrt's work.

torch and numba's parallel regions share GNU OpenMP (see ``neuralrt/__init__.py``), which cannot
run in a child forked after its threads started: the child hangs in its first parallel region,
or numba's OpenMP layer kills it ("fork() called from a process already using GNU OpenMP").
multiprocessing forks by default on Linux, so a Pool over ray batches hung with no word why. At
a fork, a parent whose numba parallel regions have run on the OpenMP layer (a model loaded, a
query) marks the child; there the entry points that would run them (a BLAS's `check_rays`,
`load_model`, `MeshBLAS`, `train`, `render`) raise one line instead, and the child's torch runs
on one thread (no pool to wake), so its own torch work still runs. numba's other threading layers
survive a fork: with them nothing is refused. A parent that ran only torch's parallel work (GNU
OpenMP's worker threads exist: `_torch_pool_may_exist`) marks the child too, unless numba is set
to a layer that survives a fork (``NUMBA_THREADING_LAYER=workqueue`` or ``tbb``): the child's
first numba region hung inside GNU OpenMP, and its torch ops did too before they were put on one
thread.
"""

from __future__ import annotations

import os
import sys
import threading

from .errors import DeviceError

__all__ = ["check_not_forked", "numba_regions_thread_safe"]

_unsafe_to_fork = False  # decided in the parent just before a fork: the child must refuse
_openmp_threads_ran = False  # ... the child's torch must run on one thread
_forked_after_openmp = False  # this process is such a fork's child


def check_not_forked(where: str) -> None:
    """A one-line `DeviceError` in a child forked after OpenMP work."""
    if _forked_after_openmp:
        raise DeviceError(
            f"{where}: this process was forked (multiprocessing's default start method on Linux) from one whose OpenMP "
            "threads had already run (neuralrt's or torch's work), and OpenMP cannot run in such a child (it would hang): start "
            "workers with multiprocessing.get_context('spawn') or 'forkserver'")


_FORK_SAFE_LAYERS = ("workqueue", "tbb")  # numba threading layers with no GNU OpenMP state to inherit


def _before_fork() -> None:
    global _unsafe_to_fork, _openmp_threads_ran
    layer = _numba_layer_chosen()
    torch_pool = _torch_pool_may_exist()
    _openmp_threads_ran = layer == "omp" or torch_pool
    _unsafe_to_fork = layer == "omp" or (torch_pool and layer is None and _configured_numba_layer() not in _FORK_SAFE_LAYERS)


def _numba_layer_chosen() -> str | None:
    """The threading layer numba's parallel regions run on, or None before the first one."""
    numba = sys.modules.get("numba")
    if numba is None:
        return None
    try:
        return numba.threading_layer()
    except ValueError:  # no parallel region has run: no layer chosen yet
        return None


def _torch_pool_may_exist() -> bool:
    """Whether GNU OpenMP's worker threads exist (torch started them in a parallel region; torch
    does not say). A worker waits inside libgomp: its system call's instruction pointer lies in
    libgomp's code (/proc/self/task/*/syscall against /proc/self/maps); one that still spins after
    its region shows as running, as any busy thread does (counted: a refusal beats a hang).
    Importing torch starts a thread too, waiting elsewhere: not counted. Where /proc cannot tell,
    no (as before this check)."""
    if "torch" not in sys.modules:
        return False
    try:
        code = _libgomp_code_ranges()
        if not code:
            return False
        me = str(threading.get_native_id())
        for tid in os.listdir("/proc/self/task"):
            if tid == me:
                continue
            with open(f"/proc/self/task/{tid}/syscall") as f:
                words = f.read().split()
            if words and words[0] == "running":
                return True  # (a worker spinning for its next region, or another busy thread: assume the former)
            if len(words) > 2 and any(lo <= int(words[-1], 16) < hi for lo, hi in code):
                return True
        return False
    except (OSError, ValueError):
        return False


def _libgomp_code_ranges() -> list[tuple[int, int]]:
    ranges = []
    with open("/proc/self/maps") as maps:
        for line in maps:
            fields = line.split()
            if len(fields) >= 6 and "libgomp" in fields[5] and "x" in fields[1]:
                lo, hi = fields[0].split("-")
                ranges.append((int(lo, 16), int(hi, 16)))
    return ranges


def numba_regions_thread_safe() -> bool:
    """Whether two threads may run numba parallel regions at once: not on numba's ``workqueue``
    layer (chosen, or configured: ``forksafe`` falls back to it beside GNU OpenMP), which aborts the
    process when they do ("Concurrent access has been detected")."""
    layer = _numba_layer_chosen() or _configured_numba_layer()
    return layer not in ("workqueue", "forksafe")


def _configured_numba_layer() -> str:
    numba = sys.modules.get("numba")
    layer = numba.config.THREADING_LAYER if numba is not None else os.environ.get("NUMBA_THREADING_LAYER", "default")
    return str(layer).lower()


def _after_fork_in_child() -> None:
    global _forked_after_openmp
    _forked_after_openmp = _forked_after_openmp or _unsafe_to_fork
    torch = sys.modules.get("torch")
    if (_forked_after_openmp or _openmp_threads_ran) and torch is not None:
        torch.set_num_threads(1)  # a one-thread region wakes no pool: the child's own torch work runs, inline


if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=_before_fork, after_in_child=_after_fork_in_child)

"""Tasks handed out one at a time inside a numba parallel loop.

numba's OpenMP threading layer (the one it uses where TBB is not installed, as here) runs a
``prange`` with a static schedule: thread t takes the t-th contiguous block of the iterations,
whatever ``numba.parallel_chunksize`` says (measured: with 64 iterations of chunk size 1 on 2
threads, thread 0 ran iterations 0-31). Where the cost per iteration varies along the range (rays
sorted by pixel or by kind, a thread descheduled on a shared machine) one thread then waits for
the other. A kernel that needs balance runs one worker per thread instead, and each worker takes
the next task from a shared counter until none is left::

    next_task = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):  # n_workers = task_workers(n_tasks), from the caller
        scratch = ...  # once per worker, not per task
        while True:
            task = take_task(next_task)
            if task >= n_tasks:
                break
            ...

This balances on every threading layer (on TBB, where workers may share a thread, a worker that
starts late finds fewer tasks left) and allocates a worker's scratch once.
"""

from __future__ import annotations

import numba
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["take_task", "task_count", "task_workers"]


@intrinsic
def take_task(typingctx, counter):
    """``counter[0]``'s value, incremented by one atomically (``counter`` a 1D int64 array):
    each call, on any thread, gets a different value, in increasing order."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64 and counter.ndim == 1 and counter.mutable):
        return None

    def codegen(context, builder, sig, args):
        array = context.make_array(sig.args[0])(context, builder, args[0])
        pointer = cgutils.get_item_pointer(context, builder, sig.args[0], array, [context.get_constant(types.intp, 0)])
        # Monotonic: the counter orders nothing else; the parallel loop's end joins the workers' writes
        return builder.atomic_rmw("add", pointer, context.get_constant(types.int64, 1), "monotonic")

    return types.int64(counter), codegen


def task_count(n_items: int, min_items: int = 1, per_thread: int = 8) -> int:
    """Tasks for ``n_items`` items: as many as hold ``min_items`` each (so that a worker's scratch
    and a task's start serve enough work), at most ``per_thread`` per numba thread, at least one."""
    return max(1, min(-(-n_items // min_items), per_thread * numba.get_num_threads()))


def task_workers(n_tasks: int) -> int:
    """Workers for ``n_tasks`` tasks: one per numba thread, at most one per task. (Called outside
    the kernel and passed in: a kernel that asks numba for its thread count is not cached.)"""
    return max(1, min(numba.get_num_threads(), n_tasks))

"""Host threads for CPU kernels that release the GIL (the shading passes): a batch cut into
balanced chunks, run on one shared thread pool per purpose and process. (Embree's queries and the
TLAS run as numba parallel regions instead: `mesh_blas_kernels`.)"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

import numba

__all__ = ["chunk_slices", "run_chunks", "thread_pool", "numba_threads"]

# Rows per chunk: enough to amortise a thread hand-off (~50 us), few enough to balance the threads
# and keep a chunk's results in cache. A batch is cut into two chunks per thread where that leaves
# MIN_CHUNK_ROWS in each (else one chunk per MIN_CHUNK_ROWS rows begun): with fixed 2^15-row
# chunks, 2^18 rays left half of 16 threads idle, and on 2 threads a 48k-row batch ran as 32k +
# 16k (exact renders: 5-16% faster per spp, docs/lsnif.md). The chunks are of equal size (a batch
# of 6,000 rows: 3,000 + 3,000, not 4,096 + 1,904).
CHUNK_ROWS = 1 << 15
MIN_CHUNK_ROWS = 1 << 12

T = TypeVar("T")
_pools: dict[str, tuple[int, int, ThreadPoolExecutor]] = {}  # purpose -> (process id, workers, pool)


def chunk_slices(n: int, threads: int) -> list[slice]:
    """Consecutive chunks of ``range(n)`` of equal size (to a row), none for no rows: at most
    CHUNK_ROWS rows each; two per thread where ``n`` fills them with MIN_CHUNK_ROWS rows, else one
    per MIN_CHUNK_ROWS rows begun (5,000 rows: 2,500 + 2,500)."""
    if n == 0:
        return []
    count = max(-(-n // CHUNK_ROWS), min(2 * max(1, threads), -(-n // MIN_CHUNK_ROWS)))
    return [slice(i * n // count, (i + 1) * n // count) for i in range(count)]


def run_chunks(fn: Callable[[slice], T], chunks: list[slice], threads: int, purpose: str) -> list[T]:
    """``fn(chunk)`` for each chunk, results in chunk order: on the calling thread for one thread or
    one chunk, else on the ``purpose`` pool of ``threads`` threads (a worker's exception re-raises here)."""
    if threads == 1 or len(chunks) == 1:
        return [fn(chunk) for chunk in chunks]
    futures = [thread_pool(purpose, threads).submit(fn, chunk) for chunk in chunks]
    return [future.result() for future in futures]


def thread_pool(purpose: str, workers: int) -> ThreadPoolExecutor:
    """The process's pool of ``workers`` threads for ``purpose`` (a forked child must not reuse its
    parent's dead threads; a new thread count replaces the pool)."""
    pool = _pools.get(purpose)
    if pool is None or pool[0] != os.getpid() or pool[1] != workers:
        pool = _pools[purpose] = (os.getpid(), workers, ThreadPoolExecutor(workers, thread_name_prefix=f"neuralrt-{purpose}"))
    return pool[2]


@contextmanager
def numba_threads(threads: int | None):
    """numba's parallel regions on ``threads`` threads (at most NUMBA_NUM_THREADS, the core count)
    for this thread's calls inside the block (numba's count is per calling thread), restored
    after; None: as they are."""
    if threads is None:
        yield
        return
    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(before)

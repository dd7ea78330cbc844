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
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

__all__ = ["BatchSource"]


class BatchSource:
    """``next(ahead)`` returns the next batch of ``batch_size`` rays from ``sampler`` and what
    ``prepare`` made of its rays (None without ``prepare``) as ``(batch, prepared)``; with
    ``ahead=True`` it also starts drawing the one after it on a background thread."""

    def __init__(self, sampler, batch_size: int, *, overlap: bool = True, prepare: Callable | None = None):
        self.sampler, self.batch_size, self.prepare = sampler, batch_size, prepare
        self.overlap = overlap and bool(getattr(sampler, "model_independent", False))
        self._executor: ThreadPoolExecutor | None = None
        self._pending: Future | None = None

    def next(self, ahead: bool):
        if self._pending is not None:
            drawn, self._pending = self._pending.result(), None  # re-raises the thread's exception here
        else:
            drawn = self._draw()
        if ahead and self.overlap:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix="neuralrt-batches")
            self._pending = self._executor.submit(self._draw)
        return drawn

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

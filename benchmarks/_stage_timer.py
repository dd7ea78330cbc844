"""`StageTimer`: milliseconds per step in each stage of LSNIF training, per thread.

Wrappers around each stage's function (restored on exit) add up wall time per (stage, thread):
the loop's thread or the batch drawing one. cProfile cannot say this on Python 3.12, where it
sees neither numba's kernels nor which thread a call ran on (and mixes threads' call stacks).
"""

from __future__ import annotations

import inspect
import threading
import time


class StageTimer:
    """``with StageTimer() as timer: <train>``, then ``timer.per_step(wall, steps)``. Nested stages
    are inside their parents' time; ``other`` is the loop's wall time outside its top-level stages."""

    # (label, owner, attribute, top-level on the loop's thread)
    def _targets(self):
        import torch

        from neuralrt.methods import lsnif, lsnif_loss
        from neuralrt.neural import mlp, sparse_hash_grid
        from neuralrt.training import prefetch, ray_distribution

        return [("wait for the batch", prefetch.BatchSource, "next", True),
                ("draw (rays + Embree)", ray_distribution.BoxRayDistribution, "sample", False),
                ("prepare (walk + selection)", lsnif.LSNIFModel, "prepare_training_batch", False),
                ("forward + loss", lsnif.LSNIFModel, "training_step", True),
                ("  encoder forward", sparse_hash_grid._SparseHashGridFunction, "forward", False),
                ("  hidden layers forward", mlp._LowPrecisionHidden, "forward", False),
                ("  output layer + loss", lsnif_loss, "training_loss_numba", False),  # (bench_training sets lsnif.training_loss)
                ("backward", torch.Tensor, "backward", True),
                ("  encoder backward", sparse_hash_grid._SparseHashGridFunction, "backward", False),
                ("  hidden layers backward", mlp._LowPrecisionHidden, "backward", False),
                ("optimizer", torch.optim.Adam, "step", True),
                ("after the step", lsnif.LSNIFModel, "after_training_step", True)]

    def __enter__(self):
        self.seconds: dict[tuple[str, str], float] = {}
        self._saved = []
        targets = self._targets()
        self._order = [label for label, *_ in targets]
        self._top_level = {label for label, _, _, top in targets if top}
        main = threading.main_thread()
        for label, owner, name, _ in targets:
            raw = inspect.getattr_static(owner, name)  # (may be inherited: restored by deleting ours)
            fn = raw.__func__ if isinstance(raw, staticmethod) else raw

            def timed(*a, _fn=fn, _label=label, **k):
                t0 = time.perf_counter()
                try:
                    return _fn(*a, **k)
                finally:
                    where = "loop" if threading.current_thread() is main else "drawing thread"
                    key = (_label, where)
                    self.seconds[key] = self.seconds.get(key, 0.0) + time.perf_counter() - t0

            setattr(owner, name, staticmethod(timed) if isinstance(raw, staticmethod) else timed)
            self._saved.append((owner, name, raw if name in vars(owner) else None))
        return self

    def __exit__(self, *exc):
        for owner, name, raw in reversed(self._saved):
            if raw is None:
                delattr(owner, name)
            else:
                setattr(owner, name, raw)

    def per_step(self, wall: float, steps: int) -> dict:
        keys = sorted(self.seconds, key=lambda k: (k[1] != "loop", self._order.index(k[0])))
        out = {f"{label} [{where}]": round(1e3 * self.seconds[(label, where)] / steps, 3) for label, where in keys}
        top = sum(s for (label, where), s in self.seconds.items() if where == "loop" and label in self._top_level)
        out["other [loop]"] = round(1e3 * (wall - top) / steps, 3)
        out["wall"] = round(1e3 * wall / steps, 3)
        return out

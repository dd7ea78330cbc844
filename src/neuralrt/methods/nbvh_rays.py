"""N-BVH's training rays (paper Sec. 4 and 5.2; METHODS-SPEC A2.2-A2.3).

Origins uniform in the object's box scaled 1.5x about its centre, directions uniform on the
sphere, a cut chosen uniformly per ray among the registered LoDs (and the live cut until LoD 0
exists), resampled until the ray crosses a leaf of its cut. Only the FIRST leaf crossed is
trained: the sample is the ray's chord through that leaf (box grown by 1e-5 + U(0, 1e-4)), from
its entry (or, for an origin inside the leaf, from the chord's start behind the origin) to its
exit; its truth is the first exact hit along the chord, so it does not depend on the origin.

Samples are kept with probability p = max(h / h_max, 0.005) (h: the leaf's heuristic, h_max: the
largest h among the leaves trained in the previous step; a leaf never sampled has p = 1) by drawing more rays than needed and keeping
the accepted ones: no slot ever holds a stale sample.

One algorithm, two implementations, chosen once by the device: on CUDA one Triton kernel
(`nbvh_rays_triton`: draws, walk, acceptance and packing on the device, a fixed-size output, no
host sync), on the CPU the same in one numba pass (`nbvh_rays_cpu`) with the same Philox streams:
the same candidates, so the same samples up to sin/cos rounding (tests/test_nbvh_rays_triton.py).
Random numbers are Philox of (training seed, draw number, candidate): a checkpoint keeps the draw
number, and no torch generator is advanced by the candidates.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import TrainingError
from ..rays import Rays
from ..training.ray_distribution import TrainingBatch

__all__ = ["NBVHRayDistribution", "morton_codes"]


def morton_codes(points: Tensor, bits: int = 10) -> Tensor:
    """[N] int64 Morton (Z-order) codes of unit-cube points [N, 3] (clamped), ``bits`` per axis."""
    q = (points.clamp(0.0, 1.0) * ((1 << bits) - 1)).long()
    code = torch.zeros(len(q), dtype=torch.long, device=points.device)
    for bit in range(bits):
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    return code


class NBVHRayDistribution:
    """Draws `TrainingBatch`es of leaf chords (object space: origin at the chord start, unit
    direction, ``t_max`` = chord length) and tells ``model`` which leaf each one trains.

    ``implementation``: ``"cpu"`` (the numba pass) or ``"triton"`` (the CUDA kernel; on CPU tensors
    it needs ``TRITON_INTERPRET=1``); default: ``"triton"`` on CUDA, ``"cpu"`` elsewhere.
    """

    def __init__(self, model, truth, device: torch.device, implementation: str | None = None):
        self.model = model
        self.truth = truth
        self.device = torch.device(device)
        self.implementation = implementation or ("triton" if self.device.type == "cuda" else "cpu")
        if self.implementation not in ("cpu", "triton"):
            raise ValueError(f"unknown N-BVH ray sampler {self.implementation!r} (cpu or triton)")
        if self.implementation == "cpu" and self.device.type != "cpu":
            raise ValueError(f"N-BVH's cpu ray sampler draws on the CPU, not on {self.device.type} (use triton there)")
        # (the stratified chord fractions' draws; the candidates are Philox streams)
        self.generator = torch.Generator(device=self.device).manual_seed(model.config.training.seed)
        self._draws = 0  # draws so far: each its own Philox stream (checkpointed)
        self._depth: int | None = None  # the base tree's depth (sizes the Triton kernel's stack)
        self._flags: list[tuple[Tensor, object]] = []  # draws' flags, read once their copy has landed
        self._last_draw: tuple[int, Tensor, int] | None = None  # the last draw: (samples, rounds per program, block)

    def _draw_cpu(self, n: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(chord starts (unit cube), directions, lengths, leaves) of ``n`` samples in spatial order:
        one numba pass (`sample_leaf_chords_cpu`), then the Morton order."""
        from .nbvh_rays_cpu import sample_leaf_chords_cpu

        return self._ordered(sample_leaf_chords_cpu(self.model, n, self.model.config.training.seed, self._draws))

    def _draw_triton(self, n: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """`_draw_cpu` on the device: one kernel (`sample_leaf_chords_triton`), then the Morton order."""
        from .nbvh_rays_triton import sample_leaf_chords_triton, tree_depth

        self._check_flags(wait=False)
        if self._depth is None:
            self._depth = tree_depth(self.model.node_children)  # once: the tree's shape never changes
        return self._ordered(sample_leaf_chords_triton(self.model, n, self.model.config.training.seed, self._draws, self._depth))

    def _ordered(self, chords) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """A draw's samples in spatial order (the Morton codes of the chord midpoints: nearby samples
        read nearby hash-table rows, 1.4x faster encoding forward + backward on the CPU, measured on
        the bunny's chords); its flag watched."""
        self._draws += 1
        self._watch(chords.flag)
        self._last_draw = (len(chords.node), chords.rounds, chords.block)
        order = torch.argsort(chords.code, stable=True)
        return chords.start[order], chords.direction[order], chords.length[order], chords.node[order]

    def last_yield(self) -> float:
        """Share of the candidate rays that became samples in the last draw (waits for it; NaN before one)."""
        if self._last_draw is None:
            return float("nan")
        n, rounds, block = self._last_draw
        return n / max(int(rounds.sum()) * block, 1)

    def _watch(self, flag: Tensor) -> None:
        """Keep a draw's flag to read later: a copy to pinned memory on CUDA (no wait), at once elsewhere."""
        if flag.device.type == "cuda":
            host = torch.empty(1, dtype=torch.int32, pin_memory=True)
            host.copy_(flag, non_blocking=True)
            done = torch.cuda.Event()
            done.record()
            self._flags.append((host, done))
        else:
            self._flags.append((flag, None))
            self._check_flags(wait=True)

    def _check_flags(self, wait: bool) -> None:
        """Raise for a draw that could not fill its batch (or overflowed its stack), once its flag is readable."""
        from .nbvh_rays_cpu import OVERFLOW, UNFILLED

        while self._flags and (wait or self._flags[0][1] is None or self._flags[0][1].query()):
            flag, done = self._flags.pop(0)
            if done is not None:
                done.synchronize()
            value = int(flag[0])
            if value & UNFILLED:
                raise TrainingError("N-BVH training rays: no sampled ray crosses a leaf of the cut "
                                    "(the leaf boxes or their error statistics are degenerate)")
            if value & OVERFLOW:
                raise RuntimeError("N-BVH training rays: the first-leaf walk overflowed its stack (a bug)")

    def sample(self, n: int) -> TrainingBatch:
        start, d, length, node = self._draw_triton(n) if self.implementation == "triton" else self._draw_cpu(n)
        model = self.model
        rays = Rays(model.unit_lo + start * model.unit_scale, d, torch.zeros_like(length), length * model.unit_scale)
        truth = self.truth.intersect(rays)
        fractions = None
        if model.config.query.chord_points == "stratified":  # one random point per third of the chord
            fractions = (torch.arange(3, device=self.device) + torch.rand(len(node), 3, generator=self.generator, device=self.device)) / 3
        model.remember_batch_leaves(node, fractions)
        return TrainingBatch(rays, torch.zeros(len(rays), dtype=torch.bool, device=self.device), truth)

    def state_dict(self) -> tuple[dict, dict]:
        return {"draws": self._draws}, {"generator": self.generator.get_state()}

    def load_state_dict(self, meta: dict, arrays: dict) -> None:
        self.generator.set_state(arrays["generator"])
        self._draws = int(meta.get("draws", 0))

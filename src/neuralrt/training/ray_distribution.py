"""The scene-independent ray distribution around one object (LSNIF paper, Sec. 5.2), with exact
ground truth: what every neural method trains on, and what `neuralrt eval` draws held-out rays from.

A share ``surface_fraction`` of the rays start on the object's surface, the rest outside it:

- **outside rays** start uniformly on a sphere enclosing the box, with directions cosine-weighted
  around the inward direction (towards the sphere's centre);
- **surface rays** start at hit points of such outside rays, offset a hair along the geometric
  normal (turned to the side the ray arrived from, as a renderer spawns a bounce), with directions
  cosine-weighted around that normal.

Surface origins come from a pool of hit points that the outside rays of every batch refill for
free, so no extra rays are cast to make them (a prototype spent 30% of its step casting rays just
to find surface origins). Everything is torch on one device with the distribution's own
`torch.Generator` (checkpointed; the global RNG is never touched). Ground truth comes from the
exact BLAS passed in, which takes and returns tensors on that device.
"""

from __future__ import annotations

import warnings

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from . import ray_distribution_cpu as cpu
from ..accel.blas import BLAS
from ..errors import ConfigError, MeshError, outside_stacklevel
from ..rays import AABB, Hits, Rays, face_forward

__all__ = ["TrainingBatch", "BoxRayDistribution", "cosine_weighted_directions", "uniform_sphere_points"]


@dataclass
class TrainingBatch:
    """Rays in object space, which of them start on the surface, and their exact closest hits."""

    rays: Rays  # N rays, on the distribution's device
    from_surface: Tensor  # [N] bool
    truth: Hits  # [N] exact closest hits


def cosine_weighted_directions(axis: Tensor, generator: torch.Generator) -> Tensor:
    """[N, 3] unit directions with pdf cos(theta)/pi around each unit ``axis`` row [N, 3] (same dtype and device)."""
    n = axis.shape[0]
    u = torch.rand(n, 2, generator=generator, device=axis.device, dtype=axis.dtype)
    r, phi = torch.sqrt(u[:, 0]), 2.0 * torch.pi * u[:, 1]
    lx, ly, lz = r * torch.cos(phi), r * torch.sin(phi), torch.sqrt(torch.clamp(1.0 - u[:, 0], min=0.0))
    # Orthonormal basis around each axis (Duff et al. 2017, branchless).
    zx, zy, zz = axis.unbind(-1)
    sign = torch.where(zz >= 0, 1.0, -1.0).to(axis.dtype)
    a = -1.0 / (sign + zz)
    b = zx * zy * a
    x = torch.stack([1.0 + sign * zx * zx * a, sign * b, -sign * zx], dim=-1)
    y = torch.stack([b, sign + zy * zy * a, -zy], dim=-1)
    return lx[:, None] * x + ly[:, None] * y + lz[:, None] * axis


def uniform_sphere_points(n: int, generator: torch.Generator, device: torch.device, dtype=torch.float32) -> Tensor:
    """[N, 3] uniform points on the unit sphere."""
    v = torch.randn(n, 3, generator=generator, device=device, dtype=dtype)
    return v / torch.clamp(torch.linalg.norm(v, dim=-1, keepdim=True), min=1e-30)


class BoxRayDistribution:
    """Draws `TrainingBatch`es from the sphere + surface distribution around one object.

    Args:
        truth: the exact intersector of the object (ground truth), e.g. `MeshBLAS`.
        box: the box the model answers in (e.g. LSNIF's inflated AABB); the sphere encloses it.
            Default: ``truth.bounds``.
        surface_fraction: share of rays that start on the surface (paper: 0.5).
        pool_size: surface points kept for surface-ray origins (refilled each batch).
        surface_offset: origin offset of surface rays along the normal, in units of the box
            diagonal (MeshBLAS's own secondary offset is 1e-4 of the diagonal).
        seed: seeds the distribution's own generator (its state is checkpointed).
        device: where rays, hits and the pool live (default: cpu).
    """

    # Batches depend only on the distribution's own generator and pool, never on the model, so
    # the training loop may draw the next one while the network runs (`BatchSource`).
    model_independent = True

    def __init__(
        self,
        truth: BLAS,
        box: AABB | None = None,
        *,
        surface_fraction: float = 0.5,
        pool_size: int = 1 << 18,
        surface_offset: float = 1e-4,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ):
        if not 0.0 <= surface_fraction <= 1.0:
            raise ConfigError(f"surface_fraction must be in [0, 1], got {surface_fraction}")
        self.truth = truth
        self.device = torch.device(device)
        self.bounds = box if box is not None else truth.bounds
        self.center = self.bounds.center.float().to(self.device)
        self.radius = 0.5 * self.bounds.diagonal
        self.surface_fraction = surface_fraction
        self.surface_offset = surface_offset * self.bounds.diagonal
        self.generator = torch.Generator(device=self.device).manual_seed(seed)
        self._pool_size = int(pool_size)
        self.pool_points = torch.zeros(0, 3, device=self.device)  # [P, 3] surface points, P <= pool_size
        self.pool_normals = torch.zeros(0, 3, device=self.device)  # [P, 3] their normals, facing the arriving ray
        self._pool_cursor = 0  # next ring-buffer slot once the pool is full
        # Chosen once: numba passes on the CPU, torch ops elsewhere (the same draws either way).
        self._sample = self._sample_cpu if self.device.type == "cpu" else self._sample_torch
        self._fill_pool()

    # -- outside rays ----------------------------------------------------------------------
    def outside_rays(self, n: int) -> Rays:
        """``n`` rays from the enclosing sphere, cosine-weighted around the inward direction."""
        p = uniform_sphere_points(n, self.generator, self.device)
        d = cosine_weighted_directions(-p, self.generator)
        return Rays(self.center + self.radius * p, d)

    def _add_to_pool(self, rays: Rays, hits: Hits) -> None:
        idx = torch.nonzero(hits.hit).squeeze(1)
        if len(idx) == 0:
            return
        p = rays.point_at(torch.where(hits.hit, hits.t, 0.0))[idx]
        ng = face_forward(hits.geometric_normal[idx], rays.directions[idx])
        k = min(len(p), self._pool_size)
        p, ng = p[:k], ng[:k]
        if len(self.pool_points) < self._pool_size:
            take = min(k, self._pool_size - len(self.pool_points))
            self.pool_points = torch.cat([self.pool_points, p[:take]])
            self.pool_normals = torch.cat([self.pool_normals, ng[:take]])
            p, ng = p[take:], ng[take:]
        if len(p):  # ring buffer: overwrite the oldest entries
            slots = (self._pool_cursor + torch.arange(len(p), device=self.device)) % self._pool_size
            self.pool_points[slots], self.pool_normals[slots] = p, ng
            self._pool_cursor = int((self._pool_cursor + len(p)) % self._pool_size)

    # Rounds of 65,536 rays that fill the pool at most: a mesh that covers little of its bounding
    # sphere (a needle, r = 1e-3 x 10: ~2e-4 of the rays hit) took minutes; capped, its whole `train
    # --preset lq --steps 20` takes 5 s on 2 cores. Later batches' hits keep filling the rest
    # (`_add_to_pool`), as for any pool larger than the first rounds found.
    FILL_ROUNDS = 64

    def _fill_pool(self) -> None:
        tries = 0
        while len(self.pool_points) < self._pool_size and tries < self.FILL_ROUNDS:
            rays = self.outside_rays(1 << 16)
            self._add_to_pool(rays, self.truth.intersect(rays))
            tries += 1
        name = getattr(getattr(self.truth, "mesh", None), "name", "the mesh")
        if len(self.pool_points) == 0:  # training checks the mesh first: this should not happen
            raise MeshError(f"{name}: none of {tries} x 65536 rays from its bounding sphere hits it: cannot build "
                            "the surface-point pool (too small, too large or too far from the origin for float32?)")
        if len(self.pool_points) < self._pool_size:
            warnings.warn(f"{name}: {tries} x 65536 rays from its bounding sphere found {len(self.pool_points):,} of "
                          f"{self._pool_size:,} surface points (the mesh covers little of its box); rays from its surface "
                          "start at those (training adds hits as it finds them)", stacklevel=outside_stacklevel())

    # -- surface rays ----------------------------------------------------------------------
    def surface_rays(self, n: int) -> Rays:
        """``n`` rays from pooled surface points, cosine-weighted around the (facing) normal."""
        idx = torch.randint(0, len(self.pool_points), (n,), generator=self.generator, device=self.device)
        p, ng = self.pool_points[idx], self.pool_normals[idx]
        d = cosine_weighted_directions(ng, self.generator)
        return Rays(p + self.surface_offset * ng, d)

    # -- batches -----------------------------------------------------------------------------
    def sample(self, n: int) -> TrainingBatch:
        """A batch of ``n`` rays (outside first, then surface) with exact ground truth."""
        return self._sample(n)

    def _sample_torch(self, n: int) -> TrainingBatch:
        n_surface = int(round(n * self.surface_fraction))
        outside = self.outside_rays(n - n_surface)
        surface = self.surface_rays(n_surface)
        rays = Rays(torch.cat([outside.origins, surface.origins]), torch.cat([outside.directions, surface.directions]))
        truth = self.truth.intersect(rays)
        self._add_to_pool(rays[: n - n_surface], truth[: n - n_surface])
        from_surface = torch.arange(n, device=self.device) >= n - n_surface
        return TrainingBatch(rays, from_surface, truth)

    def _sample_cpu(self, n: int) -> TrainingBatch:
        """`_sample_torch` with the rays made and the full pool refilled by numba passes
        (`ray_distribution_cpu`) from the same random draws, taken in the same order."""
        n_surface = int(round(n * self.surface_fraction))
        n_outside = n - n_surface
        g = self.generator
        normals, outside_u = torch.randn(n_outside, 3, generator=g), torch.rand(n_outside, 2, generator=g)
        picks = torch.randint(0, len(self.pool_points), (n_surface,), generator=g)
        surface_u = torch.rand(n_surface, 2, generator=g)
        origins, directions = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        center = self.center.numpy()
        cpu.outside_rays(normals.numpy(), outside_u.numpy(), center, np.float32(self.radius), origins, directions)
        cpu.surface_rays(picks.numpy(), surface_u.numpy(), self.pool_points.numpy(), self.pool_normals.numpy(),
                         np.float32(self.surface_offset), origins, directions, n_outside)  # fmt: skip
        rays = Rays(torch.from_numpy(origins), torch.from_numpy(directions))
        truth = self.truth.intersect(rays)
        if len(self.pool_points) == self._pool_size:
            hit, t, normal = (x[:n_outside].contiguous().numpy() for x in (truth.hit, truth.t, truth.geometric_normal))
            self._pool_cursor = int(cpu.refill_pool(origins, directions, hit, t, normal, self.pool_points.numpy(),
                                                    self.pool_normals.numpy(), self._pool_cursor))  # fmt: skip
        else:  # still filling (a pool larger than what the constructor's rays found): the torch path grows it
            self._add_to_pool(rays[:n_outside], truth[:n_outside])
        return TrainingBatch(rays, torch.from_numpy(np.arange(n) >= n_outside), truth)

    # -- checkpointing -------------------------------------------------------------------------
    def state_dict(self) -> tuple[dict, dict[str, Tensor]]:
        """(JSON-able state, CPU tensors): generator state, pool cursor, and the pool itself."""
        meta = {"pool_cursor": self._pool_cursor}
        arrays = {"generator": self.generator.get_state(), "pool_points": self.pool_points.cpu().clone(),
                  "pool_normals": self.pool_normals.cpu().clone()}
        return meta, arrays

    def load_state_dict(self, meta: dict, arrays: dict[str, Tensor]) -> None:
        """A ValueError for a state no run saves: the pool's kernels index it unchecked (a pool of
        points longer than its normals wrote past their end: a segmentation fault)."""
        points, normals, cursor = arrays["pool_points"], arrays["pool_normals"], meta["pool_cursor"]
        if not (points.dtype == normals.dtype == torch.float32 and points.ndim == normals.ndim == 2
                and points.shape == normals.shape and points.shape[1] == 3 and 0 < len(points) <= self._pool_size):
            raise ValueError(f"its surface pool is {list(points.shape)} points and {list(normals.shape)} normals "
                             f"({str(points.dtype)[6:]}, {str(normals.dtype)[6:]}); a run keeps [1..{self._pool_size}, 3] "
                             "of each, float32")
        if not (torch.isfinite(points).all() and torch.isfinite(normals).all() and (normals != 0).any(dim=1).all()):
            raise ValueError("its surface pool holds numbers that are not finite, or zero normals")
        if not isinstance(cursor, int) or isinstance(cursor, bool) or not 0 <= cursor < self._pool_size:
            raise ValueError(f"its pool cursor {cursor!r} is not a slot of its pool of {self._pool_size}")
        self.generator.set_state(arrays["generator"])
        self._pool_cursor = cursor
        self.pool_points = points.to(self.device).clone()
        self.pool_normals = normals.to(self.device).clone()

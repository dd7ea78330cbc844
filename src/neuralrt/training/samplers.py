"""The scene-independent training ray distribution of LSNIF (paper, Sec. 5.2), with exact ground truth.

Half of the rays (``surface_fraction``) start on the object's surface, half outside it:

- **outside rays** start uniformly on a sphere enclosing the (inflated) box, with directions
  cosine-weighted around the inward direction (towards the sphere's centre);
- **surface rays** start at hit points of such outside rays, offset a hair along the geometric
  normal (turned to the side the ray arrived from, as a renderer spawns a bounce), with directions
  cosine-weighted around that normal.

Ground truth comes from `MeshBLAS` (Embree). Surface origins come from a pool of hit points that
the outside rays of every batch refill for free, so no extra rays are cast to make them (a
prototype spent 30% of its step casting rays just to find surface origins).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..accel.mesh_blas import MeshBLAS
from ..rays import AABB, Hits, Rays

__all__ = ["TrainingBatch", "LSNIFRaySampler", "cosine_weighted_directions"]


@dataclass
class TrainingBatch:
    """Rays in object space, which of them start on the surface, and their exact closest hits."""

    rays: Rays
    from_surface: Tensor  # [N] bool
    truth: Hits


def cosine_weighted_directions(axis: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """[N, 3] unit directions with pdf cos(theta)/pi around each unit ``axis`` row [N, 3]."""
    n = len(axis)
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2.0 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1.0 - u1))], axis=1)
    # Orthonormal basis around each axis (Duff et al. 2017, branchless).
    z = axis.astype(np.float64)
    sign = np.where(z[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z[:, 2])
    b = z[:, 0] * z[:, 1] * a
    x = np.stack([1.0 + sign * z[:, 0] ** 2 * a, sign * b, -sign * z[:, 0]], axis=1)
    y = np.stack([b, sign + z[:, 1] ** 2 * a, -z[:, 1]], axis=1)
    return local[:, :1] * x + local[:, 1:2] * y + local[:, 2:] * z


def uniform_sphere_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """[N, 3] uniform points on the unit sphere."""
    v = rng.normal(size=(n, 3))
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-30)


class LSNIFRaySampler:
    """Draws `TrainingBatch`es from the LSNIF training distribution around one mesh.

    Args:
        truth: the exact intersector of the mesh (ground truth).
        bounds: the box the model lives in (the inflated AABB); the sphere encloses it.
        surface_fraction: share of rays that start on the surface (paper: 0.5).
        pool_size: surface points kept for surface-ray origins (refilled each batch).
        surface_offset: origin offset of surface rays along the normal, in units of the box
            diagonal (MeshBLAS's own secondary offset is 1e-4 of the diagonal).
        seed: seeds the sampler's own numpy generator (its state is checkpointed).
    """

    def __init__(
        self,
        truth: MeshBLAS,
        bounds: AABB | None = None,
        *,
        surface_fraction: float = 0.5,
        pool_size: int = 1 << 18,
        surface_offset: float = 1e-4,
        seed: int = 0,
    ):
        if not 0.0 <= surface_fraction <= 1.0:
            raise ValueError(f"surface_fraction must be in [0, 1], got {surface_fraction}")
        self.truth = truth
        self.bounds = bounds if bounds is not None else truth.bounds
        self.center = self.bounds.center.double().numpy()
        self.radius = 0.5 * self.bounds.diagonal
        self.surface_fraction = surface_fraction
        self.surface_offset = surface_offset * self.bounds.diagonal
        self.rng = np.random.Generator(np.random.PCG64(seed))
        self.pool_points = np.zeros((0, 3), np.float32)
        self.pool_normals = np.zeros((0, 3), np.float32)
        self._pool_size = int(pool_size)
        self._pool_cursor = 0
        self._fill_pool()

    # -- outside rays ----------------------------------------------------------------------
    def outside_rays(self, n: int) -> Rays:
        """``n`` rays from the enclosing sphere, cosine-weighted around the inward direction."""
        p = uniform_sphere_points(n, self.rng)
        d = cosine_weighted_directions(-p, self.rng)
        o = self.center + self.radius * p
        return Rays(torch.from_numpy(o.astype(np.float32)), torch.from_numpy(d.astype(np.float32)))

    def _add_to_pool(self, rays: Rays, hits: Hits) -> None:
        idx = torch.nonzero(hits.hit).squeeze(1)
        if len(idx) == 0:
            return
        p = rays.point_at(torch.where(hits.hit, hits.t, 0.0))[idx].numpy()
        ng = hits.geometric_normal[idx].numpy()
        d = rays.directions[idx].numpy()
        ng = np.where((np.einsum("ij,ij->i", ng, d) > 0)[:, None], -ng, ng)  # face the arriving ray
        k = min(len(p), self._pool_size)
        p, ng = p[:k], ng[:k]
        if len(self.pool_points) < self._pool_size:
            take = min(k, self._pool_size - len(self.pool_points))
            self.pool_points = np.concatenate([self.pool_points, p[:take]])
            self.pool_normals = np.concatenate([self.pool_normals, ng[:take]])
            p, ng = p[take:], ng[take:]
        if len(p):  # ring buffer: overwrite the oldest entries
            slots = (self._pool_cursor + np.arange(len(p))) % self._pool_size
            self.pool_points[slots], self.pool_normals[slots] = p, ng
            self._pool_cursor = int((self._pool_cursor + len(p)) % self._pool_size)

    def _fill_pool(self) -> None:
        tries = 0
        while len(self.pool_points) < self._pool_size:
            rays = self.outside_rays(1 << 16)
            self._add_to_pool(rays, self.truth.intersect(rays))
            tries += 1
            if tries > 64 and len(self.pool_points) == 0:
                raise ValueError("no sampled ray hits the mesh: cannot build the surface-point pool")

    # -- surface rays ----------------------------------------------------------------------
    def surface_rays(self, n: int) -> Rays:
        """``n`` rays from pooled surface points, cosine-weighted around the (facing) normal."""
        idx = self.rng.integers(0, len(self.pool_points), n)
        p, ng = self.pool_points[idx].astype(np.float64), self.pool_normals[idx].astype(np.float64)
        d = cosine_weighted_directions(ng, self.rng)
        o = p + self.surface_offset * ng
        return Rays(torch.from_numpy(o.astype(np.float32)), torch.from_numpy(d.astype(np.float32)))

    # -- batches -----------------------------------------------------------------------------
    def sample(self, n: int) -> TrainingBatch:
        """A batch of ``n`` rays (outside first, then surface) with exact ground truth."""
        n_surface = int(round(n * self.surface_fraction))
        outside = self.outside_rays(n - n_surface)
        surface = self.surface_rays(n_surface)
        rays = Rays(torch.cat([outside.origins, surface.origins]), torch.cat([outside.directions, surface.directions]))
        truth = self.truth.intersect(rays)
        self._add_to_pool(rays[: n - n_surface], truth[: n - n_surface])
        from_surface = torch.arange(n) >= n - n_surface
        return TrainingBatch(rays, from_surface, truth)

    # -- checkpointing -------------------------------------------------------------------------
    def state_dict(self) -> tuple[dict, dict[str, Tensor]]:
        """(JSON-able state, tensors): RNG state, pool cursor, and the pool itself."""
        meta = {"rng": self.rng.bit_generator.state, "pool_cursor": self._pool_cursor}
        arrays = {"pool_points": torch.from_numpy(self.pool_points.copy()), "pool_normals": torch.from_numpy(self.pool_normals.copy())}
        return meta, arrays

    def load_state_dict(self, meta: dict, arrays: dict[str, Tensor]) -> None:
        self.rng.bit_generator.state = meta["rng"]
        self._pool_cursor = int(meta["pool_cursor"])
        self.pool_points = arrays["pool_points"].numpy().copy()
        self.pool_normals = arrays["pool_normals"].numpy().copy()

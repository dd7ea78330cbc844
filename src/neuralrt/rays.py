"""Batched rays and hits, axis-aligned boxes, affine transforms.

Every stage of neuralrt passes `Rays` and `Hits` (small dataclasses of tensors, one row per ray)
and nothing else. Shapes are given as ``[N, 3]`` etc.; ``N`` is the number of rays.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
import torch
from torch import Tensor

__all__ = ["Rays", "Hits", "AABB", "Transform", "ray_box_intervals", "valid_ray_mask", "face_forward"]


@dataclass
class Rays:
    """A batch of rays ``origin + t * direction`` for ``t`` in ``(t_min, t_max)``.

    Directions need not be normalised: ``t`` is measured in units of the direction's length,
    which keeps ``t`` valid when rays are mapped through an affine transform.
    """

    origins: Tensor  # [N, 3] float32
    directions: Tensor  # [N, 3] float32
    t_min: Tensor | None = None  # [N] float32, default 0
    t_max: Tensor | None = None  # [N] float32, default +inf

    def __post_init__(self) -> None:
        self.origins = torch.as_tensor(self.origins, dtype=torch.float32)
        self.directions = torch.as_tensor(
            self.directions, dtype=torch.float32, device=self.origins.device
        )
        if self.origins.ndim != 2 or self.origins.shape[-1] != 3:
            raise ValueError(f"ray origins must have shape [N, 3], got {tuple(self.origins.shape)}")
        if self.directions.shape != self.origins.shape:
            raise ValueError(
                f"ray directions {tuple(self.directions.shape)} do not match origins "
                f"{tuple(self.origins.shape)}"
            )
        n, dev = self.origins.shape[0], self.origins.device
        if self.t_min is None:
            self.t_min = torch.zeros(n, device=dev)
        else:
            self.t_min = torch.as_tensor(self.t_min, dtype=torch.float32, device=dev).expand(n).contiguous()
        if self.t_max is None:
            self.t_max = torch.full((n,), float("inf"), device=dev)
        else:
            self.t_max = torch.as_tensor(self.t_max, dtype=torch.float32, device=dev).expand(n).contiguous()

    def __len__(self) -> int:
        return self.origins.shape[0]

    @property
    def device(self) -> torch.device:
        return self.origins.device

    def __getitem__(self, index) -> "Rays":
        """Select rays by boolean mask or index tensor."""
        return Rays(self.origins[index], self.directions[index], self.t_min[index], self.t_max[index])

    def to(self, device) -> "Rays":
        return Rays(*(getattr(self, f.name).to(device) for f in fields(self)))

    def point_at(self, t: Tensor) -> Tensor:
        return self.origins + t[:, None] * self.directions


@dataclass
class Hits:
    """Closest-hit records, one row per ray. Rows with ``hit == False`` carry ``t = inf``.

    ``albedo`` is the surface's own colour factor at the hit (texture, vertex colour, or the
    value a neural model predicts; 1 where the surface has none); scene materials multiply it.
    """

    hit: Tensor  # [N] bool
    t: Tensor  # [N] float32, inf on miss
    normal: Tensor  # [N, 3] shading normal, unit length (zeros on miss)
    geometric_normal: Tensor  # [N, 3] unit face normal (zeros on miss)
    uv: Tensor  # [N, 2] texture coordinates (zeros where absent)
    albedo: Tensor  # [N, 3] surface colour factor in [0, 1]
    material_id: Tensor  # [N] int64, per-object material index, -1 on miss
    primitive_id: Tensor  # [N] int64, triangle id (-1 on miss or for neural hits)
    instance_id: Tensor  # [N] int64, scene instance, -1 on miss or outside a scene

    @staticmethod
    def empty(n: int, device=None) -> "Hits":
        """All-miss records for ``n`` rays."""
        dev = torch.device(device) if device is not None else torch.device("cpu")
        return Hits(
            hit=torch.zeros(n, dtype=torch.bool, device=dev),
            t=torch.full((n,), float("inf"), device=dev),
            normal=torch.zeros(n, 3, device=dev),
            geometric_normal=torch.zeros(n, 3, device=dev),
            uv=torch.zeros(n, 2, device=dev),
            albedo=torch.ones(n, 3, device=dev),
            material_id=torch.full((n,), -1, dtype=torch.int64, device=dev),
            primitive_id=torch.full((n,), -1, dtype=torch.int64, device=dev),
            instance_id=torch.full((n,), -1, dtype=torch.int64, device=dev),
        )

    def __len__(self) -> int:
        return self.t.shape[0]

    def __getitem__(self, index) -> "Hits":
        return Hits(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def scatter_(self, index: Tensor, other: "Hits") -> "Hits":
        """Write ``other``'s rows into rows ``index`` of self (in place); returns self."""
        for f in fields(self):
            getattr(self, f.name)[index] = getattr(other, f.name)
        return self

    def where_(self, mask: Tensor, other: "Hits") -> "Hits":
        """Take ``other``'s rows where ``mask`` is true (in place, same length); returns self."""
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            m = mask.view(-1, *([1] * (mine.ndim - 1)))
            setattr(self, f.name, torch.where(m, theirs, mine))
        return self

    def to(self, device) -> "Hits":
        return Hits(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})


@dataclass(frozen=True)
class AABB:
    """Axis-aligned box ``[lo, hi]`` (each a float tensor of shape [3])."""

    lo: Tensor
    hi: Tensor

    @staticmethod
    def from_points(points: Tensor) -> "AABB":
        points = torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3)
        return AABB(points.min(0).values, points.max(0).values)

    @property
    def extent(self) -> Tensor:
        return self.hi - self.lo

    @property
    def center(self) -> Tensor:
        return 0.5 * (self.lo + self.hi)

    @property
    def diagonal(self) -> float:
        return float(torch.linalg.norm(self.extent))

    def corners(self) -> Tensor:
        """The 8 corners, [8, 3]."""
        idx = torch.tensor([[i >> 0 & 1, i >> 1 & 1, i >> 2 & 1] for i in range(8)], dtype=torch.bool)
        return torch.where(idx, self.hi.cpu(), self.lo.cpu()).to(self.lo.device)

    def inflated(self, relative: float) -> "AABB":
        """Grown by ``relative`` times the diagonal on each side (and never flat)."""
        pad = relative * max(self.diagonal, 1e-12)
        return AABB(self.lo - pad, self.hi + pad)

    def transformed(self, transform: "Transform") -> "AABB":
        """Bounds of this box after an affine transform."""
        return AABB.from_points(transform.apply_points(self.corners().to(transform.matrix.device)))

    def to(self, device) -> "AABB":
        return AABB(self.lo.to(device), self.hi.to(device))

    def tolist(self) -> list[list[float]]:
        return [self.lo.tolist(), self.hi.tolist()]


def valid_ray_mask(rays: Rays) -> Tensor:
    """Rays with finite origins and finite, non-zero directions and a non-empty interval."""
    finite = torch.isfinite(rays.origins).all(-1) & torch.isfinite(rays.directions).all(-1)
    nonzero = (rays.directions.abs().amax(-1) > 0)
    return finite & nonzero & ~torch.isnan(rays.t_min) & ~torch.isnan(rays.t_max) & (rays.t_max > rays.t_min)


def face_forward(normals: Tensor, directions: Tensor) -> Tensor:
    """``normals`` [..., 3] flipped where needed to face against ``directions`` [..., 3] (the side the
    ray arrives from). Works on torch tensors and numpy arrays alike (any float dtype, any device)."""
    facing_away = (normals * directions).sum(-1, keepdims=True) > 0
    where = np.where if isinstance(normals, np.ndarray) else torch.where
    return where(facing_away, -normals, normals)


def ray_box_intervals(
    origins: Tensor, directions: Tensor, lo: Tensor, hi: Tensor
) -> tuple[Tensor, Tensor]:
    """Slab test: the parametric interval ``[t_enter, t_exit]`` of each ray inside a box.

    ``lo``/``hi`` broadcast against the rays ([3] for one box, [N, 3] per ray, or [N, B, 3] with
    origins [N, 1, 3] for many boxes). The ray misses where ``t_enter > t_exit``. Zero direction
    components are handled with IEEE infinities; a ray lying exactly in a slab plane of a flat
    axis counts as inside.
    """
    inv = 1.0 / directions
    t0 = (lo - origins) * inv
    t1 = (hi - origins) * inv
    # 0 * inf gives NaN when the origin lies on a slab plane with a parallel direction: inside.
    t0 = torch.nan_to_num(t0, nan=-float("inf"))
    t1 = torch.nan_to_num(t1, nan=float("inf"))
    t_near = torch.minimum(t0, t1).amax(-1)
    t_far = torch.maximum(t0, t1).amin(-1)
    return t_near, t_far


class Transform:
    """Affine object-to-world transform held as a 4x4 matrix and its inverse.

    Points map by the full matrix, directions by its linear part (unnormalised, so a hit's ``t``
    is the same in both spaces), normals by the inverse transpose.
    """

    def __init__(self, matrix: Tensor | None = None, inverse: Tensor | None = None):
        m = torch.eye(4) if matrix is None else torch.as_tensor(matrix, dtype=torch.float64)
        m = m.to(torch.float64)
        if m.shape != (4, 4):
            raise ValueError(f"transform matrix must be 4x4, got {tuple(m.shape)}")
        if not torch.isfinite(m).all():
            raise ValueError("transform matrix has NaN or Inf entries")
        if abs(float(torch.linalg.det(m[:3, :3]))) < 1e-30:
            raise ValueError("transform matrix is singular (zero scale?)")
        self._m64 = m
        self._inv64 = torch.linalg.inv(m) if inverse is None else torch.as_tensor(inverse, dtype=torch.float64)
        self.matrix = self._m64.float()
        self.inverse_matrix = self._inv64.float()

    # -- construction ---------------------------------------------------------------------
    @staticmethod
    def identity() -> "Transform":
        return Transform()

    @staticmethod
    def translate(offset) -> "Transform":
        m = torch.eye(4, dtype=torch.float64)
        m[:3, 3] = torch.as_tensor(offset, dtype=torch.float64)
        return Transform(m)

    @staticmethod
    def scale(factors) -> "Transform":
        f = torch.as_tensor(factors, dtype=torch.float64).expand(3)
        return Transform(torch.diag(torch.cat([f, torch.ones(1, dtype=torch.float64)])))

    @staticmethod
    def rotate(axis, degrees: float) -> "Transform":
        """Rotation by ``degrees`` about ``axis`` (right-handed)."""
        a = torch.as_tensor(axis, dtype=torch.float64)
        a = a / torch.linalg.norm(a)
        th = torch.deg2rad(torch.tensor(float(degrees), dtype=torch.float64))
        c, s = torch.cos(th), torch.sin(th)
        x, y, z = a
        r = torch.stack(
            [
                torch.stack([c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s]),
                torch.stack([y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s]),
                torch.stack([z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]),
            ]
        )
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] = r
        return Transform(m)

    @staticmethod
    def look_at(eye, target, up) -> "Transform":
        """Camera-to-world: camera looks down -z, +y up, +x right (OpenGL convention)."""
        eye, target, up = (torch.as_tensor(v, dtype=torch.float64) for v in (eye, target, up))
        fwd = target - eye
        if torch.linalg.norm(fwd) == 0:
            raise ValueError("look_at: position and target coincide")
        fwd = fwd / torch.linalg.norm(fwd)
        right = torch.linalg.cross(fwd, up)
        if torch.linalg.norm(right) < 1e-12:
            raise ValueError("look_at: up vector is parallel to the view direction")
        right = right / torch.linalg.norm(right)
        true_up = torch.linalg.cross(right, fwd)
        m = torch.eye(4, dtype=torch.float64)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, -fwd, eye
        return Transform(m)

    def __matmul__(self, other: "Transform") -> "Transform":
        """Composition: ``(a @ b)`` applies ``b`` first, then ``a``."""
        return Transform(self._m64 @ other._m64, other._inv64 @ self._inv64)

    def inverse(self) -> "Transform":
        return Transform(self._inv64, self._m64)

    # -- application ------------------------------------------------------------------------
    def _on(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return self.matrix.to(x.device), self.inverse_matrix.to(x.device)

    def apply_points(self, p: Tensor) -> Tensor:
        m, _ = self._on(p)
        return p @ m[:3, :3].T + m[:3, 3]

    def apply_vectors(self, v: Tensor) -> Tensor:
        m, _ = self._on(v)
        return v @ m[:3, :3].T

    def apply_normals(self, n: Tensor) -> Tensor:
        """Normals by the inverse transpose, renormalised (zero rows stay zero)."""
        _, inv = self._on(n)
        out = n @ inv[:3, :3]
        return torch.nn.functional.normalize(out, dim=-1)

    def apply_rays(self, rays: Rays) -> Rays:
        """Map rays; ``t_min``/``t_max`` keep their meaning because directions are not renormalised."""
        return Rays(self.apply_points(rays.origins), self.apply_vectors(rays.directions), rays.t_min, rays.t_max)

    @property
    def is_identity(self) -> bool:
        return bool(torch.equal(self._m64, torch.eye(4, dtype=torch.float64)))

    def tolist(self) -> list[list[float]]:
        return self._m64.tolist()

    def __repr__(self) -> str:
        return f"Transform({self._m64.tolist()})"


def transform_hits_to_world(hits: Hits, transform: Transform) -> Hits:
    """Object-space hits to world space: normals by the inverse transpose; t unchanged."""
    return replace(
        hits,
        normal=transform.apply_normals(hits.normal) * hits.hit[:, None],
        geometric_normal=transform.apply_normals(hits.geometric_normal) * hits.hit[:, None],
    )

"""Batched rays and hits, axis-aligned boxes, affine transforms, and a pinhole ray generator.

Every stage of neuralrt passes `Rays` and `Hits` (small dataclasses of tensors, one row per ray)
and nothing else. Shapes are written nerfstudio-style: ``[N, 3]`` is N rows of xyz; ``N`` is the
number of rays. All tensors of one batch live on one device (``rays.device``): a BLAS answers on
the device of the rays it was given, and a scene refuses rays on another device than its own.
"""

from __future__ import annotations

import functools
import math
import numbers
from dataclasses import dataclass, field, fields, replace
from typing import Annotated

import numpy as np
import torch
from torch import Tensor

from .arguments import check_count
from .devices import DEVICE_TYPES, check_device, resolve_device  # (resolve_device: re-exported, its old home)
from .errors import ConfigError, DeviceError
from .fork_guard import check_not_forked

__all__ = ["Rays", "Hits", "AABB", "Transform", "ray_box_intervals", "valid_ray_mask", "face_forward", "pinhole_rays",
           "resolve_device", "check_rays"]

# Tensor type hints carrying shape and dtype (read them with typing.get_type_hints(..., include_extras=True)).
Points = Annotated[Tensor, "[N, 3] float32"]
Vectors = Annotated[Tensor, "[N, 3] float32"]
Scalars = Annotated[Tensor, "[N] float32"]
Mask = Annotated[Tensor, "[N] bool"]
Indices = Annotated[Tensor, "[N] int64"]


_RAY_FIELDS = ("origins", "directions", "t_min", "t_max")


@dataclass(eq=False)  # (identity: tensors have no single truth value; compare fields with torch.equal)
class Rays:
    """A batch of rays ``origins + t * directions`` for ``t`` in ``[t_min, t_max]``.

    Fields (``N`` rays, all on one device, float32):

    - ``origins`` [N, 3]: start points, in the space of whoever answers them (world space for a
      scene, the object's own space for a BLAS).
    - ``directions`` [N, 3]: need not be unit length: ``t`` is measured in units of the
      direction's length, which keeps ``t`` valid when rays are mapped through an affine transform.
      (Shorter than about 1e-14, Embree's answers degrade: it clamps tiny direction components;
      normalise such directions. Long ones are answered as unit ones, to 1e18 at least; beyond
      about 1e19 a neural BLAS's squared length overflows float32 and it misses.)
    - ``t_min``, ``t_max`` [N]: the interval, both ends included (as Embree's); default ``0`` and
      ``+inf``. A scalar or any tensor that broadcasts to the batch shape is accepted. A negative
      ``t_min`` is stored as 0: no BLAS answers hits behind the origin (a neural one cannot: it
      learned rays that start there), so exact and neural answers agree. Every BLAS traces from
      the origin moved to ``t_min`` (Embree's and OptiX's rays start at 0 there, a network's
      inputs are built from it), in float32: a surface at exactly ``t_min`` is found or skipped by
      that rounding (about half of them), and ``t_min == t_max`` is a miss (an interval of no
      length: the one exception to "both ends included").
      ``t_max`` holds exactly: a hit at ``t == t_max`` is kept.

    Batch shapes: origins and directions may be ``[..., 3]`` (e.g. ``[H, W, 3]``); they are
    flattened row-major to ``[N, 3]`` and ``batch_shape`` keeps the original leading shape, so
    answers reshape back with ``hits.t.reshape(rays.batch_shape)``. Rays with NaN/Inf or zero
    directions, or an empty interval, are valid input: they miss. Mis-shaped or non-numeric input
    raises a one-line `ConfigError` (a ValueError), tensors on another device than cpu or cuda
    (e.g. ``meta``) a `DeviceError`.
    """

    origins: Points
    directions: Vectors
    t_min: Scalars | None = None
    t_max: Scalars | None = None
    batch_shape: tuple[int, ...] | None = field(default=None, kw_only=True)
    """Leading shape the rays were given in (default ``(N,)``); ``N = prod(batch_shape)``."""

    def __setattr__(self, name: str, value) -> None:
        # A field set after construction is checked and converted as at construction (a 1-value
        # t_max for 2^20 rays made the kernels read past its end; a float had no .detach).
        if name in _RAY_FIELDS and self.__dict__.get("_built"):
            given = {k: self.__dict__[k] for k in _RAY_FIELDS}
            n = len(self)
            if name in ("origins", "directions"):  # (as stored, [N, 3], or in the batch shape)
                value = _float_tensor(name, value, given["origins"].device)
                value = value.reshape(n, 3) if value.shape[-1:] == (3,) and value.numel() == 3 * n else value
            given[name] = value
            checked = Rays(**given, batch_shape=self.batch_shape)
            for k in _RAY_FIELDS:
                object.__setattr__(self, k, checked.__dict__[k])
            return
        object.__setattr__(self, name, value)

    def __post_init__(self) -> None:
        origins = _float_tensor("origins", self.origins)
        directions = _float_tensor("directions", self.directions, origins.device)
        if origins.ndim < 1 or origins.shape[-1] != 3:
            raise ConfigError(f"ray origins must have shape [..., 3], got {tuple(origins.shape)}")
        if directions.shape != origins.shape:
            raise ConfigError(f"ray directions {tuple(directions.shape)} do not match origins {tuple(origins.shape)}")
        shape = tuple(origins.shape[:-1])
        if self.batch_shape is None:
            self.batch_shape = shape
        elif isinstance(self.batch_shape, (tuple, list, torch.Size)) and all(
                isinstance(d, numbers.Integral) and not isinstance(d, bool) and d >= 0 for d in self.batch_shape):
            self.batch_shape = tuple(int(d) for d in self.batch_shape)  # (numpy sizes too, kept as Python ints)
        else:
            raise ConfigError(f"batch_shape: expected a tuple of sizes, got {self.batch_shape!r}")
        n, dev = math.prod(shape), origins.device
        if math.prod(self.batch_shape) != n:
            raise ConfigError(f"batch_shape {self.batch_shape} does not hold {n} rays")
        shape = tuple(self.batch_shape)  # (what t_min / t_max broadcast to, the rays given flat or not)
        # Contiguous rows (a no-op for the usual ones): each other layout, strided or transposed,
        # compiled the exact tracer's kernel again (about 4 s each), for the same answers.
        self.origins, self.directions = origins.reshape(n, 3).contiguous(), directions.reshape(n, 3).contiguous()
        if self.t_min is None:
            self.t_min = torch.zeros(n, device=dev)
        else:  # hits behind the origin: none (NaN stays NaN, a miss)
            self.t_min = self._interval("t_min", self.t_min, shape, n, dev).clamp_min(0.0)
        self.t_max = torch.full((n,), float("inf"), device=dev) if self.t_max is None else self._interval("t_max", self.t_max, shape, n, dev)
        object.__setattr__(self, "_built", True)

    @staticmethod
    def _interval(name: str, value, shape: tuple[int, ...], n: int, dev) -> Tensor:
        t = _float_tensor(name, value, dev)
        if t.ndim == 1 and t.shape[0] == n:
            return t.contiguous()  # already per ray: the common case, no copy
        if not _broadcasts_to(tuple(t.shape), shape):
            raise ConfigError(f"ray {name} of shape {tuple(t.shape)} does not broadcast to the rays' shape {shape} "
                              f"(give a scalar or one value per ray, [{n}])")
        return t.expand(shape).reshape(n).contiguous()

    def __len__(self) -> int:
        return self.origins.shape[0]

    def __repr__(self) -> str:  # (the dataclass's printed every tensor)
        shape = "" if len(self.batch_shape) == 1 else f", batch_shape {tuple(self.batch_shape)}"
        return f"Rays({len(self)} rays{shape}, {self.device})"

    @property
    def device(self) -> torch.device:
        return self.origins.device

    def __getitem__(self, index) -> "Rays":
        """Select rays by boolean mask or index tensor (the result is a flat batch)."""
        return Rays(self.origins[index], self.directions[index], self.t_min[index], self.t_max[index])

    def to(self, device) -> "Rays":
        """The rays on ``device`` (a new `Rays`); a device this process lacks is a `DeviceError`."""
        device = check_device(device)  # (cuda on a CPU-only torch: one line, not torch's AssertionError)
        return Rays(self.origins.to(device), self.directions.to(device), self.t_min.to(device), self.t_max.to(device),
                    batch_shape=self.batch_shape)

    def point_at(self, t: Tensor) -> Tensor:
        """``origins + t * directions`` [N, 3] for ``t`` [N]."""
        return self.origins + t[:, None] * self.directions


def _float_tensor(name: str, value, device=None) -> Tensor:
    """``value`` as a float32 tensor (on ``device`` if given); a one-line error for what torch cannot
    take or compute on (strings, None; the meta device, whose tensors hold no data)."""
    if isinstance(value, Tensor):
        if value.device.type not in DEVICE_TYPES:
            raise DeviceError(f"ray {name} are on {value.device}: neuralrt computes on cpu or cuda")
        if value.dtype == torch.bool or value.is_complex():  # (torch would cast them: 0/1, the real part)
            raise ConfigError(f"ray {name}: expected real numbers, got a {value.dtype} tensor")
        return torch.as_tensor(value, dtype=torch.float32, device=device)  # (its errors, e.g. out of memory, are torch's)
    kind = getattr(getattr(value, "dtype", None), "kind", None)  # a numpy array's
    if kind in ("b", "c"):
        raise ConfigError(f"ray {name}: expected real numbers, got a {value.dtype} array")
    try:
        return torch.as_tensor(value, dtype=torch.float32, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise ConfigError(f"ray {name}: expected a float tensor or array, got {type(value).__name__}") from None


def _broadcasts_to(shape: tuple[int, ...], target: tuple[int, ...]) -> bool:
    """Whether a tensor of ``shape`` expands to ``target`` (numpy broadcasting, no new dimensions in ``target``)."""
    return len(shape) <= len(target) and all(s in (1, t) for s, t in zip(reversed(shape), reversed(target)))


def check_rays(rays, where: str) -> None:
    """One-line `ConfigError` unless ``rays`` is a `Rays` (a BLAS's entry points call it: one
    isinstance); a `DeviceError` in a process forked after OpenMP work (`neuralrt.fork_guard`)."""
    if not isinstance(rays, Rays):
        raise ConfigError(f"{where}: expected neuralrt.Rays, got {type(rays).__name__}")
    check_not_forked(where)


@dataclass(eq=False)  # (as Rays)
class Hits:
    """Closest-hit records, one row per ray, on the rays' device; in the space of the rays that
    were asked (object space from a BLAS, world space from a scene). The hit point is derived, not
    stored: `position`.

    Fields (``N`` rays; the value on a miss in brackets):

    - ``hit`` [N] bool: the ray hit something in its interval.
    - ``t`` [N] float32: ray parameter of the hit, in units of the direction's length (inf).
    - ``normal`` [N, 3] float32: unit shading normal (zeros). An exact BLAS gives the mesh's own
      side (the winding's; not flipped towards the ray); a neural BLAS gives one facing the ray, as
      it was trained (one ray cannot tell a surface's outside: LSNIF returns its prediction, so an
      undertrained model may return some facing away; N-BVH flips its output). `face_forward`
      gives one convention from both.
    - ``geometric_normal`` [N, 3] float32: unit face normal, sides as ``normal``'s (zeros); a
      neural BLAS's is its ``normal``.
    - ``uv`` [N, 2] float32: texture coordinates (zeros; zeros where the mesh has none, and from
      a neural BLAS, which learns no UVs).
    - ``albedo`` [N, 3] float32 in [0, 1]: the surface's own colour factor at the hit (texture,
      vertex colour, or the value a neural model predicts; 1 where the surface has none); scene
      materials multiply it (ones).
    - ``material_id`` [N] int64: material slot, a BLAS's ``material_names`` index, or the scene's
      material table index from a scene (-1).
    - ``primitive_id`` [N] int64: triangle index (-1; -1 for neural hits too).
    - ``instance_id`` [N] int64: scene instance (-1; -1 outside a scene).

    Queries are not differentiable: no field carries a gradient to the rays or to a model's
    parameters (training uses its own loss, `neuralrt.training`).
    """

    hit: Mask
    t: Scalars
    normal: Vectors
    geometric_normal: Vectors
    uv: Annotated[Tensor, "[N, 2] float32"]
    albedo: Vectors
    material_id: Indices
    primitive_id: Indices
    instance_id: Indices

    def __repr__(self) -> str:  # (the dataclass's printed every tensor)
        return f"Hits({self.hit.shape[0]} rays, {int(self.hit.sum())} hit, {self.hit.device})"

    @staticmethod
    def empty(n: int, device=None) -> "Hits":
        """All-miss records for ``n`` rays."""
        check_count("n", n, minimum=0)
        dev = check_device(device) if device is not None else torch.device("cpu")
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

    @staticmethod
    def uninitialized(n: int, device=None) -> "Hits":
        """Records for ``n`` rays with unspecified contents (no fill), for a pass that writes every
        row, misses included; `empty`'s shapes and dtypes."""
        device = torch.device(device) if device is not None else torch.device("cpu")
        return Hits(**{name: torch.empty((n, *shape), dtype=dtype, device=device) for name, shape, dtype in _hit_columns()})

    def __len__(self) -> int:
        return self.t.shape[0]

    def position(self, rays: Rays) -> Tensor:
        """[N, 3] hit points ``origins + t * directions`` of the ``rays`` these hits answer (same
        space as the rays); NaN rows where the ray missed. No gradient, as the queries give none."""
        if len(rays) != len(self):
            raise ConfigError(f"position: {len(rays)} rays for {len(self)} hits (give the rays these hits answer)")
        # Detached: t holds no gradient (the queries are not differentiable), so one through the rays alone would be wrong.
        origins, directions = rays.origins.detach(), rays.directions.detach()
        return torch.where(self.hit[:, None], origins + torch.where(self.hit, self.t, 0.0)[:, None] * directions, float("nan"))

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
        """The hits on ``device`` (a new `Hits`; as `Rays.to`)."""
        device = check_device(device)
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


# Limits of an object-to-world transform's linear part, for float32 rendering: each scale factor
# (singular value) within [MIN_SCALE, MAX_SCALE] keeps squared lengths of mapped points and directions
# finite; a ratio of largest to smallest above 1 / float32 epsilon flattens an axis to nothing.
MIN_SCALE, MAX_SCALE = 1e-12, 1e12
MAX_CONDITION = 1.0 / float(np.finfo(np.float32).eps)


def _float64_matrix(matrix) -> np.ndarray | None:
    """``matrix`` as a float64 array, or None when it is not numbers (ragged rows, strings)."""
    if isinstance(matrix, Tensor):
        return matrix.detach().to("cpu", torch.float64).numpy()
    try:
        a = np.asarray(matrix)
    except (TypeError, ValueError, RuntimeError):  # ragged rows; tensors numpy cannot read (requires_grad)
        a = None
    if a is not None and a.dtype.kind in "biuf":
        return a.astype(np.float64)
    try:  # what numpy holds as objects, torch may read as numbers: ints beyond int64, a list of tensors
        return torch.as_tensor(matrix, dtype=torch.float64).numpy()
    except (TypeError, ValueError, RuntimeError, OverflowError):
        return None


def _vector(name: str, values, size: int = 3) -> np.ndarray:
    """``values`` as ``size`` float64 numbers (one number for all, where ``size`` allows), else a ConfigError."""
    v = _float64_matrix(values)
    if v is None or v.shape not in ((size,), ()):
        raise ConfigError(f"transform: {name} must be {size} numbers, got {values!r}")
    return np.broadcast_to(v, (size,)).copy()


def affine_problem(matrix) -> str | None:
    """What makes ``matrix`` (4x4, row-major) unusable as an object-to-world transform, or None:
    NaN/Inf entries, a bottom row other than ``[0, 0, 0, 1]``, or a singular or ill-conditioned
    3x3 part (see MIN_SCALE, MAX_SCALE, MAX_CONDITION)."""
    m = _float64_matrix(matrix)
    if m is None:
        return "matrix must be 4x4 numbers"
    if m.shape != (4, 4):
        return f"matrix must be 4x4, got {tuple(m.shape)}"
    if not np.isfinite(m).all():
        return "not a finite affine transform (NaN or Inf entries)"
    if np.abs(m[3] - _BOTTOM_ROW).max() > 1e-9:
        return f"not an affine transform: the bottom row must be [0, 0, 0, 1], got {[round(float(v), 6) for v in m[3]]}"
    sv = np.linalg.svd(m[:3, :3], compute_uv=False)
    lo, hi = float(sv[-1]), float(sv[0])
    if lo == 0:
        return "matrix is singular (a scale factor is 0: it flattens the object)"
    if hi / lo > MAX_CONDITION:
        return f"matrix is singular for float32 (scale factors {lo:.3g} .. {hi:.3g}: a ratio over {MAX_CONDITION:.3g})"
    if lo < MIN_SCALE or hi > MAX_SCALE:
        return f"scale factors {lo:.3g} .. {hi:.3g} are outside [{MIN_SCALE:g}, {MAX_SCALE:g}] (float32 would overflow)"
    if not _finite_in_float32(m):
        return "not a finite affine transform (entries overflow float32)"
    return None


_BOTTOM_ROW = np.array([0.0, 0.0, 0.0, 1.0])


# float32 rounds to its max below max + half an ulp (2**128 - 2**103, exact in float64); from there
# up, to Inf (the midpoint ties to the even 2**128).
_FLOAT32_ROUNDS_TO_INF = 2.0**128 - 2.0**103


def _finite_in_float32(m: np.ndarray) -> bool:
    return bool(np.abs(m).max() < _FLOAT32_ROUNDS_TO_INF)


def rotation_matrix(axis, degrees: float) -> np.ndarray:
    """3x3 float64 rotation by ``degrees`` about ``axis`` (right-handed)."""
    a = _vector("rotation axis", axis)
    length = np.linalg.norm(a)
    if not np.isfinite(length) or length == 0:
        raise ConfigError(f"transform: rotation axis must be a finite non-zero vector, got {axis!r}")
    x, y, z = a / length
    th = np.deg2rad(float(degrees))
    c, s = np.cos(th), np.sin(th)
    return np.array([
        [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
        [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
        [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
    ])


def _affine_inverse(m: np.ndarray) -> np.ndarray:
    """Inverse of an affine matrix; its bottom row stays exactly [0, 0, 0, 1]."""
    inv = np.eye(4)
    inv[:3, :3] = np.linalg.inv(m[:3, :3])
    inv[:3, 3] = -inv[:3, :3] @ m[:3, 3]
    return inv


class Transform:
    """Affine object-to-world transform held as a 4x4 matrix and its inverse.

    Points map by the full matrix, directions by its linear part (unnormalised, so a hit's ``t``
    is the same in both spaces), normals by the inverse transpose. A matrix that is not finite,
    not affine (bottom row ``[0, 0, 0, 1]``) or singular for float32 (`affine_problem`) raises
    `neuralrt.errors.ConfigError` (a ValueError).
    """

    # The float64 matrices are numpy: a scene of many objects composes and checks a few 4x4
    # matrices each, where torch's per-call overhead cost ~2 ms an object.
    def __init__(self, matrix=None, inverse=None):
        problem = None if matrix is None else affine_problem(matrix)
        if problem:
            raise ConfigError(f"transform: {problem}")
        m = np.eye(4) if matrix is None else _float64_matrix(matrix).copy()
        m[3] = _BOTTOM_ROW  # exact, so products and inverses stay affine
        self._m64 = m
        self._inv64 = _affine_inverse(m) if inverse is None else _float64_matrix(inverse).copy()
        if not _finite_in_float32(self._inv64):
            raise ConfigError("transform: not a finite affine transform (its inverse overflows float32)")
        self.matrix = torch.from_numpy(self._m64.astype(np.float32))
        self.inverse_matrix = torch.from_numpy(self._inv64.astype(np.float32))

    # -- construction ---------------------------------------------------------------------
    @staticmethod
    def identity() -> "Transform":
        return Transform()

    @staticmethod
    def translate(offset) -> "Transform":
        m = np.eye(4)
        m[:3, 3] = _vector("offset", offset)
        return Transform(m)

    @staticmethod
    def scale(factors) -> "Transform":
        return Transform(np.diag(np.append(_vector("scale factors", factors), 1.0)))

    @staticmethod
    def rotate(axis, degrees: float) -> "Transform":
        """Rotation by ``degrees`` about ``axis`` (right-handed)."""
        m = np.eye(4)
        m[:3, :3] = rotation_matrix(axis, degrees)
        return Transform(m)

    @staticmethod
    def translate_rotate_scale(offset, degrees_xyz, factors) -> "Transform":
        """Scale, then rotate about x, y and z (``degrees_xyz``, in that order), then translate: the
        scene file's transform, checked once (not once per factor)."""
        m = np.eye(4)
        rx, ry, rz = (rotation_matrix(axis, d) for axis, d in zip(np.eye(3), _vector("degrees", degrees_xyz)))
        m[:3, :3] = rz @ ry @ rx * _vector("scale factors", factors)
        m[:3, 3] = _vector("offset", offset)
        return Transform(m)

    @staticmethod
    def look_at(eye, target, up) -> "Transform":
        """Camera-to-world: camera looks down -z, +y up, +x right (OpenGL convention)."""
        eye, target, up = (_vector(name, v) for name, v in (("position", eye), ("target", target), ("up", up)))
        fwd = target - eye
        if np.linalg.norm(fwd) == 0:
            raise ConfigError("look_at: position and target coincide")
        fwd = fwd / np.linalg.norm(fwd)
        right = np.cross(fwd, up)
        if np.linalg.norm(right) < 1e-12:
            raise ConfigError("look_at: up vector is parallel to the view direction")
        right = right / np.linalg.norm(right)
        true_up = np.cross(right, fwd)
        m = np.eye(4)
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
        return Rays(self.apply_points(rays.origins), self.apply_vectors(rays.directions), rays.t_min, rays.t_max,
                    batch_shape=rays.batch_shape)

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self._m64, np.eye(4)))

    def tolist(self) -> list[list[float]]:
        return self._m64.tolist()

    def __repr__(self) -> str:
        return f"Transform({self._m64.tolist()})"


def pinhole_rays(
    width: int,
    height: int,
    fov_y_degrees: float,
    origin,
    look_at,
    up=(0.0, 1.0, 0.0),
    device="cpu",
) -> Rays:
    """Camera rays through the centre of every pixel of a ``width`` x ``height`` pinhole image.

    The camera sits at ``origin`` looking at ``look_at`` with ``up`` towards the image top and a
    vertical field of view of ``fov_y_degrees`` (the same camera as scene files'). Returns
    ``H * W`` rays in row-major pixel order (pixel ``(x, y)`` is ray ``y * W + x``, row 0 at the
    top) with unit directions, so a hit's ``t`` is its distance; ``batch_shape`` is ``(H, W)``,
    e.g. ``hits.t.reshape(rays.batch_shape)`` is a depth image. cf. Open3D's ``create_rays_pinhole``.
    """
    from .render.camera import Camera

    width, height = check_count("pinhole_rays: width", width), check_count("pinhole_rays: height", height)
    if isinstance(fov_y_degrees, bool) or not isinstance(fov_y_degrees, (int, float, np.number)) or not 0 < fov_y_degrees < 180:
        raise ConfigError(f"pinhole_rays: need width, height >= 1 and 0 < fov < 180, got {width}x{height}, fov {fov_y_degrees!r}")
    origin, look_at, up = (_point(name, v) for name, v in (("origin", origin), ("look_at", look_at), ("up", up)))
    dev = check_device(device)
    camera = Camera.look_at(origin, look_at, up, fov_y_degrees, (int(width), int(height)))
    pixels = torch.arange(width * height, device=dev)
    rays = camera.generate_rays(pixels, torch.full((width * height, 2), 0.5, device=dev))
    return replace(rays, batch_shape=(height, width))


def _point(name: str, value) -> tuple[float, float, float]:
    """``value`` as three finite floats; a one-line `ConfigError` naming ``name`` otherwise."""
    try:
        xyz = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        xyz = None
    if xyz is None or xyz.shape != (3,) or not np.isfinite(xyz).all():
        raise ConfigError(f"pinhole_rays: {name} must be three finite numbers (x, y, z), got {value!r}")
    return tuple(float(v) for v in xyz)


@functools.cache
def _hit_columns() -> tuple[tuple[str, tuple[int, ...], torch.dtype], ...]:
    """Each `Hits` field's name, shape after the ray axis and dtype, as `Hits.empty` makes them."""
    template = Hits.empty(0)
    return tuple((f.name, tuple(getattr(template, f.name).shape[1:]), getattr(template, f.name).dtype) for f in fields(Hits))

"""LSNIF ray featurization: the points where a ray crosses the boundaries of occupied voxels.

A ray (in unit-box coordinates, the object's inflated AABB mapped to ``[0, 1]^3``) is clipped to
the box and walked through the ``V^3`` voxel grid in ray order (3D-DDA, Amanatides & Woo 1987).
For every occupied voxel it passes through, its entry and exit points on the voxel boundary are
kept, up to ``max_points`` (H, paper default 18); the rest of the rows are padding.

Decisions (documented here because the model and its tests rely on them):

- **Shared boundary points are kept once** (``share_boundary_points=True``): where the ray goes
  from one occupied voxel straight into the next, the exit of the first *is* the entry of the
  second, so the point is stored once. The duplicate carries no information and would waste a
  slot; with sharing, H points cover up to H-1 consecutive occupied voxels instead of H/2.
  ``share_boundary_points=False`` gives the literal two-points-per-voxel variant.
- **Rays starting inside the box** (e.g. secondary rays from the surface, pitfall 2) go through
  the same walk, from ``t = 0``. If the start voxel is occupied, the ray's origin is its first
  point, with ``face_axis == ORIGIN_POINT`` (3): it is not on a voxel face, so the encoder
  interpolates it trilinearly from its 8 grid vertices. The origin tells the network where along
  the ray the walk starts, which the local hit distance is measured from, and separates "starts
  here" from "passes through here". ``origin_point=False`` instead drops the start voxel's entry
  and keeps only its exit point (a face point). A start voxel that is empty adds nothing.
- **Face points are snapped** exactly onto the crossed voxel plane ``k / V`` and the other two
  coordinates are clamped to the voxel's face, so ``floor``/``round`` in the encoder pick the
  right cell (pitfall 3). Crossing times are computed directly from the plane equation (never
  accumulated), so the kernel and the reference agree to the last bit on plane times.
- Rays that cross no occupied voxel get ``count == 0``: with conservative voxelization they are
  certain misses, and the model skips its network for them (pitfall 6).

`featurize_rays` has two implementations with this one contract, chosen once by the rays'
device: `featurize_rays_numba` (CPU, parallel over rays) and `featurize_rays_triton` (CUDA, in
`lsnif_features_triton`, the same float64 walk as a Triton kernel; no host round trips).
`featurize_rays_reference` is a slow, per-ray implementation written from the definition (sort
every plane crossing, look up the voxel at each segment's midpoint) that the tests compare both
kernels against.

`unit_box_rays` maps valid object-space rays into the unit box before the walk (one numba pass on
the CPU, torch ops elsewhere). `select_network_rays` then keeps the rays with points (the ones the network sees) and, if asked,
each point's distance along the ray (`point_local_distances`): one numba pass on the CPU instead
of a gather per field and a chain of torch ops; torch ops elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numba
import numpy as np
import torch
from torch import Tensor

from ..rays import Rays, valid_ray_mask
from ..rays_kernels import valid_ray
from ..task_queue import take_task, task_count, task_workers

__all__ = [
    "RayFeaturePoints",
    "featurize_rays",
    "featurize_rays_numba",
    "featurize_rays_reference",
    "point_local_distances",
    "select_network_rays",
    "select_network_rows",
    "select_network_rows_numba",
    "select_network_rows_torch",
    "select_network_rays_numba",
    "select_network_rays_torch",
    "unit_box_rays",
    "unit_box_rays_numba",
    "unit_box_rays_torch",
    "PADDING",
    "ORIGIN_POINT",
]

PADDING = -1  # face_axis of an unused row (its point is 0)
ORIGIN_POINT = 3  # face_axis of a ray origin inside an occupied voxel (interpolated trilinearly)


@dataclass
class RayFeaturePoints:
    """Per-ray voxel-boundary points, in ray order, left-packed (valid rows first)."""

    points: Tensor  # [N, H, 3] float32, unit-box coordinates; padding rows = 0
    face_axis: Tensor  # [N, H] int8: 0/1/2 face normal axis, ORIGIN_POINT (3), PADDING (-1)
    count: Tensor  # [N] int32, number of valid rows (<= H)
    truncated: Tensor  # [N] bool, the ray had more than H points (those past H are dropped)
    t_enter: Tensor  # [N] float32, ray parameter where the walk starts (box entry, >= 0); inf on box miss
    t_exit: Tensor  # [N] float32, ray parameter of the box exit; inf on box miss

    def __len__(self) -> int:
        return self.count.shape[0]

    @property
    def max_points(self) -> int:
        return self.points.shape[1]

    def __getitem__(self, index) -> "RayFeaturePoints":
        """Select rays by boolean mask or index tensor."""
        return RayFeaturePoints(*(getattr(self, f.name)[index] for f in fields(self)))

    def to(self, device) -> "RayFeaturePoints":
        return RayFeaturePoints(*(getattr(self, f.name).to(device) for f in fields(self)))


# ---------------------------------------------------------------------------------------------
# Fast path: numba 3D-DDA, parallel over chunks of rays.


@numba.njit(cache=True, inline="always")
def _coord(on_plane, exiting, o, d, t, i, s, planes):
    """One coordinate of a point in voxel ``i``: the crossed plane itself, or clamped to the voxel."""
    lo = planes[i]
    hi = planes[i + 1]
    if on_plane:
        # The exit plane is ahead of the voxel (in the step direction s), the entry plane behind.
        return hi if (s > 0) == exiting else lo
    return min(max(o + t * d, lo), hi)


@numba.njit(cache=True, inline="always")
def _emit(pts, axes, n, count, max_points, t, code, exiting,
          ox, oy, oz, dx, dy, dz, ix, iy, iz, sx, sy, sz, planes):  # fmt: skip
    """Write one point; returns the new count, or -1 when the ray already has H points."""
    if count == max_points:
        return -1
    pts[n, count, 0] = _coord(code == 0, exiting, ox, dx, t, ix, sx, planes)
    pts[n, count, 1] = _coord(code == 1, exiting, oy, dy, t, iy, sy, planes)
    pts[n, count, 2] = _coord(code == 2, exiting, oz, dz, t, iz, sz, planes)
    axes[n, count] = code
    return count + 1


@numba.njit(cache=True, inline="always")
def _slab(o, d):
    """Per-axis (step, 1/d, t_near, t_far, ok) of the slab [0, 1] (same formulas as the reference)."""
    if d == 0.0:
        return 0, 0.0, -np.inf, np.inf, 0.0 <= o <= 1.0
    inv = 1.0 / d
    ta = (0.0 - o) * inv
    tb = (1.0 - o) * inv
    return (1 if d > 0.0 else -1), inv, min(ta, tb), max(ta, tb), True


@numba.njit(cache=True, inline="always")
def _start_index(o, d, t, s, res, on_entry_face):
    """Voxel index along one axis where the walk begins, biased against the direction on a plane."""
    if on_entry_face:
        return 0 if s > 0 else res - 1
    f = (o + t * d) * res
    i = int(np.floor(f))
    if s < 0 and f == i:
        i -= 1
    return min(max(i, 0), res - 1)


@numba.njit(cache=True, inline="always")
def _plane_time(o, inv, i, s, planes):
    """Ray time of the next plane crossing from voxel ``i`` stepping ``s`` (inf when s == 0)."""
    if s == 0:
        return np.inf
    return (planes[i + 1 if s > 0 else i] - o) * inv


@numba.njit(cache=True, inline="always")
def walk_ray(ox, oy, oz, dx, dy, dz, occ, planes, max_points, origin_point, share, pts, axes, row):
    """The voxel DDA of one ray (float64 scalars, unit box), writing its points into ``pts[row]`` /
    ``axes[row]``. Returns (count, truncated, t_enter, t_exit); rays that miss the box or are not
    valid give (0, False, inf, inf). Shared by `featurize_rays_numba` and the fused CPU pass."""
    # Scalars rather than small arrays throughout: they stay in registers (2-3x faster).
    inf = np.inf
    res = occ.shape[0]
    if not (np.isfinite(ox + oy + oz + dx + dy + dz)) or (dx == 0.0 and dy == 0.0 and dz == 0.0):
        return 0, False, inf, inf
    sx, inv_x, nx, fx, okx = _slab(ox, dx)
    sy, inv_y, ny, fy, oky = _slab(oy, dy)
    sz, inv_z, nz, fz, okz = _slab(oz, dz)
    if not (okx and oky and okz):
        return 0, False, inf, inf
    # Entry: the last slab entered (first axis on ties); exit: the first slab left.
    t_near, near_axis = nx, 0
    if ny > t_near:
        t_near, near_axis = ny, 1
    if nz > t_near:
        t_near, near_axis = nz, 2
    t_far = min(fx, min(fy, fz))
    inside = t_near < 0.0
    t_cur = 0.0 if inside else t_near
    if not t_cur < t_far:
        return 0, False, inf, inf
    t_start = t_cur
    ix = _start_index(ox, dx, t_cur, sx, res, not inside and near_axis == 0)
    iy = _start_index(oy, dy, t_cur, sy, res, not inside and near_axis == 1)
    iz = _start_index(oz, dz, t_cur, sz, res, not inside and near_axis == 2)
    # Next plane time per axis, always from the plane equation (never accumulated, so the
    # reference reproduces it exactly); only the stepped axis is recomputed.
    tx = _plane_time(ox, inv_x, ix, sx, planes)
    ty = _plane_time(oy, inv_y, iy, sy, planes)
    tz = _plane_time(oz, inv_z, iz, sz, planes)
    entry_code = ORIGIN_POINT if inside else near_axis
    count = 0
    last_t = -inf
    while True:
        # Closest plane; strict < so ties go to the lower axis, as in the reference.
        if ty < tx:
            axis, t_next = (2, tz) if tz < ty else (1, ty)
        else:
            axis, t_next = (2, tz) if tz < tx else (0, tx)
        if t_next == inf:  # plane times overflowed (denormal direction): nothing to walk
            break
        t_next = max(t_next, t_cur)  # rounding at the start can put a plane behind us
        if occ[ix, iy, iz] and t_next > t_cur:
            skip_entry = (share and t_cur == last_t) or (entry_code == ORIGIN_POINT and not origin_point)
            if not skip_entry:
                count = _emit(pts, axes, row, count, max_points, t_cur, entry_code, False,
                              ox, oy, oz, dx, dy, dz, ix, iy, iz, sx, sy, sz, planes)  # fmt: skip
                if count < 0:
                    break
            count = _emit(pts, axes, row, count, max_points, t_next, axis, True,
                          ox, oy, oz, dx, dy, dz, ix, iy, iz, sx, sy, sz, planes)  # fmt: skip
            if count < 0:
                break
            last_t = t_next
        if axis == 0:
            ix += sx
            if ix < 0 or ix >= res:
                break
            tx = _plane_time(ox, inv_x, ix, sx, planes)
        elif axis == 1:
            iy += sy
            if iy < 0 or iy >= res:
                break
            ty = _plane_time(oy, inv_y, iy, sy, planes)
        else:
            iz += sz
            if iz < 0 or iz >= res:
                break
            tz = _plane_time(oz, inv_z, iz, sz, planes)
        t_cur = t_next
        entry_code = axis
    if count < 0:
        return max_points, True, t_start, t_far
    return count, False, t_start, t_far



@numba.njit(parallel=True, cache=True, nogil=True)
def _featurize_kernel(
    origins, directions, occ, planes, max_points, origin_point, share, n_chunks, n_workers,
    pts, axes, counts, truncated, t_enter, t_exit,
):  # fmt: skip
    n_rays = origins.shape[0]
    next_chunk = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):  # chunks handed out one at a time (`task_queue`)
        while True:
            chunk = take_task(next_chunk)
            if chunk >= n_chunks:
                break
            for n in range(chunk * n_rays // n_chunks, (chunk + 1) * n_rays // n_chunks):
                count, cut, t0, t1 = walk_ray(
                    origins[n, 0], origins[n, 1], origins[n, 2], directions[n, 0], directions[n, 1], directions[n, 2],
                    occ, planes, max_points, origin_point, share, pts, axes, n)  # fmt: skip
                counts[n] = count
                truncated[n] = cut
                t_enter[n] = t0
                t_exit[n] = t1


def _as_occupancy(occupancy) -> np.ndarray:
    occ = occupancy.detach().cpu().numpy() if isinstance(occupancy, Tensor) else np.asarray(occupancy)
    if occ.ndim != 3 or len(set(occ.shape)) != 1:
        raise ValueError(f"occupancy must be a cubic [V, V, V] array, got shape {occ.shape}")
    return np.ascontiguousarray(occ, dtype=np.uint8)


def _host_feature_arrays(n: int, max_points: int, padded: bool) -> tuple[np.ndarray, ...]:
    """Host arrays for the CPU kernels to fill, in `RayFeaturePoints`' field order: points,
    face codes, counts, truncated, t_enter, t_exit. ``padded``: points zero and codes PADDING
    beforehand (else the kernel writes every row)."""
    if padded:
        pts, axes = np.zeros((n, max_points, 3), np.float32), np.full((n, max_points), PADDING, np.int8)
    else:
        pts, axes = np.empty((n, max_points, 3), np.float32), np.empty((n, max_points), np.int8)
    return pts, axes, np.empty(n, np.int32), np.empty(n, np.bool_), np.empty(n, np.float32), np.empty(n, np.float32)


def _feature_points_on(arrays: tuple[np.ndarray, ...], device) -> RayFeaturePoints:
    """`_host_feature_arrays` once filled, as `RayFeaturePoints` on ``device``."""
    return RayFeaturePoints(*(torch.from_numpy(a).to(device) for a in arrays))


def _check_rays(origins: Tensor, directions: Tensor, max_points: int) -> None:
    if origins.ndim != 2 or origins.shape[-1] != 3 or directions.shape != origins.shape:
        raise ValueError(
            f"origins and directions must both be [N, 3], got {tuple(origins.shape)} and "
            f"{tuple(directions.shape)}"
        )
    if max_points < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")


def featurize_rays(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor | np.ndarray,
    max_points: int = 18,
    *,
    origin_point: bool = True,
    share_boundary_points: bool = True,
) -> RayFeaturePoints:
    """Occupied-voxel boundary points of rays ``origin + t * direction``, ``t >= 0``, in ray order.

    ``origins``/``directions``: ``[N, 3]`` in unit-box coordinates (directions need not be
    normalised; zero/NaN directions give ``count == 0``). ``occupancy``: bool ``[V, V, V]``
    indexed ``[x, y, z]`` (a tensor on the rays' device avoids a copy). The walk runs in float64;
    results are on the device of ``origins``. CUDA rays run the Triton kernel
    (`featurize_rays_triton`), others the numba kernel (`featurize_rays_numba`).
    """
    _check_rays(origins, directions, max_points)
    if origins.device.type == "cuda":
        from .lsnif_features_triton import featurize_rays_triton as implementation
    else:
        implementation = featurize_rays_numba
    return implementation(origins, directions, occupancy, max_points,
                          origin_point=origin_point, share_boundary_points=share_boundary_points)  # fmt: skip


def featurize_rays_numba(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor | np.ndarray,
    max_points: int = 18,
    *,
    origin_point: bool = True,
    share_boundary_points: bool = True,
) -> RayFeaturePoints:
    """`featurize_rays` on the CPU (numba, parallel over rays); results go back to the rays' device."""
    _check_rays(origins, directions, max_points)
    device = origins.device
    o = origins.detach().to("cpu", torch.float64).contiguous().numpy()
    d = directions.detach().to("cpu", torch.float64).contiguous().numpy()
    occ = _as_occupancy(occupancy)
    n = o.shape[0]
    arrays = _host_feature_arrays(n, max_points, padded=True)
    # A few chunks per thread, handed out one at a time, balance rays of uneven length.
    n_chunks = task_count(n)
    if n:
        planes = np.arange(occ.shape[0] + 1) / occ.shape[0]  # k / V, as the reference computes it
        _featurize_kernel(o, d, occ, planes, int(max_points), bool(origin_point),
                          bool(share_boundary_points), n_chunks, task_workers(n_chunks), *arrays)  # fmt: skip
    return _feature_points_on(arrays, device)


# ---------------------------------------------------------------------------------------------
# Reference: per ray, from the definition. Slow; for tests only.


def featurize_rays_reference(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor | np.ndarray,
    max_points: int = 18,
    *,
    origin_point: bool = True,
    share_boundary_points: bool = True,
) -> RayFeaturePoints:
    """Same result as `featurize_rays`, computed by sorting all plane crossings of each ray."""
    _check_rays(origins, directions, max_points)
    occ = _as_occupancy(occupancy).astype(bool)
    res = occ.shape[0]
    o_all = origins.detach().cpu().double().numpy()
    d_all = directions.detach().cpu().double().numpy()
    n = len(o_all)
    out = RayFeaturePoints(
        torch.zeros(n, max_points, 3),
        torch.full((n, max_points), PADDING, dtype=torch.int8),
        torch.zeros(n, dtype=torch.int32),
        torch.zeros(n, dtype=torch.bool),
        torch.full((n,), float("inf")),
        torch.full((n,), float("inf")),
    )
    for r in range(n):
        o, d = o_all[r], d_all[r]
        if not (np.isfinite(o).all() and np.isfinite(d).all() and (d != 0).any()):
            continue
        if any(d[c] == 0 and not 0 <= o[c] <= 1 for c in range(3)):
            continue
        moving = [c for c in range(3) if d[c] != 0]
        inv = {c: 1.0 / d[c] for c in moving}  # the kernel multiplies by 1/d too: same rounding
        near = {c: min((0.0 - o[c]) * inv[c], (1.0 - o[c]) * inv[c]) for c in moving}
        far = {c: max((0.0 - o[c]) * inv[c], (1.0 - o[c]) * inv[c]) for c in moving}
        near_axis = max(moving, key=lambda c: (near[c], -c))  # first axis on ties
        far_axis = min(moving, key=lambda c: (far[c], c))
        inside = near[near_axis] < 0
        t0, t1 = (0.0 if inside else near[near_axis]), far[far_axis]
        if not t0 < t1:
            continue
        out.t_enter[r], out.t_exit[r] = t0, t1
        crossings = sorted(
            (t, c)
            for c in moving
            for k in range(res + 1)
            if t0 < (t := (k / res - o[c]) * inv[c]) < t1
        )
        bounds = [(t0, ORIGIN_POINT if inside else near_axis), *crossings, (t1, far_axis)]
        points: list[tuple[float, np.ndarray, int]] = []  # (t, point, face_axis)
        for (ta, code_a), (tb, code_b) in zip(bounds, bounds[1:]):
            if not tb > ta:
                continue
            voxel = np.clip(np.floor((o + 0.5 * (ta + tb) * d) * res), 0, res - 1).astype(int)
            if not occ[tuple(voxel)]:
                continue
            lo, hi = voxel / res, (voxel + 1) / res
            shared = share_boundary_points and points and points[-1][0] == ta
            dropped_origin = code_a == ORIGIN_POINT and not origin_point
            for t, code, exiting in ((ta, code_a, False), (tb, code_b, True)):
                if not exiting and (shared or dropped_origin):
                    continue
                p = np.clip(o + t * d, lo, hi)
                if code != ORIGIN_POINT:
                    p[code] = hi[code] if (d[code] > 0) == exiting else lo[code]
                points.append((t, p, code))
        kept = points[:max_points]
        out.count[r] = len(kept)
        out.truncated[r] = len(points) > max_points
        for h, (_, p, code) in enumerate(kept):
            out.points[r, h] = torch.from_numpy(p.astype(np.float32))
            out.face_axis[r, h] = code
    return out.to(origins.device)


# ---------------------------------------------------------------------------------------------
# The rays that reach the network.


# Floor of a ray's box interval (t_exit - t_enter) before dividing by it: only a zero one needs it.
# t counts direction lengths, which are arbitrary (instance transforms scale them by up to 1e12), so
# an absolute floor such as 1e-12 clipped real intervals of long directions: float32's smallest
# normal number, in every implementation (numba, SIMD, Triton, the loss).
MIN_SPAN = float(np.finfo(np.float32).tiny)


def point_local_distances(fp: RayFeaturePoints, origins: Tensor, directions: Tensor) -> Tensor:
    """[M, H] each point's ray parameter as a fraction of the ray's box interval (0 for padding)."""
    t = ((fp.points - origins[:, None]) * directions[:, None]).sum(-1) / (directions * directions).sum(-1, keepdim=True)
    span = (fp.t_exit - fp.t_enter).clamp(min=MIN_SPAN)
    local = ((t - fp.t_enter[:, None]) / span[:, None]).clamp(0, 1)
    return torch.where(fp.face_axis >= 0, local, torch.zeros_like(local))


@numba.njit(cache=True, inline="always", error_model="numpy")
def local_distance(px, py, pz, ox, oy, oz, dx, dy, dz, te, tx):
    """`point_local_distances` of one point (float32 scalars) in torch's float32 operations."""
    dd = dx * dx + dy * dy + dz * dz
    span = max(tx - te, np.float32(MIN_SPAN))
    t = ((px - ox) * dx + (py - oy) * dy + (pz - oz) * dz) / dd
    return min(max((t - te) / span, np.float32(0.0)), np.float32(1.0))


@numba.njit(cache=True, inline="always", error_model="numpy")
def _local_distances(pts, axes, n, ox, oy, oz, dx, dy, dz, te, tx, out_distances, m):
    """``out_distances[m]``: `point_local_distances` of ray n's points in torch's float32 operations."""
    for h in range(axes.shape[1]):
        if axes[n, h] < 0:
            out_distances[m, h] = np.float32(0.0)
            continue
        out_distances[m, h] = local_distance(pts[n, h, 0], pts[n, h, 1], pts[n, h, 2], ox, oy, oz, dx, dy, dz, te, tx)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _select_kernel(pts, axes, counts, truncated, t_enter, t_exit, origins, directions, point_distances,
                   keep, out_pts, out_axes, out_counts, out_truncated, out_t_enter, out_t_exit, out_origins,
                   out_directions, out_distances):  # fmt: skip
    """Rows with ``counts > 0`` copied in order into the ``out_*`` arrays (sized by the caller),
    with `point_local_distances` in the same float32 operations as torch's."""
    m = 0
    for n in range(counts.shape[0]):
        if counts[n] <= 0:
            continue
        keep[m] = n
        out_pts[m] = pts[n]
        out_axes[m] = axes[n]
        out_counts[m], out_truncated[m] = counts[n], truncated[n]
        te, tx = t_enter[n], t_exit[n]
        out_t_enter[m], out_t_exit[m] = te, tx
        ox, oy, oz = origins[n, 0], origins[n, 1], origins[n, 2]
        dx, dy, dz = directions[n, 0], directions[n, 1], directions[n, 2]
        out_origins[m, 0], out_origins[m, 1], out_origins[m, 2] = ox, oy, oz
        out_directions[m, 0], out_directions[m, 1], out_directions[m, 2] = dx, dy, dz
        if point_distances:
            _local_distances(pts, axes, n, ox, oy, oz, dx, dy, dz, te, tx, out_distances, m)
        m += 1


def select_network_rays(fp: RayFeaturePoints, origins: Tensor, directions: Tensor, point_distances: bool):
    """The rays with at least one point, which the network answers: ``(keep [M] long, their
    RayFeaturePoints, origins [M, 3], directions [M, 3], distances [M, H] or None)``, where
    ``distances`` is `point_local_distances` (asked for by ``point_distances``). On the CPU one
    numba pass (`select_network_rays_numba`), elsewhere torch ops (`select_network_rays_torch`)."""
    implementation = select_network_rays_numba if origins.device.type == "cpu" else select_network_rays_torch
    return implementation(fp, origins, directions, point_distances)


def select_network_rays_torch(fp: RayFeaturePoints, origins: Tensor, directions: Tensor, point_distances: bool):
    """`select_network_rays` as torch ops (any device)."""
    keep = torch.nonzero(fp.count > 0).squeeze(1)
    kept, o, d = fp[keep], origins[keep], directions[keep]
    return keep, kept, o, d, point_local_distances(kept, o, d) if point_distances else None


def select_network_rays_numba(fp: RayFeaturePoints, origins: Tensor, directions: Tensor, point_distances: bool):
    """`select_network_rays` on CPU tensors: one numba pass, in torch's float32 operations."""
    counts = fp.count.numpy()
    m, h = int(np.count_nonzero(counts > 0)), fp.max_points
    keep = np.empty(m, np.int64)
    out = RayFeaturePoints(np.empty((m, h, 3), np.float32), np.empty((m, h), np.int8), np.empty(m, np.int32),
                           np.empty(m, np.bool_), np.empty(m, np.float32), np.empty(m, np.float32))  # fmt: skip
    o, d = np.empty((m, 3), np.float32), np.empty((m, 3), np.float32)
    distances = np.empty((m, h) if point_distances else (0, h), np.float32)
    _select_kernel(*(getattr(fp, f.name).numpy() for f in fields(fp)), origins.detach().contiguous().numpy(),
                   directions.detach().contiguous().numpy(), bool(point_distances), keep,
                   *(getattr(out, f.name) for f in fields(out)), o, d, distances)  # fmt: skip
    kept = RayFeaturePoints(*(torch.from_numpy(getattr(out, f.name)) for f in fields(out)))
    return (torch.from_numpy(keep), kept, torch.from_numpy(o), torch.from_numpy(d),
            torch.from_numpy(distances) if point_distances else None)  # fmt: skip


@numba.njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _network_rows_kernel(pts, axes, counts, t_enter, t_exit, origins, directions, point_distances, n_blocks,
                         keep, out_t_enter, out_t_exit, out_distances):  # fmt: skip
    """`_select_kernel` without the copies: the index of the rows with ``counts > 0``, their box
    interval and `point_local_distances` (same float32 operations); in ``n_blocks`` blocks of rows
    in parallel, each block's kept rows counted first (`_unit_box_kernel`'s scheme)."""
    n_rows = counts.shape[0]
    starts = np.zeros(n_blocks + 1, np.int64)
    for block in numba.prange(n_blocks):
        kept = 0
        for n in range(block * n_rows // n_blocks, (block + 1) * n_rows // n_blocks):
            kept += counts[n] > 0
        starts[block + 1] = kept
    for block in range(n_blocks):
        starts[block + 1] += starts[block]
    for block in numba.prange(n_blocks):
        m = starts[block]
        for n in range(block * n_rows // n_blocks, (block + 1) * n_rows // n_blocks):
            if counts[n] <= 0:
                continue
            keep[m] = n
            te, tx = t_enter[n], t_exit[n]
            out_t_enter[m], out_t_exit[m] = te, tx
            if point_distances:
                _local_distances(pts, axes, n, origins[n, 0], origins[n, 1], origins[n, 2], directions[n, 0],
                                 directions[n, 1], directions[n, 2], te, tx, out_distances, m)  # fmt: skip
            m += 1


def select_network_rows(fp: RayFeaturePoints, origins: Tensor, directions: Tensor, point_distances: bool):
    """`select_network_rays` for a caller that reads the points through the index (the encoder's
    ``rows``): ``(keep [M] long, t_enter [M], t_exit [M], distances [M, H] or None)``, no copy of
    the point arrays. One numba pass on the CPU (`select_network_rows_numba`), torch ops elsewhere
    (`select_network_rows_torch`)."""
    implementation = select_network_rows_numba if origins.device.type == "cpu" else select_network_rows_torch
    return implementation(fp, origins, directions, point_distances)


def select_network_rows_torch(fp: RayFeaturePoints, origins: Tensor, directions: Tensor, point_distances: bool):
    """`select_network_rows` as torch ops (any device)."""
    keep, kept, o, d, distances = select_network_rays_torch(fp, origins, directions, point_distances)
    return keep, kept.t_enter, kept.t_exit, distances


def select_network_rows_numba(fp: RayFeaturePoints, origins: Tensor, directions: Tensor, point_distances: bool):
    """`select_network_rows` on CPU tensors: one numba pass, in torch's float32 operations."""
    counts = fp.count.numpy()
    m, h = int(np.count_nonzero(counts > 0)), fp.max_points
    keep, t_enter, t_exit = np.empty(m, np.int64), np.empty(m, np.float32), np.empty(m, np.float32)
    distances = np.empty((m, h) if point_distances else (0, h), np.float32)
    n_blocks = max(1, min(4 * numba.get_num_threads(), len(counts) // 1024))  # blocks of at least 1024 rows
    _network_rows_kernel(fp.points.numpy(), fp.face_axis.numpy(), counts, fp.t_enter.numpy(), fp.t_exit.numpy(),
                         origins.detach().contiguous().numpy(), directions.detach().contiguous().numpy(), bool(point_distances),
                         n_blocks, keep, t_enter, t_exit, distances)  # fmt: skip
    return (torch.from_numpy(keep), torch.from_numpy(t_enter), torch.from_numpy(t_exit),
            torch.from_numpy(distances) if point_distances else None)  # fmt: skip


@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def unit_box_ray(origins, directions, t_min, box_lo, box_extent, n, m, out_origins, out_directions):
    """Ray ``n`` as unit-box ray ``m`` of ``out_origins``/``out_directions``: its origin moved to a
    positive finite ``t_min`` and mapped by ``(p - box_lo) / box_extent``, its direction divided by
    ``box_extent``; returns the ``t_min`` shift. The same float32 operations as `unit_box_rays`'s
    torch path."""
    zero = np.float32(0.0)
    ox, oy, oz = origins[n, 0], origins[n, 1], origins[n, 2]
    dx, dy, dz = directions[n, 0], directions[n, 1], directions[n, 2]
    t = t_min[n]
    t = t if (np.isfinite(t) and t > zero) else zero
    out_origins[m, 0] = ((ox + t * dx) - box_lo[0]) / box_extent[0]
    out_origins[m, 1] = ((oy + t * dy) - box_lo[1]) / box_extent[1]
    out_origins[m, 2] = ((oz + t * dz) - box_lo[2]) / box_extent[2]
    out_directions[m, 0] = dx / box_extent[0]
    out_directions[m, 1] = dy / box_extent[1]
    out_directions[m, 2] = dz / box_extent[2]
    return t


@numba.njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _unit_box_kernel(origins, directions, t_min, t_max, box_lo, box_extent, n_blocks, index, out_origins, out_directions,
                     t_offset) -> int:  # fmt: skip
    """`unit_box_ray` of the valid rays (as `neuralrt.rays.valid_ray_mask`), in order, in
    ``n_blocks`` blocks of rays in parallel (each block's valid rays counted first, so each knows
    where its rows start). Returns how many."""
    n = origins.shape[0]
    starts = np.zeros(n_blocks + 1, np.int64)
    for block in numba.prange(n_blocks):
        valid = 0
        for i in range(block * n // n_blocks, (block + 1) * n // n_blocks):
            valid += valid_ray(origins, directions, t_min, t_max, i)
        starts[block + 1] = valid
    for block in range(n_blocks):
        starts[block + 1] += starts[block]
    for block in numba.prange(n_blocks):
        m = starts[block]
        for i in range(block * n // n_blocks, (block + 1) * n // n_blocks):
            if valid_ray(origins, directions, t_min, t_max, i):
                index[m] = i
                t_offset[m] = unit_box_ray(origins, directions, t_min, box_lo, box_extent, i, m, out_origins, out_directions)
                m += 1
    return starts[n_blocks]


def unit_box_rays(rays: Rays, box_lo: Tensor, box_extent: Tensor):
    """The valid rays (`neuralrt.rays.valid_ray_mask`) mapped into the unit box: ``(index [K] long,
    origins [K, 3], directions [K, 3], t_offset [K])``, where each origin is first moved to the
    ray's ``t_min`` when that is positive and finite (``t_offset``; t is unchanged by the map
    ``(p - box_lo) / box_extent``). One numba pass on the CPU (`unit_box_rays_numba`), torch ops
    elsewhere (`unit_box_rays_torch`)."""
    cpu = rays.device.type == "cpu" and box_lo.dtype == torch.float32
    return (unit_box_rays_numba if cpu else unit_box_rays_torch)(rays, box_lo, box_extent)


def unit_box_rays_torch(rays: Rays, box_lo: Tensor, box_extent: Tensor):
    """`unit_box_rays` as torch ops (any device)."""
    t_min = rays.t_min
    t_off = torch.where(torch.isfinite(t_min) & (t_min > 0), t_min, torch.zeros_like(t_min))
    idx = torch.nonzero(valid_ray_mask(rays)).squeeze(1)
    o, d, t_off = rays.origins[idx], rays.directions[idx], t_off[idx]
    return idx, ((o + t_off[:, None] * d - box_lo) / box_extent).contiguous(), (d / box_extent).contiguous(), t_off


def unit_box_rays_numba(rays: Rays, box_lo: Tensor, box_extent: Tensor):
    """`unit_box_rays` on float32 CPU tensors: a parallel numba pass, in torch's float32 operations."""
    n = len(rays)
    index, t_offset = np.empty(n, np.int64), np.empty(n, np.float32)
    o, d = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    arrays = (x.detach().contiguous().numpy() for x in (rays.origins, rays.directions, rays.t_min, rays.t_max, box_lo, box_extent))
    n_blocks = max(1, min(4 * numba.get_num_threads(), n // 4096))  # blocks of at least 4096 rays
    m = _unit_box_kernel(*arrays, n_blocks, index, o, d, t_offset)
    return torch.from_numpy(index[:m]), torch.from_numpy(o[:m]), torch.from_numpy(d[:m]), torch.from_numpy(t_offset[:m])

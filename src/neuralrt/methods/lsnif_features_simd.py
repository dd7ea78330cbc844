"""`featurize_rays` from the 16-lane float32 walk (`lsnif_walk_simd`): the points the fused CPU pass
encodes, as `RayFeaturePoints` in ray order, for training on the points inference will see.

The same counts, truncation, face codes and intervals as `featurize_rays_numba`'s float64 walk
(`walk_ray`), and points on the same planes; the other two coordinates of a point are computed in
float32, within ``2^-21 * (2 + |o|)`` of the float64 walk's (`lsnif_walk_simd`'s docstring; tested).
Where it applies (`applies`: numba compiles for AVX-512 and V is a power of two) the walk takes
about a third of the float64 walk's time.

Models trained on these points and on the float64 walk's score alike (`benchmarks/
bench_training_seeds.py`: sphere, 150 steps, seeds 0-15, median distance error 0.80-0.96% against
0.80-0.95% of the diagonal; bunny, 1,000 steps, seeds 0-2: 0.52-0.56% either way; docs/lsnif.md,
"Session 42").
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from ..simd import HAS_AVX512
from ..task_queue import take_task, task_count, task_workers
from .lsnif_features import PADDING, RayFeaturePoints, _as_occupancy, _check_rays, _feature_points_on, _host_feature_arrays
from .lsnif_walk_simd import float32_walk_applies, occupancy_bits, walk_group, walk_scratch

__all__ = ["applies", "featurize_rays_simd"]

_GROUP = 256  # rays a `walk_group` call walks (as the fused pass; a bunny batch 0.973x, 0.990x the time of 128)


def applies(resolution: int) -> bool:
    """Whether `featurize_rays_simd` walks a ``resolution^3`` grid at its speed: numba compiles for
    AVX-512 (elsewhere LLVM turns the 16-lane code into scalar loops) and V is a power of two."""
    return HAS_AVX512 and float32_walk_applies(resolution)


@numba.njit(nogil=True, cache=True)
def rows_scratch(group, max_points):
    """A thread's scratch for `walk_rows` on groups of ``group`` rays: `walk_scratch`'s, `walk_ray`'s
    (points and faces of ``group`` rows) and `walk_group`'s outputs (unordered points, per-ray counts)."""
    queue, queue_i, rays8, lane_terms, redo = walk_scratch(group)
    e = group * max_points
    return (queue, queue_i, rays8, lane_terms, redo, np.empty((group, max_points, 3), np.float32),
            np.empty((group, max_points), np.int8), np.empty(e, np.float32), np.empty(e, np.float32),
            np.empty(e, np.float32), np.empty(e, np.float32), np.empty(e, np.int32), np.empty(e, np.int32),
            np.empty(e, np.int32), np.empty(group, np.int64), np.empty(group, np.int32))  # fmt: skip


@numba.njit(nogil=True, cache=True)
def walk_rows(origins, directions, first, last, occ, occ_bits, planes, max_points, origin_point, share, scratch, pts, axes,
              counts, truncated, t_enter, t_exit, local):  # fmt: skip
    """Rays ``[first, last)`` through `walk_group`, a scratch's group at a time (`rows_scratch`), in
    ray order: each ray's points at their slots of its row of ``pts``/``axes`` (their local
    distances in ``local``'s, where it has rows), the rest of the row padding (point 0, face
    PADDING: no fill beforehand); its count, truncation (1 or True where cut short), t_enter, t_exit."""
    (queue, queue_i, rays8, lane_terms, redo, ray_pts, ray_axes, point_x, point_y, point_z, point_local, point_code, point_ray,
     point_slot, group_count, group_truncated) = scratch  # fmt: skip
    group = group_count.shape[0]
    for start in range(first, last, group):
        n = min(group, last - start)
        e = walk_group(origins, directions, start, n, occ, occ_bits, planes, max_points, origin_point, share, queue, queue_i,
                       rays8, lane_terms, redo, ray_pts, ray_axes, point_x, point_y, point_z, point_local, point_code,
                       point_ray, point_slot, group_count, group_truncated, t_enter, t_exit)  # fmt: skip
        for g in range(n):
            r = start + g
            counts[r] = group_count[g]
            truncated[r] = group_truncated[g] != 0
            for h in range(group_count[g], max_points):
                pts[r, h, 0] = pts[r, h, 1] = pts[r, h, 2] = np.float32(0.0)
                axes[r, h] = PADDING
        for i in range(e):  # the points, unordered, to their ray's row at their slot
            r, h = start + point_ray[i], point_slot[i]
            pts[r, h, 0], pts[r, h, 1], pts[r, h, 2] = point_x[i], point_y[i], point_z[i]
            axes[r, h] = point_code[i]
        if local.shape[0] > 0:  # (a loop of its own: the one above stays as the featurizer runs it)
            for i in range(e):
                local[start + point_ray[i], point_slot[i]] = point_local[i]


@numba.njit(parallel=True, nogil=True, cache=True)
def _featurize_simd_kernel(origins, directions, occ, occ_bits, planes, max_points, origin_point, share, n_chunks, n_workers,
                           pts, axes, counts, truncated, t_enter, t_exit):  # fmt: skip
    n_rays = origins.shape[0]
    next_chunk = np.zeros(1, np.int64)
    no_local = np.empty((0, 0), np.float32)
    for worker in numba.prange(n_workers):  # chunks handed out one at a time (`task_queue`)
        scratch = rows_scratch(_GROUP, max_points)
        while True:
            chunk = take_task(next_chunk)
            if chunk >= n_chunks:
                break
            walk_rows(origins, directions, chunk * n_rays // n_chunks, (chunk + 1) * n_rays // n_chunks, occ, occ_bits, planes,
                      max_points, origin_point, share, scratch, pts, axes, counts, truncated, t_enter, t_exit, no_local)  # fmt: skip


def featurize_rays_simd(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor | np.ndarray,
    max_points: int = 18,
    *,
    origin_point: bool = True,
    share_boundary_points: bool = True,
) -> RayFeaturePoints:
    """`featurize_rays` on the CPU from the 16-lane float32 walk (module docstring); float32 rays,
    V a power of two (`float32_walk_applies`; correct on any CPU, fast where `applies`)."""
    _check_rays(origins, directions, max_points)
    occ = _as_occupancy(occupancy)
    if not float32_walk_applies(occ.shape[0]):
        raise ValueError(f"the float32 walk needs a power-of-two grid, got {occ.shape[0]}^3")
    device = origins.device
    o = origins.detach().to("cpu", torch.float32).contiguous().numpy()
    d = directions.detach().to("cpu", torch.float32).contiguous().numpy()
    n = o.shape[0]
    arrays = _host_feature_arrays(n, max_points, padded=False)  # (the kernel writes the padding rows)
    n_chunks = task_count(n, _GROUP)
    if n:
        planes = np.arange(occ.shape[0] + 1) / occ.shape[0]  # k / V, as `featurize_rays_numba`
        _featurize_simd_kernel(o, d, occ, occupancy_bits(occ), planes, int(max_points), bool(origin_point),
                               bool(share_boundary_points), n_chunks, task_workers(n_chunks), *arrays)  # fmt: skip
    return _feature_points_on(arrays, device)

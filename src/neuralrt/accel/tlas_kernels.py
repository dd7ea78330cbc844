"""Numba passes of the scene TLAS on the CPU: the broad phase (ray validity + slab test against
every instance box, fused), the mapping of (ray, instance) pairs to object space, normals back to
world space, and the choice of the closest pair per ray.

They replace chains of torch ops (each allocating [N, I] or [P, 4, 4] temporaries) and compute
exactly what those ops computed, in the same float32 order, so the TLAS answers bit-identically.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["instance_overlaps", "object_space_rays", "normals_times_matrix", "closest_pair_per_ray"]

_FLOAT32_MAX = np.float32(np.finfo(np.float32).max)


@numba.njit(cache=True, inline="always")
def _slab_limit(t, nan_value):
    """torch.nan_to_num(t, nan=nan_value): NaN -> nan_value, +-inf -> +-float32 max."""
    if np.isnan(t):
        return nan_value
    if t == np.inf:
        return _FLOAT32_MAX
    if t == -np.inf:
        return -_FLOAT32_MAX
    return t


@numba.njit(parallel=True, cache=True)
def instance_overlaps(origins, directions, t_min, t_max, t_limit, lo, hi, overlap) -> int:
    """``overlap[n, g]``: ray ``n`` is valid and its interval ``(t_min, t_limit)`` meets box ``g``
    (``lo``/``hi`` [G, 3]); returns the number of true entries.

    Valid as in `neuralrt.rays.valid_ray_mask` (``t_max`` is the ray's own); the box test is
    `neuralrt.rays.ray_box_intervals` with ``t_enter <= t_exit``, ``t_exit >= t_min`` and
    ``t_enter <= t_limit``.
    """
    n, g = overlap.shape
    total = 0
    for i in numba.prange(n):
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        valid = (
            np.isfinite(ox) and np.isfinite(oy) and np.isfinite(oz)
            and np.isfinite(dx) and np.isfinite(dy) and np.isfinite(dz)
            and (dx != 0 or dy != 0 or dz != 0)
            and t_max[i] > t_min[i]
        )  # fmt: skip
        if not valid:
            for k in range(g):
                overlap[i, k] = False
            continue
        one = np.float32(1.0)
        inv = (one / dx, one / dy, one / dz)
        o = (ox, oy, oz)
        count = 0
        for k in range(g):
            t_enter = -np.inf
            t_exit = np.inf
            for a in range(3):
                t0 = _slab_limit((lo[k, a] - o[a]) * inv[a], -np.inf)
                t1 = _slab_limit((hi[k, a] - o[a]) * inv[a], np.inf)
                t_enter = max(t_enter, min(t0, t1))
                t_exit = min(t_exit, max(t0, t1))
            hit = t_enter <= t_exit and t_exit >= t_min[i] and t_enter <= t_limit[i]
            overlap[i, k] = hit
            count += hit
        total += count
    return total


@numba.njit(cache=True, inline="always")
def _affine(m, x, y, z, r, point):
    """Row ``r`` of ``m @ (x, y, z, point)``, summed as torch's small batched matmul does."""
    acc = np.float32(0.0)
    acc += m[r, 0] * x
    acc += m[r, 1] * y
    acc += m[r, 2] * z
    return acc + m[r, 3] if point else acc


@numba.njit(parallel=True, cache=True)
def object_space_rays(origins, directions, ray_idx, inst_idx, world_to_object, is_identity, out_origins, out_directions):
    """Pair ``p`` = (ray ``ray_idx[p]``, instance ``inst_idx[p]``): the ray's origin and direction
    in that instance's object space (t is unchanged by the affine map)."""
    for p in numba.prange(ray_idx.shape[0]):
        r, k = ray_idx[p], inst_idx[p]
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        if is_identity[k]:
            out_origins[p, 0], out_origins[p, 1], out_origins[p, 2] = ox, oy, oz
            out_directions[p, 0], out_directions[p, 1], out_directions[p, 2] = dx, dy, dz
        else:
            m = world_to_object[k]
            for a in range(3):
                out_origins[p, a] = _affine(m, ox, oy, oz, a, True)
                out_directions[p, a] = _affine(m, dx, dy, dz, a, False)


@numba.njit(parallel=True, cache=True)
def normals_times_matrix(normals, inst_idx, world_to_object, out) -> None:
    """``out[p] = normals[p] @ world_to_object[inst_idx[p], :3, :3]`` (the inverse transpose
    applied to a normal, before renormalisation), summed as torch's small batched matmul does."""
    for p in numba.prange(normals.shape[0]):
        m = world_to_object[inst_idx[p]]
        nx, ny, nz = normals[p, 0], normals[p, 1], normals[p, 2]
        for c in range(3):
            acc = np.float32(0.0)
            acc += nx * m[0, c]
            acc += ny * m[1, c]
            acc += nz * m[2, c]
            out[p, c] = acc


@numba.njit(cache=True)
def closest_pair_per_ray(ray_idx, hit, t, best_t, winner) -> int:
    """``winner[r]``: the pair (index into ``ray_idx``) that hits ray ``r`` closest and strictly
    before ``best_t[r]``, or -1; returns the number of rays with a winner.

    Exact ties between pairs go to the later pair, as the scatter this replaces left them.
    """
    winner[:] = -1
    closest = best_t.copy()
    found = 0
    for p in range(ray_idx.shape[0]):
        r = ray_idx[p]
        if hit[p] and t[p] < best_t[r] and (winner[r] < 0 or t[p] <= closest[r]):
            found += winner[r] < 0
            winner[r] = p
            closest[r] = t[p]
    return found

"""Numba forms of `neuralrt.rays` predicates and records, for the CPU kernels that handle rays one at a time."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def valid_ray(origins, directions, t_min, t_max, i) -> bool:
    """Ray ``i`` is valid as `neuralrt.rays.valid_ray_mask` defines it: finite origin and direction,
    a non-zero direction and ``t_min < t_max`` (NaN fails every comparison, so NaN bounds reject)."""
    ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
    dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
    return (
        np.isfinite(ox) and np.isfinite(oy) and np.isfinite(oz)
        and np.isfinite(dx) and np.isfinite(dy) and np.isfinite(dz)
        and (dx != 0 or dy != 0 or dz != 0)
        and t_max[i] > t_min[i]
    )  # fmt: skip


@numba.njit(cache=True, inline="always")
def write_miss(r, hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id, instance_id):
    """Row ``r`` of the hit columns (`neuralrt.rays.Hits`' fields, in order, as arrays) as `Hits.empty` writes it (a miss)."""
    hit[r] = False
    t[r] = np.inf
    for c in range(3):
        normal[r, c] = 0.0
        geometric_normal[r, c] = 0.0
        albedo[r, c] = 1.0
    uv[r, 0], uv[r, 1] = 0.0, 0.0
    material_id[r] = -1
    primitive_id[r] = -1
    instance_id[r] = -1

"""Numba passes of the scene TLAS on the CPU: the broad phase (ray validity + slab test against
every instance box, fused), the mapping of (ray, instance) pairs to object space, normals back to
world space, and the choice of the closest pair per ray.

They replace chains of torch ops (each allocating [N, I] or [P, 4, 4] temporaries) and compute
exactly what those ops computed, in the same float32 order, so the TLAS answers bit-identically.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

__all__ = ["instance_overlaps", "object_space_rays", "transform_rays", "normals_to_world", "merge_every_ray", "closest_pair_per_ray"]

_FLOAT32_MAX = np.float32(np.finfo(np.float32).max)


@numba.njit(cache=True, inline="always", error_model="numpy")
def _slab_limit(t, nan_value):
    """torch.nan_to_num(t, nan=nan_value): NaN -> nan_value, +-inf -> +-float32 max."""
    if np.isnan(t):
        return nan_value
    if t == np.inf:
        return _FLOAT32_MAX
    if t == -np.inf:
        return -_FLOAT32_MAX
    return t


@numba.njit(nogil=True, cache=True, error_model="numpy")
def instance_overlaps(origins, directions, t_min, t_max, t_limit, lo, hi, overlap) -> int:
    """``overlap[n, g]``: ray ``n`` is valid and its interval ``(t_min, t_limit)`` meets box ``g``
    (``lo``/``hi`` [G, 3]); returns the number of true entries.

    Valid as in `neuralrt.rays.valid_ray_mask` (``t_max`` is the ray's own); the box test is
    `neuralrt.rays.ray_box_intervals` with ``t_enter <= t_exit``, ``t_exit >= t_min`` and
    ``t_enter <= t_limit``.
    """
    n, g = overlap.shape
    total = 0
    for i in range(n):
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


@numba.njit(cache=True, inline="always", error_model="numpy")
def _affine(m, x, y, z, r, point):
    """Row ``r`` of ``m @ (x, y, z, point)``, summed as torch's small batched matmul does."""
    acc = np.float32(0.0)
    acc += m[r, 0] * x
    acc += m[r, 1] * y
    acc += m[r, 2] * z
    return acc + m[r, 3] if point else acc


@numba.njit(nogil=True, cache=True, error_model="numpy")
def object_space_rays(origins, directions, ray_idx, inst_idx, world_to_object, is_identity, out_origins, out_directions):
    """Pair ``p`` = (ray ``ray_idx[p]``, instance ``inst_idx[p]``): the ray's origin and direction
    in that instance's object space (t is unchanged by the affine map)."""
    for p in range(ray_idx.shape[0]):
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


@numba.njit(nogil=True, cache=True, error_model="numpy")
def transform_rays(origins, directions, world_to_object, out_origins, out_directions):
    """Every ray under one instance: `object_space_rays` without index arrays."""
    for r in range(origins.shape[0]):
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        for a in range(3):
            out_origins[r, a] = _affine(world_to_object, ox, oy, oz, a, True)
            out_directions[r, a] = _affine(world_to_object, dx, dy, dz, a, False)


@intrinsic
def _fma32(typingctx, a, b, c):
    """float32 fused multiply-add (one rounding), as torch's vectorised CPU kernels compute."""
    sig = types.float32(a, b, c)

    def codegen(context, builder, signature, args):
        args = [context.cast(builder, v, ty, types.float32) for v, ty in zip(args, signature.args)]
        f32 = ir.FloatType()
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(f32, [f32, f32, f32]), "llvm.fma.f32")
        return builder.call(fma, args)

    return sig, codegen


@numba.njit(cache=True, inline="always", error_model="numpy")
def _world_normal(m, identity, nx, ny, nz):
    """``normalize(n @ m[:3, :3])`` bit for bit as torch computes it on the CPU: the small batched
    matmul's sum order, `linalg.vector_norm`'s fused multiply-adds, then a division by the norm
    clamped to 1e-12 (zero stays zero)."""
    if not identity:
        x = np.float32(0.0)
        x += nx * m[0, 0]
        x += ny * m[1, 0]
        x += nz * m[2, 0]
        y = np.float32(0.0)
        y += nx * m[0, 1]
        y += ny * m[1, 1]
        y += nz * m[2, 1]
        z = np.float32(0.0)
        z += nx * m[0, 2]
        z += ny * m[1, 2]
        z += nz * m[2, 2]
        nx, ny, nz = x, y, z
    square = _fma32(nz, nz, _fma32(ny, ny, nx * nx))
    length = max(np.float32(np.sqrt(square)), np.float32(1e-12))
    return nx / length, ny / length, nz / length


@numba.njit(nogil=True, cache=True, error_model="numpy")
def normals_to_world(normals, inst_idx, world_to_object, is_identity, out) -> None:
    """``out[p] = normalize(normals[p] @ world_to_object[inst_idx[p], :3, :3])`` (the inverse
    transpose applied to a normal), as torch computes it."""
    for p in range(normals.shape[0]):
        k = inst_idx[p]
        x, y, z = _world_normal(world_to_object[k], is_identity[k], normals[p, 0], normals[p, 1], normals[p, 2])
        out[p, 0], out[p, 1], out[p, 2] = x, y, z


@numba.njit(nogil=True, cache=True, error_model="numpy")
def merge_every_ray(
    hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id, overlap, has_best,
    k, material_map, world_to_object, identity,
    best_hit, best_t, best_normal, best_geometric_normal, best_uv, best_albedo, best_material_id,
    best_primitive_id, best_instance_id,
):  # fmt: skip
    """Row ``r`` of the first group of arrays answers ray ``r`` under instance ``k``: write it, in
    world space with ``material_map`` applied, into the ``best_*`` rows where it hits (inside
    ``overlap`` when that is non-empty) closer than ``best_t`` (``has_best``) — or, without a
    previous best, write miss rows everywhere else."""
    n_map = material_map.shape[0]
    use_overlap = overlap.shape[0] > 0
    for r in range(hit.shape[0]):
        closer = hit[r] and (not use_overlap or overlap[r]) and (not has_best or t[r] < best_t[r])
        if closer:
            best_hit[r] = True
            best_t[r] = t[r]
            x, y, z = _world_normal(world_to_object, identity, normal[r, 0], normal[r, 1], normal[r, 2])
            best_normal[r, 0], best_normal[r, 1], best_normal[r, 2] = x, y, z
            x, y, z = _world_normal(
                world_to_object, identity, geometric_normal[r, 0], geometric_normal[r, 1], geometric_normal[r, 2]
            )
            best_geometric_normal[r, 0], best_geometric_normal[r, 1], best_geometric_normal[r, 2] = x, y, z
            best_uv[r, 0], best_uv[r, 1] = uv[r, 0], uv[r, 1]
            best_albedo[r, 0], best_albedo[r, 1], best_albedo[r, 2] = albedo[r, 0], albedo[r, 1], albedo[r, 2]
            best_material_id[r] = material_map[min(max(material_id[r], 0), n_map - 1)]
            best_primitive_id[r] = primitive_id[r]
            best_instance_id[r] = k
        elif not has_best:  # the rows of Hits.empty
            best_hit[r] = False
            best_t[r] = np.inf
            for c in range(3):
                best_normal[r, c] = 0.0
                best_geometric_normal[r, c] = 0.0
                best_albedo[r, c] = 1.0
            best_uv[r, 0], best_uv[r, 1] = 0.0, 0.0
            best_material_id[r] = -1
            best_primitive_id[r] = -1
            best_instance_id[r] = -1


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

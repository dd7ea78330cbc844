"""Numba passes of the scene TLAS on the CPU: the broad phase (ray validity + slab test against
every instance box, fused; or a walk of a BVH over the instance boxes that emits the overlapping
(ray, instance) pairs directly), the mapping of (ray, instance) pairs to object space, normals back to
world space, and the choice of the closest pair per ray with its write into the scene's hits.

They replace chains of torch ops (each allocating [N, I] or [P, 4, 4] temporaries) and compute
exactly what those ops computed, in the same float32 order, so the TLAS answers bit-identically.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from ..rays_kernels import valid_ray, write_miss
from ..simd import prefetch_row
from .embree_api import HIT_U, HIT_V, PRIM_ID, TFAR, ray_record
from .mesh_blas_kernels import embree_ray, next_rows, surface_at, trace_closest, trace_occluded

__all__ = ["instance_overlaps", "instance_pairs", "object_space_rays", "transform_rays", "merge_every_ray", "merge_pairs",
           "instance_closest_hits", "instance_occluded", "pair_embree_rays", "merge_pair_hits", "finish_hits", "mark_blocked"]

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


@numba.njit(nogil=True, cache=True, error_model="numpy", parallel=True)
def instance_overlaps(origins, directions, t_min, t_max, t_limit, lo, hi, overlap) -> int:
    """``overlap[n, g]``: ray ``n`` is valid and its interval ``(t_min, t_limit)`` meets box ``g``
    (``lo``/``hi`` [G, 3]); returns the number of true entries.

    Valid as in `neuralrt.rays.valid_ray_mask` (``t_max`` is the ray's own); the box test is
    `neuralrt.rays.ray_box_intervals` with ``t_enter <= t_exit``, ``t_exit >= t_min`` and
    ``t_enter <= t_limit``. Parallel over chunks of rays (a render's one-box groups test every
    ray of the wavefront here).
    """
    n, g = overlap.shape
    n_chunks = min(n, _CHUNKS) if n >= _PARALLEL_MIN_RAYS else min(n, 1)
    counts = np.zeros(n_chunks, np.int64)
    for chunk in numba.prange(n_chunks):
        count = 0
        for i in range(chunk * n // n_chunks, (chunk + 1) * n // n_chunks):
            if not valid_ray(origins, directions, t_min, t_max, i):
                for k in range(g):
                    overlap[i, k] = False
                continue
            one = np.float32(1.0)
            ix, iy, iz = one / directions[i, 0], one / directions[i, 1], one / directions[i, 2]
            for k in range(g):
                hit = _box_overlap(origins[i, 0], origins[i, 1], origins[i, 2], ix, iy, iz, lo, hi, k, t_min[i], t_limit[i])
                overlap[i, k] = hit
                count += hit
        counts[chunk] = count
    return counts.sum()


_PARALLEL_MIN_RAYS = 1 << 14  # fewer rays: one chunk (the threads' start costs more than they save)
_CHUNKS = 64  # chunks handed out to the threads (enough for 16)


@numba.njit(cache=True, inline="always", error_model="numpy")
def _box_overlap(ox, oy, oz, ix, iy, iz, lo, hi, k, t_min, t_limit):
    """The slab test of `instance_overlaps` for box ``k`` of ``lo``/``hi`` (same float32 values)."""
    t0 = _slab_limit((lo[k, 0] - ox) * ix, -np.inf)
    t1 = _slab_limit((hi[k, 0] - ox) * ix, np.inf)
    t_enter, t_exit = min(t0, t1), max(t0, t1)
    t0 = _slab_limit((lo[k, 1] - oy) * iy, -np.inf)
    t1 = _slab_limit((hi[k, 1] - oy) * iy, np.inf)
    t_enter, t_exit = max(t_enter, min(t0, t1)), min(t_exit, max(t0, t1))
    t0 = _slab_limit((lo[k, 2] - oz) * iz, -np.inf)
    t1 = _slab_limit((hi[k, 2] - oz) * iz, np.inf)
    t_enter, t_exit = max(t_enter, min(t0, t1)), min(t_exit, max(t0, t1))
    return t_enter <= t_exit and t_exit >= t_min and t_enter <= t_limit


@numba.njit(cache=True, inline="always", error_model="numpy")
def _finite_box_overlap(ox, oy, oz, ix, iy, iz, lo, hi, k, t_min, t_limit):
    """`_box_overlap` for a ray whose inverse direction is finite: no slab bound is NaN then, so
    clamping to +-float32 max (branch-free min/max) is `_slab_limit`."""
    big = _FLOAT32_MAX
    t0 = min(max((lo[k, 0] - ox) * ix, -big), big)
    t1 = min(max((hi[k, 0] - ox) * ix, -big), big)
    t_enter, t_exit = min(t0, t1), max(t0, t1)
    t0 = min(max((lo[k, 1] - oy) * iy, -big), big)
    t1 = min(max((hi[k, 1] - oy) * iy, -big), big)
    t_enter, t_exit = max(t_enter, min(t0, t1)), min(t_exit, max(t0, t1))
    t0 = min(max((lo[k, 2] - oz) * iz, -big), big)
    t1 = min(max((hi[k, 2] - oz) * iz, -big), big)
    t_enter, t_exit = max(t_enter, min(t0, t1)), min(t_exit, max(t0, t1))
    return (t_enter <= t_exit) & (t_exit >= t_min) & (t_enter <= t_limit)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def instance_pairs(origins, directions, t_min, t_max, t_limit, lo, hi, node_lo, node_hi, children, leaf_start,
                   leaf_count, prim_order):  # fmt: skip
    """The true entries of `instance_overlaps`'s ``overlap`` as (ray [P], box [P]) index arrays in
    row-major order (as ``np.nonzero`` lists them), found by walking a binary BVH over the boxes
    (`neuralrt.geometry.bvh.build_box_bvh`: ``node_lo``/``node_hi``, ``children`` [M, 2],
    ``leaf_start``/``leaf_count`` into ``prim_order``) instead of testing every box.

    A node box contains its boxes, and each slab bound is a monotone function of the box bound
    when the ray's inverse direction is finite, so a box that passes the test lies in nodes that
    pass it: the pairs are exactly the brute-force ones. Rays with an infinite inverse direction
    component (0 * inf = NaN breaks that monotonicity) test every box instead.
    """
    n, g = origins.shape[0], lo.shape[0]
    capacity = max(16, 2 * n)
    ray_out = np.empty(capacity, np.int64)
    box_out = np.empty(capacity, np.int64)
    found = np.empty(g, np.int64)
    stack = np.empty(children.shape[0] + 1, np.int64)
    total = 0
    one = np.float32(1.0)
    for i in range(n):
        if not valid_ray(origins, directions, t_min, t_max, i):
            continue
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        ix, iy, iz = one / dx, one / dy, one / dz
        t0, t1 = t_min[i], t_limit[i]
        m = 0
        if np.isfinite(ix) and np.isfinite(iy) and np.isfinite(iz):
            sp = 0
            if _finite_box_overlap(ox, oy, oz, ix, iy, iz, node_lo, node_hi, 0, t0, t1):
                stack[0] = 0
                sp = 1
            while sp > 0:
                sp -= 1
                node = stack[sp]
                if leaf_count[node] > 0:
                    for j in range(leaf_start[node], leaf_start[node] + leaf_count[node]):
                        k = prim_order[j]
                        if _finite_box_overlap(ox, oy, oz, ix, iy, iz, lo, hi, k, t0, t1):
                            # Insertion in ascending box order (np.nonzero's order within a row).
                            p = m
                            while p > 0 and found[p - 1] > k:
                                found[p] = found[p - 1]
                                p -= 1
                            found[p] = k
                            m += 1
                    continue
                for c in range(2):
                    child = children[node, c]
                    if _finite_box_overlap(ox, oy, oz, ix, iy, iz, node_lo, node_hi, child, t0, t1):
                        stack[sp] = child
                        sp += 1
        else:
            for k in range(g):
                if _box_overlap(ox, oy, oz, ix, iy, iz, lo, hi, k, t0, t1):
                    found[m] = k
                    m += 1
        if total + m > capacity:
            capacity = max(2 * capacity, total + m)
            ray_out = _grown(ray_out, capacity, total)
            box_out = _grown(box_out, capacity, total)
        for p in range(m):
            ray_out[total + p] = i
            box_out[total + p] = found[p]
        total += m
    return ray_out[:total], box_out[:total]


@numba.njit(cache=True, inline="always")
def _grown(buffer, capacity, used):
    out = np.empty(capacity, buffer.dtype)
    out[:used] = buffer[:used]
    return out


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


_FACE_AHEAD = 16  # rows ahead whose face records are prefetched
_VERTEX_AHEAD = 8  # rows ahead whose vertex rows are prefetched (their face records arrived by then)


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
        elif not has_best:
            write_miss(r, best_hit, best_t, best_normal, best_geometric_normal, best_uv, best_albedo, best_material_id,
                       best_primitive_id, best_instance_id)  # fmt: skip


@numba.njit(nogil=True, cache=True, error_model="numpy")
def merge_pairs(
    ray_idx, inst_idx, hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id,
    material_maps, world_to_object, is_identity,
    best_hit, best_t, best_normal, best_geometric_normal, best_uv, best_albedo, best_material_id,
    best_primitive_id, best_instance_id,
) -> int:  # fmt: skip
    """Pair ``p`` = (ray ``ray_idx[p]``, instance ``inst_idx[p]``) with object-space answer row ``p``
    of the first group of arrays: each ray's closest pair that hits strictly before ``best_t``
    (exact ties to the later pair, as the scatter this replaces left them) is written into the
    ``best_*`` rows in world space (normals by the inverse transpose, ``material_maps`` applied);
    returns the number of rays written."""
    n_map = material_maps.shape[1]
    winner = np.full(best_t.shape[0], -1, np.int64)
    closest = best_t.copy()
    found = 0
    for p in range(ray_idx.shape[0]):
        r = ray_idx[p]
        if hit[p] and t[p] < best_t[r] and (winner[r] < 0 or t[p] <= closest[r]):
            found += winner[r] < 0
            winner[r] = p
            closest[r] = t[p]
    for p in range(ray_idx.shape[0]):
        r = ray_idx[p]
        if winner[r] != p:
            continue
        k = inst_idx[p]
        m, identity = world_to_object[k], is_identity[k]
        best_hit[r] = True
        best_t[r] = t[p]
        x, y, z = _world_normal(m, identity, normal[p, 0], normal[p, 1], normal[p, 2])
        best_normal[r, 0], best_normal[r, 1], best_normal[r, 2] = x, y, z
        x, y, z = _world_normal(m, identity, geometric_normal[p, 0], geometric_normal[p, 1], geometric_normal[p, 2])
        best_geometric_normal[r, 0], best_geometric_normal[r, 1], best_geometric_normal[r, 2] = x, y, z
        best_uv[r, 0], best_uv[r, 1] = uv[p, 0], uv[p, 1]
        best_albedo[r, 0], best_albedo[r, 1], best_albedo[r, 2] = albedo[p, 0], albedo[p, 1], albedo[p, 2]
        best_material_id[r] = material_maps[k, min(max(material_id[p], 0), n_map - 1)]
        best_primitive_id[r] = primitive_id[p]
        best_instance_id[r] = k
    return found


# --- fused path for scenes of Embree meshes: Embree's raw answers merged, attributes of the winners ---


@numba.njit(cache=True, inline="always", error_model="numpy")
def _instance_embree_ray(origins, directions, t_min, t_max, i, limit, lo, hi, world_to_object, identity):
    """Ray ``i`` of a one-instance group as Embree takes it: (traced, origin moved to t_min and
    direction in object space, interval length). Traced when the ray is valid, its interval
    ``(t_min, limit)`` meets the instance's box (``lo``/``hi`` [1, 3]) and it is valid in object
    space. The same float32 values as `instance_overlaps`, `transform_rays` and
    `mesh_blas_kernels.embree_ray` in sequence."""
    zero = np.float32(0.0)
    ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
    dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
    if not valid_ray(origins, directions, t_min, t_max, i):
        return False, zero, zero, zero, dx, dy, dz, zero
    one = np.float32(1.0)
    if not _box_overlap(ox, oy, oz, one / dx, one / dy, one / dz, lo, hi, 0, t_min[i], limit):
        return False, zero, zero, zero, dx, dy, dz, zero
    if not identity:
        m = world_to_object
        ox, oy, oz, dx, dy, dz = (_affine(m, ox, oy, oz, 0, True), _affine(m, ox, oy, oz, 1, True),
                                  _affine(m, ox, oy, oz, 2, True), _affine(m, dx, dy, dz, 0, False),
                                  _affine(m, dx, dy, dz, 1, False), _affine(m, dx, dy, dz, 2, False))  # fmt: skip
    ok, sx, sy, sz, tfar = embree_ray(ox, oy, oz, dx, dy, dz, t_min[i], limit)
    return ok, sx, sy, sz, dx, dy, dz, tfar


@numba.njit(nogil=True, cache=True, error_model="numpy", parallel=True)
def instance_closest_hits(scene, workers, origins, directions, t_min, t_max, has_best, lo, hi, world_to_object, identity, k,
                          best_t, best_prim, best_u, best_v, best_instance) -> None:  # fmt: skip
    """A one-instance group's (instance ``k``, its mesh's Embree ``scene``) closest-hit step, per
    ray, by ``workers`` workers (`mesh_blas_kernels.embree_workers`): broad phase and mapping
    (`_instance_embree_ray`, the interval's end ``min(t_max, best_t)`` with ``has_best``),
    Embree, and the merge: a hit's t (Embree's t_far from the origin moved to t_min) replaces
    the ray's best where it is closer (anywhere without ``has_best``), as `merge_every_ray` decides."""
    n = origins.shape[0]
    zero = np.float32(0.0)
    next_block = np.zeros(1, np.int64)
    for _ in numba.prange(workers):
        words, ids, address = ray_record()
        while True:
            start, stop = next_rows(next_block, n)
            if start >= n:
                break
            for i in range(start, stop):
                limit = min(t_max[i], best_t[i]) if has_best else t_max[i]  # best_t is never NaN: torch.minimum
                ok, sx, sy, sz, dx, dy, dz, tfar = _instance_embree_ray(origins, directions, t_min, t_max, i, limit, lo, hi,
                                                                        world_to_object, identity)  # fmt: skip
                if not ok:
                    continue
                if not trace_closest(scene, words, ids, address, sx, sy, sz, dx, dy, dz, tfar):
                    continue
                t = words[TFAR] + (t_min[i] if np.isfinite(t_min[i]) else zero)
                if has_best and not (t < best_t[i]):
                    continue
                best_t[i], best_prim[i], best_u[i], best_v[i], best_instance[i] = t, ids[PRIM_ID], words[HIT_U], words[HIT_V], k


@numba.njit(nogil=True, cache=True, error_model="numpy", parallel=True)
def instance_occluded(scene, workers, origins, directions, t_min, t_max, blocked, lo, hi, world_to_object, identity) -> None:
    """`instance_closest_hits` for shadow rays: rays not yet ``blocked`` whose interval (t_min,
    t_max) meets the box, valid in object space, are traced and marked where Embree finds a blocker."""
    n = origins.shape[0]
    next_block = np.zeros(1, np.int64)
    for _ in numba.prange(workers):
        words, ids, address = ray_record()
        while True:
            start, stop = next_rows(next_block, n)
            if start >= n:
                break
            for i in range(start, stop):
                if blocked[i]:
                    continue
                ok, sx, sy, sz, dx, dy, dz, tfar = _instance_embree_ray(origins, directions, t_min, t_max, i, t_max[i], lo, hi,
                                                                        world_to_object, identity)  # fmt: skip
                if ok:
                    blocked[i] = trace_occluded(scene, words, ids, address, sx, sy, sz, dx, dy, dz, tfar)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def pair_embree_rays(origins, directions, t_min, t_limit, ray_idx, inst_idx, world_to_object, is_identity,
                     out_origins, out_directions, out_tfar, out_pair) -> int:  # fmt: skip
    """(ray, instance) pairs: `object_space_rays` and Embree's preparation (interval ``(t_min,
    t_limit)`` of the ray) in one pass, the pairs valid in object space compacted with their index
    in ``out_pair``; returns their count."""
    count = 0
    for p in range(ray_idx.shape[0]):
        r, k = ray_idx[p], inst_idx[p]
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        if not is_identity[k]:
            m = world_to_object[k]
            ox, oy, oz, dx, dy, dz = (_affine(m, ox, oy, oz, 0, True), _affine(m, ox, oy, oz, 1, True),
                                      _affine(m, ox, oy, oz, 2, True), _affine(m, dx, dy, dz, 0, False),
                                      _affine(m, dx, dy, dz, 1, False), _affine(m, dx, dy, dz, 2, False))  # fmt: skip
        ok, sx, sy, sz, tfar = embree_ray(ox, oy, oz, dx, dy, dz, t_min[r], t_limit[r])
        if ok:
            out_origins[count, 0], out_origins[count, 1], out_origins[count, 2] = sx, sy, sz
            out_directions[count, 0], out_directions[count, 1], out_directions[count, 2] = dx, dy, dz
            out_tfar[count] = tfar
            out_pair[count] = p
            count += 1
    return count


@numba.njit(nogil=True, cache=True, error_model="numpy")
def merge_pair_hits(out_pair, prim, tfar, bary_u, bary_v, ray_idx, inst_idx, t_min, best_t, best_prim, best_u, best_v,
                    best_instance) -> None:  # fmt: skip
    """Embree's answers for pairs (row ``j`` for pair ``out_pair[j]``): each ray's closest hit
    strictly before ``best_t``, exact ties to the later pair, as `merge_pairs` decides."""
    zero = np.float32(0.0)
    winner = np.full(best_t.shape[0], -1, np.int64)  # per ray: the row of its closest improving pair
    closest = np.empty(best_t.shape[0], np.float32)
    for j in range(out_pair.shape[0]):
        if prim[j] < 0:
            continue
        r = ray_idx[out_pair[j]]
        t = tfar[j] + (t_min[r] if np.isfinite(t_min[r]) else zero)
        if t < best_t[r] and (winner[r] < 0 or t <= closest[r]):
            winner[r] = j
            closest[r] = t
    for j in range(out_pair.shape[0]):
        r = ray_idx[out_pair[j]]
        if prim[j] >= 0 and winner[r] == j:
            best_t[r], best_prim[r], best_u[r], best_v[r], best_instance[r] = closest[r], prim[j], bary_u[j], bary_v[j], inst_idx[out_pair[j]]


@numba.njit(nogil=True, cache=True, error_model="numpy", parallel=True)
def finish_hits(
    best_t, best_prim, best_u, best_v, best_instance, instance_group, group, write_misses,
    faces, face_normals, vertex_normals, face_material_ids, uvs, vertex_colors, material_albedo, use_uvs, use_vertex_colors,
    material_maps, world_to_object, is_identity,
    hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id, instance_id,
):  # fmt: skip
    """The world-space hit records of the rays whose winning instance is in ``group`` (its mesh's
    tables), as `MeshBLAS.intersect` (`mesh_blas_kernels.surface_at`) then `merge_every_ray` /
    `merge_pairs` write them; with ``write_misses`` also the rows of `Hits.empty` for rays that
    hit nothing."""
    n_map = material_maps.shape[1]
    n = best_t.shape[0]
    for r in numba.prange(n):
        ahead = r + _FACE_AHEAD
        if ahead < n and best_instance[ahead] >= 0 and instance_group[best_instance[ahead]] == group:
            q = best_prim[ahead]
            prefetch_row(faces, q)
            prefetch_row(face_normals, q)
            prefetch_row(face_material_ids, q)
        ahead = r + _VERTEX_AHEAD
        if ahead < n and best_instance[ahead] >= 0 and instance_group[best_instance[ahead]] == group:
            q = best_prim[ahead]
            for c in range(3):
                prefetch_row(vertex_normals, faces[q, c])
                if use_uvs:
                    prefetch_row(uvs, faces[q, c])
                if use_vertex_colors:
                    prefetch_row(vertex_colors, faces[q, c])
        k = best_instance[r]
        if k < 0:
            if write_misses:
                write_miss(r, hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id, instance_id)
            continue
        if instance_group[k] != group:
            continue
        p = best_prim[r]
        sx, sy, sz, gx, gy, gz, m, u0, u1, ar, ag, ab = surface_at(
            p, best_u[r], best_v[r], faces, face_normals, vertex_normals, face_material_ids, uvs, vertex_colors,
            material_albedo, use_uvs, use_vertex_colors, True)  # fmt: skip
        w2o, identity = world_to_object[k], is_identity[k]
        hit[r] = True
        t[r] = best_t[r]
        normal[r, 0], normal[r, 1], normal[r, 2] = _world_normal(w2o, identity, sx, sy, sz)
        geometric_normal[r, 0], geometric_normal[r, 1], geometric_normal[r, 2] = _world_normal(w2o, identity, gx, gy, gz)
        uv[r, 0], uv[r, 1] = u0, u1
        albedo[r, 0], albedo[r, 1], albedo[r, 2] = ar, ag, ab
        material_id[r] = material_maps[k, min(max(m, 0), n_map - 1)]
        primitive_id[r] = p
        instance_id[r] = k


@numba.njit(nogil=True, cache=True)
def mark_blocked(out_ray, geom_id, blocked) -> None:
    """``blocked[out_ray[j]]`` where Embree reported a blocker for row ``j``."""
    for j in range(out_ray.shape[0]):
        if geom_id[j] >= 0:
            blocked[out_ray[j]] = True

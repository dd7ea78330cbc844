"""`EmbreeMeshBLAS`'s queries as numba kernels: per ray, one pass validates it, moves its origin
to t_min, traces it through Embree's C API (`embree_api`) and writes its hit record.

`MeshBLAS` once spent more time in numpy/torch glue (a dozen temporaries per ray, gathers over
index arrays) than Embree spent tracing, then in Python threads handing chunks to embreex. Here
each input is read once and each output written once, in one parallel region. All arithmetic
stays in float32 and in the same order as the numpy reference in tests/test_mesh_blas_kernels.py,
so results are bit-identical to it.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..rays_kernels import write_miss
from ..task_queue import take_task, task_workers
from .embree_api import (DIR, FLAGS, GEOM_ID, HIT_U, HIT_V, INST_ID, INVALID_ID, MASK, ORG, PRIM_ID, RAY_ID, TFAR, TIME,
                         TNEAR, ray_record, rtc_intersect1, rtc_occluded1)  # fmt: skip

__all__ = ["intersect_rays", "occluded_rays", "closest_prepared", "occluded_prepared", "embree_workers", "EMBREE_TFAR_MAX"]

# Embree works in float32; "infinite" t_max is passed as a large finite value.
EMBREE_TFAR_MAX = np.float32(1e37)
_NORMAL_EPS = np.float32(1e-12)
# Rows a worker takes at a time (`task_queue`: the next block, whichever thread is free), so a
# batch ordered by cost (a training batch: outside rays, then ~2.3x costlier surface rays) is
# shared evenly; a block of rows is contiguous, so threads rarely write the same cache line.
BLOCK_ROWS = 256


def embree_workers(n: int) -> int:
    """Workers of a kernel below for ``n`` rays (passed in: `task_queue.task_workers`)."""
    return task_workers(-(-n // BLOCK_ROWS))


@numba.njit(cache=True, inline="always")
def next_rows(next_block, n):
    """The next block's rows ``(start, stop)`` of ``n`` (`task_queue.take_task` on ``next_block``);
    ``start >= n`` once none is left."""
    start = take_task(next_block) * BLOCK_ROWS
    return start, min(n, start + BLOCK_ROWS)


@numba.njit(cache=True, inline="always", error_model="numpy")
def embree_ray(ox, oy, oz, dx, dy, dz, t0, t1):
    """A ray with interval (t0, t1) as Embree takes it: (valid, origin moved to t0 (Embree starts at
    t = 0), interval length capped at EMBREE_TFAR_MAX). Valid as `neuralrt.rays.valid_ray_mask`
    defines it; an invalid ray is not traced."""
    ok = (np.isfinite(ox) and np.isfinite(oy) and np.isfinite(oz) and np.isfinite(dx) and np.isfinite(dy)
          and np.isfinite(dz) and (dx != 0 or dy != 0 or dz != 0) and t1 > t0)  # fmt: skip
    if not ok:
        return False, np.float32(0.0), np.float32(0.0), np.float32(0.0), np.float32(0.0)
    start = t0 if np.isfinite(t0) else np.float32(0.0)
    length = t1 - t0  # float32, as t_max - t_min in numpy
    if not (length <= EMBREE_TFAR_MAX):  # also catches NaN (-inf t_min with +inf t_max)
        length = EMBREE_TFAR_MAX
    return True, ox + start * dx, oy + start * dy, oz + start * dz, length


@numba.njit(cache=True, inline="always")
def row_embree_ray(origins, directions, t_min, t_max, i):
    """`embree_ray` of row ``i`` of ray arrays."""
    return embree_ray(origins[i, 0], origins[i, 1], origins[i, 2], directions[i, 0], directions[i, 1], directions[i, 2],
                      t_min[i], t_max[i])  # fmt: skip


@numba.njit(cache=True, inline="always")
def set_ray(words, ids, ox, oy, oz, dx, dy, dz, tfar) -> None:
    """Fill the RTCRayHit ``words`` / ``ids`` (`embree_api.ray_record`) for a query from t = 0 to ``tfar``."""
    words[ORG], words[ORG + 1], words[ORG + 2], words[TNEAR] = ox, oy, oz, np.float32(0.0)
    words[DIR], words[DIR + 1], words[DIR + 2], words[TIME] = dx, dy, dz, np.float32(0.0)
    words[TFAR] = tfar
    ids[MASK], ids[RAY_ID], ids[FLAGS] = INVALID_ID, 0, 0  # mask: every bit set
    ids[PRIM_ID], ids[GEOM_ID], ids[INST_ID] = INVALID_ID, INVALID_ID, INVALID_ID


@numba.njit(cache=True, inline="always")
def trace_closest(scene, words, ids, address, ox, oy, oz, dx, dy, dz, tfar) -> bool:
    """Embree's closest hit of one ray from t = 0 to ``tfar`` (`set_ray` into the record at
    ``address``); True on a hit, whose distance, triangle and (u, v) are then ``words[TFAR]``,
    ``ids[PRIM_ID]``, ``words[HIT_U]`` / ``words[HIT_V]``."""
    set_ray(words, ids, ox, oy, oz, dx, dy, dz, tfar)
    rtc_intersect1(scene, address)
    return ids[GEOM_ID] != INVALID_ID


@numba.njit(cache=True, inline="always")
def trace_occluded(scene, words, ids, address, ox, oy, oz, dx, dy, dz, tfar) -> bool:
    """Embree's any-hit query of one ray from t = 0 to ``tfar``: True where a triangle blocks it
    (Embree marks a blocked ray by setting its t_far to -inf)."""
    set_ray(words, ids, ox, oy, oz, dx, dy, dz, tfar)
    rtc_occluded1(scene, address)
    return words[TFAR] == -np.inf


@numba.njit(parallel=True, nogil=True, cache=True)
def intersect_rays(
    scene, workers, origins, directions, t_min, t_max,
    faces, face_normals, vertex_normals, face_material_ids, uvs, vertex_colors, material_albedo,
    use_uvs, use_vertex_colors, finish_albedo,
    hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id, instance_id, bary_u, bary_v,
):  # fmt: skip
    """Closest hits through Embree, with `hit_attributes` written per ray (misses as `Hits.empty`
    writes them; ``instance_id`` is -1 already), by ``workers`` workers (`embree_workers`).
    Embree's (u, v) also go to ``bary_u`` / ``bary_v`` unless those are empty (the caller's
    texture step reads them)."""
    n = origins.shape[0]
    keep_barycentrics = bary_u.shape[0] > 0
    next_block = np.zeros(1, np.int64)
    for _ in numba.prange(workers):
        words, ids, address = ray_record()
        # A block is traced first, then its records written in a tight loop of its own, where the
        # CPU overlaps the table reads of many rays; each ray's reads used to wait behind its own
        # Embree call (2.4M-triangle hairball, 131k rays on one thread: the work around Embree's
        # 145 ms took 44 ms, now 25).
        block_prim = np.empty(BLOCK_ROWS, np.int64)
        block_t, block_u, block_v = np.empty(BLOCK_ROWS, np.float32), np.empty(BLOCK_ROWS, np.float32), np.empty(BLOCK_ROWS, np.float32)
        while True:
            start, stop = next_rows(next_block, n)
            if start >= n:
                break
            for i in range(start, stop):
                ok, sx, sy, sz, tfar = row_embree_ray(origins, directions, t_min, t_max, i)
                block_prim[i - start] = -1
                if ok and trace_closest(scene, words, ids, address, sx, sy, sz, directions[i, 0], directions[i, 1], directions[i, 2],
                                        tfar):  # fmt: skip
                    block_prim[i - start] = ids[PRIM_ID]
                    block_t[i - start], block_u[i - start], block_v[i - start] = words[TFAR], words[HIT_U], words[HIT_V]
            for i in range(start, stop):
                p = block_prim[i - start]
                if p < 0:
                    write_miss(i, hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id, instance_id)
                    continue
                u, v = block_u[i - start], block_v[i - start]
                if keep_barycentrics:
                    bary_u[i], bary_v[i] = u, v
                hit_attributes(i, p, block_t[i - start], u, v, t_min[i],
                               faces, face_normals, vertex_normals, face_material_ids, uvs, vertex_colors, material_albedo,
                               use_uvs, use_vertex_colors, finish_albedo,
                               hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id)  # fmt: skip


@numba.njit(parallel=True, nogil=True, cache=True)
def occluded_rays(scene, workers, origins, directions, t_min, t_max, blocked) -> None:
    """``blocked[i]``: Embree finds a triangle within ray i's interval (invalid rays: False); as
    `intersect_rays`, by ``workers`` workers."""
    n = origins.shape[0]
    next_block = np.zeros(1, np.int64)
    for _ in numba.prange(workers):
        words, ids, address = ray_record()
        while True:
            start, stop = next_rows(next_block, n)
            if start >= n:
                break
            for i in range(start, stop):
                ok, sx, sy, sz, tfar = row_embree_ray(origins, directions, t_min, t_max, i)
                blocked[i] = ok and trace_occluded(scene, words, ids, address, sx, sy, sz, directions[i, 0], directions[i, 1],
                                                   directions[i, 2], tfar)  # fmt: skip


@numba.njit(parallel=True, nogil=True, cache=True)
def closest_prepared(scene, workers, shifted, directions, tfar, prim_id, bary_u, bary_v) -> None:
    """Closest hits of prepared valid rays (origin at t = 0, interval length ``tfar``; the scene
    TLAS's pairs), by ``workers`` workers (`embree_workers`): ``prim_id`` (-1: miss), ``tfar``
    overwritten with the hit's distance on hits, ``bary_u`` / ``bary_v`` Embree's (u, v)."""
    n = shifted.shape[0]
    next_block = np.zeros(1, np.int64)
    for _ in numba.prange(workers):
        words, ids, address = ray_record()
        while True:
            start, stop = next_rows(next_block, n)
            if start >= n:
                break
            for i in range(start, stop):
                found = trace_closest(scene, words, ids, address, shifted[i, 0], shifted[i, 1], shifted[i, 2], directions[i, 0],
                                      directions[i, 1], directions[i, 2], tfar[i])  # fmt: skip
                prim_id[i] = np.int32(ids[PRIM_ID]) if found else np.int32(-1)
                if found:
                    tfar[i] = words[TFAR]
                bary_u[i], bary_v[i] = words[HIT_U], words[HIT_V]


@numba.njit(parallel=True, nogil=True, cache=True)
def occluded_prepared(scene, workers, shifted, directions, tfar, geom_id) -> None:
    """`closest_prepared` for shadow rays: ``geom_id`` 0 where blocked, -1 where not."""
    n = shifted.shape[0]
    next_block = np.zeros(1, np.int64)
    for _ in numba.prange(workers):
        words, ids, address = ray_record()
        while True:
            start, stop = next_rows(next_block, n)
            if start >= n:
                break
            for i in range(start, stop):
                blocked = trace_occluded(scene, words, ids, address, shifted[i, 0], shifted[i, 1], shifted[i, 2], directions[i, 0],
                                         directions[i, 1], directions[i, 2], tfar[i])  # fmt: skip
                geom_id[i] = 0 if blocked else -1


@numba.njit(cache=True, inline="always")
def surface_at(p, bu, bv, faces, face_normals, vertex_normals, face_material_ids, uvs, vertex_colors, material_albedo,
               use_uvs, use_vertex_colors, finish_albedo):  # fmt: skip
    """Triangle ``p``'s object-space surface at Embree's (u, v) = (``bu``, ``bv``), which weight
    its vertices 1 and 2: shading normal (x, y, z), geometric normal (x, y, z), material id, uv
    (2), albedo (3). The shading normal interpolates ``vertex_normals``, falling back to the face
    normal where that vanishes; uv interpolates ``uvs`` when ``use_uvs`` (zeros otherwise). The
    albedo is ``material_albedo[clip(material)]``; with ``finish_albedo`` it is also multiplied by
    the interpolated vertex colour (``use_vertex_colors``) and clipped to [0, 1] — without it the
    caller still applies textures, vertex colours and the clip. Float32 operations in the order of
    the numpy reference (tests/test_mesh_blas_kernels.py), so `MeshBLAS.intersect` and the scene
    TLAS's fused path (`tlas_kernels.finish_hits`) answer bit for bit alike."""
    one = np.float32(1.0)
    zero = np.float32(0.0)
    bw = one - bu - bv
    a, b, c3 = faces[p, 0], faces[p, 1], faces[p, 2]
    sx = bw * vertex_normals[a, 0] + bu * vertex_normals[b, 0] + bv * vertex_normals[c3, 0]
    sy = bw * vertex_normals[a, 1] + bu * vertex_normals[b, 1] + bv * vertex_normals[c3, 1]
    sz = bw * vertex_normals[a, 2] + bu * vertex_normals[b, 2] + bv * vertex_normals[c3, 2]
    gx, gy, gz = face_normals[p, 0], face_normals[p, 1], face_normals[p, 2]
    length = np.float32(math.sqrt(sx * sx + sy * sy + sz * sz))  # float32 root of a float32 sum, as np.linalg.norm
    if length > _NORMAL_EPS:
        sx, sy, sz = sx / length, sy / length, sz / length
    else:
        sx, sy, sz = gx, gy, gz
    m = face_material_ids[p]
    u0, u1 = zero, zero
    if use_uvs:
        u0 = bw * uvs[a, 0] + bu * uvs[b, 0] + bv * uvs[c3, 0]
        u1 = bw * uvs[a, 1] + bu * uvs[b, 1] + bv * uvs[c3, 1]
    k = min(max(m, 0), material_albedo.shape[0] - 1)
    r, g, bl = material_albedo[k, 0], material_albedo[k, 1], material_albedo[k, 2]
    if finish_albedo:
        if use_vertex_colors:
            r = r * (bw * vertex_colors[a, 0] + bu * vertex_colors[b, 0] + bv * vertex_colors[c3, 0])
            g = g * (bw * vertex_colors[a, 1] + bu * vertex_colors[b, 1] + bv * vertex_colors[c3, 1])
            bl = bl * (bw * vertex_colors[a, 2] + bu * vertex_colors[b, 2] + bv * vertex_colors[c3, 2])
        r, g, bl = min(max(r, zero), one), min(max(g, zero), one), min(max(bl, zero), one)
    return sx, sy, sz, gx, gy, gz, m, u0, u1, r, g, bl


@numba.njit(cache=True, inline="always")
def hit_attributes(
    i, p, tfar, bu, bv, t_min,
    faces, face_normals, vertex_normals, face_material_ids, uvs, vertex_colors, material_albedo,
    use_uvs, use_vertex_colors, finish_albedo,
    hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id,
):  # fmt: skip
    """Row ``i``'s hit record from Embree's hit: triangle ``p``, distance ``tfar`` from the origin
    moved to ``t_min``, barycentrics (``bu``, ``bv``); the surface as `surface_at` gives it."""
    hit[i] = True
    # Embree measured from the origin moved to t_min (to the origin itself when t_min = -inf).
    t[i] = tfar + (t_min if np.isfinite(t_min) else np.float32(0.0))
    primitive_id[i] = p
    (normal[i, 0], normal[i, 1], normal[i, 2], geometric_normal[i, 0], geometric_normal[i, 1], geometric_normal[i, 2],
     material_id[i], uv[i, 0], uv[i, 1], albedo[i, 0], albedo[i, 1], albedo[i, 2]) = surface_at(
        p, bu, bv, faces, face_normals, vertex_normals, face_material_ids, uvs, vertex_colors, material_albedo,
        use_uvs, use_vertex_colors, finish_albedo)  # fmt: skip

"""Fused numba passes around an Embree query: one before (validate rays, move origins to t_min,
clamp t_far) and one after (hit mask, t, interpolated hit attributes).

`MeshBLAS` spent more time in numpy/torch glue (a dozen temporaries per ray, 2-thread torch
validation, gathers over index arrays) than Embree spent tracing. These passes read each input
once and write each output once. They release the GIL: `MeshBLAS` runs them, with Embree (which
releases it too), on chunks of rays in parallel threads. All arithmetic stays in float32 and in the
same order as the numpy code they replaced, so results are bit-identical to it.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..rays_kernels import valid_ray

__all__ = ["prepare_embree_rays", "placeholder_directions", "closest_hit_attributes", "occlusion_result"]

# Embree works in float32; "infinite" t_max is passed as a large finite value.
EMBREE_TFAR_MAX = np.float32(1e37)
_NORMAL_EPS = np.float32(1e-12)


@numba.njit(nogil=True, cache=True)
def prepare_embree_rays(origins, directions, t_min, t_max, shifted, tfar, valid) -> int:
    """Fill ``shifted`` [N,3] (origin moved to ``t_min``; Embree always starts at t = 0), ``tfar``
    [N] (interval length, -1 for invalid rays) and ``valid`` [N]; returns the number of invalid rays.

    A ray is valid when its origin and direction are finite, its direction non-zero and
    ``t_min < t_max`` (neither NaN), as `neuralrt.rays.valid_ray_mask` defines it.
    """
    n = origins.shape[0]
    n_invalid = 0
    for i in range(n):
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        t0, t1 = t_min[i], t_max[i]
        ok = valid_ray(origins, directions, t_min, t_max, i)
        valid[i] = ok
        if not ok:
            # A harmless placeholder that Embree skips (t_far < t_near = 0).
            shifted[i, 0] = np.float32(0.0)
            shifted[i, 1] = np.float32(0.0)
            shifted[i, 2] = np.float32(0.0)
            tfar[i] = np.float32(-1.0)
            n_invalid += 1
            continue
        start = t0 if np.isfinite(t0) else np.float32(0.0)
        shifted[i, 0] = ox + start * dx
        shifted[i, 1] = oy + start * dy
        shifted[i, 2] = oz + start * dz
        length = t1 - t0  # float32, as t_max - t_min in numpy
        if not (length <= EMBREE_TFAR_MAX):  # also catches NaN (-inf t_min with +inf t_max)
            length = EMBREE_TFAR_MAX
        tfar[i] = length
    return n_invalid


@numba.njit(nogil=True, cache=True)
def placeholder_directions(directions, valid, out) -> None:
    """``out`` = ``directions`` with invalid rows replaced by (1, 0, 0), so Embree never sees NaN."""
    for i in range(directions.shape[0]):
        if valid[i]:
            out[i, 0], out[i, 1], out[i, 2] = directions[i, 0], directions[i, 1], directions[i, 2]
        else:
            out[i, 0], out[i, 1], out[i, 2] = np.float32(1.0), np.float32(0.0), np.float32(0.0)


@numba.njit(nogil=True, cache=True)
def occlusion_result(geom_id, valid, out) -> None:
    """``out`` = Embree reported a blocker (geomID >= 0) on a valid ray."""
    for i in range(geom_id.shape[0]):
        out[i] = geom_id[i] >= 0 and valid[i]


@numba.njit(nogil=True, cache=True)
def closest_hit_attributes(
    prim_id, tfar, bary_u, bary_v, valid, t_min,
    faces, face_normals, vertex_normals, face_material_ids, uvs, vertex_colors, material_albedo,
    use_uvs, use_vertex_colors, finish_albedo,
    hit, t, normal, geometric_normal, uv, albedo, material_id, primitive_id,
):  # fmt: skip
    """Per-ray hit record from Embree's primID / tfar / (u, v), written into the output arrays.

    Misses get t = inf, zero normals and uv, albedo 1, material and primitive id -1. For hits the
    shading normal interpolates ``vertex_normals`` (falling back to the face normal when that
    vanishes); ``uv`` interpolates ``uvs`` when ``use_uvs`` (zeros otherwise). ``albedo`` is
    ``material_albedo[clip(material)]``; with ``finish_albedo`` it is also multiplied by the
    interpolated vertex colour (``use_vertex_colors``) and clipped to [0, 1] — without it the caller
    still applies textures, vertex colours and the clip.
    """
    n = prim_id.shape[0]
    n_materials = material_albedo.shape[0]
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for i in range(n):
        p = prim_id[i]
        if p < 0 or not valid[i]:
            hit[i] = False
            t[i] = np.inf
            for c in range(3):
                normal[i, c] = zero
                geometric_normal[i, c] = zero
                albedo[i, c] = one
            uv[i, 0] = zero
            uv[i, 1] = zero
            material_id[i] = -1
            primitive_id[i] = -1
            continue
        hit[i] = True
        # Embree measured from the origin moved to t_min (to the origin itself when t_min = -inf).
        t[i] = tfar[i] + (t_min[i] if np.isfinite(t_min[i]) else zero)
        primitive_id[i] = p
        # Embree's (u, v) weight vertices 1 and 2 of the triangle.
        bu, bv = bary_u[i], bary_v[i]
        bw = one - bu - bv
        a, b, c3 = faces[p, 0], faces[p, 1], faces[p, 2]
        sx = bw * vertex_normals[a, 0] + bu * vertex_normals[b, 0] + bv * vertex_normals[c3, 0]
        sy = bw * vertex_normals[a, 1] + bu * vertex_normals[b, 1] + bv * vertex_normals[c3, 1]
        sz = bw * vertex_normals[a, 2] + bu * vertex_normals[b, 2] + bv * vertex_normals[c3, 2]
        gx, gy, gz = face_normals[p, 0], face_normals[p, 1], face_normals[p, 2]
        geometric_normal[i, 0], geometric_normal[i, 1], geometric_normal[i, 2] = gx, gy, gz
        # float32 square root of a float32 sum, as np.linalg.norm computes it.
        length = np.float32(math.sqrt(sx * sx + sy * sy + sz * sz))
        if length > _NORMAL_EPS:
            normal[i, 0], normal[i, 1], normal[i, 2] = sx / length, sy / length, sz / length
        else:
            normal[i, 0], normal[i, 1], normal[i, 2] = gx, gy, gz
        m = face_material_ids[p]
        material_id[i] = m
        if use_uvs:
            uv[i, 0] = bw * uvs[a, 0] + bu * uvs[b, 0] + bv * uvs[c3, 0]
            uv[i, 1] = bw * uvs[a, 1] + bu * uvs[b, 1] + bv * uvs[c3, 1]
        else:
            uv[i, 0] = zero
            uv[i, 1] = zero
        k = min(max(m, 0), n_materials - 1)
        for c in range(3):
            value = material_albedo[k, c]
            if finish_albedo:
                if use_vertex_colors:
                    cv = bw * vertex_colors[a, c] + bu * vertex_colors[b, c] + bv * vertex_colors[c3, c]
                    value = value * cv
                value = min(max(value, zero), one)
            albedo[i, c] = value

"""`BoxRayDistribution`'s ray construction and pool refill on the CPU: numba passes over the random
numbers the distribution's torch generator drew (the same draws, in the same order, as its torch
path, which stays the path on other devices and the reference these are tested against).

Why: with the ~25 small torch ops of a batch (gathers, sin/cos/sqrt, stacks, masks) the drawing
thread spent ~2.8 ms of a bunny `hq` batch around Embree's ~1.7 ms, and on two cores that time is
taken from the training step running beside it. The math is the torch path's, in float32; sin,
cos and sqrt may round differently (last-ulp differences, tested).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def _cosine_direction(u0, u1, zx, zy, zz, out, i):
    """``out[i]``: the direction with pdf cos/pi around the unit axis (zx, zy, zz) for uniforms
    (u0, u1); the orthonormal basis of Duff et al. 2017, as `cosine_weighted_directions`."""
    r = np.float32(math.sqrt(u0))
    phi = np.float32(2.0 * math.pi) * u1
    lx, ly = r * np.float32(math.cos(phi)), r * np.float32(math.sin(phi))
    lz = np.float32(math.sqrt(max(np.float32(1.0) - u0, np.float32(0.0))))
    sign = np.float32(1.0) if zz >= 0 else np.float32(-1.0)
    a = np.float32(-1.0) / (sign + zz)
    b = zx * zy * a
    out[i, 0] = lx * (np.float32(1.0) + sign * zx * zx * a) + ly * b + lz * zx
    out[i, 1] = lx * (sign * b) + ly * (sign + zy * zy * a) + lz * zy
    out[i, 2] = lx * (-sign * zx) + ly * (-zy) + lz * zz


# Rays per parallel block: a multiple of every SIMD width, so that the same rays fall in a
# vectorised loop's body or remainder whatever the thread count (the same bits on any machine size).
_BLOCK = 512


@numba.njit(cache=True, parallel=True)
def outside_rays(normals, uniforms, center, radius, origins, directions):
    """Rays ``[0, n)`` of ``origins``/``directions``: from ``center + radius * p`` with ``p`` the
    normalised Gaussian draw ``normals[i]``, cosine-weighted around ``-p``. Blocks of rays in
    parallel: the drawing thread's serial work would otherwise grow against a step that shrinks
    with more cores."""
    n = normals.shape[0]
    for block in numba.prange((n + _BLOCK - 1) // _BLOCK):
        for i in range(block * _BLOCK, min(n, (block + 1) * _BLOCK)):
            vx, vy, vz = normals[i, 0], normals[i, 1], normals[i, 2]
            length = max(np.float32(math.sqrt(vx * vx + vy * vy + vz * vz)), np.float32(1e-30))
            px, py, pz = vx / length, vy / length, vz / length
            origins[i, 0] = center[0] + radius * px
            origins[i, 1] = center[1] + radius * py
            origins[i, 2] = center[2] + radius * pz
            _cosine_direction(uniforms[i, 0], uniforms[i, 1], -px, -py, -pz, directions, i)


@numba.njit(cache=True, parallel=True)
def surface_rays(picks, uniforms, pool_points, pool_normals, offset, origins, directions, first):
    """Rays ``first + i``: from pool point ``picks[i]`` offset along its normal, cosine-weighted
    around that normal (blocks of rays in parallel, as `outside_rays`)."""
    n = picks.shape[0]
    for block in numba.prange((n + _BLOCK - 1) // _BLOCK):
        lo, hi = block * _BLOCK, min(n, (block + 1) * _BLOCK)
        # The pool's points and normals gathered first, in a loop of loads alone: the pool (2^18
        # entries, 6 MB) misses the caches at random, and with the direction's math in the same
        # loop few of those misses overlapped (0.37 ms for a bunny batch's 4,096 surface rays).
        for i in range(lo, hi):
            k, j = picks[i], first + i
            for c in range(3):
                origins[j, c] = pool_points[k, c]
                directions[j, c] = pool_normals[k, c]
        for i in range(lo, hi):
            j = first + i
            nx, ny, nz = directions[j, 0], directions[j, 1], directions[j, 2]
            origins[j, 0] += offset * nx
            origins[j, 1] += offset * ny
            origins[j, 2] += offset * nz
            _cosine_direction(uniforms[i, 0], uniforms[i, 1], nx, ny, nz, directions, j)


@numba.njit(cache=True)
def refill_pool(origins, directions, hit, t, normals, pool_points, pool_normals, cursor):
    """Writes the hit points of rays ``[0, len(hit))`` (and their normals, turned to face the
    arriving ray) into the full ring buffer from slot ``cursor`` on, oldest first, at most one
    pass over it; returns the next cursor."""
    size = pool_points.shape[0]
    written = 0
    for i in range(hit.shape[0]):
        if not hit[i] or written == size:
            continue
        slot = (cursor + written) % size
        for c in range(3):
            pool_points[slot, c] = origins[i, c] + t[i] * directions[i, c]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        flip = nx * directions[i, 0] + ny * directions[i, 1] + nz * directions[i, 2] > 0
        pool_normals[slot, 0] = -nx if flip else nx
        pool_normals[slot, 1] = -ny if flip else ny
        pool_normals[slot, 2] = -nz if flip else nz
        written += 1
    return (cursor + written) % size

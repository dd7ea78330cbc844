"""Conservative surface voxelization of triangles, and bit-packed occupancy.

A voxel is marked when a triangle overlaps its *closed* box (touching counts), decided exactly by
the separating-axis test of Akenine-Möller ("Fast 3D triangle-box overlap testing", 2001): the
13 candidate axes are the 3 box normals, the triangle normal and the 9 cross products of box
and triangle edges. Sampling points on triangles instead is not conservative (it misses thin
parts), and a missed voxel makes the hits inside it impossible for LSNIF to learn.

Coordinates are *unit-box* coordinates: the caller maps the object's (inflated) AABB to
``[0, 1]^3``. Voxel ``(i, j, k)`` covers ``[i/V, (i+1)/V] x [j/V, (j+1)/V] x [k/V, (k+1)/V]`` and
occupancy is indexed ``occ[x, y, z]``.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["voxelize_triangles", "pack_occupancy", "unpack_occupancy", "DEFAULT_TOLERANCE"]

# Voxel boxes are grown by this many voxel widths before the overlap test. It is far below a
# voxel, but above the float32 error of points computed on the surface (e.g. Embree hit points
# mapped to the unit box), so a surface point never lands in a voxel its triangle was not
# counted in.
DEFAULT_TOLERANCE = 1e-4


@numba.njit(cache=True, inline="always")
def _separated_on_axis(ax, ay, az, v0, v1, v2, half) -> bool:
    """True when the triangle's projection onto axis ``a`` misses the box's projection."""
    p0 = ax * v0[0] + ay * v0[1] + az * v0[2]
    p1 = ax * v1[0] + ay * v1[1] + az * v1[2]
    p2 = ax * v2[0] + ay * v2[1] + az * v2[2]
    radius = half * (abs(ax) + abs(ay) + abs(az))
    lo = min(p0, min(p1, p2))
    hi = max(p0, max(p1, p2))
    # Strict comparisons: a triangle touching the closed box is not separated.
    return lo > radius or hi < -radius


@numba.njit(cache=True)
def _triangle_box_overlap(v0, v1, v2, half) -> bool:
    """Separating-axis test of a triangle (vertices relative to the box centre) and a cube."""
    e = np.empty((3, 3))
    for c in range(3):
        e[0, c] = v1[c] - v0[c]
        e[1, c] = v2[c] - v1[c]
        e[2, c] = v0[c] - v2[c]
    # Box normals (the triangle's bounding box against the cube).
    for axis in range(3):
        lo = min(v0[axis], min(v1[axis], v2[axis]))
        hi = max(v0[axis], max(v1[axis], v2[axis]))
        if lo > half or hi < -half:
            return False
    # Triangle normal.
    nx = e[0, 1] * e[1, 2] - e[0, 2] * e[1, 1]
    ny = e[0, 2] * e[1, 0] - e[0, 0] * e[1, 2]
    nz = e[0, 0] * e[1, 1] - e[0, 1] * e[1, 0]
    if _separated_on_axis(nx, ny, nz, v0, v1, v2, half):
        return False
    # Cross products of box axes and triangle edges (a zero axis never separates).
    for i in range(3):
        ex, ey, ez = e[i, 0], e[i, 1], e[i, 2]
        if _separated_on_axis(0.0, -ez, ey, v0, v1, v2, half):  # x cross e
            return False
        if _separated_on_axis(ez, 0.0, -ex, v0, v1, v2, half):  # y cross e
            return False
        if _separated_on_axis(-ey, ex, 0.0, v0, v1, v2, half):  # z cross e
            return False
    return True


@numba.njit(parallel=True, cache=True)
def _voxelize_kernel(tris, resolution, tolerance, occ):
    """Mark every voxel whose closed (tolerance-grown) box overlaps a triangle.

    ``tris`` are in voxel units ([0, V]^3). Parallel over triangles; concurrent stores all write
    1, so the races are benign.
    """
    half = 0.5 + tolerance
    for f in numba.prange(tris.shape[0]):
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        outside = False
        for c in range(3):
            mn = min(tris[f, 0, c], min(tris[f, 1, c], tris[f, 2, c]))
            mx = max(tris[f, 0, c], max(tris[f, 1, c], tris[f, 2, c]))
            if not (mx >= -tolerance and mn <= resolution + tolerance):  # also rejects NaN
                outside = True
                break
            lo[c] = max(0, int(np.floor(mn - tolerance)))
            hi[c] = min(resolution - 1, int(np.floor(mx + tolerance)))
        if outside:
            continue
        v0 = np.empty(3)
        v1 = np.empty(3)
        v2 = np.empty(3)
        for i in range(lo[0], hi[0] + 1):
            for j in range(lo[1], hi[1] + 1):
                for k in range(lo[2], hi[2] + 1):
                    if occ[i, j, k]:
                        continue
                    centre = (i + 0.5, j + 0.5, k + 0.5)
                    for c in range(3):
                        v0[c] = tris[f, 0, c] - centre[c]
                        v1[c] = tris[f, 1, c] - centre[c]
                        v2[c] = tris[f, 2, c] - centre[c]
                    if _triangle_box_overlap(v0, v1, v2, half):
                        occ[i, j, k] = 1


def voxelize_triangles(
    triangles: np.ndarray, resolution: int = 32, *, tolerance: float = DEFAULT_TOLERANCE
) -> np.ndarray:
    """Surface occupancy ``occ[x, y, z]`` (bool ``[V, V, V]``) of triangles in unit-box coordinates.

    A voxel is occupied when some triangle overlaps its closed box grown by ``tolerance`` voxel
    widths (exact separating-axis test, so thin parts are never lost). Triangles or parts outside
    ``[0, 1]^3`` are ignored. Degenerate triangles (segments, points) mark the voxels they touch.
    """
    tris = np.asarray(triangles)
    if tris.ndim != 3 or tris.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape [F, 3, 3], got {tris.shape}")
    if int(resolution) != resolution or resolution < 1:
        raise ValueError(f"voxel resolution must be a positive integer, got {resolution}")
    if not tolerance >= 0:
        raise ValueError(f"voxelization tolerance must be >= 0, got {tolerance}")
    resolution = int(resolution)
    occ = np.zeros((resolution,) * 3, np.uint8)
    if len(tris):
        # float64 in voxel units: the test is then exact up to double rounding.
        scaled = np.ascontiguousarray(tris, dtype=np.float64) * resolution
        _voxelize_kernel(scaled, resolution, float(tolerance), occ)
    return occ.astype(bool)


def pack_occupancy(occ: np.ndarray) -> np.ndarray:
    """Occupancy ``[V, V, V]`` bool -> ``ceil(V^3 / 8)`` uint8 bytes (C order, big-endian bits)."""
    occ = np.asarray(occ)
    if occ.ndim != 3 or len(set(occ.shape)) != 1:
        raise ValueError(f"occupancy must be a cubic [V, V, V] array, got shape {occ.shape}")
    return np.packbits(occ.astype(bool).ravel())


def unpack_occupancy(bits: np.ndarray, resolution: int) -> np.ndarray:
    """Inverse of `pack_occupancy`: ``ceil(V^3 / 8)`` uint8 bytes -> bool ``[V, V, V]``."""
    bits = np.asarray(bits)
    n = int(resolution) ** 3
    if bits.dtype != np.uint8 or bits.ndim != 1 or bits.size != (n + 7) // 8:
        raise ValueError(
            f"packed occupancy for resolution {resolution} must be {(n + 7) // 8} uint8 bytes, "
            f"got {bits.size} of {bits.dtype}"
        )
    return np.unpackbits(bits, count=n).astype(bool).reshape((resolution,) * 3)

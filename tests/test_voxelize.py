"""Voxelization: exact against a brute-force clipping reference, conservative, packing round trip."""

import numpy as np
import pytest
import trimesh

from neuralrt.geometry.voxelize import (
    DEFAULT_TOLERANCE,
    pack_occupancy,
    unpack_occupancy,
    voxelize_triangles,
)


def _clip_polygon(poly: list[np.ndarray], axis: int, bound: float, keep_below: bool) -> list:
    """Sutherland-Hodgman: keep the part of a convex polygon with x[axis] <= bound (or >=)."""
    out = []
    sign = 1.0 if keep_below else -1.0
    for a, b in zip(poly, poly[1:] + poly[:1]):
        da, db = sign * (a[axis] - bound), sign * (b[axis] - bound)
        if da <= 0:
            out.append(a)
        if (da < 0 < db) or (db < 0 < da):
            out.append(a + (b - a) * (da / (da - db)))
    return out


def _brute_force_occupancy(tris: np.ndarray, res: int, tol: float) -> np.ndarray:
    """Occupied iff clipping the triangle to the closed (grown) voxel box leaves anything."""
    occ = np.zeros((res,) * 3, bool)
    scaled = tris.astype(np.float64) * res
    for i, j, k in np.ndindex(occ.shape):
        lo = np.array([i, j, k], float) - tol
        hi = lo + 1 + 2 * tol
        for tri in scaled:
            poly = list(tri)
            for axis in range(3):
                poly = _clip_polygon(poly, axis, hi[axis], True) if poly else poly
                poly = _clip_polygon(poly, axis, lo[axis], False) if poly else poly
            if poly:
                occ[i, j, k] = True
                break
    return occ


def test_matches_brute_force_on_random_triangles():
    rng = np.random.default_rng(1)
    centres = rng.uniform(0, 1, (40, 1, 3))
    tris = centres + rng.normal(0, 0.15, (40, 3, 3))  # some cross the box boundary
    occ = voxelize_triangles(tris, 8)
    assert occ.any()
    np.testing.assert_array_equal(occ, _brute_force_occupancy(tris, 8, DEFAULT_TOLERANCE))


def test_matches_brute_force_on_thin_slivers():
    rng = np.random.default_rng(2)
    a = rng.uniform(0.1, 0.9, (30, 3))
    b = rng.uniform(0.1, 0.9, (30, 3))
    c = a + 1e-3 * rng.normal(size=(30, 3))  # needle triangles, thinner than a voxel
    tris = np.stack([a, b, c], axis=1)
    np.testing.assert_array_equal(
        voxelize_triangles(tris, 6), _brute_force_occupancy(tris, 6, DEFAULT_TOLERANCE)
    )


def test_no_point_on_a_mesh_lands_in_an_empty_voxel():
    mesh = trimesh.creation.torus(0.3, 0.08)
    verts = (mesh.vertices - mesh.bounds[0]) / (mesh.bounds[1] - mesh.bounds[0]).max() * 0.9 + 0.05
    tris = verts[mesh.faces]
    occ = voxelize_triangles(tris, 32)
    rng = np.random.default_rng(3)
    uv = rng.uniform(size=(tris.shape[0], 64, 2))
    flip = uv.sum(-1) > 1
    uv[flip] = 1 - uv[flip]
    pts = tris[:, None, 0] + uv[..., :1] * (tris[:, None, 1] - tris[:, None, 0]) + uv[..., 1:] * (
        tris[:, None, 2] - tris[:, None, 0]
    )
    idx = np.clip(np.floor(pts.reshape(-1, 3) * 32).astype(int), 0, 31)
    assert occ[idx[:, 0], idx[:, 1], idx[:, 2]].all()
    # and it is a surface voxelization, not a solid one: the torus hole and far corners are empty
    assert not occ[15:17, 15:17, :].any() and 0.02 < occ.mean() < 0.3


def test_closed_boxes_count_touching_faces():
    # A triangle lying exactly on the plane x = 0.5 touches voxels on both sides.
    tris = np.array([[[0.5, 0.3, 0.3], [0.5, 0.34, 0.3], [0.5, 0.3, 0.34]]])
    occ = voxelize_triangles(tris, 4)
    assert occ[1, 1, 1] and occ[2, 1, 1] and occ.sum() == 2


def test_tiny_triangle_marks_exactly_its_voxel():
    tris = np.array([[[0.30, 0.60, 0.10], [0.31, 0.60, 0.10], [0.30, 0.61, 0.11]]])
    occ = voxelize_triangles(tris, 8)
    assert occ.sum() == 1 and occ[2, 4, 0]


def test_outside_and_degenerate_input():
    tris = np.array(
        [
            [[1.5, 1.5, 1.5], [1.6, 1.5, 1.5], [1.5, 1.6, 1.5]],  # outside the box
            [[np.nan, 0, 0], [0, 0, 0], [0, 0, 0]],  # NaN
            [[0.1, 0.1, 0.1], [0.9, 0.1, 0.1], [0.5, 0.1, 0.1]],  # a segment along x
        ]
    )
    occ = voxelize_triangles(tris, 4)
    assert occ[:, 0, 0].all() and occ.sum() == 4
    assert not voxelize_triangles(np.zeros((0, 3, 3)), 4).any()
    with pytest.raises(ValueError, match="shape"):
        voxelize_triangles(np.zeros((3, 3)), 4)
    with pytest.raises(ValueError, match="resolution"):
        voxelize_triangles(np.zeros((1, 3, 3)), 0)


def test_pack_round_trip_and_size():
    rng = np.random.default_rng(4)
    occ = rng.uniform(size=(32, 32, 32)) < 0.1
    bits = pack_occupancy(occ)
    assert bits.dtype == np.uint8 and bits.nbytes == 4096
    np.testing.assert_array_equal(unpack_occupancy(bits, 32), occ)
    odd = rng.uniform(size=(5, 5, 5)) < 0.5
    np.testing.assert_array_equal(unpack_occupancy(pack_occupancy(odd), 5), odd)
    with pytest.raises(ValueError, match="4096"):
        unpack_occupancy(bits[:-1], 32)
    with pytest.raises(ValueError, match="cubic"):
        pack_occupancy(np.zeros((4, 4, 2), bool))

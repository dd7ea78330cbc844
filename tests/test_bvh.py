"""Our SAH BVH: a real tree (every triangle once, boxes nest, leaf sizes) that traces like Embree."""

import time

import numpy as np
import pytest
import torch

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.errors import MeshError
from neuralrt.geometry import procedural as P
from neuralrt.geometry.bvh import BVH, build_bvh, collapse_bvh
from neuralrt.rays import Rays


@pytest.fixture(scope="module")
def statue_mesh():
    return P.statue(0, seed=2)


@pytest.fixture(scope="module")
def binary(statue_mesh):
    return build_bvh(statue_mesh)


def _closest_hit(bvh: BVH, tri: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[float, int]:
    """Reference traversal: slab test per node, Moller-Trumbore in leaves, keep the closest."""
    best_t, best_prim = np.inf, -1
    inv = 1.0 / np.where(d == 0, 1e-30, d)
    stack = [0]
    while stack:
        node = stack.pop()
        t0 = (bvh.node_lo[node] - o) * inv
        t1 = (bvh.node_hi[node] - o) * inv
        t_near, t_far = np.minimum(t0, t1).max(), np.maximum(t0, t1).min()
        if t_near > t_far * (1 + 1e-6) + 1e-7 or t_far < 0 or t_near > best_t:
            continue
        if bvh.leaf_count[node]:
            s = bvh.leaf_start[node]
            for prim in bvh.prim_order[s:s + bvh.leaf_count[node]]:
                v0, v1, v2 = tri[prim]
                e1, e2 = v1 - v0, v2 - v0
                p = np.cross(d, e2)
                det = e1 @ p
                if abs(det) < 1e-12:
                    continue
                tv = o - v0
                u = (tv @ p) / det
                q = np.cross(tv, e1)
                v = (d @ q) / det
                t = (e2 @ q) / det
                if u >= 0 and v >= 0 and u + v <= 1 and 0 < t < best_t:
                    best_t, best_prim = t, int(prim)
        else:
            stack.extend(int(c) for c in bvh.children[node] if c >= 0)
    return best_t, best_prim


def _check_structure(bvh: BVH, tri: np.ndarray, max_leaf: int) -> None:
    n = len(tri)
    # Every triangle in exactly one leaf, and leaf ranges tile prim_order.
    assert np.array_equal(np.sort(bvh.prim_order), np.arange(n))
    leaves = np.nonzero(bvh.is_leaf)[0]
    covered = np.zeros(n, np.int64)
    for leaf in leaves:
        covered[bvh.leaf_start[leaf]:bvh.leaf_start[leaf] + bvh.leaf_count[leaf]] += 1
    assert (covered == 1).all()
    assert bvh.leaf_count.max() <= max_leaf
    # Tree shape: each non-root node has exactly one parent; leaves have no children.
    kids = bvh.children[bvh.children >= 0]
    assert np.array_equal(np.sort(kids), np.arange(1, bvh.num_nodes))
    assert (bvh.children[leaves] == -1).all()
    assert (bvh.child_counts()[~bvh.is_leaf] >= 2).all()
    assert bvh.children.shape[1] == bvh.width
    # Boxes nest: parents contain children, leaves contain their triangles.
    parent = np.repeat(np.arange(bvh.num_nodes), bvh.width).reshape(-1, bvh.width)[bvh.children >= 0]
    assert (bvh.node_lo[kids] >= bvh.node_lo[parent]).all() and (bvh.node_hi[kids] <= bvh.node_hi[parent]).all()
    leaf_of = np.repeat(leaves, bvh.leaf_count[leaves])
    prims = np.concatenate([bvh.prim_order[bvh.leaf_start[l]:bvh.leaf_start[l] + bvh.leaf_count[l]] for l in leaves])
    assert (tri[prims].min(1) >= bvh.node_lo[leaf_of]).all() and (tri[prims].max(1) <= bvh.node_hi[leaf_of]).all()
    assert np.allclose(bvh.node_lo[0], tri.reshape(-1, 3).min(0)) and np.allclose(bvh.node_hi[0], tri.reshape(-1, 3).max(0))


@pytest.mark.parametrize("width", [2, 4, 8])
def test_tree_structure(statue_mesh, binary, width):
    bvh = binary if width == 2 else collapse_bvh(binary, width)
    _check_structure(bvh, statue_mesh.triangles(), max_leaf=2)
    assert bvh.num_leaves == binary.num_leaves  # collapsing only removes internal nodes
    if width > 2:
        assert bvh.num_internal < binary.num_internal
        assert bvh.depth() < binary.depth()
        assert bvh.child_counts().max() == width


@pytest.mark.parametrize("max_leaf", [1, 3, 8])
def test_leaf_size_limit(statue_mesh, max_leaf):
    bvh = build_bvh(statue_mesh, width=4, max_leaf_size=max_leaf, num_bins=8)
    _check_structure(bvh, statue_mesh.triangles(), max_leaf=max_leaf)
    if max_leaf == 1:
        assert bvh.num_leaves == statue_mesh.num_triangles


def test_leaf_boxes_are_tight(binary, statue_mesh):
    """The SAH tree is tight: summed leaf box areas stay within a small factor of the triangle areas."""
    leaves = binary.is_leaf
    ext = binary.node_hi[leaves] - binary.node_lo[leaves]
    box_area = 2 * (ext[:, 0] * ext[:, 1] + ext[:, 1] * ext[:, 2] + ext[:, 2] * ext[:, 0])
    assert box_area.sum() < 3 * 2 * statue_mesh.face_areas().sum()  # measured 1.8x


@pytest.mark.parametrize("width", [2, 4, 8])
def test_traversal_agrees_with_embree(statue_mesh, binary, width):
    rng = np.random.default_rng(0)
    n = 200
    origins = rng.normal(size=(n, 3))
    origins = 2.5 * origins / np.linalg.norm(origins, axis=1, keepdims=True)
    lo, hi = statue_mesh.bounds
    targets = lo + rng.uniform(size=(n, 3)) * (hi - lo)
    dirs = targets - origins
    rays = Rays(torch.tensor(origins, dtype=torch.float32), torch.tensor(dirs, dtype=torch.float32),
                torch.zeros(n), torch.full((n,), np.inf))
    ref = MeshBLAS(statue_mesh).intersect(rays)

    bvh = binary if width == 2 else collapse_bvh(binary, width)
    tri = statue_mesh.triangles().astype(np.float64)
    o32, d32 = rays.origins.numpy().astype(np.float64), rays.directions.numpy().astype(np.float64)
    ours = [_closest_hit(bvh, tri, o32[i], d32[i]) for i in range(n)]
    t = np.array([x[0] for x in ours])
    prim = np.array([x[1] for x in ours])
    assert np.array_equal(np.isfinite(t), ref.hit.numpy())
    assert ref.hit.sum() > 50  # the rays really hit the figure
    hit = ref.hit.numpy()
    assert np.allclose(t[hit], ref.t.numpy()[hit], rtol=1e-4, atol=1e-6)
    assert (prim[hit] == ref.primitive_id.numpy()[hit]).mean() > 0.97  # ties on shared edges may differ


def test_coincident_centroids_and_single_triangle():
    tri = np.tile(np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.float32), (9, 1, 1))
    bvh = build_bvh(tri, width=4)
    _check_structure(bvh, tri, max_leaf=2)
    one = build_bvh(tri[:1], width=8)
    assert one.num_nodes == 1 and one.num_leaves == 1 and one.leaf_count[0] == 1


def test_skewed_input_builds_a_valid_deep_tree():
    """Triangles at geometrically shrinking positions: each binned split peels off only a few."""
    k = np.arange(400)
    x = (0.9**k).astype(np.float32)
    tri = np.zeros((400, 3, 3), np.float32)
    tri[:, :, 0] = x[:, None] * np.array([1.0, 1.0001, 1.0002], np.float32)
    tri[:, 1, 1] = tri[:, 2, 2] = 1e-3
    bvh = build_bvh(tri)
    _check_structure(bvh, tri, max_leaf=2)
    assert bvh.depth() > 2 * np.log2(400)  # far deeper than a balanced tree


def test_bad_input_is_rejected():
    with pytest.raises(MeshError, match="shape"):
        build_bvh(np.zeros((4, 3), np.float32))
    with pytest.raises(MeshError, match="NaN"):
        build_bvh(np.full((2, 3, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="max_leaf_size"):
        build_bvh(np.zeros((2, 3, 3), np.float32), max_leaf_size=0)


def test_deterministic(statue_mesh, binary):
    again = build_bvh(statue_mesh)
    assert np.array_equal(again.prim_order, binary.prim_order) and np.array_equal(again.children, binary.children)


@pytest.mark.slow
def test_million_triangle_build_is_fast():
    mesh = P.hairball(5)
    build_bvh(mesh.triangles()[:1000])  # compile (cached on disk after the first run)
    start = time.perf_counter()
    bvh = build_bvh(mesh, width=4)
    elapsed = time.perf_counter() - start
    assert mesh.num_triangles > 1_000_000
    assert elapsed < 30.0
    assert bvh.num_triangles == mesh.num_triangles and bvh.leaf_count.max() <= 2

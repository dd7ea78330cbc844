"""Classical BVH memory accounting: formulas over the node counts of trees we really build."""

import json
import math

import numpy as np
import pytest

from neuralrt.accel.classical_memory import ClassicalMemory, classical_memory
from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.geometry import procedural as P
from neuralrt.geometry.bvh import build_bvh, collapse_bvh
from neuralrt.geometry.mesh import Mesh, load_mesh


@pytest.fixture(scope="module")
def statue_memory() -> tuple[Mesh, ClassicalMemory]:
    mesh = P.statue(1)
    return mesh, classical_memory(mesh)


def test_formulas_match_node_counts():
    mesh = P.hairball(0)
    mem = classical_memory(mesh)
    binary = build_bvh(mesh)
    a, b = collapse_bvh(binary, 4), collapse_bvh(binary, 8)
    assert mem.triangles == mesh.num_triangles == 37_248
    assert mem.mesh_bytes == mesh.nbytes() == 12 * len(mesh.vertices) + 12 * mesh.num_triangles
    assert (mem.bvh_a_internal_nodes, mem.bvh_a_leaf_nodes) == (a.num_internal, a.num_leaves)
    assert mem.bvh_a_bytes == 128 * (a.num_internal + a.num_leaves)
    assert mem.bvh_b_nodes == b.num_internal and mem.bvh_b_leaves == b.num_leaves == a.num_leaves
    assert mem.bvh_b_bytes == 80 * b.num_internal + 4 * mesh.num_triangles


def test_node_counts_obey_tree_bounds(statue_memory):
    mesh, mem = statue_memory
    f = mesh.num_triangles
    # leaves hold 1..2 triangles; an N-wide tree over L leaves needs >= (L - 1) / (N - 1) internal nodes
    assert math.ceil(f / 2) <= mem.bvh_a_leaf_nodes <= f
    assert mem.bvh_a_internal_nodes >= math.ceil((mem.bvh_a_leaf_nodes - 1) / 3)
    assert mem.bvh_b_nodes >= math.ceil((mem.bvh_b_leaves - 1) / 7)
    assert mem.bvh_b_nodes < mem.bvh_a_internal_nodes < mem.bvh_a_leaf_nodes


def test_bytes_per_triangle_are_in_the_papers_range(statue_memory):
    _, mem = statue_memory
    # LSNIF Table 1 implies ~140 B/triangle for BVH A and ~28 for BVH B; our SAH tree lands near.
    assert 80 <= mem.bvh_a_bytes_per_triangle <= 170
    assert 8 <= mem.bvh_b_bytes_per_triangle <= 40
    assert mem.bvh_b_bytes < mem.bvh_a_bytes / 3


def test_single_triangle_and_as_dict_is_json():
    mesh = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]]))
    mem = classical_memory(mesh)
    assert (mem.bvh_a_internal_nodes, mem.bvh_a_leaf_nodes, mem.bvh_a_bytes) == (0, 1, 128)
    assert (mem.bvh_b_nodes, mem.bvh_b_bytes) == (1, 84)
    d = json.loads(json.dumps(mem.as_dict()))
    assert d["mesh_bytes"] == 36 + 12 and d["bvh_a_bytes_per_triangle"] == 128.0


def test_mesh_blas_reports_mesh_and_bvh_a(statue_memory):
    mesh, mem = statue_memory
    report = MeshBLAS(mesh).memory_bytes()
    assert report.parts == {"mesh": mem.mesh_bytes, "bvh_a": mem.bvh_a_bytes}


def test_shared_mesh_bunny(shared_mesh):
    mesh = load_mesh(shared_mesh("bunny00.off"))
    mem = classical_memory(mesh)
    assert mem.triangles == 75_408
    assert 80 <= mem.bvh_a_bytes_per_triangle <= 170

"""Procedural meshes: determinism, sizes, bounds, validity, orientation, the registry's errors."""

import numpy as np
import pytest
import torch
import trimesh

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.errors import NeuralRTError
from neuralrt.geometry import procedural as P
from neuralrt.geometry.mesh import Mesh
from neuralrt.rays import Rays


def _assert_valid(mesh: Mesh) -> None:
    assert mesh.vertices.dtype == np.float32 and mesh.faces.dtype == np.int32
    assert np.isfinite(mesh.vertices).all() and np.isfinite(mesh.vertex_normals).all()
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
    assert np.allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1.0, atol=1e-4)
    assert (mesh.face_areas() > 0).mean() > 0.999
    assert len(mesh.face_material_ids) == mesh.num_triangles
    assert mesh.face_material_ids.max() < len(mesh.materials)
    # Triangles are wound about their vertex normals (an emitter emits, and an exported mesh
    # faces, by its winding): foliage's leaves were wound against theirs.
    corners = mesh.vertex_normals[mesh.faces].mean(axis=1)
    assert ((mesh.face_normals() * corners).sum(axis=1) < 0).mean() < 0.005


def _signed_volume(mesh: Mesh) -> float:
    return float(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).volume)


@pytest.mark.parametrize("name", ["statue", "hairball", "foliage"])
def test_detailed_generators_are_deterministic_valid_and_in_unit_cube(name):
    gen = P.GENERATORS[name]
    a, b, other = gen(detail=0, seed=5), gen(detail=0, seed=5), gen(detail=0, seed=6)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.vertex_normals, b.vertex_normals)
    assert not (a.vertices.shape == other.vertices.shape and np.array_equal(a.vertices, other.vertices))
    _assert_valid(a)
    lo, hi = a.bounds
    assert (lo >= -1).all() and (hi <= 1).all()


@pytest.mark.parametrize(
    "name, counts",
    [("hairball", {0: 37_248, 1: 74_496, 2: 148_992}), ("foliage", {0: 3_236, 1: 10_736, 2: 40_736})],
)
def test_triangle_counts_match_documented_formula(name, counts):
    for detail, expected in counts.items():
        assert P.GENERATORS[name](detail=detail).num_triangles == expected


def test_statue_counts_grow_by_four_and_default_is_render_sized():
    n1, n2 = P.statue(1).num_triangles, P.statue(2).num_triangles
    assert n2 == 4 * n1
    assert 50_000 <= n2 <= 150_000
    assert P.statue(0).num_triangles < n1


def test_statue_is_a_figure_standing_on_y_minus_one():
    m = P.statue(1)
    lo, hi = m.bounds
    assert lo[1] == pytest.approx(-1.0) and hi[1] > 0.9
    assert abs(lo[0] + hi[0]) < 1e-5 and abs(lo[2] + hi[2]) < 1e-5  # centred in x and z
    assert _signed_volume(m) > 0  # closed-ish surface wound outward
    # Not a sphere: the figure is much taller than it is deep.
    assert (hi - lo)[1] > 2.5 * (hi - lo)[2]


def test_hairball_tubes_are_closed_and_inside_unit_ball():
    m = P.hairball(0, seed=1)
    tm = trimesh.Trimesh(m.vertices, m.faces)
    assert tm.is_watertight and tm.volume > 0
    assert np.linalg.norm(m.vertices, axis=1).max() <= 1.0
    assert len(tm.split(only_watertight=False)) == 32  # one component per tube at detail 0


def test_foliage_has_leaves_above_a_trunk():
    m = P.foliage(1)
    names = [mat.name for mat in m.materials]
    leaf = m.face_material_ids == names.index("leaf")
    assert leaf.sum() == 2 * 1250 * 4
    leaf_y = m.vertices[m.faces[leaf]][..., 1]
    bark_y = m.vertices[m.faces[~leaf]][..., 1]
    assert bark_y.min() == pytest.approx(-1.0) and leaf_y.min() > -0.5


def test_box_is_closed_with_outward_flat_normals():
    m = P.box((2.0, 1.0, 0.5))
    _assert_valid(m)
    assert m.num_triangles == 12 and len(m.vertices) == 24
    tm = trimesh.Trimesh(m.vertices, m.faces)  # merges the split vertices
    assert tm.is_watertight
    assert tm.volume == pytest.approx(1.0)
    centres = m.triangles().mean(1)
    assert ((m.face_normals() * centres).sum(1) > 0).all()
    # flat shading: each face's vertex normals equal its geometric normal
    assert np.allclose(m.vertex_normals[m.faces], m.face_normals()[:, None, :], atol=1e-6)


def test_plane_faces_up_with_unit_uvs():
    m = P.plane(3.0)
    _assert_valid(m)
    assert m.num_triangles == 2
    assert np.allclose(m.face_normals(), [0, 1, 0])
    assert np.allclose(m.vertices[:, 1], 0) and np.abs(m.vertices).max() == pytest.approx(1.5)
    assert m.uvs.min() == 0 and m.uvs.max() == 1


def test_sphere_radius_and_normals():
    m = P.sphere(subdivisions=2, radius=0.5)
    _assert_valid(m)
    assert m.num_triangles == 20 * 4**2
    assert np.allclose(np.linalg.norm(m.vertices, axis=1), 0.5, atol=1e-6)
    assert np.allclose(m.vertex_normals, m.vertices / 0.5, atol=1e-5)
    assert _signed_volume(m) > 0


def test_cornell_box_materials_and_inward_normals():
    m = P.cornell_box()
    _assert_valid(m)
    assert [x.name for x in m.materials] == ["white", "red", "green", "light"]
    assert all(np.array_equal(x.base_color, [1, 1, 1]) for x in m.materials)  # the scene's materials colour the slots
    normals, centres = m.face_normals(), m.triangles().mean(1)
    walls = m.face_material_ids != 3
    assert ((normals[walls] * centres[walls]).sum(1) < 0).all()  # every wall faces the box centre
    assert not (centres[:, 2] > 0.999).any()  # open at +z
    light = m.face_material_ids == 3
    assert np.allclose(normals[light], [0, -1, 0]) and np.allclose(m.triangles()[light][..., 1], 0.998)
    assert np.abs(m.triangles()[light][..., [0, 2]]).max() == pytest.approx(0.25)
    red, green = m.face_material_ids == 1, m.face_material_ids == 2
    assert np.allclose(centres[red, 0], -1) and np.allclose(centres[green, 0], 1)


def test_cornell_box_rays_from_camera_hit_walls_and_light():
    blas = MeshBLAS(P.cornell_box())
    n = 64
    origins = torch.tensor([[0.0, 0.0, 3.9]]).repeat(n, 1)
    targets = torch.rand(n, 3) * 1.8 - 0.9
    targets[:, 2] = -1.0
    hits = blas.intersect(Rays(origins, targets - origins, torch.zeros(n), torch.full((n,), float("inf"))))
    assert hits.hit.all()
    # the shading normal faces the camera ray (inward walls)
    assert ((hits.normal * (targets - origins)).sum(1) < 0).all()
    up = blas.intersect(Rays(torch.zeros(1, 3), torch.tensor([[0.0, 1.0, 0.0]]), torch.zeros(1), torch.full((1,), 10.0)))
    assert up.material_id.item() == 3 and up.t.item() == pytest.approx(0.998)


def test_make_procedural_dispatches_and_rejects_bad_input():
    assert P.make_procedural("sphere", subdivisions=1).num_triangles == 80
    assert set(P.GENERATORS) == {"statue", "hairball", "foliage", "box", "plane", "sphere", "cornell_box"}
    with pytest.raises(NeuralRTError, match="unknown procedural mesh 'teapot'"):
        P.make_procedural("teapot")
    with pytest.raises(NeuralRTError, match="unknown parameter.*radius"):
        P.make_procedural("box", radius=2)
    with pytest.raises(NeuralRTError, match="detail"):
        P.make_procedural("statue", detail=-1)
    with pytest.raises(NeuralRTError, match="detail"):
        P.make_procedural("hairball", detail=2.5)
    with pytest.raises(NeuralRTError, match="size"):
        P.make_procedural("box", size=(1, -1, 1))
    with pytest.raises(NeuralRTError, match="size"):
        P.make_procedural("plane", size=0)


@pytest.mark.slow
def test_large_details_reach_documented_millions():
    assert P.statue(4).num_triangles == 1_211_520
    assert P.hairball(5).num_triangles == 1_191_936
    assert P.hairball(6).num_triangles == 2_383_872
    big = P.foliage(5)
    assert big.num_triangles == 2_560_736
    lo, hi = big.bounds
    assert (lo >= -1).all() and (hi <= 1).all()

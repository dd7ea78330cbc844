"""Mesh loading: every format trimesh reads, materials/UVs/textures kept, bad files rejected."""

import numpy as np
import pytest
import trimesh
from PIL import Image

from neuralrt import Mesh, load_mesh
from neuralrt.errors import MeshError


def _write_two_material_obj(folder):
    Image.fromarray(np.full((4, 4, 3), (255, 0, 0), np.uint8)).save(folder / "tex.png")
    (folder / "m.mtl").write_text(
        "newmtl plain\nKd 0.5 0.5 0.5\n\nnewmtl textured\nKd 1 1 1\nmap_Kd tex.png\n"
    )
    (folder / "m.obj").write_text(
        "mtllib m.mtl\n"
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "usemtl plain\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
        "usemtl textured\nf 5/1 6/2 7/3\n"
    )
    return folder / "m.obj"


def test_obj_with_materials_and_texture(tmp_path):
    mesh = load_mesh(_write_two_material_obj(tmp_path))
    assert mesh.num_triangles == 3
    by_name = {m.name: k for k, m in enumerate(mesh.materials)}
    assert set(by_name) == {"plain", "textured"}
    counts = np.bincount(mesh.face_material_ids, minlength=2)
    assert counts[by_name["plain"]] == 2 and counts[by_name["textured"]] == 1
    textured = mesh.materials[by_name["textured"]]
    assert textured.texture is not None and textured.texture[0, 0, 0] == pytest.approx(1.0)
    plain = mesh.materials[by_name["plain"]]
    assert plain.texture is None and plain.base_color[0] == pytest.approx(0.214, abs=3e-3)  # sRGB 0.5 (stored as 128/255) -> linear
    assert mesh.uvs is not None and mesh.uvs.shape == (len(mesh.vertices), 2)


@pytest.mark.parametrize("ext", ["ply", "off", "stl", "glb", "obj"])
def test_formats_round_trip_geometry(tmp_path, ext):
    src = trimesh.creation.icosphere(subdivisions=2)
    path = tmp_path / f"sphere.{ext}"
    src.export(path)
    mesh = load_mesh(path)
    assert mesh.num_triangles == len(src.faces)
    assert np.allclose(np.sort(mesh.vertices.ravel()).max(), np.abs(src.vertices).max(), atol=1e-5)
    assert np.allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1, atol=1e-4)
    assert mesh.face_areas().sum() == pytest.approx(src.area, rel=1e-4)


def test_shared_mesh_loads(shared_mesh):
    mesh = load_mesh(shared_mesh("bunny00.off"))
    assert mesh.num_triangles == 75408


def test_missing_file():
    with pytest.raises(MeshError, match="not found"):
        load_mesh("/nonexistent/mesh.obj")


def test_malformed_and_empty_files(tmp_path):
    bad = tmp_path / "bad.off"
    bad.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")  # truncated
    with pytest.raises(MeshError, match="bad.off"):
        load_mesh(bad)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(MeshError, match="empty.obj"):
        load_mesh(empty)


def test_out_of_range_indices_and_nan_vertices(tmp_path):
    p = tmp_path / "oob.off"
    p.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
    with pytest.raises(MeshError, match="oob.off"):
        load_mesh(p)
    with pytest.raises(MeshError, match="out of range"):
        Mesh(np.zeros((3, 3)), np.array([[0, 1, 3]]), name="direct")
    with pytest.raises(MeshError, match="NaN or Inf"):
        Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]), np.array([[0, 1, 2]]))


def test_degenerate_mesh_rejected():
    with pytest.raises(MeshError, match="degenerate"):
        Mesh(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.array([[0, 1, 2]]))


def test_content_hash_changes_with_geometry():
    t = trimesh.creation.box()
    a = Mesh(t.vertices, t.faces)
    b = Mesh(t.vertices * 1.001, t.faces)
    assert a.content_hash() == Mesh(t.vertices, t.faces).content_hash()
    assert a.content_hash() != b.content_hash()


def test_face_material_ids_must_index_the_materials():
    from neuralrt.geometry.mesh import MeshMaterial

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    with pytest.raises(MeshError, match=r"face_material_ids must be one index per face into its 1 materials"):
        Mesh(v, [[0, 1, 2]], face_material_ids=[1])
    with pytest.raises(MeshError, match="face_material_ids"):
        Mesh(v, [[0, 1, 2]], face_material_ids=[0, 0], materials=[MeshMaterial("a")])
    assert Mesh(v, [[0, 1, 2]], face_material_ids=[1], materials=[MeshMaterial("a"), MeshMaterial("b")]).face_material_ids.tolist() == [1]

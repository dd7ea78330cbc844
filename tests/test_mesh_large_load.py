"""The lean loading path for large meshes (chunked validation and normals, trimesh's arrays freed
early) gives exactly what trimesh's own processing gave, and the same one-line errors."""

import numpy as np
import pytest
import trimesh

from neuralrt import Mesh, load_mesh
from neuralrt.errors import MeshError
from neuralrt.geometry import mesh as mesh_module


@pytest.fixture
def tiny_chunks(monkeypatch):
    """Chunks of 5 faces, so that every per-face pass crosses many chunk boundaries."""
    monkeypatch.setattr(mesh_module, "_CHUNK", 5)


def _bumpy_sphere():
    """A noisy icosphere plus one degenerate face and one unreferenced vertex (the edge cases of
    trimesh's normals: skipped faces, zero normals)."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(3)
    vertices = sphere.vertices * (1 + 0.1 * rng.random((len(sphere.vertices), 1)))
    vertices = np.vstack([vertices, [[5.0, 5.0, 5.0]]])  # unreferenced
    faces = np.vstack([sphere.faces, [[0, 0, 1]]])  # degenerate
    return vertices, faces


@pytest.mark.parametrize("ext", ["ply", "off", "obj"])
def test_lean_load_equals_trimesh_processing(tmp_path, tiny_chunks, ext):
    vertices, faces = _bumpy_sphere()
    path = tmp_path / f"bumpy.{ext}"
    trimesh.Trimesh(vertices, faces, process=False).export(path, **({"include_normals": False} if ext == "obj" else {}))
    reference = trimesh.load(str(path), process=False)  # what load_mesh used to copy out
    mesh = load_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, np.asarray(reference.vertices, np.float32))
    np.testing.assert_array_equal(mesh.faces, np.asarray(reference.faces, np.int32))
    assert mesh.vertex_normals.dtype == np.float32
    np.testing.assert_array_equal(mesh.vertex_normals, np.asarray(reference.vertex_normals, np.float32))  # bitwise
    if ext != "obj":  # trimesh's OBJ reader drops unreferenced vertices
        assert len(mesh.vertices) == len(vertices) and not mesh.vertex_normals[-1].any()  # zero, as trimesh gives
    assert mesh.face_material_ids.dtype == np.int32 and not mesh.face_material_ids.any()


def test_a_tiny_mesh_gets_the_normals_its_unit_size_copy_gets(tmp_path):
    # trimesh skips faces whose cross product is under 1e-13: a mesh 1e-6 across had all-zero normals
    # (binary PLY: trimesh writes OBJ and OFF coordinates to 8 decimals, 2 digits at this size)
    vertices, faces = _bumpy_sphere()
    vertices = vertices[:-1]  # (no unreferenced vertex: every normal is a unit one)
    faces = faces[:-1]
    normals = {}
    for scale in (1.0, 2.0 ** -20, 1e-6):
        path = tmp_path / f"bumpy{scale}.ply"
        trimesh.Trimesh(vertices * scale, faces, process=False).export(
            path)
        normals[scale] = load_mesh(path).vertex_normals
    np.testing.assert_array_equal(normals[2.0 ** -20], normals[1.0])  # (a power of two: bitwise)
    np.testing.assert_allclose(normals[1e-6], normals[1.0], atol=1e-5)
    assert np.allclose(np.linalg.norm(normals[1e-6], axis=1), 1.0, atol=1e-6)


def test_file_normals_are_kept(tmp_path, tiny_chunks):
    vertices, faces = _bumpy_sphere()
    normals = np.tile(np.float32([0.0, 0.6, 0.8]), (len(vertices), 1))
    path = tmp_path / "with_normals.ply"
    trimesh.Trimesh(vertices, faces, vertex_normals=normals, process=False).export(path, include_attributes=True)
    np.testing.assert_array_equal(load_mesh(path).vertex_normals, normals)


def test_chunked_smooth_normals_match_one_pass(monkeypatch):
    vertices, faces = _bumpy_sphere()
    vertices = vertices.astype(np.float32)
    whole = mesh_module.smooth_vertex_normals(vertices, faces)
    monkeypatch.setattr(mesh_module, "_CHUNK", 7)
    np.testing.assert_allclose(mesh_module.smooth_vertex_normals(vertices, faces), whole, atol=1e-6)
    np.testing.assert_array_equal(whole[-1], [0.0, 0.0, 1.0])  # unreferenced vertex: +z


def _write_off(path, vertices, faces):
    lines = ["OFF", f"{len(vertices)} {len(faces)} 0"]
    lines += [" ".join(repr(float(c)) for c in v) for v in vertices]
    lines += ["3 " + " ".join(str(i) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_degenerate_check_spans_chunks(tmp_path, tiny_chunks):
    """One triangle with area in the last chunk keeps the mesh; none anywhere is the one-line error."""
    flat = [[0, 1, 1]] * 12  # zero area
    vertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    assert load_mesh(_write_off(tmp_path / "ok.off", vertices, flat + [[0, 1, 2]])).num_triangles == 13
    with pytest.raises(MeshError) as err:
        load_mesh(_write_off(tmp_path / "flat.off", vertices, flat))
    assert "\n" not in str(err.value) and "degenerate (all 12 triangles have zero area)" in str(err.value)


@pytest.mark.parametrize("faces, vertex, message", [
    ([[0, 1, 7]], [0.0, 1.0, 0.0], "cannot read mesh: not a valid OFF file, or damaged (ValueError: OFF file has a face index outside the range of its vertices)"),
    ([[0, 1, 2]], [float("nan"), 1.0, 0.0], "1 vertices have NaN or Inf coordinates (in float32, where beyond 3.4e38 is Inf)"),
])
def test_bad_input_one_line_errors(tmp_path, tiny_chunks, faces, vertex, message):
    path = _write_off(tmp_path / "bad.off", [[0, 0, 0], [1, 0, 0], vertex], faces)
    with pytest.raises(MeshError) as err:
        load_mesh(path)
    assert "\n" not in str(err.value) and str(err.value) == f"{path}: {message}"


def test_out_of_range_indices_one_line_error(tiny_chunks):
    with pytest.raises(MeshError) as err:
        Mesh(np.eye(3, dtype=np.float32), np.array([[0, 1, 2]] * 6 + [[0, 1, 7]]), name="m")
    assert str(err.value) == "m: face indices out of range [0, 2] (found 0..7)"

"""The lean Loop subdivision gives trimesh's triangles (closed meshes, open ones, two levels)."""

import numpy as np
import pytest
import trimesh

from neuralrt.geometry.subdivision import loop_subdivided


def _noisy(mesh, seed=0):
    rng = np.random.default_rng(seed)
    return mesh.vertices * (1 + 0.05 * rng.random((len(mesh.vertices), 1))), np.asarray(mesh.faces)


@pytest.mark.parametrize("name", ["closed", "open"])
def test_same_triangles_as_trimesh(name):
    vertices, faces = _noisy(trimesh.creation.icosphere(subdivisions=2))
    if name == "open":  # a hole: boundary edges and boundary vertices
        faces = faces[5:]
    ref_v, ref_f = vertices, faces
    v, f = vertices, faces
    for _ in range(2):
        ref = trimesh.Trimesh(ref_v, ref_f, process=False).subdivide_loop(iterations=1)
        ref_v, ref_f = ref.vertices, ref.faces
        v, f = loop_subdivided(v, f)
        n = len(vertices)  # the original vertices keep their numbers at every level, as in trimesh
        np.testing.assert_allclose(v[:n], ref_v[:n], rtol=0, atol=1e-12)
        assert f.dtype == np.int32 and v.dtype == np.float64 and f.shape == ref_f.shape and len(v) == len(ref_v)
        np.testing.assert_allclose(v[f], ref_v[ref_f], rtol=0, atol=1e-12)  # corner by corner


def test_non_manifold_edge_is_an_error():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    with pytest.raises(ValueError, match="more than 2 faces"):
        loop_subdivided(vertices, np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]]))

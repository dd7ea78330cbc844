"""api.render takes a scene dict (with in-memory meshes) or a built Scene as well as a path."""

import numpy as np
import pytest

from neuralrt import api, load_dict
from neuralrt.errors import NeuralRTError
from neuralrt.geometry.procedural import make_procedural
from neuralrt.io.images import read_image


def _scene_dict(mesh):
    return {
        "camera": {"position": [0, 0.3, 3], "resolution": [24, 16]},
        "materials": [{"name": "white", "type": "diffuse", "albedo": [0.7, 0.7, 0.7]}],
        "objects": [{"mesh": mesh, "material": "white"}],
        "environment": {"color": [1, 1, 1]},
    }


def test_render_dict_and_scene_object_give_the_same_image(tmp_path):
    mesh = make_procedural("sphere")
    a = api.render(_scene_dict(mesh), tmp_path / "a.exr", spp=2, seed=3, progress=False)
    scene = load_dict(_scene_dict(mesh))
    b = api.render(scene, tmp_path / "b.exr", spp=2, seed=3, progress=False)
    assert a["resolution"] == b["resolution"] == [24, 16]
    img_a, img_b = read_image(tmp_path / "a.exr"), read_image(tmp_path / "b.exr")
    np.testing.assert_array_equal(img_a, img_b)
    assert img_a.mean() > 0.05  # lit by the environment: not an empty image


def test_render_dict_resolution_override(tmp_path):
    out = api.render(_scene_dict(make_procedural("sphere")), tmp_path / "c.exr", spp=1, resolution=(8, 6), progress=False)
    assert out["resolution"] == [8, 6]


def test_render_built_scene_rejects_build_options(tmp_path):
    scene = load_dict(_scene_dict(make_procedural("sphere")))
    with pytest.raises(NeuralRTError, match="belong to a built Scene"):
        api.render(scene, tmp_path / "d.exr", spp=1, resolution=(8, 8), progress=False)
    with pytest.raises(NeuralRTError, match="scene must be"):
        api.render(42, tmp_path / "e.exr", spp=1, progress=False)

"""One mesh or model rendered alone (`neuralrt.scene.studio`): ``neuralrt render bunny.obj`` /
``bunny.nrt`` / ``procedural:NAME:DETAIL`` frame the object whole, light it, and read the file once."""

import numpy as np
import pytest
import torch

from neuralrt import api
from neuralrt.cli import main
from neuralrt.errors import SceneError
from neuralrt.render.integrator import render
from neuralrt.scene.loader import load_scene


def _coverage(scene, size=24):
    result = render(scene, spp=2, max_depth=2, progress=False)
    return np.asarray(result.coverage).reshape(size, size), np.asarray(result.image)


@pytest.mark.parametrize("offset, scale", [((0, 0, 0), 1.0), ((40.0, -20.0, 3.0), 0.05), ((0, 0, 0), 300.0),
                                           ((0, 0, 0), 1e-7)])  # (a floor of 1e-6 on the radius showed a dot)
def test_a_mesh_alone_is_framed_whole_and_lit(tmp_path, offset, scale):
    # Wherever the file puts the object, and at any size: it fills the middle of the frame, touches
    # no border, and is lit (brighter than the sky behind it on its lit side).
    import trimesh

    statue = trimesh.creation.capsule(height=2.0, radius=0.4)
    statue.apply_scale(scale)
    statue.apply_translation(offset)
    statue.export(tmp_path / "capsule.obj")
    coverage, image = _coverage(load_scene(tmp_path / "capsule.obj", resolution=(24, 24)))
    assert coverage[10:14, 10:14].min() == 1.0  # the middle: the object
    borders = np.concatenate([coverage[0], coverage[-1], coverage[:, 0], coverage[:, -1]])
    assert borders.max() == 0.0  # whole in the frame
    assert 0.1 < coverage.mean() < 0.6
    assert image[coverage == 1.0].max() > image[coverage == 0.0].mean()


def test_a_procedural_mesh_and_its_api_call_render_alike(tmp_path):
    out = api.render("procedural:statue:0", tmp_path / "a.exr", spp=1, resolution=(16, 16), progress=False)
    assert main(["render", "procedural:statue:0", "-o", str(tmp_path / "b.exr"), "--spp", "1", "--res", "16x16",
                 "--quiet"]) == 0
    from neuralrt.io.images import read_image

    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), read_image(tmp_path / "b.exr"))
    assert out["scene"] == "procedural:statue:0"


def test_a_model_alone_renders_what_it_learned_without_a_word(tmp_path):
    import warnings

    api.train("procedural:statue:0", tmp_path / "statue.nrt", preset="lq", steps=30, batch=2048, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (no "cannot check that the model belongs": there is no object mesh)
        scene = load_scene(tmp_path / "statue.nrt", resolution=(24, 24))
    exact_coverage, _ = _coverage(load_scene("procedural:statue:0", resolution=(24, 24)))
    coverage, _ = _coverage(scene)
    assert coverage.sum() > 0.5 * exact_coverage.sum()  # the model's statue, about where the mesh's is
    assert np.concatenate([coverage[0], coverage[-1], coverage[:, 0], coverage[:, -1]]).max() == 0.0


@pytest.mark.parametrize("argv, needle", [
    (["render", "missing.nrt"], "missing.nrt: model file not found"),
    (["render", "model.nrt.ckpt"], "model.nrt.ckpt: a training checkpoint, not a scene"),
    (["render", "procedural:statue:0", "--detail", "2"], "--detail applies to built-in scenes (builtin:NAME); a "
                                                         "procedural mesh names its detail (procedural:NAME:DETAIL)"),
    (["render", "missing.obj"], "missing.obj"),
    (["render", "procedural:teapot:1"], "teapot"),
])
def test_bad_lone_objects_are_one_line(tmp_path, capsys, argv, needle):
    assert main(argv + ["-o", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("neuralrt: error: ") and needle in err and err.count("\n") == 1
    assert "objects.0" not in err  # (a lone model's errors named an internal key, and the file twice)
    assert not (tmp_path / "x.exr").exists()


def test_load_scene_spec_points_a_mesh_to_render_and_train(tmp_path):
    from neuralrt.scene.loader import load_scene_spec

    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(SceneError, match="not a scene file"):
        load_scene_spec(tmp_path / "m.obj")
    assert torch.is_tensor(load_scene(tmp_path / "m.obj").accel.instances[0].blas.bounds.lo)

"""Our path tracer against Mitsuba 3's on the same scenes (`neuralrt.eval.mitsuba_reference`): a
Cornell box with a diffuse ball (area light, 5 bounces), a ball on a floor under a point light
and a constant sky, and a coarse mirrored emissive ball over a floor (direct lighting). Each renderer renders 8 seeds; block means must agree to
their seed spread (`agreement`'s block chi-square near 1; a bounce more or fewer gives 5-21
here, measured when the test was written). Both shading implementations are
checked. Skipped without Mitsuba (the ``[gpu]`` extra)."""

import numpy as np
import pytest

from neuralrt.errors import SceneError
from neuralrt.eval.mitsuba_reference import agreement, mitsuba_reference_available, reference_render
from neuralrt.render.integrator import render
from neuralrt.scene.loader import load_dict

pytestmark = pytest.mark.skipif(not mitsuba_reference_available(), reason="needs mitsuba 3 (scalar_rgb)")

SEEDS = 8
CORNELL = {
    "camera": {"position": [0, 0, 3.9], "look_at": [0, 0, 0], "fov": 39, "resolution": [16, 16]},
    "materials": [
        {"name": "white", "albedo": [0.73, 0.73, 0.73]},
        {"name": "red", "albedo": [0.63, 0.065, 0.05]},
        {"name": "green", "albedo": [0.14, 0.45, 0.091]},
        {"name": "light", "type": "emissive", "emission": [17, 12, 4], "albedo": [0.78, 0.78, 0.78]},
        {"name": "ball", "albedo": [0.75, 0.6, 0.4]},
    ],
    "objects": [
        {"generator": {"name": "cornell_box"}},
        {"generator": {"name": "sphere", "params": {"subdivisions": 4}}, "material": "ball",
         "transform": {"translate": [0.3, -0.6, 0.2], "scale": 0.4}},
    ],
}
BALL_UNDER_SKY = {
    "camera": {"position": [0, 1.0, 3.5], "look_at": [0, 0, 0], "fov": 40, "resolution": [16, 12]},
    "materials": [{"name": "floor", "albedo": [0.5, 0.6, 0.7]}, {"name": "ball", "albedo": [0.8, 0.3, 0.2]}],
    "objects": [
        {"generator": {"name": "plane", "params": {"size": 4}}, "material": "floor", "transform": {"translate": [0, -0.5, 0]}},
        {"generator": {"name": "sphere", "params": {"subdivisions": 3}}, "material": "ball",
         "transform": {"scale": 0.5, "translate": [0.2, 0, 0]}},
    ],
    "lights": [{"position": [1, 2, 1], "intensity": [3, 2.5, 2]}],
    "environment": {"color": [0.2, 0.25, 0.3]},
}

# A coarse emissive ball, mirrored, over a floor: the export's emitter faces its triangles' normals
# (as ours), not the interpolated ones (a trial measured block chi-square 6.2-13.9 before), and a
# mirroring transform reverses the winding that gives it.
MIRRORED_COARSE_EMITTER = {
    "camera": {"position": [0, 1.5, 4.0], "look_at": [0, 0, 0], "fov": 45, "resolution": [16, 16]},
    "materials": [{"name": "floor", "albedo": [0.6, 0.6, 0.6]}, {"name": "light", "type": "emissive", "emission": [3, 3, 3]}],
    "objects": [
        {"generator": {"name": "plane", "params": {"size": 6}}, "material": "floor", "transform": {"translate": [0, -0.5, 0]}},
        {"generator": {"name": "sphere", "params": {"subdivisions": 0}}, "material": "light",
         "transform": {"matrix": [[-0.5, 0, 0, 0], [0, 0.5, 0, 0.6], [0, 0, 0.5, 0], [0, 0, 0, 1]]}},
    ],
}


@pytest.mark.parametrize("shading", ["numba", "torch"])
@pytest.mark.parametrize("description, max_depth", [(CORNELL, 5), (BALL_UNDER_SKY, 1), (MIRRORED_COARSE_EMITTER, 1)],
                         ids=["cornell", "sky", "coarse-emitter"])
def test_images_agree_with_mitsuba_to_their_noise(description, max_depth, shading):
    scene = load_dict(description)
    ours = [render(scene, spp=256, seed=s, max_depth=max_depth, progress=False, shading=shading).image for s in range(SEEDS)]
    theirs = [reference_render(scene, spp=256, seed=100 + s, max_depth=max_depth) for s in range(SEEDS)]
    stats = agreement([np.asarray(i) for i in ours], theirs)
    assert stats["block_chi2"] < 3.5, stats  # measured 1.77 (cornell) and 0.59 (sky), both shadings
    assert abs(stats["mean_z"]) < 4, stats


@pytest.mark.parametrize("their_depth", [4, 6])
def test_agreement_sees_a_bounce_more_or_fewer(their_depth):
    # The threshold above fails on a real difference: measured 20.9 (4 bounces) and 5.3 (6).
    scene = load_dict(CORNELL)
    ours = [np.asarray(render(scene, spp=256, seed=s, max_depth=5, progress=False).image) for s in range(SEEDS)]
    theirs = [reference_render(scene, spp=256, seed=100 + s, max_depth=their_depth) for s in range(SEEDS)]
    assert agreement(ours, theirs)["block_chi2"] > 3.5


def _png(path):
    from PIL import Image

    Image.fromarray(np.full((4, 8, 3), 128, np.uint8)).save(path)
    return str(path)


@pytest.mark.parametrize("change, message", [
    (lambda d, tmp: d["materials"].__setitem__(4, {"name": "ball", "type": "plastic"}),
     "material 'ball': plastic is not the same model in Mitsuba"),
    (lambda d, tmp: d["materials"].__setitem__(4, {"name": "ball", "type": "conductor"}),
     "material 'ball': conductor is not the same model in Mitsuba"),
    (lambda d, tmp: d["materials"].__setitem__(4, {"name": "ball", "albedo": _png(tmp / "t.png")}),
     "instance 1 .*: textures are not exported"),
    (lambda d, tmp: d.update(environment={"image": _png(tmp / "sky.png")}), "an environment image is not exported"),
])
def test_what_mitsuba_does_not_share_is_refused(tmp_path, change, message):
    description = {**CORNELL, "materials": list(CORNELL["materials"])}
    change(description, tmp_path)
    with pytest.warns(UserWarning) if "textures" in message else _nothing():
        scene = load_dict(description)
    with pytest.raises(SceneError, match=message):
        reference_render(scene, spp=1)


def _nothing():
    import contextlib

    return contextlib.nullcontext()


def test_a_normal_mapped_mesh_is_refused():
    from neuralrt.geometry.mesh import Mesh, MeshMaterial

    quad = Mesh(np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32), np.array([[0, 1, 2], [0, 2, 3]]),
                uvs=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32),
                materials=[MeshMaterial("bumpy", normal_map=np.full((2, 2, 3), 0.5, np.float32))])
    scene = load_dict({"objects": [{"mesh": quad}], "environment": {"color": [1, 1, 1]}})
    with pytest.raises(SceneError, match="normal maps are not exported"):
        reference_render(scene, spp=1)


def test_agreement_needs_two_seeds_a_side():
    with pytest.raises(ValueError, match="at least 2 images"):
        agreement([np.zeros((4, 4, 3))], [np.zeros((4, 4, 3))] * 2)
    with pytest.raises(ValueError, match=r"images of at least 4x4 pixels \(block\), got 8x3"):  # (NaN statistics)
        agreement([np.zeros((3, 8, 3))] * 2, [np.zeros((3, 8, 3))] * 2)

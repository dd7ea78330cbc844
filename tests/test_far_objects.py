"""An object far from the origin for its size is told before the render: float32 shading left its
shadow rays past it, silently (a unit sphere at x = 1e7 cast no shadow)."""

import warnings

import pytest

from neuralrt import api
from neuralrt.render.far_objects import FAR_OFFSET_FRACTION, far_object_notes
from neuralrt.render.shading_kernels import POSITION_OFFSET
from neuralrt.scene.loader import load_dict


def scene(at: float, ball_scale: float = 1.0) -> dict:
    return {"camera": {"position": [at, 1.0, 6.0], "look_at": [at, 0.0, 0.0], "resolution": [8, 8]},
            "objects": [{"name": "ball", "generator": {"name": "sphere", "params": {"subdivisions": 1}},
                         "transform": {"translate": [at, 0.0, 0.0], "scale": ball_scale}},
                        {"name": "floor", "generator": {"name": "box"},
                         "transform": {"translate": [at, -1.5, 0.0], "scale": [10.0, 0.5, 10.0]}}],
            "lights": [{"position": [at, 5.0, 0.0], "intensity": [10.0, 10.0, 10.0]}]}


@pytest.mark.parametrize("at", [0.0, 1e4, -5e4])
def test_near_enough_is_not_told(at):
    assert far_object_notes(load_dict(scene(at))) == []


def test_the_worst_object_is_named_with_its_offset_and_the_others_counted():
    notes = far_object_notes(load_dict(scene(1e6)))
    size = 3 ** 0.5 * 2  # the unit sphere's box diagonal
    assert len(notes) == 1 and "object 'ball' (and 1 other) is 1e+06 from the origin, far for its size (3.46)" in notes[0]
    assert f"leave its surfaces {POSITION_OFFSET * 1e6:.2g} away" in notes[0] and "14% of its size" in notes[0]
    assert POSITION_OFFSET * 1e6 / size > FAR_OFFSET_FRACTION


def test_a_large_object_far_away_is_not_told_a_small_one_is():
    # (the floor, 20 units wide, keeps its shadows at 1e5; the unit ball does not)
    notes = far_object_notes(load_dict(scene(1e5)))
    assert len(notes) == 1 and "object 'ball' is 1e+05" in notes[0] and "other" not in notes[0]
    assert far_object_notes(load_dict(scene(1e5, ball_scale=3.0))) == []


def test_render_warns_before_it_renders(tmp_path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        api.render(scene(1e6), tmp_path / "far.exr", spp=1, progress=False)
    assert [str(w.message).split(": object")[0] for w in caught] == [f"scene rendered to {tmp_path / 'far.exr'}"]

"""A camera or point light inside an object is told before the render (it rendered black, silently)."""

import json

import pytest
import torch

from neuralrt import api
from neuralrt.render.enclosure import ENCLOSURE_DIRECTIONS, enclosing_instance, enclosure_notes
from neuralrt.scene.builtins import BUILTIN_SCENES
from neuralrt.scene.loader import load_dict, load_scene

BALL = {"name": "ball", "generator": {"name": "sphere", "params": {"subdivisions": 2}}}  # unit radius, at the origin
ROOM = {"name": "room", "generator": {"name": "box"}, "transform": {"scale": 8.0}}
LAMP = {"name": "lamp", "generator": {"name": "sphere"}, "material": "lamp",  # small: no ray of the 26 meets it
        "transform": {"translate": [0.0, -3.5, 0.0], "scale": 0.1}}


def scene(camera=(0.0, 0.0, 3.9), lights=(), objects=(BALL,), **sections):
    return load_dict({"camera": {"position": list(camera), "look_at": [0.0, 0.0, 0.0], "resolution": [8, 8]},
                      "objects": [dict(o) for o in objects],
                      "lights": [{"position": list(p), "intensity": [5.0, 5.0, 5.0]} for p in lights], **sections})


def test_the_26_directions_cover_the_sphere():
    assert ENCLOSURE_DIRECTIONS.shape == (26, 3)
    assert torch.allclose(ENCLOSURE_DIRECTIONS.norm(dim=-1), torch.ones(26))
    assert torch.allclose(ENCLOSURE_DIRECTIONS.sum(0), torch.zeros(3), atol=1e-6)


def test_a_point_is_enclosed_only_when_every_ray_meets_one_instance():
    s = scene(objects=(BALL, {**BALL, "name": "other", "transform": {"translate": [5.0, 0.0, 0.0]}}))
    assert enclosing_instance(s.accel, [0.0, 0.0, 0.0]) == 0
    assert enclosing_instance(s.accel, [5.0, 0.2, 0.0]) == 1
    assert enclosing_instance(s.accel, [0.0, 0.0, 3.0]) is None  # outside: rays escape
    assert enclosing_instance(s.accel, [2.5, 0.0, 0.0]) is None  # between: every ray escapes or meets one of two


def test_a_camera_inside_an_object_with_the_light_outside_is_told():
    notes = enclosure_notes(scene(camera=(0.0, 0.1, 0.2), lights=[(0.0, 3.0, 3.0)]))
    assert notes == ["scene: the camera at (0, 0.1, 0.2) seems to be inside object 'ball' (each of 26 rays from it, "
                     "in all directions, meets it first) and no light is inside it: the image shows its inside, unlit"]


def test_a_point_light_inside_an_object_the_camera_is_not_in_is_told():
    notes = enclosure_notes(scene(lights=[(0.0, 3.0, 3.0), (0.0, 0.0, 0.25)]))
    assert len(notes) == 1 and notes[0].startswith("scene: point light 1 at (0, 0, 0.25) seems to be inside object 'ball' ")
    assert notes[0].endswith(": little or none of its light leaves it")


@pytest.mark.parametrize("case", ["light inside with the camera", "emitting enclosure", "area light in the room",
                                  "camera outside", "room lit by its inside light",
                                  "camera in the lit room"])
def test_scenes_that_render_as_meant_get_no_note(case):
    lamp = {"materials": [{"name": "lamp", "type": "emissive", "emission": [4.0, 4.0, 4.0]}]}
    s = {
        "light inside with the camera": lambda: scene(camera=(0.0, 0.0, 0.5), lights=[(0.0, 0.2, 0.0)]),
        "emitting enclosure": lambda: scene(camera=(0.0, 0.0, 0.5), objects=({**BALL, "material": "lamp"},), **lamp),
        "area light in the room": lambda: scene(camera=(1.0, 1.0, 2.5), objects=(ROOM, LAMP), **lamp),
        "camera outside": lambda: scene(lights=[(0.0, 3.0, 3.0)], environment={"color": [0.5, 0.5, 0.5]}),
        # (the light's rays meet the ball too: it is not enclosed by the room, only within its bounds)
        "room lit by its inside light": lambda: scene(camera=(1.0, 1.0, 2.5), lights=[(0.0, 3.0, 0.0)], objects=(ROOM, BALL)),
        # (the light is enclosed by the room; the camera's rays meet the ball, but it is within the room's bounds)
        "camera in the lit room": lambda: scene(camera=(0.0, 0.0, 3.0), lights=[(3.0, 3.5, -1.0)], objects=(ROOM, BALL)),
    }[case]()
    assert enclosure_notes(s) == []
    if case not in ("camera outside", "camera in the lit room"):  # (a camera enclosed, told apart from the unlit case)
        assert enclosing_instance(s.accel, s.camera.position, camera_rays=True) == 0
    if case == "camera in the lit room":
        assert enclosing_instance(s.accel, s.lights.points.positions[0]) == 0


@pytest.mark.parametrize("name", sorted(BUILTIN_SCENES))
def test_the_builtin_scenes_get_no_note(name):
    assert enclosure_notes(load_scene(f"builtin:{name}?detail=1", resolution=(8, 8))) == []


def test_render_warns_before_it_renders_a_camera_inside_an_object(tmp_path):
    path = tmp_path / "inside.json"
    path.write_text(json.dumps({"camera": {"position": [0.0, 0.0, 0.3], "resolution": [6, 4]}, "objects": [BALL],
                                "lights": [{"position": [0.0, 3.0, 3.0], "intensity": [5.0, 5.0, 5.0]}]}))
    with pytest.warns(UserWarning, match=r"inside.json: the camera at \(0, 0, 0\.3\) seems to be inside object 'ball'"):
        result = api.render(str(path), tmp_path / "x.exr", spp=1, progress=False)
    assert result["spp"] == 1


def test_render_warns_of_a_lit_point_light_inside_an_object_and_not_of_a_dark_one(tmp_path):
    path = tmp_path / "lamp.json"
    path.write_text(json.dumps({"camera": {"position": [0.0, 0.0, 3.9], "resolution": [6, 4]}, "objects": [BALL],
                                "lights": [{"position": [0.0, 0.0, 0.2], "intensity": [0.0, 0.0, 0.0]},
                                           {"position": [0.0, 0.3, 0.0], "intensity": [5.0, 5.0, 5.0]}],
                                "environment": {"color": [0.1, 0.1, 0.1]}}))
    with pytest.warns(UserWarning) as caught:
        api.render(str(path), tmp_path / "x.exr", spp=1, progress=False)
    assert [str(w.message) for w in caught] == [
        f"{path}: point light 1 at (0, 0.3, 0) seems to be inside object 'ball' (each of 26 rays from it, in all "
        "directions, meets it first): little or none of its light leaves it"]


def test_many_points_are_judged_in_one_query(monkeypatch):
    from neuralrt.render.enclosure import enclosing_instances

    s = scene()
    calls = []
    original = s.accel.intersect
    monkeypatch.setattr(s.accel, "intersect", lambda rays, **kw: calls.append(len(rays)) or original(rays, **kw))
    assert enclosing_instances(s.accel, [[0.0, 0.0, 0.0], [0.0, 0.0, 3.0], [0.1, 0.2, 0.3]]) == [0, None, 0]
    assert calls == [3 * 26] and enclosing_instances(s.accel, []) == []

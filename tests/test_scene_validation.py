"""Bad scene input is one line naming the key, raised at load time: singular / non-affine / float32-
overflowing transforms, a resolution override over the cap, materials without ``type``, NaN in
bounded fields, and pydantic's union labels kept out of key paths."""

import json
import math

import numpy as np
import pytest
from pydantic import ValidationError, field_validator

from neuralrt import api
from neuralrt.cli import main
from neuralrt.errors import ConfigError, NeuralRTError, SceneError, validation_errors, validation_message
from neuralrt.rays import Transform, affine_problem
from neuralrt.scene import schema
from neuralrt.scene.loader import load_dict, load_scene, load_scene_spec
from neuralrt.scene.schema import DiffuseMaterialSpec, ObjectSpec, SceneSpec

SPHERE = {"generator": {"name": "sphere", "params": {"subdivisions": 1}}}
IDENTITY = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
ROW_ZERO = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]
BOTTOM_ZERO = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 0]]
TINY_AXIS = [[1e-30, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
FAR = [[1, 0, 0, 1e39], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


def scene_file(tmp_path, obj: dict | None = None, name: str = "scene.json", **sections) -> str:
    """A small JSON scene (a procedural sphere; json writes NaN / Infinity as given)."""
    data = {"camera": {"resolution": [8, 8]}, "objects": [{**SPHERE, **(obj or {})}], **sections}
    path = tmp_path / name
    path.write_text(json.dumps(data))
    return str(path)


def cli_error(capsys, args: list[str]) -> str:
    """The CLI's single ``neuralrt: error:`` line (exit 2, nothing else on stderr)."""
    assert main(args) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("neuralrt: error: "), lines
    return lines[0].removeprefix("neuralrt: error: ")


# --- transforms ------------------------------------------------------------------------------------

BAD_TRANSFORMS = [
    ({"matrix": ROW_ZERO}, "objects.0.transform: matrix is singular"),
    ({"matrix": BOTTOM_ZERO}, "objects.0.transform: not an affine transform: the bottom row must be [0, 0, 0, 1]"),
    ({"matrix": TINY_AXIS}, "objects.0.transform: matrix is singular for float32"),
    ({"matrix": FAR}, "objects.0.transform: not a finite affine transform"),
    ({"scale": 1e-300}, "objects.0.transform.scale: scale must be within 1e-12 to 1e+12"),
    ({"scale": 1e300}, "objects.0.transform.scale: scale must be within 1e-12 to 1e+12"),
    ({"scale": [1, 1e-8, 1]}, "objects.0.transform: matrix is singular for float32"),
    ({"scale": [1, 0, 1]}, "objects.0.transform.scale: scale must be finite and non-zero"),
    ({"matrix": IDENTITY, "scale": [1, 2, 1]}, "objects.0.transform: give either matrix or translate/rotate/scale, not both"),
]


def test_a_matrix_beside_the_default_scale_spelled_per_axis_is_accepted():
    # (translate [0, 0, 0] beside a matrix was accepted, scale [1, 1, 1] refused as "both given")
    for defaults in ({"scale": [1, 1, 1]}, {"scale": 1.0}, {"translate": [0, 0, 0]}):
        load_dict({"objects": [{**SPHERE, "transform": {"matrix": IDENTITY, **defaults}}]})


@pytest.mark.parametrize("transform,message", BAD_TRANSFORMS)
def test_bad_transform_is_a_scene_error_at_load(tmp_path, transform, message):
    path = scene_file(tmp_path, {"transform": transform})
    with pytest.raises(SceneError) as info:
        load_scene_spec(path)  # validation alone: nothing is built
    assert str(info.value).startswith(f"{path}: {message}") and "\n" not in str(info.value)  # the path as given
    with pytest.raises(SceneError, match="objects.0.transform"):
        load_dict({"objects": [{**SPHERE, "transform": transform}]})


@pytest.mark.parametrize("command", ["info", "render"])
@pytest.mark.parametrize("transform,message", BAD_TRANSFORMS[:4])
def test_bad_transform_is_one_line_from_the_cli(tmp_path, capsys, command, transform, message):
    path = scene_file(tmp_path, {"transform": transform})
    out = tmp_path / "out"
    args = [command, path] + (["-o", str(out / "x.exr")] if command == "render" else [])
    assert cli_error(capsys, args).startswith(f"{path}: {message}")
    assert not out.exists()


@pytest.mark.parametrize("matrix", [ROW_ZERO, BOTTOM_ZERO, TINY_AXIS, FAR, [[1, 0], [0, 1]], [[1, 2, 3], [4]]])
def test_transform_class_raises_config_error(matrix):
    with pytest.raises(ConfigError, match="^transform: ") as info:
        Transform(matrix)
    assert isinstance(info.value, ValueError) and isinstance(info.value, NeuralRTError)


@pytest.mark.parametrize("factors", [0.0, 1e-300, 1e300, [1.0, 1e-8, 1.0]])
def test_transform_scale_out_of_float32_range(factors):
    with pytest.raises(ConfigError):
        Transform.scale(factors)


def test_valid_transforms_stay_affine_and_invertible():
    xf = Transform.translate([1, 2, 3]) @ Transform.rotate([1, 1, 0], 37) @ Transform.scale([1e-3, 2, 1e3])
    assert xf.tolist()[3] == [0, 0, 0, 1] and xf.inverse().tolist()[3] == [0, 0, 0, 1]
    identity = (xf @ xf.inverse()).tolist()
    assert all(math.isclose(identity[i][j], float(i == j), abs_tol=1e-9) for i in range(4) for j in range(4))
    # Bottom-row noise from an exporter is accepted and made exact.
    assert Transform([[2, 0, 0, 1], [0, 2, 0, 0], [0, 0, 2, 0], [1e-12, 0, 0, 1]]).tolist()[3] == [0, 0, 0, 1]


def test_scene_transform_is_scale_then_rotations_then_translation():
    # The scene file's one-step composition equals the chain of single transforms it stands for.
    rng = np.random.default_rng(3)
    for _ in range(50):
        offset, degrees, factors = rng.normal(size=3) * 5, rng.uniform(-360, 360, 3), rng.uniform(0.1, 3, 3)
        chain = (Transform.translate(offset) @ Transform.rotate([0, 0, 1], degrees[2]) @ Transform.rotate([0, 1, 0], degrees[1])
                 @ Transform.rotate([1, 0, 0], degrees[0]) @ Transform.scale(factors))
        one = Transform.translate_rotate_scale(offset, degrees, factors)
        np.testing.assert_allclose(one.tolist(), chain.tolist(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(one.inverse().tolist(), chain.inverse().tolist(), rtol=0, atol=1e-9)


@pytest.mark.filterwarnings("ignore:Converting a tensor with requires_grad")  # (torch's, reading the list)
def test_transform_takes_what_it_took_and_names_what_it_cannot():
    import torch

    identity = np.eye(4).tolist()
    for matrix in (torch.eye(4, dtype=torch.bfloat16), [[torch.tensor(float(v), requires_grad=True) for v in row] for row in identity],
                   [[1, 0, 0, 2**70], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]):
        Transform(matrix)  # (each failed inside numpy after the move from torch; the re-trial)
    for call, message in [(lambda: Transform.translate("abc"), "offset must be 3 numbers, got 'abc'"),
                          (lambda: Transform.translate(None), "offset must be 3 numbers, got None"),
                          (lambda: Transform.scale([1, 2]), r"scale factors must be 3 numbers, got \[1, 2\]"),
                          (lambda: Transform.rotate([0, 0, 0], 30), "rotation axis must be a finite non-zero vector")]:
        with pytest.raises(ConfigError, match="^transform: " + message):
            call()


def test_float32_overflow_edge_of_a_matrix_entry():
    # float32 rounds below max + half an ulp to its max, and from there up to Inf.
    f32_max = float(np.finfo(np.float32).max)
    half_ulp = 2.0**103
    for value, finite in [(f32_max, True), (f32_max + half_ulp * 0.99, True), (f32_max + half_ulp, False)]:
        with np.errstate(over="ignore"):
            assert bool(np.isfinite(np.float32(value))) == finite  # what the check stands for
        matrix = [[1, 0, 0, value], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
        assert (affine_problem(matrix) is None) == finite, value


def test_with_paths_leaves_the_original_spec_alone(tmp_path):
    spec, _, _ = load_scene_spec(scene_file(tmp_path))
    spec = spec.model_copy(update={"objects": spec.objects + [ObjectSpec(mesh="m.obj")]})
    mapped = spec.with_paths(lambda p: "/elsewhere/" + p)
    assert mapped.objects[-1].mesh == "/elsewhere/m.obj" and spec.objects[-1].mesh == "m.obj"
    mapped.objects[0].transform.translate = (1.0, 2.0, 3.0)  # a copy shares nothing
    assert spec.objects[0].transform.translate == (0.0, 0.0, 0.0)


def test_scenes_built_from_one_spec_share_nothing_with_it(tmp_path):
    # A trial found two scenes of one spec, and the spec, editing each other's settings (session 52).
    from neuralrt.scene.loader import build_scene

    spec, folder, _ = load_scene_spec(scene_file(tmp_path))
    a, b = build_scene(spec, folder), build_scene(spec, folder)
    a.settings.spp = 64
    a.spec.camera.resolution = (4, 4)
    spec.render.max_depth = 1
    assert b.settings.spp == spec.render.spp != 64 and spec.camera.resolution != (4, 4)
    assert a.settings.max_depth == b.settings.max_depth != 1


def test_camera_position_beyond_float32(tmp_path):
    path = scene_file(tmp_path, camera={"position": [0, 0, 1e39]})
    with pytest.raises(SceneError, match="scene.json: camera: camera position is beyond the float32 range"):
        load_scene_spec(path)


# --- resolution override ---------------------------------------------------------------------------

def test_resolution_over_the_cap_from_the_cli(tmp_path, capsys):
    out = tmp_path / "out"
    err = cli_error(capsys, ["render", scene_file(tmp_path), "-o", str(out / "b.exr"), "--res", "100000x100000"])
    assert err == "--res: 100000x100000 is over the largest allowed 16384x16384"  # (named as typed)
    assert not out.exists()


@pytest.mark.parametrize("resolution,message", [
    ((100000, 100000), "resolution: 100000x100000 is over the largest allowed 16384x16384"),
    ((16385, 8), "resolution: 16385x8 is over the largest allowed"),
    ((0, 8), "resolution: 0x8 must be at least 1x1"),
    ((8.5, 8), "resolution: expected two whole numbers"),
    ((8,), "resolution: expected two whole numbers"),
])
def test_resolution_override_is_a_config_error(tmp_path, resolution, message):
    with pytest.raises(ConfigError) as info:
        load_scene(scene_file(tmp_path), resolution=resolution)
    assert str(info.value).startswith(message)
    with pytest.raises(ConfigError, match="^resolution: "):
        api.render(scene_file(tmp_path), tmp_path / "x.exr", resolution=resolution, progress=False)
    assert not (tmp_path / "x.exr").exists()


def test_resolution_override_within_the_cap(tmp_path):
    scene = load_scene(scene_file(tmp_path), resolution=(6.0, 4))
    assert (scene.camera.width, scene.camera.height) == (6, 4)


# --- materials without type ------------------------------------------------------------------------

def test_material_without_type_is_diffuse(tmp_path, capsys):
    materials = [{"name": "m"}, {"name": "gold", "albedo": [0.9, 0.7, 0.2]}]
    spec, _, _ = load_scene_spec(scene_file(tmp_path, {"material": "m"}, materials=materials))
    assert all(isinstance(m, DiffuseMaterialSpec) for m in spec.materials)
    assert spec.materials[1].albedo == (0.9, 0.7, 0.2)
    assert main(["info", scene_file(tmp_path, {"material": "m"}, materials=materials)]) == 0
    assert load_dict({"materials": materials, "objects": [{**SPHERE, "material": "m"}]}).materials.names[:2] == ["m", "gold"]


def test_unknown_or_incomplete_material_type_still_named(tmp_path):
    with pytest.raises(SceneError, match=r"scene.json: materials.0: .*'glass'.*'diffuse', 'conductor', 'plastic', 'emissive'"):
        load_scene_spec(scene_file(tmp_path, materials=[{"name": "m", "type": "glass"}]))
    with pytest.raises(SceneError, match=r"scene.json: materials.0.emission: Field required"):
        load_scene_spec(scene_file(tmp_path, materials=[{"name": "m", "type": "emissive"}]))
    with pytest.raises(SceneError, match=r"scene.json: materials.0.roughness: Extra inputs are not permitted"):
        load_scene_spec(scene_file(tmp_path, materials=[{"name": "m", "roughness": 0.5}]))  # diffuse by default


# --- non-finite numbers ----------------------------------------------------------------------------

NAN = float("nan")


@pytest.mark.parametrize("sections,key", [
    ({"camera": {"fov": NAN}}, "camera.fov"),
    ({"camera": {"fov": float("inf")}}, "camera.fov"),
    ({"materials": [{"name": "m", "type": "plastic", "roughness": NAN}]}, "materials.0.roughness"),
    ({"materials": [{"name": "m", "type": "plastic", "ior": NAN}]}, "materials.0.ior"),
    ({"materials": [{"name": "m", "type": "conductor", "roughness": NAN}]}, "materials.0.roughness"),
    ({"materials": [{"name": "m", "albedo": [0.5, NAN, 0.5]}]}, "materials.0.albedo.1"),
    ({"materials": [{"name": "m", "type": "emissive", "emission": [1, 1, NAN]}]}, "materials.0.emission.2"),
    ({"environment": {"color": [1, 1, 1], "scale": NAN}}, "environment.scale"),
    ({"lights": [{"position": [0, 2, 0], "intensity": [NAN, 1, 1]}]}, "lights.0.intensity.0"),
    ({"objects": [{"generator": {"name": "sphere", "params": {"radius": NAN}}}]}, "objects.0.generator.params.radius"),
    ({"objects": [{**SPHERE, "transform": {"scale": NAN}}]}, "objects.0.transform.scale"),
])
def test_non_finite_numbers_say_finite_and_name_the_key(tmp_path, capsys, sections, key):
    path = scene_file(tmp_path, **sections)
    with pytest.raises(SceneError) as info:
        load_scene_spec(path)
    assert str(info.value).startswith(f"{path}: {key}: Input should be a finite number (got ")
    assert "more problem" not in str(info.value)  # the other union members' complaints are dropped
    assert cli_error(capsys, ["info", path]) == str(info.value)


def test_every_scene_model_rejects_nan_before_bounds():
    models = [v for v in vars(schema).values() if isinstance(v, type) and issubclass(v, schema._Strict)]
    assert len(models) >= 12 and all(m.model_config.get("allow_inf_nan") is False for m in models)


# --- validation_message ----------------------------------------------------------------------------

def _errors(data) -> ValidationError:
    with pytest.raises(ValidationError) as info:
        SceneSpec.model_validate(data)
    return info.value


def test_union_labels_are_dropped_from_keys():
    exc = _errors({"materials": [{"name": "m", "type": "conductor", "albedo": [1, NAN, 1]}], "objects": [SPHERE]})
    assert validation_errors(exc, SceneSpec) == [("materials.0.albedo.1", "Input should be a finite number (got nan)")]
    # Without the model, only bracketed labels can be told from keys.
    assert validation_message(exc).startswith("materials.0.conductor.albedo.1: Input should be a finite number")


def test_keys_that_look_like_labels_are_kept():
    # A mesh material slot named like a union tag / type label is a user key, not pydantic's.
    exc = _errors({"objects": [{**SPHERE, "materials": {"diffuse": 3, "str": "x"}}]})
    assert validation_errors(exc, SceneSpec) == [("objects.0.materials.diffuse", "Input should be a valid string (got 3)")]


def test_alternatives_of_a_union_read_as_one_error():
    exc = _errors({"materials": [{"name": "m", "albedo": 5}], "objects": [SPHERE]})
    assert validation_message(exc, SceneSpec) == "materials.0.albedo: Input should be a valid tuple or a valid string (got 5)"


def test_messages_are_one_line_without_prefix_or_link():
    exc = _errors({"objects": [{**SPHERE, "mesh": "a.obj"}]})
    assert validation_message(exc, SceneSpec) == "objects.0: give either mesh or generator, not both"

    class Linked(schema._Strict):
        x: int = 0

        @field_validator("x")
        @classmethod
        def _nested(cls, v):
            try:
                Linked(x="no")
            except ValidationError as inner:
                raise ValueError(str(inner)) from None  # multi-line, with pydantic's link

    with pytest.raises(ValidationError) as info:
        Linked(x=1)
    msg = validation_message(info.value)
    assert "\n" not in msg and "errors.pydantic.dev" not in msg and not msg.startswith("x: Value error")


# --- detail -------------------------------------------------------------------------------------------


def test_detail_given_twice_differently_is_an_error(tmp_path, capsys):
    assert load_scene_spec("builtin:cornell-statue?detail=0", detail=0)[0].objects  # the same value twice is fine
    message = cli_error(capsys, ["render", "builtin:cornell-statue?detail=0", "--detail", "1", "-o",
                                 str(tmp_path / "i.exr"), "--quiet"])
    assert "detail given twice (0 in the name, 1 as --detail): give it once" in message
    assert not list(tmp_path.iterdir())


def test_detail_on_a_scene_file_is_an_error(tmp_path, capsys):
    message = cli_error(capsys, ["render", scene_file(tmp_path), "--detail", "1", "-o", str(tmp_path / "i.exr"), "--quiet"])
    assert "--detail applies to built-in scenes (builtin:NAME), not to a scene file" in message


def test_the_reference_page_states_each_enforced_range():
    # derived from the schema's bounds, so the page says what validation refuses
    from neuralrt.scene.schemadoc import scene_reference

    page = scene_reference()
    for row in ("| `fov` | `40.0` | > 0, < 180 |", "| `ior` | `1.5` | > 1, <= 4 |", "| `max_depth` | `5` | >= 1, <= 256 |",
                "| `resolution` | `[256, 256]` | each > 0, <= 16384 |", "| `emission` |"):
        assert row in page, row


def test_save_scene_takes_a_spec_and_says_so():
    """The obvious misuse, load_scene_spec's whole tuple, was an AttributeError from inside."""
    from neuralrt.scene.loader import load_scene_spec
    from neuralrt.scene.scene import save_scene

    with pytest.raises(SceneError, match=r"^spec: expected a SceneSpec \(load_scene_spec\(path\)\[0\], or one built in Python\), got tuple$"):
        save_scene(load_scene_spec("builtin:cornell-statue"), "x.toml")
    with pytest.raises(ConfigError, match=r"^path: expected a path"):
        save_scene(load_scene_spec("builtin:cornell-statue")[0], None)


@pytest.mark.parametrize("section,message", [
    ({"objects": [{"generator": {"name": "sphere"}, "transform": {"scale": "2"}}]},
     r"^scene: objects.0.transform.scale: expected a number, got '2'$"),  # (read as 2.0)
    ({"objects": [{"generator": {"name": "sphere"}, "transform": {"scale": ["1", True, 2]}}]},
     r"^scene: objects.0.transform.scale.0: expected a number, got '1' \(and 1 more problem\)$"),
    ({"objects": [{"generator": {"name": "sphere"}}], "lights": [{"position": [1e39, 0, 0], "intensity": [1, 1, 1]}]},
     r"^scene: lights.0.position.0: Input should be less than or equal to 1e\+18 \(got 1e\+39\)$"),  # (contributed 0)
    ({"camera": {"fov": "40"}, "objects": [{"generator": {"name": "sphere"}}]},
     r"^scene: camera.fov: expected a number, got '40'$"),  # (the input was named twice)
])
def test_scene_numbers_found_by_the_authoring_trial(section, message):
    from neuralrt.scene.loader import load_dict

    with pytest.raises(SceneError, match=message):
        load_dict(section)


@pytest.mark.parametrize("name, text, message", [
    ("huge.toml", "[render]\nspp = " + "9" * 5000 + "\n[[objects]]\ngenerator = { name = \"box\" }\n",
     "not valid TOML: Exceeds the limit"),
    ("huge.json", '{"render": {"spp": ' + "9" * 5000 + '}, "objects": [{"generator": {"name": "box"}}]}',
     "not valid JSON: Exceeds the limit"),
    ("twice.json", '{"objects": [{"generator": {"name": "box"}}], "objects": []}',
     "not valid JSON: key 'objects' is given twice in one object"),
])
def test_scene_text_python_cannot_take_is_one_line(tmp_path, name, text, message):
    (tmp_path / name).write_text(text)
    with pytest.raises(SceneError, match=message):
        load_scene_spec(tmp_path / name)


def test_a_scene_file_with_a_byte_order_mark_reads_as_without(tmp_path):
    (tmp_path / "bom.toml").write_bytes(b"\xef\xbb\xbf[[objects]]\ngenerator = { name = \"box\" }\n")
    (tmp_path / "bom.json").write_bytes(b'\xef\xbb\xbf{"objects": [{"generator": {"name": "box"}}]}')
    assert load_scene_spec(tmp_path / "bom.toml")[0] == load_scene_spec(tmp_path / "bom.json")[0]


def test_a_model_header_with_an_integer_python_cannot_read_is_one_line(tmp_path):
    import torch
    from safetensors.torch import save_file

    from neuralrt.errors import ModelFileError
    from neuralrt.methods import load_model

    save_file({"x": torch.zeros(1)}, str(tmp_path / "m.nrt"), metadata={"neuralrt": '{"format_version": ' + "9" * 5000 + "}"})
    with pytest.raises(ModelFileError, match=r"m.nrt: corrupted header \(Exceeds the limit"):
        load_model(tmp_path / "m.nrt")


@pytest.mark.parametrize("camera, message", [
    ({"position": [0, 1]}, "camera.position: takes 3 values, got 2"),  # was "camera.position.2: Field required"
    ({"position": [0]}, "camera.position: takes 3 values, got 1"),  # (once, not once per missing value)
    ({"position": [0, 1, 2, 3]}, "camera.position: takes 3 values, got 4"),  # was "Tuple should have at most 3 items ..."
    ({"resolution": [8, 8, 8]}, "camera.resolution: takes 2 values, got 3"),
])
def test_a_list_of_the_wrong_length_says_how_many_values_it_takes(tmp_path, camera, message):
    with pytest.raises(SceneError) as info:
        load_scene_spec(scene_file(tmp_path, camera={"resolution": [8, 8], **camera}))
    assert str(info.value) == f"{tmp_path / 'scene.json'}: {message}"


def test_a_config_list_of_too_few_values_says_how_many_it_takes():
    from neuralrt.methods.lsnif_config import LSNIFConfig

    with pytest.raises(ConfigError, match=r"^lsnif config: encoding\.resolutions: takes at least 1 value, got 0$"):
        LSNIFConfig.preset("hq", encoding={"resolutions": []})

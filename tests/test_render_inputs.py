"""Bad input to render, eval and scene files (found by a new-user trial): radiance that would overflow
float32, unreadable radiance images, outputs blocked beside the image, unbounded counts, argument
types, and scene spellings that should mean the same thing."""

import json

import numpy as np
import pytest

from neuralrt import api
from neuralrt.cli import main
from neuralrt.errors import ConfigError, NeuralRTError, SceneError
from neuralrt.io.images import write_exr
from neuralrt.render.film import output_files
from neuralrt.render.integrator import render
from neuralrt.scene.loader import load_dict, load_scene

SPHERE = {"name": "ball", "generator": {"name": "sphere", "params": {"subdivisions": 1}}}


def scene_file(tmp_path, objects=None, **sections) -> str:
    data = {"camera": {"resolution": [6, 4]}, "objects": objects or [dict(SPHERE)], "environment": {"color": [0.5, 0.5, 0.5]},
            **sections}  # (lit: an unlit scene's render warns)
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(data))
    return str(path)


# -- radiance -------------------------------------------------------------------------------------


@pytest.mark.parametrize("sections,key", [
    ({"lights": [{"position": [0, 2, 0], "intensity": [1e39, 1, 1]}]}, "lights.0.intensity.0"),
    ({"materials": [{"name": "lamp", "type": "emissive", "emission": [1, 1e21, 1]}]}, "materials.0.emission.1"),
    ({"environment": {"color": [1, 1, 3e38]}}, "environment.color.2"),
    ({"environment": {"color": [1, 1, 1], "scale": 1e30}}, "environment.scale"),
])
def test_radiance_beyond_the_float32_margin_is_refused(tmp_path, sections, key):
    with pytest.raises(SceneError, match=rf"{key}: Input should be less than or equal to 1e\+20"):
        load_scene(scene_file(tmp_path, **sections))


def test_environment_color_times_scale_is_bounded(tmp_path):
    with pytest.raises(SceneError, match=r"environment: color times scale is above 1e\+20"):
        load_scene(scene_file(tmp_path, environment={"color": [1e15, 1, 1], "scale": 1e10}))


@pytest.mark.parametrize("value,problem", [
    (np.nan, "1 pixel is NaN or infinite"),
    (np.inf, "1 pixel is NaN or infinite"),
    (-1.0, "1 pixel is negative"),
    (1e30, r"pixel values times scale reach 1e\+30, above 1e\+20"),
])
def test_environment_images_must_be_renderable_radiance(tmp_path, capsys, value, problem):
    pixels = np.ones((4, 8, 3), np.float32)
    pixels[1, 2, 0] = value
    write_exr(tmp_path / "sky.exr", pixels)
    path = scene_file(tmp_path, environment={"image": "sky.exr"})
    with pytest.raises(SceneError, match=rf"environment.image: .*sky.exr: {problem}"):
        load_scene(path)
    assert main(["render", path, "-o", str(tmp_path / "out" / "x.exr"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("neuralrt: error: ") and err.count("\n") == 1 and not (tmp_path / "out").exists()


def test_texture_with_nan_pixels_is_refused(tmp_path):
    pixels = np.full((4, 4, 3), 0.5, np.float32)
    pixels[0, 0] = np.nan
    write_exr(tmp_path / "tex.exr", pixels)
    path = scene_file(tmp_path, materials=[{"name": "t", "type": "diffuse", "albedo": "tex.exr"}],
                      objects=[{**SPHERE, "material": "t"}])
    with pytest.raises(SceneError, match=r"materials.0.albedo: .*tex.exr: 1 pixel is NaN or infinite"):
        load_scene(path)


# -- outputs and counts ---------------------------------------------------------------------------


def test_render_checks_every_output_before_it_starts(tmp_path):
    (tmp_path / "y_depth.exr").mkdir()  # in the way of one AOV
    with pytest.raises(NeuralRTError, match=r"y_depth.exr: is a folder, not a render output"):
        api.render(scene_file(tmp_path), tmp_path / "y.exr", spp=1, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.json", "y_depth.exr"]  # nothing rendered, nothing written


def test_output_name_is_kept_as_given(tmp_path):
    result = api.render(scene_file(tmp_path), tmp_path / "Up.EXR", spp=1, progress=False)
    assert result["output"].endswith("Up.EXR") and (tmp_path / "Up.EXR").is_file()
    assert [str(p) for p in output_files(tmp_path / "Up.EXR")] == result["files"]
    assert all(p.is_file() for p in output_files(tmp_path / "Up.EXR"))


def test_spp_and_eval_rays_are_bounded(tmp_path):
    with pytest.raises(ConfigError, match=r"spp: must be at most 1048576"):
        api.render(scene_file(tmp_path), tmp_path / "x.exr", spp=1 << 40, progress=False)
    with pytest.raises(SceneError, match=r"render.spp: Input should be less than or equal to 1048576"):
        load_scene(scene_file(tmp_path, render={"spp": 1 << 21}))
    from neuralrt.render.integrator import render

    scene = load_scene(scene_file(tmp_path))
    with pytest.raises(ConfigError, match=r"spp: must be at most 1048576"):  # the integrator's own call too
        render(scene, spp=1 << 40, progress=False)
    with pytest.raises(ConfigError, match=r"max_depth: must be at most 256"):
        render(scene, spp=1, max_depth=257, progress=False)
    with pytest.raises(ConfigError, match=r"rays: must be at most 4194304"):
        api.evaluate(tmp_path / "m.nrt", tmp_path / "mesh.obj", rays=99999999999999)


def test_api_render_takes_seed_none_as_the_default(tmp_path):
    a = api.render(scene_file(tmp_path), tmp_path / "a.exr", spp=1, seed=None, progress=False)
    b = api.render(scene_file(tmp_path), tmp_path / "b.exr", spp=1, seed=0, progress=False)
    from neuralrt.io.images import read_image

    assert np.array_equal(read_image(a["output"]), read_image(b["output"]))


@pytest.mark.parametrize("kwargs,message", [
    ({"spp": 0}, "spp: must be at least 1"),
    ({"spp": 2.5}, "spp: must be an integer"),
    ({"spp": True}, "spp: must be an integer"),
    ({"max_depth": 0}, "max_depth: must be at least 1"),
    ({"max_depth": 2.5}, "max_depth: must be an integer"),
    ({"seed": -1}, "seed: must be at least 0"),
    ({"primary": "x"}, "primary must be 'exact' or 'neural'"),
    ({"resolution": (0, 5)}, r"resolution: 0x5 must be at least 1x1"),  # (was a ZeroDivisionError)
    ({"resolution": (-4, 4)}, r"resolution: -4x4 must be at least 1x1"),
    ({"resolution": (4.5, 4)}, r"resolution: expected two whole numbers"),  # (was taken as 4)
    ({"resolution": "8x8"}, r"resolution: expected two whole numbers"),
    ({"shading": "x"}, r"shading must be one of 'auto', 'torch', 'numba', got 'x'"),
    ({"device": "tpu"}, r"device='tpu': not a torch device"),
])
def test_integrator_render_checks_its_arguments(kwargs, message):
    scene = load_dict({"camera": {"resolution": [4, 4]}, "objects": [SPHERE]})
    with pytest.raises(ConfigError if "device" not in kwargs else NeuralRTError, match=message):
        render(scene, progress=False, **{"spp": 1, **kwargs})


def test_integrator_render_takes_a_loaded_scene():
    with pytest.raises(ConfigError, match=r"^scene: expected a loaded neuralrt Scene \(load_scene, load_dict\), got str$"):
        render("builtin:cornell-statue", spp=1, progress=False)  # (was an AttributeError)


def test_render_results_save_only_under_an_exr_name(tmp_path):
    """A .png name was written twice (the EXR's data, then the PNG over it), a name without a suffix as EXR data."""
    result = render(load_dict({"camera": {"resolution": [4, 4]}, "objects": [SPHERE]}), spp=1, progress=False)
    for name in ("img.png", "img"):
        with pytest.raises(ConfigError, match=r"output must be an \.exr file"):
            result.save(tmp_path / name)
    assert not list(tmp_path.iterdir())
    assert [p.name for p in result.save(tmp_path / "img.EXR")][:2] == ["img.EXR", "img.png"]
    assert result != render(load_dict({"camera": {"resolution": [4, 4]}, "objects": [SPHERE]}), spp=1, progress=False)


def test_detail_of_the_wrong_type_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="detail: must be an integer, got 'x'"):
        api.render("builtin:instances", tmp_path / "x.exr", spp=1, detail="x", progress=False)


# -- scene spellings ------------------------------------------------------------------------------


def test_the_implicit_default_material_can_be_named(tmp_path):
    scene = load_scene(scene_file(tmp_path, objects=[{**SPHERE, "material": "default"},
                                                     {"name": "b", "generator": {"name": "box"}, "materials": {"default": "default"}}]))
    assert scene.materials.names == ["default"]


def test_equal_generator_arguments_share_one_mesh(tmp_path):
    spellings = [{}, {"subdivisions": 4}, {"subdivisions": 4.0}, {"radius": 1.0}, {"subdivisions": 4, "radius": 1}]
    objects = [{"name": f"s{i}", "generator": {"name": "sphere", "params": p}} for i, p in enumerate(spellings)]
    info = api.info(scene_file(tmp_path, objects=objects + [{"name": "other", "generator": {"name": "sphere", "params": {"subdivisions": 2}}}]))
    assert info["instances"] == 6 and info["unique_blas"] == 2


def test_list_builtins_as_json(capsys):
    assert main(["render", "--list-builtins", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert rows == api.list_builtins() and all(r["scene"].startswith("builtin:") for r in rows)


@pytest.mark.parametrize("sections,key", [
    ({"camera": {"fov": "40"}}, "camera.fov"),
    ({"camera": {"resolution": [True, 4]}}, "camera.resolution.0"),
    ({"render": {"spp": True}}, "render.spp"),
    ({"materials": [{"name": "m", "type": "plastic", "albedo": [0.5, 0.5, 0.5], "ior": "1.5"}]}, "materials.0.ior"),
])
def test_text_and_booleans_are_not_numbers(tmp_path, sections, key):
    with pytest.raises(SceneError, match=rf"{key}: expected a number, got"):
        load_scene(scene_file(tmp_path, **sections))


def test_numpy_numbers_are_numbers():
    scene = load_dict({"camera": {"resolution": [np.int64(6), 4], "fov": np.float32(35)}, "objects": [SPHERE],
                       "render": {"spp": np.int32(2)}})
    assert (scene.camera.width, scene.camera.height) == (6, 4) and scene.settings.spp == 2


def test_numpy_integer_counts_are_counts():
    scene = load_dict({"camera": {"resolution": [4, 4]}, "objects": [SPHERE]})
    assert render(scene, spp=np.int64(2), max_depth=np.int32(2), seed=np.uint8(3), progress=False).spp == 2


def test_a_materials_map_naming_no_slot_warns(tmp_path):
    objects = [{"name": "b", "generator": {"name": "box"}, "materials": {"default": "default", "nonexist": "default"}}]
    with pytest.warns(UserWarning, match=r"objects.0.materials: no material slot named 'nonexist' \(the object's slots: default\)"):
        load_scene(scene_file(tmp_path, objects=objects))


def test_render_time_leaves_the_one_time_warm_up_out(tmp_path):
    """The first render in a process loads its kernels (~0.3 s): `seconds` counted it, so the time per
    sample fell ~20x from 1 to 32 spp. api.render warms up untimed and reports it apart."""
    from neuralrt.render.integrator import warm_up

    result = api.render(scene_file(tmp_path), tmp_path / "x.exr", spp=1, progress=False)
    assert result["warmup_seconds"] > 0 and result["seconds"] > 0
    scene = load_scene(scene_file(tmp_path))
    before = render(scene, spp=2, seed=3, progress=False).image
    assert warm_up(scene) > 0
    assert np.array_equal(render(scene, spp=2, seed=3, progress=False).image, before)  # it changes nothing


def test_a_render_larger_than_the_memory_left_is_refused_before_it_starts(tmp_path, monkeypatch, capsys):
    # The schema allows 16384x16384; at 96 bytes a pixel of float64 sums that took ~26 GiB, and failed
    # in torch's allocator (a traceback) after the scene was built.
    import neuralrt.devices

    monkeypatch.setattr(neuralrt.devices, "available_bytes", lambda device: 1000)
    with pytest.raises(ConfigError, match=r"^a 6x4 render needs \d+ KiB of memory, 1 KiB is available on cpu: render at a lower resolution$"):
        render(load_scene(scene_file(tmp_path)), spp=1, progress=False)
    assert main(["render", scene_file(tmp_path), "-o", str(tmp_path / "x.exr"), "--spp", "1", "--quiet"]) == 2
    assert "render needs" in capsys.readouterr().err and not (tmp_path / "x.exr").exists()
    monkeypatch.setattr(neuralrt.devices, "available_bytes", lambda device: None)  # unknown: no check
    assert render(load_scene(scene_file(tmp_path)), spp=1, progress=False).image.shape == (4, 6, 3)


def test_rendering_a_scene_without_light_warns_that_it_renders_black(tmp_path):
    unlit = tmp_path / "unlit.json"
    unlit.write_text(json.dumps({"camera": {"resolution": [6, 4]}, "objects": [dict(SPHERE)]}))
    with pytest.warns(UserWarning, match=r"unlit.json: the scene has no light .*: it renders black"):
        result = api.render(str(unlit), tmp_path / "x.exr", spp=1, progress=False)
    assert result["spp"] == 1


def test_each_dark_scene_dict_of_a_sweep_is_told(tmp_path):
    """Every dict scene was "scene" in its warnings, so Python, which shows a warning of the same
    text from the same line once, told only the first dark scene of a sweep."""
    import warnings

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("default")
        for k in range(2):
            api.render({"camera": {"resolution": [6, 4]}, "objects": [dict(SPHERE)]}, tmp_path / f"x{k}.exr", spp=1,
                       progress=False)
    assert [str(w.message).split(": the scene has no light")[0] for w in seen] == [
        f"scene rendered to {tmp_path / 'x0.exr'}", f"scene rendered to {tmp_path / 'x1.exr'}"]


def test_a_texture_with_a_negative_texel_is_refused_as_a_negative_albedo_is(tmp_path):
    texels = np.full((4, 4, 3), 0.5, np.float32)
    texels[0, 0] = -0.5
    write_exr(tmp_path / "tex.exr", texels)
    scene = scene_file(tmp_path, materials=[{"name": "m", "type": "diffuse", "albedo": str(tmp_path / "tex.exr")}],
                       objects=[{**SPHERE, "material": "m"}])
    with pytest.raises(NeuralRTError, match=r"materials.0.albedo: .*tex.exr: 1 texel is negative \(albedo must be >= 0\)"):
        api.render(scene, tmp_path / "x.exr", spp=1, progress=False)

"""`neuralrt.api` checks its arguments as the CLI does: a wrong type or value is one `NeuralRTError`
naming the argument, before any work (never a TypeError from deep inside)."""

import json

import pytest
import trimesh

from neuralrt import api
from neuralrt.cli import main
from neuralrt.errors import ConfigError, DeviceError, NeuralRTError


@pytest.fixture
def ball(tmp_path):
    path = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=1).export(path)
    return path


@pytest.mark.parametrize("call, message", [
    (lambda d, b: api.render("builtin:cornell-statue", ["a.exr"]), "output: expected a path \\(str or os.PathLike\\), got list"),
    (lambda d, b: api.train(None, d / "m.nrt"), "mesh: expected a path"),
    (lambda d, b: api.train(b, [d / "m.nrt"]), "output: expected a path"),
    (lambda d, b: api.evaluate([d / "m.nrt"], b), "model: expected a path"),
    (lambda d, b: api.evaluate(d / "m.nrt", None), "mesh: expected a path"),
    (lambda d, b: api.evaluate(d / "m.nrt", b, image_dir=["x"]), "image_dir: expected a path"),
    (lambda d, b: api.evaluate(d / "m.nrt", b, timing="no"), "timing: expected True or False, got str"),
    # A flag given as a word counted as true ("no" allowed the mismatch): each API flag is checked.
    (lambda d, b: api.render("builtin:cornell-statue", d / "a.exr", allow_mesh_mismatch="no"),
     "allow_mesh_mismatch: expected True or False, got str 'no'"),
    (lambda d, b: api.compare(d / "a.exr", d / "b.exr", hdr="yes"), "hdr: expected True or False"),
    (lambda d, b: api.convert(d / "s.toml", d / "o.toml", group="yes"), "group: expected True or False"),
    (lambda d, b: api.train(b, d / "m.nrt", progress=2), "progress: expected True or False, got int 2"),
    (lambda d, b: api.demo(d / "x", quick="yes"), "quick: expected True or False"),
    (lambda d, b: api.train(b, d / "m.nrt", plot=["c.png"]), "plot: expected a path"),
    (lambda d, b: api.info(b, plot=3), "plot: expected a path"),
    (lambda d, b: api.compare(None, d / "b.exr"), "reference: expected a path"),
    (lambda d, b: api.compare(d / "a.exr", d / "b.exr", heatmap=["h.png"]), "heatmap: expected a path"),
    (lambda d, b: api.info(""), "path: expected a path \\(str or os.PathLike\\), got an empty string"),
    (lambda d, b: api.demo(["x"]), "out_dir: expected a path"),
    (lambda d, b: api.convert(["s.toml"], d / "o.toml"), "scene: expected a path"),
    (lambda d, b: api.convert("builtin:cornell-statue", d / "o.toml", models_dir=["m"]), "models_dir: expected a path"),
])
def test_paths_of_the_wrong_type_are_named(tmp_path, ball, call, message):
    with pytest.raises(ConfigError, match=message):
        call(tmp_path, ball)


def test_a_path_whose_bytes_are_not_text_is_refused_before_the_work(tmp_path, ball):
    # (train wrote a model no command could read back: safetensors and OpenEXR take text paths only;
    # render failed after the work and left a new empty folder)
    import os

    bad = os.fsdecode(b"e\xff")  # (as Python decodes such a name from the command line or a listing)
    message = r"/e\\xff/m.nrt: this path's bytes are not UTF-8 text, which the libraries that open model, image and scene"
    with pytest.raises(ConfigError, match=message):
        api.train(ball, tmp_path / bad / "m.nrt", steps=1, progress=False)
    with pytest.raises(ConfigError, match=message.replace("m.nrt", "r.exr")):
        api.render("builtin:cornell-statue", tmp_path / bad / "r.exr", progress=False)
    assert not (tmp_path / bad).exists()


def test_a_mesh_given_as_the_model_says_so(ball):
    from neuralrt import load_mesh

    with pytest.raises(ConfigError, match="model: got a Mesh; evaluate\\(model, mesh\\) takes the model first"):
        api.evaluate(load_mesh(ball), ball)


@pytest.mark.parametrize("call, message", [
    (lambda d, b: api.render("builtin:cornell-statue", d / "i.exr", seed="x"), "seed: must be an integer, got 'x'"),
    (lambda d, b: api.render("builtin:cornell-statue", d / "i.exr", seed=-1), "seed: must be at least 0, got -1"),
    (lambda d, b: api.render("builtin:cornell-statue", d / "i.exr", nif=123), "nif: expected 'auto' or object names"),
    (lambda d, b: api.train(b, d / "m.nrt", seed=2**70), "seed: must be at most 9223372036854775807"),
    (lambda d, b: api.train(b, d / "m.nrt", preset=["lq"]), "preset: expected a name \\(str\\), got list"),
    (lambda d, b: api.evaluate(d / "m.nrt", b, seed=1.5), "seed: must be an integer, got 1.5"),
    (lambda d, b: api.convert("builtin:cornell-statue", d / "o.toml", min_triangles=-5), "min_triangles: must be at least 0"),
    (lambda d, b: api.convert("builtin:cornell-statue", d / "o.toml", select=123), "select: expected object names"),
    (lambda d, b: api.convert("builtin:cornell-statue", d / "o.toml", seed=2**70), "seed: must be at most"),
    (lambda d, b: api.demo(d / "demo", quick=True, bogus=3), "demo: unknown setting\\(s\\) bogus \\(known: scene"),
])
def test_bad_values_are_named(tmp_path, ball, call, message):
    with pytest.raises(ConfigError, match=message):
        call(tmp_path, ball)
    assert not (tmp_path / "demo").exists() and not (tmp_path / "o.toml").exists()


def test_convert_takes_convert_scenes_keywords_by_name():
    """help(api.convert) lists each option (it showed ``**options``): the same names, kinds and
    defaults as `convert_scene`, so a keyword added there is not silently missing here."""
    import inspect

    from neuralrt.scene.convert import convert_scene

    def keywords(f):
        return [(p.name, p.kind, p.default) for p in inspect.signature(f).parameters.values()]

    assert keywords(api.convert) == keywords(convert_scene)
    with pytest.raises(TypeError, match="unexpected keyword argument .bogus."):
        api.convert("builtin:cornell-statue", "o.toml", bogus=1)


def test_convert_select_string_is_comma_separated_as_on_the_command_line(tmp_path):
    # (a plain string used to be read as a list of one-letter names)
    with pytest.raises(NeuralRTError, match="select: no object named 'nope' \\(objects: "):
        api.convert("builtin:cornell-statue?detail=0", tmp_path / "o.toml", select="statue, nope", steps=1)


def test_ray_executor_checks_the_device_name_and_cpus_up_front(tmp_path, capsys):
    with pytest.raises(DeviceError, match="device=.tpu.: not a torch device"):
        api.convert("builtin:cornell-statue", tmp_path / "o.toml", executor="ray", device="tpu")
    assert main(["convert", "builtin:cornell-statue", "-o", str(tmp_path / "o.toml"), "--executor", "ray",
                 "--cpus-per-model", "inf"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cpus-per-model: Input should be a finite number" in err[0], err


def test_seed_beyond_64_bits_is_one_line_from_the_cli(ball, tmp_path, capsys):
    assert main(["eval", str(tmp_path / "m.nrt"), str(ball), "--seed", str(10**23)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "seed: must be at most" in err[0], err


def test_interrupted_before_the_first_checkpoint_says_so_and_leaves_no_folder(tmp_path, ball, monkeypatch, capsys):
    from neuralrt.training import api as training_api

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(training_api, "train", interrupted)
    out = tmp_path / "new" / "sub" / "m.nrt"
    assert main(["train", str(ball), "-o", str(out), "--steps", "5", "--quiet"]) == 130
    assert "no checkpoint was written yet: run the command again to start over" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_info_shows_a_scene_whose_model_belongs_to_another_mesh(tmp_path, capsys):
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel

    LSNIFModel.from_mesh(sphere(1), LSNIFConfig.preset("lq")).save(tmp_path / "m.nrt")
    (tmp_path / "scene.toml").write_text(
        '[[objects]]\nmodel = "m.nrt"\ngenerator = { name = "sphere", params = { subdivisions = 2 } }\n')
    assert main(["info", str(tmp_path / "scene.toml"), "--json"]) == 0
    assert '"neural_instances": 1' in capsys.readouterr().out


def test_set_changes_config_keys_of_the_preset(ball, tmp_path, capsys):
    model = tmp_path / "m.nrt"
    assert main(["train", str(ball), "-o", str(model), "--preset", "lq", "--steps", "2", "--batch", "256", "--quiet",
                 "--set", "voxel.resolution=16", "--set", "inference.occlusion_threshold=0.4"]) == 0
    capsys.readouterr()
    assert main(["info", str(model), "--json"]) == 0
    config = json.loads(capsys.readouterr().out)["config"]
    assert config["voxel"]["resolution"] == 16 and config["inference"]["occlusion_threshold"] == 0.4
    assert config["network"]["hidden_width"] == 64  # the rest is the preset's


@pytest.mark.parametrize("item, message", [
    ("bogus", "--set bogus: expected SECTION.KEY=VALUE"),
    ("voxel.resolution=31", "hash grid resolutions (64, 128) must be positive multiples of the voxel resolution 31"),
    ("voxel.nope=1", "voxel.nope: Extra inputs are not permitted"),
])
def test_bad_set_is_one_line_before_training(ball, tmp_path, capsys, item, message):
    assert main(["train", str(ball), "-o", str(tmp_path / "m.nrt"), "--set", item, "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    with pytest.raises(ConfigError, match="settings: expected a dict"):
        api.convert("builtin:cornell-statue", tmp_path / "o.toml", settings=["voxel.resolution=16"])


@pytest.mark.parametrize("api_call, argv, from_python, from_cli", [
    (lambda d, b: api.render("builtin:cornell-statue", d / "x.exr", nif_train_spp=4),
     lambda d, b: ["render", "builtin:cornell-statue", "-o", str(d / "x.exr"), "--nif-train-spp", "4"],
     "nif_train_spp needs nif", "--nif-train-spp needs --nif OBJECTS|auto"),
    (lambda d, b: api.render("builtin:cornell-statue", d / "x.exr", device="tpu"),
     lambda d, b: ["render", "builtin:cornell-statue", "-o", str(d / "x.exr"), "--device", "tpu"],
     "device='tpu': not a torch device", "--device tpu: not a torch device"),
    (lambda d, b: api.evaluate(d / "m.nrt", b, images=False, image_dir=d / "img"),
     lambda d, b: ["eval", str(d / "m.nrt"), str(b), "--no-images", "--images", str(d / "img")],
     "image_dir and images=False contradict", None),  # (argparse's exclusive group on the command line)
    (lambda d, b: api.convert("builtin:cornell-statue", d / "o.toml", executor="dask"),
     lambda d, b: ["convert", "builtin:cornell-statue", "-o", str(d / "o.toml"), "--executor", "dask"],
     "executor='dask': choose from", None),  # (argparse refuses it first on the command line)
    (lambda d, b: api.convert("builtin:cornell-statue", d / "o.toml", address="localhost:1"),
     lambda d, b: ["convert", "builtin:cornell-statue", "-o", str(d / "o.toml"), "--address", "localhost:1"],
     "address: only with executor='ray'", "--address: only with --executor ray"),
])
def test_errors_name_arguments_as_the_caller_spelled_them(tmp_path, ball, capsys, api_call, argv, from_python, from_cli):
    """From Python an argument is ``nif_train_spp``, from the command line ``--nif-train-spp`` (API
    errors used to name CLI flags)."""
    with pytest.raises(NeuralRTError) as info:
        api_call(tmp_path, ball)
    assert from_python in str(info.value) and "--" not in str(info.value), info.value
    if from_cli is not None:
        assert main(argv(tmp_path, ball)) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and from_cli in err[0], err


def test_every_top_level_name_resolves_whatever_was_imported_before():
    """``neuralrt.render`` was the render function until a neuralrt.render module was imported, then
    the subpackage: the function is ``render_scene``."""
    import neuralrt
    import neuralrt.render.film  # noqa: F401  (binds the subpackage, as any render import does)
    from neuralrt.render.integrator import render

    assert neuralrt.render_scene is render
    assert all(getattr(neuralrt, name) is not None for name in neuralrt.__all__)
    assert {"NBVHConfig", "NBVHModel", "NIFConfig", "LSNIFConfig"} <= set(neuralrt.__all__)
    assert "list_presets" in api.__all__


def test_info_counts_camera_only_meshes_apart(tmp_path):
    """A hybrid scene keeps a neural object's mesh for camera rays: it counted in triangles_unique
    but not in triangles_instanced (unique > instanced)."""
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel

    LSNIFModel.from_mesh(sphere(2), LSNIFConfig.preset("lq")).save(tmp_path / "m.nrt")
    (tmp_path / "scene.toml").write_text(
        '[[objects]]\nmodel = "m.nrt"\ngenerator = { name = "sphere", params = { subdivisions = 2 } }\n'
        '[[objects]]\ngenerator = { name = "plane" }\n[[objects]]\ngenerator = { name = "plane" }\n')
    info = api.info(tmp_path / "scene.toml")
    assert (info["triangles_unique"], info["triangles_instanced"], info["triangles_camera_only"]) == (2, 4, 320)


@pytest.mark.parametrize("argv, line", [
    (["render", "builtin:cornell-statue", "-o", "{d}/i.exr", "--spp", "0"], "--spp: must be at least 1, got 0"),
    (["render", "builtin:cornell-statue", "-o", "{d}/i.exr", "--max-depth", "0"], "--max-depth: must be at least 1"),
    (["train", "procedural:statue:0", "-o", "{d}/m.nrt", "--steps", "0"], "--steps: must be at least 1, got 0"),
    (["train", "procedural:statue:0", "-o", "{d}/m.nrt", "--batch", "0"], "--batch: must be at least 1, got 0"),
    (["eval", "{d}/m.nrt", "procedural:statue:0", "--rays", "0"], "--rays: must be at least 2, got 0"),
    (["convert", "builtin:instances", "-o", "{d}/o.toml", "--min-triangles", "-1"], "--min-triangles: must be at least 0"),
])
def test_counts_out_of_range_name_the_flag(tmp_path, capsys, argv, line):
    # (they said "spp: ...", "rays: ...": the Python names, where every other CLI error names the flag)
    assert main([a.format(d=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"neuralrt: error: {line}") and err.count("\n") == 1


def test_numpy_integers_are_taken_as_python_ints():
    # A numpy integer passed the checks, then: the demo's report.json failed after the whole run,
    # evaluate's seed failed inside torch, and results held int64 (not JSON).
    import numpy as np

    from neuralrt.demo import DemoSettings
    from neuralrt.geometry.procedural import make_procedural
    from neuralrt.methods.lsnif import LSNIFModel
    from neuralrt.methods.lsnif_config import LSNIFConfig
    from neuralrt.scene.loader import load_scene_spec

    settings = DemoSettings(spp=np.int64(2), steps=np.int32(10), seed=np.uint8(3), resolution=(np.int64(16), 16))
    assert json.loads(json.dumps([settings.spp, settings.steps, settings.seed, settings.resolution])) == [2, 10, 3, [16, 16]]
    ball = make_procedural("sphere", subdivisions=1)
    model = LSNIFModel.from_mesh(ball, LSNIFConfig.preset("lq"))
    result = api.evaluate(model, ball, rays=np.int64(256), seed=np.int64(5), images=False, timing=False, progress=False)
    assert type(result["rays"]) is int and json.dumps(result["rays"]) == "256"
    assert load_scene_spec("builtin:cornell-statue", detail=np.int64(0))[0].objects  # (it said "must be an integer")
    with pytest.raises(ConfigError, match=r"^resolution: expected two whole numbers \(width, height\), got \(True, 16\)$"):
        api.render("builtin:cornell", "x.exr", resolution=(True, 16), progress=False)  # (it rendered 1x16)

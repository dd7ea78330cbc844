"""Bad input to N-BVH, NIF and the training loop (found by a new-user trial): one-line errors of
the package's own classes before any long work, warnings where a run would otherwise be silently
pointless, and checkpoints that `info` describes."""

import json
import subprocess
import sys

import pytest

from neuralrt import api
from neuralrt.cli import main
from neuralrt.errors import ConfigError, NeuralRTError, TrainingError
from neuralrt.geometry.procedural import plane, sphere
from neuralrt.methods.config import parse_settings
from neuralrt.methods.lsnif import LSNIFModel
from neuralrt.methods.lsnif_config import LSNIFConfig
from neuralrt.methods.nbvh import NBVHModel
from neuralrt.methods.nbvh_config import NBVHConfig
from neuralrt.render.nif_render import render_nif
from neuralrt.scene.loader import load_dict
from neuralrt.training.api import train


def _obj(path, mesh) -> str:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in mesh.vertices.tolist()] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces.tolist()]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _nbvh(**overrides):
    return NBVHConfig.preset("cpu", **overrides)


# -- the training loop ---------------------------------------------------------------------------


def test_a_diverging_run_stops_with_one_line_and_writes_no_model(tmp_path, capsys):
    config = _nbvh(training={"steps": 20, "batch_size": 256, "learning_rate": 1e6})
    with pytest.raises(TrainingError, match=r"training diverged at step \d+: the loss is (nan|inf) .*learning_rate, now 1e\+06"):
        train(sphere(1), config, progress=False)
    mesh = _obj(tmp_path / "ball.obj", sphere(1))
    out = tmp_path / "models" / "ball.nrt"
    args = ["train", str(mesh), "-o", str(out), "--method", "nbvh", "--steps", "20", "--batch", "256", "--quiet",
            "--set", "training.learning_rate=1e6"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("neuralrt: error: training diverged at step") and err.count("\n") == 1
    assert not out.exists() and not (tmp_path / "models").exists()


def test_weights_past_the_storage_range_write_no_model_and_no_checkpoint(tmp_path, capsys):
    """A learning rate that grows the hash table past float16's range with a finite loss: the model
    file would hold infinities no command loads (a new-user trial), so nothing is written."""
    mesh = _obj(tmp_path / "ball.obj", sphere(1))
    out = tmp_path / "models" / "ball.nrt"
    args = ["train", str(mesh), "-o", str(out), "--preset", "lq", "--steps", "30", "--batch", "1024", "--quiet",
            "--set", "training.learning_rate=1e5"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"neuralrt: error: {out}: the model cannot be stored: its encoder.table holds NaN or infinite "
                          f"values as float16") and err.count("\n") == 1
    assert not (tmp_path / "models").exists()


@pytest.mark.parametrize("setting, message", [
    ("encoding.init_scale=1e5", "encoding.init_scale: Input should be less than or equal to 1"),
    ("training.adam_betas=[2,-1]", "training.adam_betas.0: Input should be less than 1"),
])
def test_settings_torch_would_refuse_after_set_up_are_refused_first(setting, message):
    for config_class in (LSNIFConfig, NBVHConfig):
        with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
            config_class.preset(next(iter(config_class.PRESETS)), **parse_settings([setting]))


def test_rerunning_without_resume_warns_that_the_checkpoint_is_replaced(tmp_path):
    mesh = _obj(tmp_path / "ball.obj", sphere(1))
    out = tmp_path / "ball.nrt"
    stale = out.with_name("ball.nrt.ckpt")
    stale.write_bytes(b"from an earlier run")
    # (as Python spells it: the warning said --resume to an API caller)
    with pytest.warns(UserWarning, match=r"ball.nrt.ckpt: an earlier interrupted run's checkpoint .*\(resume=True continues it instead\)"):
        api.train(mesh, out, preset="lq", steps=2, batch=256, progress=False)
    assert out.is_file() and not stale.exists()


@pytest.mark.parametrize("name,value", [("steps", True), ("steps", "5"), ("steps", 5.0), ("batch", 1e3), ("batch", "256")])
def test_api_train_counts_must_be_integers(tmp_path, name, value):
    with pytest.raises(ConfigError, match=f"{name}: must be an integer"):
        api.train(sphere(1), tmp_path / "m.nrt", progress=False, **{name: value})
    assert not (tmp_path / "m.nrt").exists()


# -- N-BVH's config and levels of detail -----------------------------------------------------------


@pytest.mark.parametrize("overrides,message", [
    ({"cut": {"lods": 3}, "inference": {"lod": 5}}, r"inference.lod: 5 is coarser than every level of detail cut.lods = 3 registers \(0..2\)"),
    ({"training": {"dilation": 1e9}}, r"training.dilation: Input should be less than or equal to 0.1"),
    ({"training": {"dilation_jitter": 0.5}}, r"training.dilation_jitter: Input should be less than or equal to 0.1"),
    ({"inference": {"box_dilation": 1.0}}, r"inference.box_dilation: Input should be less than or equal to 0.1"),
    ({"training": {"surface_offset": 0.3}}, r"training.surface_offset: unused by N-BVH .*leave it at 0.0001"),
    ({"training": {"surface_pool_size": 16}}, r"training.surface_pool_size: unused by N-BVH"),
    ({"training": {"surface_fraction": 0.9}}, r"training.surface_fraction: unused by N-BVH"),
])
def test_nbvh_config_refuses_meaningless_values(overrides, message):
    with pytest.raises(ConfigError, match=message):
        _nbvh(**overrides)


def test_nbvh_defaults_and_presets_still_validate():
    for name in NBVHConfig.PRESETS:
        config = NBVHConfig.preset(name)
        assert NBVHConfig.model_validate(config.model_dump(mode="json")) == config  # a saved header loads back


def test_set_takes_python_spellings_of_none_and_booleans():
    assert parse_settings(["inference.secondary_lod=None", "a.b=True", "a.c=False", "a.d=null", "a.e=none"]) == {
        "inference": {"secondary_lod": None}, "a": {"b": True, "c": False, "d": None, "e": "none"}}
    assert _nbvh(**parse_settings(["inference.secondary_lod=None"])).inference.secondary_lod is None


@pytest.mark.parametrize("lod", [1.5, True, "1", -1, 3, None])
def test_at_lod_takes_only_a_registered_level(lod):
    model = NBVHModel.from_mesh(sphere(1), _nbvh(cut={"lods": 3}))
    with pytest.raises(ConfigError, match=r"N-BVH level of detail: expected an integer in 0..2 \(cut.lods = 3\)"):
        model.at_lod(lod)
    assert model.at_lod(2).config.inference.lod == 2


# -- saving models -------------------------------------------------------------------------------


def test_save_needs_an_nrt_path_where_files_can_be_written(tmp_path):
    model = LSNIFModel.from_mesh(sphere(1), LSNIFConfig.preset("lq"))
    with pytest.raises(ConfigError, match=r"noext: a model file must end in .nrt"):
        model.save(tmp_path / "noext")
    (tmp_path / "folder.nrt").mkdir()
    with pytest.raises(NeuralRTError, match="is a folder, not a model file"):
        model.save(tmp_path / "folder.nrt")
    with pytest.raises(ConfigError, match="path"):
        model.save(42)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.nrt"]  # no temporary file left
    assert model.save(tmp_path / "m.NRT").is_file()


# -- info on checkpoints -------------------------------------------------------------------------


def test_info_describes_a_checkpoint_under_either_name(tmp_path, capsys):
    ckpt = tmp_path / "ball.nrt.ckpt"
    config = LSNIFConfig.preset("lq").with_training(steps=4, batch_size=256, checkpoint_every=2)
    train(sphere(1), config, progress=False, checkpoint=ckpt)
    for path in (ckpt, tmp_path / "renamed.nrt"):
        if not path.exists():
            path.write_bytes(ckpt.read_bytes())
        info = api.info(path)
        assert info["kind"] == "checkpoint" and info["method"] == "lsnif" and info["step"] == 4
        assert info["training"]["steps"] == 4 and "steps" not in info["config"]["training"]
    assert api.info(ckpt)["resume"].startswith(f"neuralrt train MESH -o {tmp_path / 'ball.nrt'} --resume")
    convert_named = tmp_path / "statue-0123456789-abcdef01.ckpt"  # (a convert models folder's: a rerun resumes it)
    convert_named.write_bytes(ckpt.read_bytes())
    assert api.info(convert_named)["resume"].startswith("run the neuralrt convert command that wrote it again")
    (tmp_path / "other.ckpt").write_bytes(ckpt.read_bytes()[:10])
    assert main(["info", str(tmp_path / "other.ckpt")]) == 2
    assert capsys.readouterr().err.startswith("neuralrt: error: ")


def test_a_closed_pipe_ends_the_cli_quietly(tmp_path):
    ckpt = tmp_path / "ball.nrt.ckpt"
    train(sphere(1), LSNIFConfig.preset("lq").with_training(steps=2, batch_size=256), progress=False, checkpoint=ckpt)
    proc = subprocess.Popen([sys.executable, "-m", "neuralrt", "info", str(ckpt)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # as `| head -0` would
    err = proc.stderr.read()
    assert proc.wait() in (0, 141) and err == b""


# -- NIF -----------------------------------------------------------------------------------------


def _scene(lights=True):
    objects = [
        {"name": "ball", "mesh": sphere(subdivisions=2), "material": "white", "transform": {"scale": 0.5}},
        {"name": "floor", "mesh": plane(size=6.0), "material": "white", "transform": {"translate": [0, -0.6, 0]}},
    ]
    if lights:
        objects.append({"name": "lamp", "mesh": plane(size=1.0), "material": "lamp",
                        "transform": {"translate": [0, 2.5, 0], "rotate": [180, 0, 0]}})
    return load_dict({
        "camera": {"position": [0, 1.5, 5], "look_at": [0, 0, 0], "resolution": [12, 8]},
        "materials": [{"name": "white", "type": "diffuse", "albedo": [0.7, 0.7, 0.7]},
                      *([{"name": "lamp", "type": "emissive", "emission": [8, 8, 8]}] if lights else [])],
        "objects": objects,
    })


@pytest.mark.parametrize("args,message", [
    (dict(scene="builtin:cornell-statue"), "scene must be a loaded Scene"),
    (dict(nif=5), "nif: expected 'auto' or object names"),
    (dict(nif=None), "nif: expected 'auto' or object names"),
    (dict(spp="x"), "spp: must be an integer"),
    (dict(train_spp=2.7), "^train_spp: must be an integer"),
    (dict(seed=-1), "seed: must be at least 0"),
    (dict(answer="foo"), "answer: must be 'answer' or 'exact'"),
    (dict(config={"training": {"passes_per_spp": 0}}), r"nif config: training.passes_per_spp: Input should be greater than or equal to 1"),
    (dict(config={"foo": 1}), "nif config: foo: Extra inputs are not permitted"),
    (dict(config="fp32"), "config: expected a NIFConfig or a dict"),
])
def test_render_nif_arguments_are_config_errors(args, message):
    call = dict(scene=None, nif="ball", spp=4, train_spp=2, progress=False) | args
    call["scene"] = call["scene"] or _scene()
    with pytest.raises(ConfigError, match=message):
        render_nif(**call)


@pytest.mark.filterwarnings("ignore:NIF. the networks trained only")  # (a few pixels: a few steps)
def test_render_nif_takes_a_dict_config_and_defaults_to_half_the_spp():
    with pytest.warns(UserWarning, match=r"NIF trains on the first 2 of 4 samples per pixel \(its default, 32, is not below spp"):
        result, report = render_nif(_scene(), "ball", spp=4, config={"training": {"passes_per_spp": 2}}, progress=False)
    assert report["train_spp"] == 2 and report["passes_per_spp"] == 2 and result.spp == 4
    assert report["training"]["outer_pairs"] > 0
    with pytest.raises(ConfigError, match="at least 2 samples per pixel"):
        render_nif(_scene(), "ball", spp=1, progress=False)


def test_render_nif_warns_when_nothing_trained_it():
    with pytest.warns(UserWarning, match="NIF: no shadow ray toward the chosen objects was traced"):
        _, report = render_nif(_scene(lights=False), "ball", spp=3, train_spp=2, progress=False)
    assert report["training"]["outer_pairs"] == 0
    with pytest.warns(UserWarning) as caught:  # lit: trained, but on a few pixels: a few steps
        render_nif(_scene(), "ball", spp=3, train_spp=2, progress=False)
    assert [str(w.message).split(" (")[0] for w in caught] == ["NIF: the networks trained only 1 outer + 1 inner steps"]


@pytest.mark.parametrize("nif", [[], "nosuch"])
def test_api_render_keeps_the_config_error_class(tmp_path, nif):
    with pytest.raises(ConfigError):
        api.render(_scene(), tmp_path / "x.exr", spp=4, nif=nif, progress=False)


def test_cli_nif_with_the_scene_default_spp_renders(tmp_path, capsys):
    out = tmp_path / "img.exr"
    args = ["render", "builtin:cornell-statue?detail=0", "-o", str(out), "--res", "12x8", "--quiet", "--json", "--nif", "statue"]
    assert main(args) == 0
    captured = capsys.readouterr()
    assert "neuralrt: warning: NIF trains on the first 8 of 16 samples per pixel" in captured.err
    assert json.loads(captured.out)["nif"]["train_spp"] == 8 and out.exists()


def test_info_of_a_model_set_past_its_preset_names_the_nearest_preset_and_the_keys(tmp_path):
    out = tmp_path / "k.nrt"
    api.train("procedural:statue:0", out, preset="lq", steps=2, batch=256, progress=False,
              settings={"network": {"hidden_width": 32}})
    info = api.info(out)
    assert info["preset"] is None and info["nearest_preset"] == "lq"
    assert info["changed_from_preset"] == {"network.hidden_width": 32}
    plain = tmp_path / "plain.nrt"
    api.train("procedural:statue:0", plain, preset="lq", steps=2, batch=256, progress=False)
    assert api.info(plain)["preset"] == "lq" and "nearest_preset" not in api.info(plain)


def test_eval_set_changes_how_the_model_answers_and_takes_inference_keys_only(tmp_path, capsys):
    from neuralrt.methods.nbvh_config import NBVHConfig
    from neuralrt.training.api import train

    from neuralrt.geometry.mesh import load_mesh

    model = train(load_mesh("procedural:statue:0"), NBVHConfig.preset("cpu").with_training(steps=40, batch_size=1024),
                  progress=False)
    path = model.save(tmp_path / "statue.nrt")
    common = ["eval", str(path), "procedural:statue:0", "--rays", "2048", "--no-images", "--no-timing", "--quiet", "--json"]
    assert main(common) == 0
    finest = json.loads(capsys.readouterr().out)
    coarse_lod = max(model.registered_lods())
    assert main([*common, "--set", f"inference.lod={coarse_lod}"]) == 0
    coarse = json.loads(capsys.readouterr().out)
    assert coarse["inference"] == {"lod": coarse_lod} and "inference" not in finest
    assert coarse["outside"] != finest["outside"]  # (another cut answered)
    assert main([*common, "--set", "training.steps=5"]) == 2
    assert "eval --set takes inference.KEY=VALUE only" in capsys.readouterr().err
    assert main([*common, "--set", "inference.storage_precision=fp32"]) == 2
    assert "storage_precision is how the model's parameters were stored" in capsys.readouterr().err
    assert main([*common, "--set", "inference.occlusion_threshold=0.4"]) == 0  # (a key every method has)
    capsys.readouterr()
    assert main([*common, "--set", "inference.lodd=1"]) == 2
    assert "inference.lodd: not a setting of any method's models (theirs: occlusion_threshold" in capsys.readouterr().err

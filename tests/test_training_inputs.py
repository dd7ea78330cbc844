"""Bad input to training is one line naming the argument or key, raised before any work: configs
and presets, `neuralrt.train`'s arguments, meshes float32 cannot trace, resuming a checkpoint."""

import warnings

import numpy as np
import pytest
import torch

import neuralrt
from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.cli import main
from neuralrt.errors import ConfigError, DeviceError, MeshError, ModelFileError
from neuralrt.geometry.mesh import Mesh, check_float32_extent, load_mesh
from neuralrt.geometry.procedural import sphere
from neuralrt.methods import get_method
from neuralrt.methods.config import TrainingConfig
from neuralrt.methods.lsnif import LSNIFConfig
from neuralrt.methods.nbvh_config import NBVHConfig
from neuralrt.methods.nif_config import NIFConfig
from neuralrt.training import api as training_api
from neuralrt.training.ray_distribution import BoxRayDistribution
from neuralrt.training.trainer import checkpoint_run, identity_differences

SMALL = {"steps": 4, "batch_size": 256, "surface_pool_size": 1024}


def _one_line(message: str) -> bool:
    return "\n" not in message and "Traceback" not in message


# -- configs and presets ----------------------------------------------------------------------


@pytest.mark.parametrize("seed, problem", [(2**70, "less than 9223372036854775808"), (2**63, "less than"),
                                           (-1, "greater than or equal to 0")])
def test_seeds_beyond_what_the_generators_take_are_config_errors(seed, problem):
    with pytest.raises(ConfigError, match=f"training.seed: Input should be {problem}") as err:
        LSNIFConfig.preset("lq").with_training(seed=seed)
    assert _one_line(str(err.value))
    with pytest.raises(ConfigError, match="training.seed"):
        get_method("nbvh").config("cpu", seed=seed)
    assert LSNIFConfig.preset("lq").with_training(seed=2**63 - 1).training.seed == 2**63 - 1


@pytest.mark.parametrize("name", ["nope", None, ["lq"]])
def test_unknown_presets_are_config_errors_listing_the_presets(name):
    with pytest.raises(ConfigError, match=r"unknown lsnif preset .* \(choose from hq, lq, gpu\)") as err:
        LSNIFConfig.preset(name)
    assert isinstance(err.value, ValueError)  # callers catching ValueError keep working


@pytest.mark.parametrize("changes, key", [({"steps": 0}, "training.steps"), ({"bogus": 1}, "training.bogus"),
                                          ({"learning_rate": float("nan")}, "training.learning_rate"),
                                          ({"batch_size": "x"}, "training.batch_size")])
def test_bad_training_changes_are_one_line_config_errors(changes, key):
    with pytest.raises(ConfigError, match=f"^lsnif config: {key}: ") as err:
        LSNIFConfig.preset("lq").with_training(**changes)
    assert _one_line(str(err.value))
    with pytest.raises(ConfigError, match=f"^lsnif config: {key}: "):
        LSNIFConfig.preset("lq", training=changes)


def test_bad_preset_overrides_name_the_section():
    with pytest.raises(ConfigError, match="^lsnif config: training: Input should be a valid dictionary"):
        LSNIFConfig.preset("lq", training=5)
    with pytest.raises(ConfigError, match="^lsnif config: bogus: Extra inputs"):
        LSNIFConfig.preset("lq", bogus={"a": 1})


def test_plain_construction_and_assignment_are_one_line_config_errors():
    """As from a file or --set (they were pydantic's multi-line dumps); a ConfigError is a ValueError too."""
    with pytest.raises(ConfigError, match=r"^lsnif config: training\.steps: Input should be greater than or equal to 1 \(got 0\)$"):
        LSNIFConfig(training={"steps": 0})
    config = LSNIFConfig.preset("lq")
    with pytest.raises(ConfigError, match=r"^TrainingConfig: steps: Input should be greater"):  # caught where it is assigned
        config.training.steps = 0
    assert config.training.steps == LSNIFConfig.preset("lq").training.steps
    with pytest.raises(ConfigError, match=r"^nbvh config: cut\.lods: .*\(got 0\)$"):
        NBVHConfig(cut={"lods": 0})
    with pytest.raises(ConfigError, match=r"^nif config: bogus: Extra inputs are not permitted \(got 1\)$"):
        NIFConfig(bogus=1)
    with pytest.raises(ConfigError, match=r"^TrainingConfig: steps: Input should be a valid integer"):
        TrainingConfig(steps="many")
    assert "\n" not in str(pytest.raises(ValueError, NIFConfig, training={"seed": -1}).value)


def test_default_preset_of_a_bad_device_is_one_line():
    with pytest.raises(DeviceError, match="tpu"):
        get_method("lsnif").config(device="tpu")


# -- neuralrt.train's arguments -----------------------------------------------------------------


@pytest.fixture
def no_work(monkeypatch):
    """Fails the test if training gets as far as picking the method (every check comes before)."""

    def started(*args, **kwargs):
        raise AssertionError("training started before the bad argument was found")

    monkeypatch.setattr(training_api, "get_method", started)


def _lq():
    return LSNIFConfig.preset("lq").with_training(**SMALL)


@pytest.mark.parametrize("config", [{"method": "lsnif"}, "lq", 5])
def test_a_config_that_is_not_a_method_config(no_work, config):
    with pytest.raises(ConfigError, match=f"^config: expected a method config .* got {type(config).__name__}$"):
        neuralrt.train(sphere(1), config, progress=False)


def test_a_config_with_values_set_past_validation(no_work):
    config = _lq()
    bad = config.model_copy(update={"training": config.training.model_copy(update={"steps": 0})})  # copies skip validation
    with pytest.raises(ConfigError, match="^lsnif config: training.steps: Input should be greater than or equal to 1"):
        neuralrt.train(sphere(1), bad, progress=False)


@pytest.mark.parametrize("mesh", [None, ["ball.obj"], 3])
def test_a_mesh_that_is_neither_a_mesh_nor_a_path(no_work, mesh):
    with pytest.raises(ConfigError, match=f"^mesh: expected a Mesh or a mesh file path, got {type(mesh).__name__}$"):
        neuralrt.train(mesh, _lq(), progress=False)


def test_devices_this_process_cannot_use(no_work, monkeypatch):
    with pytest.raises(DeviceError, match="tpu"):
        neuralrt.train(sphere(1), _lq(), progress=False, device="tpu")
    monkeypatch.setattr(torch.backends.cuda, "is_built", lambda: False)
    with pytest.raises(DeviceError, match=r"^device='cuda': this torch .* without CUDA"):
        neuralrt.train(sphere(1), _lq(), progress=False, device="cuda")


@pytest.mark.parametrize("kwargs, message", [
    ({"resume": True}, "^resume=True needs checkpoint=PATH"),
    ({"checkpoint": ["x.ckpt"]}, r"^checkpoint: expected a path \(str or os.PathLike\), got list$"),
    ({"resume": "yes", "checkpoint": "x.ckpt"}, "^resume: expected True or False, got str 'yes'$"),
    ({"on_step": 3}, "^on_step: expected a function"),
])
def test_bad_checkpoint_resume_and_hook_arguments(no_work, kwargs, message):
    with pytest.raises(ConfigError, match=message):
        neuralrt.train(sphere(1), _lq(), progress=False, **kwargs)


def test_resume_without_a_checkpoint_file_starts_afresh(tmp_path):
    """The scene converter makes one call for a first run and a rerun: a missing file is a fresh start."""
    model = neuralrt.train(sphere(1), _lq(), progress=False, checkpoint=tmp_path / "run.ckpt", resume=True)
    assert model.training_record["resumed_from"] is None and model.training_record["steps"] == SMALL["steps"]


# -- meshes float32 cannot trace ------------------------------------------------------------------


def _ball(scale: float = 1.0, shift: float = 0.0, name: str = "ball") -> Mesh:
    base = sphere(1)
    return Mesh(base.vertices.astype(np.float64) * scale + shift, base.faces, name=name)


@pytest.mark.parametrize("scale, shift, problem", [
    (1e30, 0.0, r"bounding-box diagonal 3\.46e\+30 is outside \[1e-08, 1e\+08\]"),
    (1e-30, 0.0, r"bounding-box diagonal 3\.46e-30 is outside"),
    (1.0, 1e7, r"coordinates reach 1e\+07, too far from the origin .* float32 rounds them by 1,"),
])
def test_meshes_float32_cannot_trace_fail_before_training(no_work, scale, shift, problem):
    mesh = _ball(scale, shift)  # a Mesh holds them (`neuralrt info` reports such meshes) ...
    with pytest.raises(MeshError, match=f"^ball: {problem}"):  # ... but training refuses them up front
        neuralrt.train(mesh, _lq(), progress=False)


@pytest.mark.parametrize("scale, shift", [(1e-7, 0.0), (1e7, 0.0), (1.0, 100.0), (229.0, 97.0)])
def test_sizes_and_offsets_float32_traces_are_accepted(scale, shift):
    check_float32_extent(_ball(scale, shift))  # (229, 97: armadillo.off's diagonal and largest coordinate)


def test_coordinates_beyond_float32_are_one_error_without_a_numpy_warning(tmp_path):
    obj = tmp_path / "over.obj"
    obj.write_text("v -1e39 0 0\nv 1e39 0 0\nv 0 1e39 0\nf 1 2 3\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's "overflow encountered in cast" would fail the test
        with pytest.raises(MeshError, match="3 vertices have NaN or Inf coordinates"):
            load_mesh(obj)
        with pytest.raises(MeshError, match="NaN or Inf"):
            _ball(1e39)


def test_a_mesh_no_sampled_ray_hits_is_a_mesh_error():
    blas = MeshBLAS(sphere(1))

    class NeverHits:
        bounds, mesh = blas.bounds, blas.mesh

        def intersect(self, rays):
            hits = blas.intersect(rays)
            hits.hit.zero_()
            return hits

    with pytest.raises(MeshError, match="cannot build the surface-point pool"):
        BoxRayDistribution(NeverHits(), pool_size=64)


def test_bad_surface_fraction_is_a_config_error():
    with pytest.raises(ConfigError, match="surface_fraction"):
        BoxRayDistribution(MeshBLAS(sphere(1)), surface_fraction=1.5, pool_size=64)


# -- resuming ---------------------------------------------------------------------------------------


@pytest.fixture
def checkpoint(tmp_path):
    """A checkpoint at step 4 of `_lq` on sphere(1)."""
    path = tmp_path / "run.ckpt"
    neuralrt.train(sphere(1), _lq(), progress=False, checkpoint=path)
    return path


@pytest.mark.parametrize("mesh, config, difference", [
    (sphere(1), lambda: _lq().with_training(seed=3), "(training.seed: checkpoint 0, now 3)"),
    (sphere(1), lambda: _lq().with_training(batch_size=512), "(training.batch_size: checkpoint 256, now 512)"),
    (sphere(2), _lq, "(mesh: a different mesh (hash "),
    (sphere(1), lambda: get_method("nbvh").config("cpu", steps=4, batch_size=256), "(method: checkpoint lsnif, now nbvh)"),
])
def test_resume_mismatch_names_what_differs(checkpoint, mesh, config, difference):
    with pytest.raises(ModelFileError, match="checkpoint belongs to another run") as err:
        neuralrt.train(mesh, config(), progress=False, checkpoint=checkpoint, resume=True)
    assert difference in str(err.value) and _one_line(str(err.value))


def test_identity_differences_name_a_few_keys():
    saved = {"mesh_sha256": "a" * 64, "config": {"method": "lsnif", "training": {"seed": 0, "batch_size": 256},
                                                  "network": {"hidden_width": 64, "hidden_layers": 2}}}
    now = {"mesh_sha256": "b" * 64, "config": {"method": "lsnif", "training": {"seed": 1, "batch_size": 512},
                                                "network": {"hidden_width": 128, "hidden_layers": 2}}}
    assert identity_differences(saved, now) == (
        f"mesh: a different mesh (hash {'a' * 12} in the checkpoint, {'b' * 12} now); training.seed: checkpoint 0, now 1; "
        "training.batch_size: checkpoint 256, now 512 and 1 more")
    assert identity_differences(None, now) == "the checkpoint records no run identity"


def test_resuming_past_the_asked_steps_warns_and_keeps_the_checkpoint_model(checkpoint):
    with pytest.warns(UserWarning, match=r"already at step 4, past steps=2: the model is saved as of step 4$"):
        model = neuralrt.train(sphere(1), _lq().with_training(steps=2), progress=False, checkpoint=checkpoint, resume=True)
    assert model.training_record["steps"] == 4 and model.training_record["resumed_from"] == 4


# -- the CLI ----------------------------------------------------------------------------------------


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("neuralrt: error: ") and "\n" not in err, err
    return err


def _obj(path, mesh: Mesh) -> str:
    """``mesh`` as an OBJ file, coordinates in full (trimesh's export rounds 1e-30 to 0)."""
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in mesh.vertices.tolist()] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces.tolist()]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


TRAIN = ["--preset", "lq", "--batch", "256", "--quiet"]


@pytest.mark.parametrize("scale, needle", [(1e30, "bounding-box diagonal"), (1e-30, "bounding-box diagonal")])
def test_cli_train_of_a_mesh_float32_cannot_trace(tmp_path, capsys, scale, needle):
    mesh = _obj(tmp_path / "ball.obj", _ball(scale))
    assert main(["train", mesh, "-o", str(tmp_path / "m.nrt"), "--steps", "20", *TRAIN]) == 2
    assert needle in _error_line(capsys)


def test_cli_train_of_coordinates_beyond_float32_is_one_line(tmp_path, capsys):
    obj = tmp_path / "over.obj"
    obj.write_text("v -1e39 0 0\nv 1e39 0 0\nv 0 1e39 0\nf 1 2 3\n")
    assert main(["train", str(obj), "-o", str(tmp_path / "m.nrt"), "--steps", "2", *TRAIN]) == 2
    assert "NaN or Inf" in _error_line(capsys)  # and no numpy warning line before it


def test_cli_seed_beyond_64_bits_is_one_line(tmp_path, capsys):
    mesh = _obj(tmp_path / "ball.obj", sphere(1))
    assert main(["train", mesh, "-o", str(tmp_path / "m.nrt"), "--steps", "2", "--seed", "99999999999999999999999", *TRAIN]) == 2
    assert "seed" in _error_line(capsys)


def test_cli_resume_mismatch_and_resume_past_the_steps(tmp_path, capsys):
    mesh = _obj(tmp_path / "ball.obj", sphere(1))
    out = tmp_path / "m.nrt"
    config = get_method("lsnif").config("lq", steps=4, batch_size=256)  # what the CLI builds from TRAIN
    neuralrt.train(load_mesh(mesh), config, progress=False, checkpoint=f"{out}.ckpt")
    assert main(["train", mesh, "-o", str(out), "--steps", "8", "--seed", "3", "--resume", *TRAIN]) == 2
    assert "(training.seed: checkpoint 0, now 3)" in _error_line(capsys)
    assert main(["train", mesh, "-o", str(out), "--steps", "2", "--resume", *TRAIN]) == 0
    err = capsys.readouterr().err.strip()
    assert err == (f"neuralrt: warning: {out}.ckpt: the checkpoint is already at step 4, past steps=2: "
                   "the model is saved as of step 4")
    assert neuralrt.load_model(out).training_record["steps"] == 4


def test_cli_resume_takes_the_method_and_n_bvh_steps_from_the_checkpoint(tmp_path, capsys):
    """``--resume`` alone continues the run: an N-BVH checkpoint resumes as N-BVH, at the run's step
    count (its cut schedule spans them), and a count given that differs is named."""
    mesh = _obj(tmp_path / "ball.obj", sphere(1))
    out = tmp_path / "m.nrt"
    config = get_method("nbvh").config("cpu", steps=4, batch_size=256)
    neuralrt.train(load_mesh(mesh), config, progress=False, checkpoint=f"{out}.ckpt")
    assert main(["train", mesh, "-o", str(out), "--resume", "--steps", "6", "--batch", "256", "--quiet"]) == 2
    assert "(training.steps: checkpoint 4, now 6)" in _error_line(capsys)
    assert main(["train", mesh, "-o", str(out), "--resume", "--batch", "256", "--quiet"]) == 0
    model = neuralrt.load_model(out)
    assert model.config.method == "nbvh" and model.training_record["resumed_from"] == 4
    assert model.config.training.steps == 4 and not (tmp_path / "m.nrt.ckpt").exists()


def test_cli_resume_keeps_the_runs_checkpoint_interval_unless_given(tmp_path, capsys):
    """``checkpoint_every`` is not part of a run's identity (the model is the same), so a resumed run
    took the preset's 200 and recorded it in its model file; it now keeps the run's."""
    mesh = _obj(tmp_path / "ball.obj", sphere(1))
    out = tmp_path / "m.nrt"
    config = get_method("lsnif").config("lq", steps=4, batch_size=256, checkpoint_every=3)
    neuralrt.train(load_mesh(mesh), config, progress=False, checkpoint=f"{out}.ckpt")
    assert checkpoint_run(tmp_path / "m.nrt.ckpt") == ("lsnif", None, 3)  # (LSNIF's steps may change on resume)
    kept = tmp_path / "kept.ckpt"
    kept.write_bytes((tmp_path / "m.nrt.ckpt").read_bytes())
    assert main(["train", mesh, "-o", str(out), "--steps", "4", "--resume", *TRAIN]) == 0
    assert neuralrt.load_model(out).config.training.checkpoint_every == 3
    out.unlink()
    (tmp_path / "m.nrt.ckpt").write_bytes(kept.read_bytes())
    assert main(["train", mesh, "-o", str(out), "--steps", "4", "--resume", "--set", "training.checkpoint_every=5", *TRAIN]) == 0
    assert neuralrt.load_model(out).config.training.checkpoint_every == 5


def test_train_validates_the_config_it_is_given_again():
    """An assignment can break a rule across sections, and ``model_copy(update=...)`` leaves a dict
    where a section was (train then failed with an AttributeError deep inside)."""
    mesh = sphere(1)
    broken = LSNIFConfig.preset("lq")
    broken.voxel.resolution = 33  # each section alone is valid
    with pytest.raises(ConfigError, match=r"^lsnif config: hash grid resolutions \(64, 128\) must be positive multiples"):
        neuralrt.train(mesh, broken, progress=False)
    copied = LSNIFConfig.preset("lq").model_copy(update={"training": dict(SMALL)})
    model = neuralrt.train(mesh, copied, progress=False)
    assert model.config.training.steps == 4 and model.config.training.batch_size == 256

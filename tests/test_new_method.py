"""A newcomer's method plugs in by registering alone: a toy method (one learned sphere, answered
analytically) trains, saves, loads, evaluates, converts and renders through the unchanged CLI,
model-file code, loader, converter and path tracer, and passes the BLAS contract checks.

The toy method lives only in this test; the registry entry is removed again after each test.
"""

import json
from typing import ClassVar, Literal

import numpy as np
import pytest
import torch
import trimesh
from pydantic import Field

from neuralrt.accel.blas import MemoryReport
from neuralrt.cli import main
from neuralrt.methods import MethodConfig, MethodSpec, NeuralBLAS, load_model, registry
from neuralrt.methods.base import material_table
from neuralrt.methods.config import InferenceConfig, TrainingConfig
from neuralrt.rays import AABB, Hits, Rays
from neuralrt.training.step import StepResult


class ToyConfig(MethodConfig):
    method: Literal["toy"] = Field("toy", description="the toy method")
    training: TrainingConfig = Field(default_factory=lambda: TrainingConfig(learning_rate=0.05, lr_decay_final=1.0))
    inference: InferenceConfig = Field(default_factory=InferenceConfig)
    PRESETS: ClassVar[dict] = {}


ToyConfig.PRESETS = {"default": ToyConfig}


class ToyModel(NeuralBLAS):
    """A sphere (learned centre and radius) answering rays exactly."""

    METHOD: ClassVar[str] = "toy"
    TITLE: ClassVar[str] = "toy"
    CONFIG: ClassVar[type] = ToyConfig

    def __init__(self, config, bounds, materials=None):
        super().__init__(config, bounds, materials)
        self.center = torch.nn.Parameter(bounds.center.float().clone() + 0.1 * bounds.extent.float())
        self.log_radius = torch.nn.Parameter(torch.tensor([np.log(0.25 * bounds.diagonal)], dtype=torch.float32))

    @classmethod
    def from_mesh(cls, mesh, config=None):
        lo, hi = mesh.bounds
        model = cls(config or ToyConfig(), AABB(torch.as_tensor(lo), torch.as_tensor(hi)), material_table(mesh))
        model._remember_mesh(mesh)
        return model

    def _t(self, rays: Rays) -> torch.Tensor:
        """Ray/sphere: the nearest root in [t_min, t_max], inf where none."""
        oc = rays.origins - self.center
        a = (rays.directions**2).sum(1)
        b = (oc * rays.directions).sum(1)
        c = (oc**2).sum(1) - torch.exp(self.log_radius) ** 2
        disc = b * b - a * c
        root = torch.sqrt(torch.clamp(disc, min=0))
        t = torch.where((-b - root) / a > rays.t_min, (-b - root) / a, (-b + root) / a)
        ok = (disc >= 0) & (t >= rays.t_min) & (t <= rays.t_max) & torch.isfinite(t)  # both ends included
        return torch.where(ok, t, torch.full_like(t, float("inf")))

    def training_step(self, rays, truth):
        hit = truth.hit
        p = rays.point_at(torch.where(hit, truth.t, 0.0))[hit]
        loss = ((torch.linalg.norm(p - self.center, dim=1) - torch.exp(self.log_radius)) ** 2).mean()
        with torch.no_grad():
            correct = int((torch.isfinite(self._t(rays)) == hit).sum())
        return StepResult(loss, {"surface": float(loss)}, correct, len(rays), len(rays))

    def _intersect_chunk(self, rays):
        hits = Hits.empty(len(rays), rays.device)
        t = self._t(rays)
        hit = torch.isfinite(t)
        normal = torch.nn.functional.normalize(rays.point_at(torch.where(hit, t, 0.0)) - self.center, dim=1)
        normal = torch.where(((normal * rays.directions).sum(1, keepdim=True) > 0), -normal, normal) * hit[:, None]
        hits.hit, hits.t, hits.normal, hits.geometric_normal = hit, t, normal, normal
        hits.material_id = torch.where(hit, 0, -1)
        return hits

    def memory_bytes(self):
        return MemoryReport({"sphere": 4 * self.storage_bytes})

    def _arrays(self):
        return self._stored({"center": self.center, "log_radius": self.log_radius})

    @classmethod
    def _from_arrays(cls, config, bounds, materials, arrays):
        model = cls(config, bounds, materials)
        cls._load_parameters({"center": model.center, "log_radius": model.log_radius}, arrays)
        return model


@pytest.fixture
def toy(monkeypatch):
    spec = MethodSpec("toy", ToyConfig, f"{__name__}:ToyModel", "a learned sphere (test only)", {"*": "default"})
    monkeypatch.setitem(registry._METHODS, "toy", spec)
    return spec


@pytest.fixture
def ball(tmp_path):
    path = tmp_path / "ball.obj"
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    mesh.apply_translation((0.3, -0.2, 0.1)).export(path)
    return path


def _json(capsys):
    return json.loads(capsys.readouterr().out)


def test_a_registered_method_goes_through_the_whole_pipeline(toy, ball, tmp_path, capsys):
    model = tmp_path / "ball.nrt"
    assert main(["train", "--list-presets"]) == 0
    assert "toy      default" in capsys.readouterr().out
    assert main(["train", str(ball), "-o", str(model), "--method", "toy", "--steps", "150", "--batch", "1024",
                 "--quiet", "--json"]) == 0
    assert _json(capsys)["method"] == "toy"

    loaded = load_model(model)
    assert isinstance(loaded, ToyModel)
    assert float(torch.exp(loaded.log_radius)) == pytest.approx(0.8, rel=0.03)  # it learned the sphere

    assert main(["info", str(model), "--json"]) == 0
    info = _json(capsys)
    assert info["method"] == "toy" and info["config"]["method"] == "toy" and info["memory_parts"] == {"sphere": 8}

    assert main(["eval", str(model), str(ball), "--rays", "2048", "--no-images", "--json"]) == 0
    assert _json(capsys)["outside"]["accuracy"] > 0.97

    scene = tmp_path / "scene.toml"
    scene.write_text(f"""
[camera]
position = [0, 0, 4]
look_at = [0, 0, 0]
resolution = [12, 12]

[[objects]]
name = "ball"
mesh = "{ball}"
""")
    converted = tmp_path / "out" / "scene.toml"
    assert main(["convert", str(scene), "-o", str(converted), "--method", "toy", "--min-triangles", "10", "--steps", "20",
                 "--batch", "512", "--quiet", "--json"]) == 0
    assert _json(capsys)["unique_models"] == 1
    assert main(["render", str(converted), "-o", str(tmp_path / "img.exr"), "--spp", "1", "--primary", "neural",
                 "--quiet", "--json"]) == 0
    assert (tmp_path / "img.png").is_file()


def test_a_registered_method_passes_the_blas_contract(toy, ball, tmp_path):
    from neuralrt.geometry.mesh import load_mesh
    from neuralrt.testing import CONTRACT_CHECKS, check_contract
    from neuralrt.training.api import train

    mesh = load_mesh(ball)
    blas = train(mesh, toy.config(steps=100, batch_size=1024), progress=False)
    cpu_checks = [name for name in CONTRACT_CHECKS if name != "rays_on_another_device"]
    assert check_contract(blas, mesh, tmp_dir=tmp_path) == cpu_checks


def _run(args, tmp_path, plugins):
    import os
    import subprocess
    import sys

    env = {**os.environ, "NEURALRT_PLUGINS": plugins,
           "PYTHONPATH": os.pathsep.join([str(tmp_path), os.path.dirname(__file__), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "neuralrt", *args], env=env, capture_output=True, text=True, timeout=120)


def test_a_plugin_module_is_loaded_before_the_cli_parses_its_arguments(tmp_path):
    # Out of tree: the method's module registers it when imported; NEURALRT_PLUGINS names it.
    (tmp_path / "toy_plugin.py").write_text(
        "from test_new_method import ToyConfig\n"
        "from neuralrt.methods import MethodSpec, register_method\n"
        "register_method(MethodSpec('toy', ToyConfig, 'test_new_method:ToyModel', 'a learned sphere', {'*': 'default'}))\n")
    listed = _run(["train", "--list-presets"], tmp_path, "toy_plugin")
    assert listed.returncode == 0 and "toy      default" in listed.stdout, listed.stderr
    # A plugin that fails to import is one warning line; the built-in methods still work.
    broken = _run(["train", "--list-presets"], tmp_path, "toy_plugin, no_such_plugin")
    assert broken.returncode == 0 and "toy      default" in broken.stdout and "lsnif" in broken.stdout
    assert broken.stderr.strip() == ("neuralrt: warning: method plugin 'no_such_plugin' (NEURALRT_PLUGINS) not loaded: "
                                     "ModuleNotFoundError: No module named 'no_such_plugin'")


def test_a_model_file_of_an_unregistered_method_says_how_to_register_it(toy, ball, tmp_path, monkeypatch):
    from neuralrt.errors import ModelFileError
    from neuralrt.geometry.mesh import load_mesh
    from neuralrt.training.api import train

    path = train(load_mesh(ball), toy.config(steps=2, batch_size=256), progress=False).save(tmp_path / "toy.nrt")
    monkeypatch.delitem(registry._METHODS, "toy")
    with pytest.raises(ModelFileError, match="method 'toy' is not registered in this neuralrt .*NEURALRT_PLUGINS"):
        load_model(path)  # (the file names no code to import: it is data)


def test_registration_checks_the_spec_up_front(toy):
    from pydantic import Field as F

    from neuralrt.errors import ConfigError

    class NoPresets(MethodConfig):
        method: Literal["bare"] = F("bare")

    with pytest.raises(ValueError, match="PRESETS names no preset"):
        registry.register_method(MethodSpec("bare", NoPresets, f"{__name__}:ToyModel", "no presets"))
    with pytest.raises(ValueError, match="config_class must be a MethodConfig subclass"):
        registry.register_method(MethodSpec("toy", dict, f"{__name__}:ToyModel", "not a config"))
    with pytest.raises(ValueError, match="default_presets name no preset of ToyConfig: fast"):
        registry.register_method(MethodSpec("toy", ToyConfig, f"{__name__}:ToyModel", "toy", {"*": "fast"}))
    # The same method registered again (its module re-imported) replaces the entry; another is refused.
    again = MethodSpec("toy", ToyConfig, f"{__name__}:ToyModel", "a learned sphere, reloaded", {"*": "default"})
    assert registry.register_method(again) is registry.get_method("toy")
    with pytest.raises(ValueError, match="already registered"):
        registry.register_method(MethodSpec("toy", ToyConfig, "elsewhere:ToyModel", "another toy", {"*": "default"}))
    # A model class that cannot be imported, or does not declare the method, is one line at first use.
    for target, needle in ((f"{__name__}:NoSuchModel", "cannot import its model class"),
                           ("neuralrt.methods.lsnif:LSNIFModel", "must declare METHOD = 'toy'")):
        registry._METHODS["toy"] = MethodSpec("toy", ToyConfig, target, "broken", {"*": "default"})
        with pytest.raises(ConfigError, match=needle):
            registry.get_method("toy").model_class


def test_a_model_without_trainable_parameters_is_one_line(toy, ball, monkeypatch):
    from neuralrt.errors import ConfigError
    from neuralrt.geometry.mesh import load_mesh
    from neuralrt.training.api import train

    built = ToyModel.from_mesh.__func__

    def frozen(cls, mesh, config=None):
        model = built(cls, mesh, config)
        for p in model.parameters():
            p.requires_grad_(False)
        return model

    monkeypatch.setattr(ToyModel, "from_mesh", classmethod(frozen))
    with pytest.raises(ConfigError, match="ToyModel: no trainable parameters, nothing to train"):  # (was Adam's traceback)
        train(load_mesh(ball), toy.config(steps=2, batch_size=256), progress=False)

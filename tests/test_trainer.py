"""The shared training loop: the per-step hook, method statistics in the record's extra dict."""

import torch

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.geometry.procedural import sphere
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel
from neuralrt.training.ray_distribution import BoxRayDistribution
from neuralrt.training.trainer import train_model


def test_hook_runs_after_every_step_and_extra_holds_method_statistics():
    mesh = sphere(2)
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq"))
    rays = BoxRayDistribution(MeshBLAS(mesh), model.box, pool_size=1024, seed=0)
    calls = []

    def hook(step, optimizer):
        assert isinstance(optimizer, torch.optim.Adam)
        calls.append(step)

    record = train_model(model, rays, steps=4, batch_size=256, learning_rate=0.01, progress=False, on_step=hook)
    assert calls == [0, 1, 2, 3]
    assert record.steps == 4 and record.rays == 4 * 256
    assert set(record.extra) == {"truncated_fraction"} and 0.0 <= record.extra["truncated_fraction"] <= 1.0


def test_training_runs_on_every_device(device):
    from neuralrt.training.api import train

    mesh = sphere(2)
    model = train(mesh, LSNIFConfig.preset("lq").with_training(steps=5, batch_size=512), progress=False, device=device)
    assert model.device.type == device.type and model.training_record["device"] == device.type
    assert model.training_record["steps"] == 5 and model.training_record["compute_precision"] in ("bf16", "fp32")

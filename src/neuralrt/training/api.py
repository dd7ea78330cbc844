"""`train`: one call from a mesh to a trained model of any registered method (the CLI's ``neuralrt train``)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import torch

from ..accel.mesh_blas import MeshBLAS
from ..geometry.mesh import Mesh, load_mesh
from ..methods import DEFAULT_METHOD, MethodConfig, NeuralBLAS, get_method
from ..neural.precision import precision_name
from .trainer import TrainingRecord, train_model

__all__ = ["train", "run_identity"]


def run_identity(model: NeuralBLAS, config: MethodConfig) -> dict:
    """What a checkpoint must match to be resumed: the mesh and the config, except the step count
    (a run may be resumed to train longer) and the checkpoint interval."""
    run_config = config.model_dump(mode="json")
    run_config["training"].pop("steps")
    run_config["training"].pop("checkpoint_every")
    return {"mesh_sha256": model.mesh_hash, "config": run_config}


def _then(first: Callable, second: Callable | None) -> Callable:
    """``first``, then ``second`` (if any), with the same arguments."""
    if second is None:
        return first

    def both(*args):
        first(*args)
        second(*args)

    return both


def train(
    mesh: Mesh | str | os.PathLike,
    config: MethodConfig | None = None,
    *,
    progress: bool = True,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    device: str | torch.device = "cpu",
    on_step: Callable[[int, torch.optim.Optimizer], None] | None = None,
) -> NeuralBLAS:
    """Train a model of ``mesh`` with ``config`` (its ``method`` picks the method) and return it.

    ``config`` defaults to the default method's default preset for ``device`` (LSNIF: ``hq`` on
    the CPU, ``gpu`` on CUDA). Rays come from ``model.training_rays`` (default `BoxRayDistribution`) with exact ground truth, on
    ``device``. With ``checkpoint``, training state is saved periodically there; ``resume=True``
    continues from it. The returned model's parameters are rounded to the storage precision, so
    it answers exactly as its saved file. ``on_step(step, optimizer)`` runs after the model's own
    per-step work (e.g. progress reports from `neuralrt.scene.convert_executors`).
    """
    if isinstance(mesh, (str, Path, os.PathLike)):
        mesh = load_mesh(mesh)
    device = torch.device(device)
    spec = get_method(config.method if config is not None else DEFAULT_METHOD)
    config = config or spec.config(device=device.type)
    tc = config.training
    model = spec.model_class.from_mesh(mesh, config).to(device)
    rays = model.training_rays(MeshBLAS(mesh, device=device), device)  # default: BoxRayDistribution
    start = TrainingRecord(compute_precision=precision_name(model.compute_dtype(training=True)), device=device.type)
    record = train_model(
        model, rays, steps=tc.steps, batch_size=tc.batch_size, learning_rate=tc.learning_rate,
        adam_betas=tc.adam_betas, adam_eps=tc.adam_eps, lr_decay_final=tc.lr_decay_final,
        checkpoint=checkpoint, checkpoint_every=tc.checkpoint_every, resume=resume, identity=run_identity(model, config),
        progress=progress, description=f"{spec.name} {mesh.name}", on_step=_then(model.after_training_step, on_step), record=start,
    )
    model.training_record = record.as_dict()
    return model.round_to_storage_precision_().eval()

"""`train_lsnif`: one call from a mesh to a trained LSNIF model (the CLI's ``neuralrt train``)."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from ..accel.mesh_blas import MeshBLAS
from ..geometry.mesh import Mesh, load_mesh
from ..methods.lsnif import LSNIFConfig, LSNIFModel
from .samplers import LSNIFRaySampler
from .trainer import train_model

__all__ = ["train_lsnif"]


def train_lsnif(
    mesh: Mesh | str | os.PathLike,
    config: LSNIFConfig | None = None,
    *,
    progress: bool = True,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    device: str | torch.device = "cpu",
) -> LSNIFModel:
    """Voxelize ``mesh``, train an LSNIF on rays from the paper's distribution, return the model.

    ``config`` defaults to the ``hq`` preset. With ``checkpoint``, training state is saved
    periodically there; ``resume=True`` continues from it. The returned model's parameters are
    rounded to the storage precision (fp16 by default), so it answers exactly as its saved file.
    """
    if isinstance(mesh, (str, Path, os.PathLike)):
        mesh = load_mesh(mesh)
    config = config or LSNIFConfig.preset("hq")
    tc = config.training
    model = LSNIFModel.from_mesh(mesh, config).to(device)
    sampler = LSNIFRaySampler(
        MeshBLAS(mesh), model.box, surface_fraction=tc.surface_fraction, pool_size=tc.surface_pool_size,
        surface_offset=tc.surface_offset, seed=tc.seed,
    )
    # A checkpoint resumes only the same run; the step count may grow (to train longer).
    run_config = config.model_dump(mode="json")
    run_config["training"].pop("steps")
    run_config["training"].pop("checkpoint_every")
    identity = {"mesh_sha256": model.mesh_hash, "config": run_config}
    record = train_model(
        model, sampler, steps=tc.steps, batch_size=tc.batch_size, learning_rate=tc.learning_rate,
        adam_betas=tc.adam_betas, adam_eps=tc.adam_eps, lr_decay_final=tc.lr_decay_final,
        checkpoint=checkpoint, checkpoint_every=tc.checkpoint_every, resume=resume, identity=identity,
        progress=progress, description=f"lsnif {mesh.name}",
    )
    model.training_record = record.as_dict()
    return model.round_to_storage_precision_().eval()

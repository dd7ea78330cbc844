"""`train`: one call from a mesh to a trained model of any registered method (the CLI's ``neuralrt train``)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable

import torch

from ..accel.mesh_blas import MeshBLAS
from ..arguments import check_flags, given
from ..devices import check_device, check_memory, check_path
from ..errors import ConfigError
from ..fork_guard import check_not_forked
from ..geometry.mesh import Mesh, check_float32_extent, load_mesh
from ..io.run_lock import held_alone
from ..methods import DEFAULT_METHOD, MethodConfig, NeuralBLAS, get_method
from ..neural.precision import precision_name
from .trainer import TrainingRecord, check_checkpoint, train_model

# Memory a training step holds per ray of its batch, measured on the CPU (peak RSS at 2^16 and 2^19
# rays, statue(0), 3 steps: LSNIF hq 1.72 KB, lq 1.05 KB, N-BVH 1.76 KB per ray), rounded up.
TRAINING_BYTES_PER_RAY = 2048

__all__ = ["train", "run_identity"]


def run_identity(mesh_hash: str, config: MethodConfig) -> dict:
    """What a checkpoint must match to be resumed: the mesh (its content hash) and the config,
    except the checkpoint interval and, unless the method's schedule spans the run (N-BVH), the
    step count (a run may be resumed to train longer)."""
    run_config = config.model_defining()
    if not config.SCHEDULE_SPANS_THE_STEPS:
        run_config["training"].pop("steps")
    return {"mesh_sha256": mesh_hash, "config": run_config}


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
    continues from it if that file exists, else starts afresh (the scene converter makes the same
    call for a first run and a rerun; ``neuralrt.api.train`` is the one that requires the file).
    The returned model's parameters are rounded to the storage precision, so it answers exactly as
    its saved file. ``on_step(step, optimizer)`` runs after the model's own per-step work (e.g.
    progress reports from `neuralrt.scene.convert_executors`).

    Bad arguments, a config with bad values and a mesh float32 cannot trace (`check_float32_extent`)
    are one-line `NeuralRTError`s, raised before any work.
    """
    device = check_device(device)
    check_not_forked("train")
    config = _checked_config(config)
    checkpoint = check_path("checkpoint", checkpoint, optional=True)
    check_flags(resume=resume)
    if resume and checkpoint is None:
        raise ConfigError("resume=True needs checkpoint=PATH, the checkpoint to resume from")
    if on_step is not None and not callable(on_step):
        raise ConfigError(f"on_step: expected a function (step, optimizer) or None, got {type(on_step).__name__}")
    mesh = _checked_mesh(mesh)
    spec = get_method(config.method if config is not None else DEFAULT_METHOD)
    config = config or spec.config(device=device.type)
    tc = config.training
    if device.type == "cpu":  # (the figure is the CPU's; CUDA's torch caching allocator holds memory it would reuse)
        check_memory(f"a training batch of {tc.batch_size:,} rays", tc.batch_size * TRAINING_BYTES_PER_RAY, device,
                     f"give a smaller {given('batch')} (training.batch_size)")
    identity = run_identity(mesh.content_hash(), config)
    # (two runs on one checkpoint would each overwrite the other's: the second is told, here)
    with held_alone(checkpoint) if checkpoint is not None else contextlib.nullcontext():
        if resume and checkpoint.exists():  # a truncated or foreign checkpoint is told before the set-up (seconds)
            check_checkpoint(checkpoint, identity)
        model = spec.model_class.from_mesh(mesh, config).to(device)
        rays = model.training_rays(MeshBLAS(mesh, device=device), device)  # default: BoxRayDistribution
        start = TrainingRecord(compute_precision=precision_name(model.compute_dtype(training=True)), device=device.type)
        record = train_model(
            model, rays, steps=tc.steps, batch_size=tc.batch_size, learning_rate=tc.learning_rate,
            adam_betas=tc.adam_betas, adam_eps=tc.adam_eps, adam_l2=tc.adam_l2, lr_decay_final=tc.lr_decay_final,
            checkpoint=checkpoint, checkpoint_every=tc.checkpoint_every, resume=resume, identity=identity,
            progress=progress, description=f"{spec.name} {mesh.name}", on_step=_then(model.after_training_step, on_step),
            record=start,
        )
    model.training_record = record.as_dict()
    return model.round_to_storage_precision_().eval()


def _checked_config(config) -> MethodConfig | None:
    """``config`` validated again, as a new config: values set past validation (``model_construct``,
    an assignment that breaks a cross-section rule) fail here in one line, and a section that
    ``model_copy(update=...)`` left a dict becomes a section."""
    if config is None:
        return None
    if not isinstance(config, MethodConfig):
        raise ConfigError(f"config: expected a method config such as LSNIFConfig.preset('lq') (or None), got {type(config).__name__}")
    return type(config).validated(config.model_dump(warnings=False))


def _checked_mesh(mesh) -> Mesh:
    """``mesh`` (a `Mesh` or a mesh file path) loaded, and one that float32 ray tracing keeps (checked before any work)."""
    if isinstance(mesh, Mesh):
        check_float32_extent(mesh)
        return mesh
    if not isinstance(mesh, (str, os.PathLike)):
        raise ConfigError(f"mesh: expected a Mesh or a mesh file path, got {type(mesh).__name__}")
    loaded = load_mesh(mesh)
    check_float32_extent(loaded, str(mesh))
    return loaded

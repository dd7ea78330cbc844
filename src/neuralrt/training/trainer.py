"""The training loop shared by neural intersectors: Adam, progress bar, checkpoints, resume.

A model plugs in by offering ``training_step(rays, truth) -> StepResult`` (loss plus hit/miss
counts), and optionally ``prepare_training_batch(rays)`` (what a step computes from the batch
alone: drawn ahead with the batch, then ``training_step(rays, truth, prepared)``); a ray distribution by offering ``sample(n) -> TrainingBatch`` and ``state_dict``/
``load_state_dict``. ``on_step(step, optimizer)`` runs after every optimizer step (N-BVH refines
its BVH cut there). Checkpoints are `.nrt` files (method ``"checkpoint"``) holding the model's
state, Adam's moments, the step and the ray distribution's state (its own generator and surface
pool), written atomically, so an interrupted run resumes where its last checkpoint left it, bit
for bit. The global torch RNG is neither used nor touched.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, field
from pathlib import Path

import torch
from pydantic import ConfigDict, NonNegativeFloat, NonNegativeInt, PositiveInt, ValidationError
from pydantic.dataclasses import dataclass as pydantic_dataclass
from torch import nn

from ..arguments import given
from ..errors import ConfigError, ModelFileError, TrainingError, outside_stacklevel, validation_message
from ..io.model_file import read_header, read_model_file, write_model_file
from ..methods.config import ABSENT, MAX_STEPS, differing_keys
from .curve import TrainingCurve, curve_problem
from .prefetch import BatchSource

__all__ = ["TrainingRecord", "train_model", "identity_differences", "checkpoint_run", "CHECKPOINT_METHOD"]

CHECKPOINT_METHOD = "checkpoint"


@pydantic_dataclass(config=ConfigDict(strict=True, extra="forbid"))
class TrainingRecord:
    """What a training run did; stored in the model file's header. Types are checked (strictly: no
    "12" for 12) when one is made, so a checkpoint's edited record is refused, not copied on."""

    steps: NonNegativeInt = 0
    batch_size: NonNegativeInt = 0
    seconds: NonNegativeFloat = 0.0  # wall time spent in steps (summed over resumed sessions; setup before the first step not counted)
    rays: NonNegativeInt = 0  # rays drawn in total
    network_rays: NonNegativeInt = 0  # of those, rays that reached the network
    rays_per_second: NonNegativeFloat = 0.0  # over the steps after each session's first (see first_step_seconds)
    # Of `seconds` and `rays`: each session's first step, which loads the kernels (compiling them on
    # a cold numba cache: 31 s for an N-BVH step of 0.1 s), left out of rays_per_second.
    first_step_seconds: NonNegativeFloat = 0.0
    first_step_rays: NonNegativeInt = 0
    final_loss: float = float("nan")  # mean over the last `window` steps, of the weighted sum the optimizer minimizes
    final_losses: dict = field(default_factory=dict)  # each term's mean, unweighted (N-BVH: `loss.*_weight` scale them)
    hit_accuracy: float = float("nan")  # running hit/miss accuracy over the last `window` steps
    compute_precision: str = ""  # arithmetic of the hidden layers in training: "bf16" or "fp32"
    device: str = ""  # where it trained, e.g. "cpu", "cuda"
    resumed_from: NonNegativeInt | None = None
    batches_drawn_ahead: bool | None = None  # as `BatchSource.draws_ahead` at the end (None: trial unfinished)
    window: PositiveInt = 50
    extra: dict = field(default_factory=dict)  # method-specific: "<count>_fraction" over the last `window` steps
    curve: dict = field(default_factory=dict)  # loss, hit accuracy, loss terms over the steps (`TrainingCurve.as_dict`)

    def __post_init__(self):
        problem = curve_problem(self.curve)
        if problem:
            raise ValueError(f"curve: {problem}")

    def as_dict(self) -> dict:
        return asdict(self)


class _Running:
    """Means over the last ``window`` steps (for the progress bar and the record)."""

    def __init__(self, window: int):
        self.window, self.items = window, []

    def add(self, **values) -> None:
        self.items.append(values)
        del self.items[: -self.window]

    def mean(self, key: str) -> float:
        vals = [v[key] for v in self.items if key in v]
        return float(sum(vals) / len(vals)) if vals else float("nan")

    def ratio(self, num: str, den: str) -> float:
        d = sum(v.get(den, 0) for v in self.items)
        return float(sum(v.get(num, 0) for v in self.items) / d) if d else float("nan")


def _optimizer_arrays(opt: torch.optim.Optimizer) -> tuple[dict, dict[str, torch.Tensor]]:
    state = opt.state_dict()
    arrays, meta = {}, {"param_groups": state["param_groups"], "params": []}
    for pid, s in state["state"].items():
        meta["params"].append(pid)
        for k, v in s.items():
            arrays[f"adam.{pid}.{k}"] = torch.as_tensor(v).detach().cpu().clone()
    return meta, arrays


def _is_flag(value) -> bool:
    return isinstance(value, bool) or value is None


def _same_kind(ours, theirs) -> bool:
    """Whether ``theirs`` (from a file) is a value of ``ours``'s kind: a finite number for a number,
    as many such for a tuple, the same value for a flag or None, the same type for anything else."""
    if _is_flag(ours):  # (this run's own, as Adam's step reads it: amsgrad true wanted state no run saves,
        return theirs is ours  # maximize trained uphill)
    if isinstance(ours, (int, float)):
        return isinstance(theirs, (int, float)) and not isinstance(theirs, bool) and math.isfinite(theirs)
    if isinstance(ours, (tuple, list)):
        return isinstance(theirs, (tuple, list)) and len(theirs) == len(ours) and all(map(_same_kind, ours, theirs))
    return type(theirs) is type(ours)


def _load_optimizer(opt: torch.optim.Optimizer, meta: dict, arrays: dict[str, torch.Tensor], device) -> None:
    state = {}
    for pid in meta["params"]:
        prefix = f"adam.{pid}."
        state[pid] = {k[len(prefix):]: v.to(device) if v.ndim else v for k, v in arrays.items() if k.startswith(prefix)}
    fresh = [{k: v for k, v in group.items() if k != "params"} for group in opt.param_groups]
    opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
    # A file's hyperparameters of another kind ("betas": "ab") failed inside Adam's step, after set-up.
    for ours, loaded in zip(fresh, opt.param_groups):
        for key, value in ours.items():
            if not _same_kind(value, loaded.get(key)):
                raise ValueError(f"Adam's {key} is {loaded.get(key)!r}, " + (f"this run's {value!r}" if _is_flag(value)
                                                                            else f"not a value like {value!r}"))
    # torch takes moments of any shape, and the step after would fail inside Adam's kernel.
    for p in (p for group in opt.param_groups for p in group["params"]):
        held = opt.state.get(p, {})
        missing = sorted({"step", "exp_avg", "exp_avg_sq"} - set(held)) if held else []
        if missing:  # (Adam's next step reads them: a KeyError there, after set-up)
            raise ValueError(f"Adam's state of a parameter lacks {', '.join(missing)}")
        for name, value in held.items():
            if value.ndim and value.shape != p.shape:
                raise ValueError(f"Adam's {name} has shape {list(value.shape)}, its parameter {list(p.shape)}")
            if value.is_floating_point() and not torch.isfinite(value).all():
                raise ValueError(f"Adam's {name} holds NaN or infinite values")
            if name in ("step", "exp_avg_sq") and (value < 0).any():  # (a diverged loss was blamed on the learning rate)
                raise ValueError(f"Adam's {name} holds negative values")


def save_checkpoint(path: Path, model: nn.Module, opt, sampler, step: int, record: TrainingRecord, identity: dict,
                    checkpoint_every: int) -> None:
    """(``record.curve`` holds the open bin, if any: the resumed run fills it. ``checkpoint_every`` is
    kept beside the identity, which leaves it out: a resumed run keeps the run's by default.)"""
    sampler_meta, sampler_arrays = sampler.state_dict()
    opt_meta, opt_arrays = _optimizer_arrays(opt)
    arrays = {f"model.{k}": v.detach().cpu().clone() for k, v in model.state_dict().items()}
    arrays.update({f"sampler.{k}": v for k, v in sampler_arrays.items()})
    arrays.update(opt_arrays)
    header = {"step": step, "identity": identity, "sampler": sampler_meta, "optimizer": opt_meta, "record": record.as_dict(),
              "mesh_name": getattr(model, "mesh_name", None),  # (shown by `info`; not part of the run's identity)
              "checkpoint_every": checkpoint_every}
    write_model_file(path, CHECKPOINT_METHOD, header, arrays)


def check_checkpoint(path: Path, identity: dict, header: dict | None = None) -> None:
    """A one-line `ModelFileError` unless ``path`` is a checkpoint (well formed: its header read,
    not its arrays) of the run ``identity`` names."""
    header = header if header is not None else read_header(path, method=CHECKPOINT_METHOD)
    if header.get("identity") != identity:
        raise ModelFileError(f"{path}: checkpoint belongs to another run ({identity_differences(header.get('identity'), identity)}); "
                             f"give the checkpoint's settings to resume it, or drop {given('resume', True, flag='--resume')} to start afresh")
    step = header.get("step")
    if not isinstance(step, int) or isinstance(step, bool) or not 0 <= step <= MAX_STEPS:
        raise ModelFileError(f"{path}: corrupted checkpoint (step {step!r}); delete it or drop {given('resume', True, flag='--resume')}")


def checkpoint_run(path: Path) -> tuple[str | None, int | None, int | None]:
    """(method, training.steps, training.checkpoint_every) of the run the checkpoint at ``path``
    holds, where it records them (the steps: where the method's schedule spans them; how often it
    saves: since session 59); Nones where there is no readable checkpoint (`check_checkpoint` then
    says what is wrong with it)."""
    try:
        header = read_header(path, method=CHECKPOINT_METHOD)
    except (OSError, ModelFileError):
        return None, None, None
    identity = header.get("identity")
    config = identity.get("config") if isinstance(identity, dict) else None
    config = config if isinstance(config, dict) else {}
    method, training = config.get("method"), config.get("training")
    steps = training.get("steps") if isinstance(training, dict) else None
    every = header.get("checkpoint_every")
    return (method if isinstance(method, str) else None, steps if _is_count(steps) else None,
            every if _is_count(every) and every >= 1 else None)


def _is_count(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def load_checkpoint(path: Path, model: nn.Module, opt, sampler, identity: dict) -> tuple[int, TrainingRecord]:
    f = read_model_file(path, method=CHECKPOINT_METHOD)
    check_checkpoint(path, identity, f.header)
    try:
        state = {k[len("model."):]: v for k, v in f.arrays.items() if k.startswith("model.")}
        dev = next(model.parameters()).device
        model.load_state_dict({k: v.to(dev) for k, v in state.items()})
        bad = [k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()]
        if bad:  # (the run would write a model no one can load)
            raise ValueError(f"the model's {bad[0]} holds NaN or infinite values")
        _load_optimizer(opt, f.header["optimizer"], {k: v for k, v in f.arrays.items() if k.startswith("adam.")}, dev)
        sampler.load_state_dict(f.header["sampler"], {k[len("sampler."):]: v for k, v in f.arrays.items() if k.startswith("sampler.")})
        record = _record(f.header["record"])
    except Exception as exc:  # well formed, checksums right, yet not this run's state (edited, or another version's)
        msg = " ".join(str(exc).split())
        raise ModelFileError(f"{path}: cannot resume from this checkpoint ({type(exc).__name__}: {msg[:200]}); "
                             f"delete it or drop {given('resume', True, flag='--resume')}") from None
    return f.header["step"], record


def _record(stored) -> TrainingRecord:
    if not isinstance(stored, dict):
        raise ValueError(f"its record is a {type(stored).__name__}, not a table")
    try:
        return TrainingRecord(**stored)
    except ValidationError as exc:  # (one line, keys named; pydantic's own text spans lines)
        raise ValueError(f"its record: {validation_message(exc)}") from None


def identity_differences(saved, now: dict, limit: int = 3) -> str:
    """What differs between a checkpoint's identity and this run's (`run_identity`'s form), at most
    ``limit`` parts: ``mesh: a different mesh (hash 1a2b3c4d5e6f in the checkpoint, ... now); training.seed: checkpoint 0, now 3``.
    The config's keys are named as in a config file; a different method is named alone (every key follows from it)."""
    if not isinstance(saved, dict):
        return "the checkpoint records no run identity"
    diffs = dict(sorted(differing_keys(saved, now), key=lambda kv: kv[0] != "mesh_sha256"))  # (the mesh first)
    if "config.method" in diffs:
        diffs = {"config.method": diffs["config.method"]}
    parts = [_difference(key, *values) for key, values in diffs.items()]
    more = f" and {len(parts) - limit} more" if len(parts) > limit else ""
    return "; ".join(parts[:limit]) + more


def _difference(key: str, saved, now) -> str:
    if key == "mesh_sha256":
        return f"mesh: a different mesh (hash {_shown(saved)[:12]} in the checkpoint, {_shown(now)[:12]} now)"
    return f"{key.removeprefix('config.')}: checkpoint {_shown(saved)}, now {_shown(now)}"


def _shown(value) -> str:
    text = "(none)" if value is ABSENT else str(value)
    return text if len(text) <= 40 else text[:37] + "..."


def train_model(
    model: nn.Module,
    sampler,
    *,
    steps: int,
    batch_size: int,
    learning_rate: float,
    adam_betas: tuple[float, float] = (0.9, 0.999),
    adam_eps: float = 1e-8,
    adam_l2: float = 0.0,
    lr_decay_final: float = 1.0,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = 200,
    resume: bool = False,
    identity: dict | None = None,
    progress: bool = True,
    description: str = "train",
    on_step: Callable[[int, torch.optim.Optimizer], None] | None = None,
    record: TrainingRecord | None = None,
    overlap_sampling: bool | None = None,
) -> TrainingRecord:
    """Optimise ``model`` for ``steps`` batches from ``sampler``; returns the `TrainingRecord`.

    With ``checkpoint``, state is saved every ``checkpoint_every`` steps and at the end; with
    ``resume`` too, a run restarts from that file (which must come from the same ``identity``,
    e.g. mesh hash and config). The learning rate decays exponentially to ``lr_decay_final``
    times its start over the run (1 = constant). ``on_step(step, optimizer)`` runs after each
    optimizer step; ``record`` starts the record (e.g. with the precision and device filled in).
    A sampler that declares ``model_independent = True`` may draw batch k+1 on a background thread
    while step k runs (same batches, same order; `BatchSource`): always with ``overlap_sampling=True``,
    never with False, and with None where the run's own first steps measure it faster.
    """
    from ..progress import progress_bar

    parameters = list(model.parameters())
    if not any(p.requires_grad for p in parameters):
        raise ConfigError(f"{type(model).__name__}: no trainable parameters, nothing to train")
    # The fused (single-kernel) Adam step is ~3x faster than the default over the 786k-entry hash tables.
    # weight_decay is Adam's L2 term (added to the gradient), as tiny-cuda-nn's l2_reg; not AdamW's decoupled decay.
    opt = torch.optim.Adam(parameters, lr=learning_rate, betas=tuple(adam_betas), eps=adam_eps, weight_decay=adam_l2, fused=True)
    gamma = lr_decay_final ** (1.0 / max(steps, 1))
    identity = identity or {}
    ckpt = Path(checkpoint) if checkpoint is not None else None
    start, record = 0, record or TrainingRecord()
    record.batch_size = batch_size
    if ckpt is not None and resume and ckpt.exists():
        start, record = load_checkpoint(ckpt, model, opt, sampler, identity)
        record.resumed_from = start
        if start > steps:  # kept (see below), but the run then ends with more steps than asked: say so
            warnings.warn(f"{ckpt}: the checkpoint is already at step {start}, past steps={steps}: "
                          f"the model is saved as of step {start}", stacklevel=outside_stacklevel())
    running = _Running(record.window)
    curve = TrainingCurve.from_dict(record.curve, start=start)
    curve.states = getattr(model, "curve_states", None)
    model.train()
    bar = progress_bar(total=steps, initial=start, desc=description, disable=not progress, dynamic_ncols=True, unit="step")
    step = start
    prepare = getattr(model, "prepare_training_batch", None)
    batches = BatchSource(sampler, batch_size, overlap=overlap_sampling, prepare=prepare)
    try:
        for step in range(start, steps):
            for g in opt.param_groups:
                g["lr"] = learning_rate * gamma**step
            checkpoint_after = ckpt is not None and (step + 1) % checkpoint_every == 0 and step + 1 < steps
            t0 = time.perf_counter()
            # Not ahead of a checkpoint: the saved sampler state must be the one before the next batch.
            batch, prepared = batches.next(ahead=step + 1 < steps and not checkpoint_after)
            if prepared is None:
                result = model.training_step(batch.rays, batch.truth)
            else:
                result = model.training_step(batch.rays, batch.truth, prepared)
            opt.zero_grad(set_to_none=True)
            result.loss.backward()
            opt.step()
            loss = result.loss.item()
            if not math.isfinite(loss):  # before on_step: N-BVH's cut would split on NaN statistics
                raise TrainingError(_diverged(step + 1, loss, learning_rate))
            if on_step is not None:
                on_step(step, opt)
            dt = time.perf_counter() - t0
            record.seconds += dt
            record.rays += result.count
            if step == start:
                record.first_step_seconds += dt
                record.first_step_rays += result.count
            record.network_rays += result.network_rays
            running.add(loss=loss, correct=result.correct, count=result.count,
                        **{f"count_{k}": v for k, v in result.ray_counts.items()},
                        **{f"loss_{k}": v for k, v in result.parts.items()})
            curve.add(step + 1, record.seconds, loss, result.correct, result.count, result.parts)
            bar.update(1)
            if progress and (step % 10 == 0 or step == steps - 1):
                bar.set_postfix(loss=f"{running.mean('loss'):.4f}", hit_acc=f"{running.ratio('correct', 'count'):.4f}",
                                rays_s=f"{result.count / max(dt, 1e-9):.3g}", **getattr(model, "progress_fields", dict)(),
                                refresh=False)  # (shown at the bar's next redraw: a redraw here went into logs too)
            if checkpoint_after:
                _finish(record, running, step + 1)
                record.curve = curve.as_dict(checkpoint=True)
                save_checkpoint(ckpt, model, opt, sampler, step + 1, record, identity, checkpoint_every)
    finally:
        batches.close()
        bar.close()
    record.batches_drawn_ahead = batches.draws_ahead
    if steps > start:  # a run resumed at (or past) its last step trained nothing: keep the checkpoint's figures
        _finish(record, running, steps)
    curve.close()
    record.curve = curve.as_dict()
    if ckpt is not None:
        try:
            save_checkpoint(ckpt, model, opt, sampler, record.steps, record, identity, checkpoint_every)
        except OSError as exc:  # insurance only (~7x the model's bytes): a full disk must not cost the trained model
            warnings.warn(f"{ckpt}: the final checkpoint could not be written ({exc.strerror or exc}); training "
                          "goes on to write the model", stacklevel=outside_stacklevel())
    model.eval()
    return record


def _diverged(step: int, loss: float, learning_rate: float) -> str:
    return (f"training diverged at step {step}: the loss is {loss} (try a lower training.learning_rate, "
            f"now {learning_rate:g}); no model was written")


def _finish(record: TrainingRecord, running: _Running, steps: int) -> None:
    record.steps = steps
    seconds, rays = record.seconds - record.first_step_seconds, record.rays - record.first_step_rays
    if not (seconds > 0 and rays > 0):  # (a run of one step per session: that step is all there is)
        seconds, rays = record.seconds, record.rays
    record.rays_per_second = rays / seconds if seconds > 0 else 0.0
    record.final_loss = running.mean("loss")
    keys = sorted({k for item in running.items for k in item if k.startswith("loss_")})
    record.final_losses = {k[len("loss_"):]: running.mean(k) for k in keys}
    record.hit_accuracy = running.ratio("correct", "count")
    counted = sorted({k for item in running.items for k in item if k.startswith("count_")})
    record.extra = {f"{k[len('count_'):]}_fraction": running.ratio(k, "count") for k in counted}

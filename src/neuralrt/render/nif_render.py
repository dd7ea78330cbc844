"""Render with NIF shadow rays (Fujieda et al., HPG 2023): pick the objects, train online from the
current view, then answer their shadow rays with the networks.

`render_nif` renders the first ``train_spp`` samples per pixel with exact shadow rays while every
(shadow ray, NIF object) pair NIF takes (``config.shadow_rays``: those of the camera rays' hits by
default) is labelled and trained on (`NIFShadowAccel` in ``"collect"`` mode), then the remaining
samples with those shadow rays answered by the networks. Camera and
bounce rays stay exact throughout. The two parts are separate `render` calls (the second with
seed ``seed + SECOND_PART_SEED``, so its samples are new), merged by sample count. A new call
trains afresh: the networks hold only what this view and these lights taught them.

`select_nif_instances` checks the ``--nif`` argument against the scene before any rendering.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import replace

import numpy as np
import torch
from pydantic import ValidationError

from ..arguments import check_count, given, seed_or_default
from ..errors import ConfigError, outside_stacklevel, validation_message
from ..methods.config import merged_settings
from ..methods.nif import NIFNetworks, NIFPairs
from ..methods.nif_config import NIFConfig
from ..methods.nif_training import NIFTrainer
from .film import RenderResult
from .integrator import WARM_UP_RESOLUTION, render
from .nif_shadows import NIFShadowAccel

__all__ = ["render_nif", "select_nif_instances", "check_nif_names", "checked_nif_config", "SECOND_PART_SEED"]

SECOND_PART_SEED = 104_729  # added to the seed of the samples after training (any offset gives new wavefront seeds)


def _instance_problem(scene, inst) -> str | None:
    from ..methods.base import is_neural

    if is_neural(inst.blas):
        return "is answered by a neural model (NIF learns from exact shadow rays: give the object its mesh alone)"
    if getattr(inst.blas, "mesh", None) is None:
        return "has no exact mesh (NIF learns from exact shadow rays)"
    emissive = scene.materials.emissive_mask.to(inst.material_map.device)[inst.material_map]
    if bool(emissive.any()):
        return "is emissive (a light): its shadow rays end on it"
    return None


def check_nif_names(nif) -> None:
    """A one-line `ConfigError` unless ``nif`` is ``"auto"`` or object names (a str or a list of str);
    whether the scene has them is `select_nif_instances`' question."""
    if not (isinstance(nif, str) or (isinstance(nif, (list, tuple)) and all(isinstance(n, str) for n in nif))):
        raise ConfigError(f"nif: expected 'auto' or object names (a str or a list of str), got {type(nif).__name__}")


def checked_nif_config(config, name: str = "config") -> NIFConfig:
    """``config`` (None, a `NIFConfig`, or a dict of the keys to change from the defaults, at any
    depth: ``{"outer": {"hidden_width": 32}}``) as a `NIFConfig`; a bad one is a one-line
    `ConfigError` (naming ``name``, the argument as the caller spells it)."""
    if config is None:
        return NIFConfig()
    if isinstance(config, NIFConfig):
        return config
    if not isinstance(config, dict):
        raise ConfigError(f"{name}: expected a NIFConfig or a dict, got {type(config).__name__}")
    try:
        return NIFConfig.model_validate(merged_settings(NIFConfig().model_dump(), config))
    except ValidationError as exc:
        raise ConfigError(f"nif config: {validation_message(exc, NIFConfig)}") from None


def select_nif_instances(scene, nif: str | list[str], config: NIFConfig | None = None) -> list[int]:
    """Indices of the scene instances whose shadow rays NIF answers.

    ``nif`` is ``"auto"`` (every exact, non-emissive object with more than
    ``config.auto_min_triangles`` triangles) or object names (a list, or one comma-separated
    string). A name matching no object, an emissive object (a light) or an object without an exact
    mesh is a one-line `ConfigError`, as is ``auto`` finding nothing."""
    config = config or NIFConfig()
    instances = scene.accel.instances
    if isinstance(nif, str) and nif.strip() == "auto":
        chosen = [k for k, inst in enumerate(instances) if _instance_problem(scene, inst) is None
                  and inst.blas.mesh.num_triangles > config.auto_min_triangles]
        if not chosen:
            biggest = max((inst.blas.mesh.num_triangles for inst in instances if getattr(inst.blas, "mesh", None) is not None), default=0)
            raise ConfigError(f"{given('nif', 'auto')}: no object has more than {config.auto_min_triangles:,} triangles "
                              f"(the largest has {biggest:,}); name the objects instead")
        return chosen
    names = [n.strip() for n in (nif.split(",") if isinstance(nif, str) else nif)]
    if not names or any(not n for n in names):
        raise ConfigError(f"{given('nif', nif)}: give object names separated by commas, or auto")
    known = [inst.name for inst in instances]
    chosen = []
    for name in names:
        matches = [k for k, inst in enumerate(instances) if inst.name == name]
        if not matches:
            raise ConfigError(f"{given('nif', name)}: no object of that name (objects: {', '.join(dict.fromkeys(known))})")
        for k in matches:
            problem = _instance_problem(scene, instances[k])
            if problem:
                raise ConfigError(f"{given('nif', name)}: the object {problem}")
        chosen.extend(matches)
    return sorted(set(chosen))


def _merge(a: RenderResult, b: RenderResult, seconds: float) -> RenderResult:
    """One result from two renders of the same view, weighted by their sample counts."""
    wa, wb = a.spp, b.spp
    spp = wa + wb

    def mean(x, y):
        return ((x.astype(np.float64) * wa + y.astype(np.float64) * wb) / spp).astype(np.float32)

    hits_a, hits_b = a.coverage.astype(np.float64) * wa, b.coverage.astype(np.float64) * wb
    hits = hits_a + hits_b
    depth = np.where(hits > 0, (a.depth * hits_a + b.depth * hits_b) / np.maximum(hits, 1e-30), 0.0).astype(np.float32)
    normal = mean(a.normal, b.normal)  # means of unit means: the AOV's direction, renormalised
    normal = (normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)).astype(np.float32)
    stats = {"nonfinite_samples": a.stats.get("nonfinite_samples", 0) + b.stats.get("nonfinite_samples", 0)}
    return RenderResult(image=mean(a.image, b.image), albedo=mean(a.albedo, b.albedo), normal=normal, depth=depth,
                        coverage=mean(a.coverage, b.coverage), spp=spp, seconds=seconds, stats=stats)


def _warm_up(scene, chosen: list[int], config: NIFConfig, boxes: list, render_kwargs: dict) -> float:
    """Load NIF's kernels untimed, on throwaway networks: one training round on synthetic pairs (a
    tiny render may give none) and their answers, then a few pixels through the shadow accelerator
    collecting and answering. Returns its seconds. (The first render in a process otherwise counts
    their loading, or compiling on a cold numba cache: seconds, against ~20 ms of training.)"""
    start = time.perf_counter()
    networks = NIFNetworks(config, boxes).to(scene.device)
    trainer = NIFTrainer(networks)
    generator = torch.Generator().manual_seed(0)
    objects = torch.arange(len(boxes)).repeat_interleave(64)
    lo, hi = networks.box_lo.cpu()[objects], networks.box_hi.cpu()[objects]
    inside = lo + torch.rand(len(objects), 3, generator=generator) * (hi - lo)
    outside = inside + torch.linalg.norm(hi - lo, dim=-1, keepdim=True) * torch.randn(len(objects), 3, generator=generator)
    origins = torch.where((torch.arange(len(objects)) % 2 == 0)[:, None], inside, outside)  # (inner and outer pairs)
    pairs = NIFPairs(objects, origins, inside.flip(0) - origins, torch.zeros(len(objects)), torch.full((len(objects),), 1e30))
    pairs = NIFPairs(*(getattr(pairs, k).to(scene.device) for k in ("obj", "origins", "directions", "t_min", "t_max")))
    queries = networks.queries(pairs)
    trainer.add(queries, torch.rand(len(objects), generator=generator).to(scene.device) < 0.5)
    trainer.finish()
    networks.occluded(pairs, queries)
    shadows = NIFShadowAccel(scene.accel, chosen, networks, trainer, every_hit=config.shadow_rays == "every_hit")
    few_pixels = {**render_kwargs, "progress": False, "resolution": WARM_UP_RESOLUTION}
    for mode in ("collect", "answer"):
        shadows.mode = mode
        render(replace(scene, accel=shadows), spp=1, **few_pixels)
    return time.perf_counter() - start


# Fewer optimizer steps than this learn nothing beyond "visible" (docs/nif.md: 5 outer steps on the
# instances scene learned nothing; ~150 on statue(2) halve the "visible" error).
FEW_STEPS = 20


def _warn_undertrained(stats) -> None:
    """Warn where the networks that will answer saw no pairs, or too few steps to learn."""
    if stats.outer_pairs == 0 and stats.inner_pairs == 0:
        warnings.warn("NIF: no shadow ray toward the chosen objects was traced while training (has the scene "
                      "lights that they can shadow?): the networks answer untrained", stacklevel=outside_stacklevel())
    elif stats.outer_steps + stats.inner_steps < FEW_STEPS:
        warnings.warn(f"NIF: the networks trained only {stats.outer_steps} outer + {stats.inner_steps} inner steps "
                      f"({stats.outer_pairs + stats.inner_pairs:,} pairs), too few to learn much beyond \"visible\" "
                      f"(fewer than {FEW_STEPS}): raise {given('nif_train_spp')} or the resolution", stacklevel=outside_stacklevel())


def render_nif(scene, nif: str | list[str] = "auto", spp: int | None = None, train_spp: int | None = None, seed: int = 0,
               config: NIFConfig | None = None, answer: str = "answer", audit: bool = False, **render_kwargs) -> tuple[RenderResult, dict]:
    """Render ``scene`` with NIF answering the shadow rays of the objects ``nif`` names (see
    `select_nif_instances`). ``train_spp`` (default ``config.training.train_spp``, or half of
    ``spp`` with a warning when that is not below ``spp``) samples per pixel train the networks;
    the other ``spp - train_spp`` use them. ``config``: a `NIFConfig` or a dict shaped like one. ``answer="exact"`` renders
    the same samples with exact shadow rays instead (the reference that differs only in who
    answered); ``audit=True`` also runs every shadow ray NIF answers exactly, timing it and
    counting disagreements. ``render_kwargs`` go to `neuralrt.render.integrator.render` (``resolution``,
    ``max_depth``, ``progress``, ...).

    Returns the merged `RenderResult` and the NIF report (objects, memory, training time per spp,
    shadow rays by network, times)."""
    from ..scene.scene import Scene

    if not isinstance(scene, Scene):
        raise ConfigError(f"render_nif: scene must be a loaded Scene (neuralrt.scene.load_scene), not {type(scene).__name__}")
    check_nif_names(nif)
    spp = check_count("spp", spp)
    train_spp = check_count("train_spp", train_spp)
    seed = seed_or_default("seed", seed)
    if answer not in ("answer", "exact"):
        raise ConfigError(f"answer: must be 'answer' or 'exact', got {answer!r}")
    config = checked_nif_config(config)
    chosen = select_nif_instances(scene, nif, config)
    spp = spp if spp is not None else scene.settings.spp  # (Python ints: the checks return them, the scene's are)
    if train_spp is None and config.training.train_spp >= spp:  # the defaults clash (32 vs a scene's 16): train on half
        if spp < 2:
            raise ConfigError(f"{given('spp', spp)}: NIF needs at least 2 samples per pixel (some to train on, some to answer)")
        warnings.warn(f"NIF trains on the first {spp // 2} of {spp} samples per pixel (its default, "
                      f"{config.training.train_spp}, is not below spp; set {given('nif_train_spp')} to choose)",
                      stacklevel=outside_stacklevel())
        train_spp = spp // 2
    if train_spp is not None:
        config = config.model_copy(update={"training": config.training.model_copy(update={"train_spp": train_spp})})
    train_spp = config.training.train_spp
    if spp <= train_spp:
        raise ConfigError(f"{given('nif_train_spp', train_spp)} leaves no samples for NIF at {given('spp', spp)} (it must be below spp)")

    accel = scene.accel
    blases = list({id(accel.instances[k].blas): accel.instances[k].blas for k in chosen}.values())
    boxes = [b.bounds.inflated(config.box_inflation) for b in blases]
    networks = NIFNetworks(config, boxes).to(scene.device)
    trainer = NIFTrainer(networks)
    # The exact reference needs no networks: nothing is trained for it.
    shadows = NIFShadowAccel(accel, chosen, networks, trainer if answer == "answer" else None, audit=audit,
                             every_hit=config.shadow_rays == "every_hit")
    nif_scene = replace(scene, accel=shadows)

    warmup_seconds = _warm_up(scene, chosen, config, boxes, render_kwargs)  # (untimed, as `api.render`'s own)
    start = time.perf_counter()
    shadows.mode = "collect"
    first = render(nif_scene, spp=train_spp, seed=seed, progress_label="render, NIF collecting", **render_kwargs)
    trainer.finish()
    if answer == "answer":
        _warn_undertrained(trainer.stats)
    shadows.mode = answer
    second = render(nif_scene, spp=spp - train_spp, seed=seed + SECOND_PART_SEED,
                    progress_label="render, NIF answering" if answer == "answer" else "render, exact shadows", **render_kwargs)
    total = time.perf_counter() - start
    result = _merge(first, second, total)

    tr = trainer.stats
    names = list(dict.fromkeys(accel.instances[k].name for k in chosen))
    report = {
        "objects": names,
        "instances": len(chosen),
        "unique_meshes": len(blases),
        "triangles": [int(b.mesh.num_triangles) for b in blases],
        "spp": spp,
        "train_spp": train_spp,
        "passes_per_spp": config.training.passes_per_spp,
        "pair_fraction": config.training.pair_fraction,
        "shadow_rays_of": config.shadow_rays,
        "answer": answer,
        "training": tr.as_dict(),
        "training_seconds": tr.seconds,
        "warmup_seconds": warmup_seconds,
        "training_seconds_per_spp": tr.seconds / train_spp,
        "training_share_of_render": tr.seconds / max(total, 1e-12),
        "render_seconds": {"train_part": first.seconds, "finish_training": total - first.seconds - second.seconds,
                           "answer_part": second.seconds, "total": total},
        "shadow_rays_training": shadows.stats["collect"].as_dict(),
        "shadow_rays": shadows.stats[answer].as_dict(),
        "memory": networks.memory_report(),
        "device": str(scene.device),
        "torch_threads": torch.get_num_threads(),
    }
    return result, report

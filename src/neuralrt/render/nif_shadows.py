"""Shadow rays of chosen objects answered by NIF: a stand-in for the scene's accelerator.

`NIFShadowAccel` wraps a `SceneAccel`. ``intersect`` (camera and bounce rays) goes to the wrapped
accelerator unchanged. ``occluded`` (shadow rays) is answered in two parts:

- the exact objects: a `SceneAccel` over every other instance;
- the NIF objects, in two stages (the paper's Sec. 4.1). Stage 1: the TLAS stages of a `SceneAccel`
  over the NIF instances give every (ray, instance) pair whose interval meets the instance's box,
  with the ray in object space; instances of one mesh are one NIF object (occlusion is
  object-space, so they share its grids). Stage 2: the MLP inputs of all pairs at once
  (`nif_features`: a fused numba pass on the CPU, torch ops elsewhere, chosen here once), then
  one MLP call for every outer pair and one for every inner pair (`NIFNetworks.occluded_from_features`).

A ray is occluded if an exact object blocks it or any NIF object's answer says so. The integrator
calls ``occluded`` as on any accelerator and never knows a network answered. Only the shadow rays
of the camera rays' hits go through NIF (the paper's use), unless ``every_hit``
(``nif.shadow_rays = "every_hit"``); the others are traced exactly, in every mode.

Modes (``mode``): ``"collect"`` answers NIF objects exactly (each object's own `occluded` on the
pair's object-space ray) and hands every pair with its label to the `NIFTrainer` (all pairs, also
of rays an exact object already blocks: each is a valid sample of that object's visibility);
``"answer"`` answers them with the networks; ``"exact"`` answers exactly without training (a
reference that takes the same path as ``"answer"``). With ``audit=True`` every ``occluded`` call
also runs the wrapped accelerator on the same rays, timing it and counting disagreements.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from torch import Tensor

from ..accel.tlas import SceneAccel
from ..methods.nif import NIFNetworks, NIFPairs
from ..methods.nif_features import nif_features_for
from ..methods.nif_training import NIFTrainer
from ..rays import Rays

__all__ = ["NIFShadowAccel", "ShadowRayStats"]

MODES = ("collect", "answer", "exact")


@dataclass
class ShadowRayStats:
    """What the shadow rays of one mode cost and who answered them."""

    calls: int = 0
    shadow_rays: int = 0
    pairs: int = 0  # (ray, NIF instance) pairs from stage 1
    outer: int = 0  # pairs answered by (or labelled for) the outer network
    inner: int = 0
    exact_seconds: float = 0.0  # the exact objects' part
    stage1_seconds: float = 0.0  # NIF pairs and their object-space rays
    stage2_seconds: float = 0.0  # networks (answer), or exact labels + queries (collect / exact)
    audit_exact_seconds: float = 0.0  # audit: the whole exact accelerator on the same rays
    audit_disagreements: int = 0  # audit: rays whose answer differs from the exact one
    audit_false_visible: int = 0  # audit: NIF says visible, exact says blocked
    exact_only_rays: int = 0  # shadow rays of later bounces, traced exactly (not in ``shadow_rays``)
    exact_only_seconds: float = 0.0
    audit_blocked_by_nif_objects_only: int = 0  # audit: rays only NIF objects block (the errors of answering "visible")

    def as_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        rays = max(self.shadow_rays, 1)
        d["outer_share"], d["inner_share"] = self.outer / rays, self.inner / rays
        d["seconds"] = self.exact_seconds + self.stage1_seconds + self.stage2_seconds  # (NIF's shadow rays only)
        return d


class NIFShadowAccel:
    """``accel`` with the shadow rays of instances ``nif_instances`` answered by ``networks``.

    Args:
        accel: the scene's accelerator.
        nif_instances: indices into ``accel.instances`` (exact mesh BLASes).
        networks: `NIFNetworks` with one object per unique BLAS of those instances, in first-seen order.
        trainer: where ``"collect"`` sends labelled pairs.
        audit: also trace every shadow ray exactly, counting disagreements.
        every_hit: NIF takes the shadow rays of every bounce, not only of the camera rays' hits.
    """

    def __init__(self, accel: SceneAccel, nif_instances: list[int], networks: NIFNetworks, trainer: NIFTrainer | None = None,
                 audit: bool = False, every_hit: bool = False):
        chosen = set(nif_instances)
        if not chosen:
            raise ValueError("no NIF instances")
        self.accel = accel
        self.networks = networks
        self.trainer = trainer
        self.audit = audit
        self.every_hit = every_hit
        self.mode = "collect"
        dev = accel.device
        exact = [inst for k, inst in enumerate(accel.instances) if k not in chosen]
        self.exact = SceneAccel(exact, dev) if exact else None
        nif = [accel.instances[k] for k in sorted(chosen)]
        self.nif = SceneAccel(nif, dev)
        objects: dict[int, list[int]] = {}
        self.blases = []
        for k, inst in enumerate(nif):
            if id(inst.blas) not in objects:
                objects[id(inst.blas)] = []
                self.blases.append(inst.blas)
            objects[id(inst.blas)].append(k)
        if len(self.blases) != networks.num_objects:
            raise ValueError(f"{len(self.blases)} NIF objects but networks for {networks.num_objects}")
        self._groups = [torch.tensor(ids, dtype=torch.int64, device=dev) for ids in objects.values()]
        self.features = nif_features_for(dev)  # stage 2 inputs: numba on the CPU, torch elsewhere
        self.stats = {m: ShadowRayStats() for m in MODES}

    def __getattr__(self, name):  # everything else (instances, bounds, device, memory) is the wrapped accelerator's
        if name == "accel":  # not set yet (e.g. during copying): no recursion
            raise AttributeError(name)
        return getattr(self.accel, name)

    def intersect(self, rays: Rays, camera_rays: bool = False):
        return self.accel.intersect(rays, camera_rays=camera_rays)

    # -- stage 1 -----------------------------------------------------------------------------------
    def pairs(self, rays: Rays, t_limit: Tensor) -> tuple[NIFPairs, Tensor]:
        """Every (ray, NIF instance) pair whose ``(t_min, t_limit)`` meets the instance's world box:
        the pairs (object index, object-space ray) and each pair's ray index."""
        stages, n, dev = self.nif.stages, len(rays), rays.device
        valid = stages.valid_mask(rays)
        parts, ray_ids = [], []
        for obj, instance_ids in enumerate(self._groups):
            ray_idx, inst_idx, overlap = stages.candidate_pairs(rays, instance_ids, t_limit, valid)
            if ray_idx is None:  # the one-instance shortcut: every ray, ``overlap`` marking the real pairs
                ray_idx = torch.arange(n, device=dev) if overlap is None else torch.nonzero(overlap).reshape(-1)
                inst_idx = inst_idx[:1].expand(ray_idx.numel()).contiguous()
            if ray_idx.numel() == 0:
                continue
            local = stages.object_space_rays(rays, ray_idx, inst_idx, rays.t_max[ray_idx])
            parts.append(NIFPairs(torch.full_like(ray_idx, obj), local.origins, local.directions, local.t_min, local.t_max))
            ray_ids.append(ray_idx)
        ray_idx = torch.cat(ray_ids) if ray_ids else torch.zeros(0, dtype=torch.int64, device=dev)
        return NIFPairs.cat(parts, dev), ray_idx

    def exact_labels(self, pairs: NIFPairs) -> Tensor:
        """[P] bool: the pair's object blocks its ray (each object's exact BLAS)."""
        blocked = torch.zeros(len(pairs), dtype=torch.bool, device=pairs.obj.device)
        for obj, blas in enumerate(self.blases):
            sel = torch.nonzero(pairs.obj == obj).reshape(-1)
            if sel.numel():
                blocked[sel] = blas.occluded(Rays(pairs.origins[sel], pairs.directions[sel], pairs.t_min[sel], pairs.t_max[sel]))
        return blocked

    # -- shadow rays ------------------------------------------------------------------------------------
    def occluded(self, rays: Rays, camera_hits: bool = False) -> Tensor:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        st = self.stats[self.mode]
        if not (camera_hits or self.every_hit):
            t = time.perf_counter()
            blocked = self.accel.occluded(rays)
            st.exact_only_rays += len(rays)
            st.exact_only_seconds += time.perf_counter() - t
            return blocked
        st.calls += 1
        st.shadow_rays += len(rays)
        t = time.perf_counter()
        blocked = self.exact.occluded(rays) if self.exact is not None else torch.zeros(len(rays), dtype=torch.bool, device=rays.device)
        st.exact_seconds += time.perf_counter() - t
        t = time.perf_counter()
        # Collecting takes every pair; answering skips rays an exact object already blocks.
        t_limit = rays.t_max if self.mode == "collect" else torch.where(blocked, -torch.inf, rays.t_max)
        pairs, ray_idx = self.pairs(rays, t_limit)
        st.stage1_seconds += time.perf_counter() - t
        t = time.perf_counter()
        if self.mode == "answer":
            outer_pair, outer_x, inner_pair, inner_x = self.features(self.networks, pairs)
            hit = self.networks.occluded_from_features(len(pairs), outer_pair, outer_x, inner_pair, inner_x)
            n_outer, n_inner = outer_pair.numel(), inner_pair.numel()
        else:
            queries = self.networks.queries(pairs)
            hit = self.exact_labels(pairs)
            if self.mode == "collect" and self.trainer is not None:
                trained = self.trainer.stats.seconds
                self.trainer.add(queries, ~hit)
                t += self.trainer.stats.seconds - trained  # training rounds are counted by the trainer, not here
            n_outer, n_inner = queries.outer_pair.numel(), queries.inner_pair.numel()
        st.stage2_seconds += time.perf_counter() - t
        st.pairs += len(pairs)
        st.outer += n_outer
        st.inner += n_inner
        exact_blocked, blocked = blocked, blocked.clone()
        blocked[ray_idx[hit]] = True
        if self.audit:
            t = time.perf_counter()
            truth = self.accel.occluded(rays)
            st.audit_exact_seconds += time.perf_counter() - t
            st.audit_disagreements += int((truth != blocked).sum())
            st.audit_false_visible += int((truth & ~blocked).sum())
            st.audit_blocked_by_nif_objects_only += int((truth & ~exact_blocked).sum())
        return blocked

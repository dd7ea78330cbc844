"""The scene's top-level accelerator: instances of bottom-level accelerators (BLAS) under transforms.

Broad phase: the (ray, instance) pairs whose ray meets the instance's world-space box; on the CPU
a group of several instances is walked as a BVH over their boxes, elsewhere every ray is tested
against every box (slabs, batched) — the same pairs either way.
Narrow phase: the surviving (ray, instance) pairs are grouped by BLAS, so that each BLAS — an
Embree scene or a neural model — runs once per call over all of its rays from all of its
instances; rays are mapped to object space per pair, and the closest hit over all pairs wins.
The integrator only sees `intersect` / `occluded`; it never knows which kind of BLAS answered.

The whole-batch stages (broad phase, ray mapping, merging) have two implementations with one
contract (`tlas_stages`): fused numba passes on the CPU, torch ops elsewhere, picked once when the
accelerator is built. A single-instance group that most rays overlap takes every ray as is (no
gather, no scatter), and an identity instance skips the matrix products. On the CPU a scene with
Embree meshes answers through a fused path instead (`NumbaTLASStages.intersect_fused` /
``occluded_fused``: only overlapping rays reach Embree, hit attributes only for each ray's final
hit; neural groups take their usual step in their turn), with the same answers bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..errors import DeviceError
from ..rays import AABB, Hits, Rays, Transform, check_rays, resolve_device
from .blas import BLAS, MemoryReport
from .tlas_stages import InstanceTable, intersect_group, occluded_group, stages_for

__all__ = ["Instance", "SceneAccel"]

@dataclass(frozen=True)
class Instance:
    """One placed object: a BLAS in object space, its object-to-world transform and materials.
    Frozen: a `SceneAccel` copies its instances into its tables when built, so a field changed
    afterwards would change nothing it answers (edit a scene by building another: `load_dict`
    with the loaded models reuses them)."""

    blas: BLAS  # answers rays in object space (MeshBLAS, or a neural model)
    transform: Transform  # object -> world
    material_map: Tensor  # [K] int64: BLAS-local material id -> scene material index
    name: str = ""
    camera_blas: BLAS | None = None  # answers camera rays instead of `blas` when set (hybrid mode)
    world_bounds: AABB = field(init=False)

    def __post_init__(self) -> None:
        material_map = torch.as_tensor(self.material_map, dtype=torch.int64).reshape(-1).clone()
        if material_map.numel() == 0:
            raise ValueError(f"instance {self.name!r}: material_map is empty")
        object.__setattr__(self, "material_map", material_map)  # (its own copy: the caller's stays theirs)
        object.__setattr__(self, "world_bounds", self.blas.bounds.transformed(self.transform))

    def blas_for(self, camera_rays: bool) -> BLAS:
        return self.camera_blas if (camera_rays and self.camera_blas is not None) else self.blas


# Growth of a broad-phase box, relative to its largest coordinate (~128 float32 ulps), so that the
# slab test, run on the rounded world box, never culls a hit the BLAS finds in object space: a
# flat box (a floor) failed `t_enter <= t_max` by rounding for t_max equal to the hit's t, and so
# did a rotated instance hit at a grazing angle to its box until 2^-18 (measured; 2^-16 kept).
BROAD_PHASE_GROWTH = 2.0**-16


def _broad_phase_box(instance: Instance) -> AABB:
    """The world box the broad phase tests ``instance`` against: where its BLASes may report hits
    (a neural BLAS's ``box``, which holds its bounds: LSNIF answers inside its padded voxel box, a
    little beyond the mesh), transformed, grown by `BROAD_PHASE_GROWTH`."""
    boxes = [getattr(b, "box", b.bounds) for b in (instance.blas, instance.camera_blas) if b is not None]
    lo = torch.stack([b.lo.cpu() for b in boxes]).float().min(0).values
    hi = torch.stack([b.hi.cpu() for b in boxes]).float().max(0).values
    world = AABB(lo, hi).transformed(instance.transform)
    grow = BROAD_PHASE_GROWTH * float(torch.cat([world.lo.abs(), world.hi.abs()]).max())
    return AABB(world.lo - grow, world.hi + grow)


@dataclass
class _Group:
    """Instances that share one BLAS: intersected together in one call."""

    blas: BLAS
    instance_ids: Tensor  # [G] int64


class SceneAccel:
    """Two-level accelerator over `Instance`s, answering world-space rays.

    ``intersect`` returns world-space `Hits` whose ``instance_id`` indexes ``instances`` and whose
    ``material_id`` is already mapped to the scene's material table. Normals are unit world-space
    vectors, not flipped towards the ray. Rays must be on ``device``.

    ``stages`` picks the implementation of the whole-batch stages (`neuralrt.accel.tlas_stages`);
    by default the one for ``device`` (numba on the CPU, torch elsewhere), chosen here once.
    """

    def __init__(self, instances: list[Instance], device="cpu", stages: type | None = None):
        if not instances:
            raise ValueError("a scene needs at least one instance")
        self.instances = tuple(instances)  # (read into the tables below: a tuple, as nothing added later would count)
        self.device = resolve_device(device)
        dev = self.device
        n_inst = len(self.instances)
        self.bounds = AABB(torch.stack([i.world_bounds.lo for i in self.instances]).float().min(0).values.to(dev),
                           torch.stack([i.world_bounds.hi for i in self.instances]).float().max(0).values.to(dev))
        boxes = [_broad_phase_box(i) for i in self.instances]
        box_lo = torch.stack([b.lo for b in boxes]).float().to(dev)  # [I, 3]
        box_hi = torch.stack([b.hi for b in boxes]).float().to(dev)
        max_k = max(i.material_map.numel() for i in self.instances)
        material_maps = torch.full((n_inst, max_k), -1, dtype=torch.int64, device=dev)
        for k, inst in enumerate(self.instances):
            material_maps[k, : inst.material_map.numel()] = inst.material_map.to(dev)
        self.table = InstanceTable(
            box_lo=box_lo,
            box_hi=box_hi,
            world_to_object=torch.stack([i.transform.inverse_matrix for i in self.instances]).to(dev).contiguous(),
            material_maps=material_maps,
            is_identity=torch.tensor([i.transform.is_identity for i in self.instances], dtype=torch.bool, device=dev),
        )
        self.stages = stages_for(self.table) if stages is None else stages(self.table)
        self._groups = {mode: self._group_by_blas(mode) for mode in (False, True)}

    def _group_by_blas(self, camera_rays: bool) -> list[_Group]:
        order: dict[int, tuple[BLAS, list[int]]] = {}
        for k, inst in enumerate(self.instances):
            blas = inst.blas_for(camera_rays)
            order.setdefault(id(blas), (blas, []))[1].append(k)
        return [_Group(b, torch.tensor(ids, dtype=torch.int64, device=self.device)) for b, ids in order.values()]

    @property
    def unique_blases(self) -> list[BLAS]:
        seen: dict[int, BLAS] = {}
        for inst in self.instances:
            for b in (inst.blas, inst.camera_blas):
                if b is not None:  # a view of a neural model (e.g. another LoD) shares its model's bytes
                    seen.setdefault(id(getattr(b, "memory_owner", b)), b)
        return list(seen.values())

    def _check_device(self, rays: Rays) -> None:
        if rays.device != self.device:
            raise DeviceError(f"rays are on {rays.device} but the scene is on {self.device}: move them with rays.to({str(self.device)!r})")

    # -- queries ----------------------------------------------------------------------------------
    def intersect(self, rays: Rays, camera_rays: bool = False) -> Hits:
        """Closest world-space hit per ray over all instances."""
        check_rays(rays, "intersect")
        self._check_device(rays)
        n, stages = len(rays), self.stages
        if n == 0:
            return Hits.empty(0, rays.device)
        fused = stages.intersect_fused(rays, self._groups[camera_rays])
        if fused is not None:
            return fused
        best: Hits | None = None  # Hits.empty(n) until a group hits something
        valid = stages.valid_mask(rays)
        for group in self._groups[camera_rays]:
            # Rays already closer than a box cannot improve: the box test uses the current best t.
            t_limit = rays.t_max if best is None else torch.minimum(rays.t_max, best.t)
            best = intersect_group(stages, rays, group, t_limit, valid, best)
        return Hits.empty(n, rays.device) if best is None else best

    def occluded(self, rays: Rays, camera_hits: bool = False) -> Tensor:
        """[N] bool: does any instance block the ray within [t_min, t_max]? ``camera_hits``: the
        rays leave the camera rays' hits (direct light at the first hit), which a stand-in may
        answer otherwise (`NIFShadowAccel`); answered alike here."""
        check_rays(rays, "occluded")
        self._check_device(rays)
        stages = self.stages
        if len(rays) == 0:
            return torch.zeros(0, dtype=torch.bool, device=rays.device)
        fused = stages.occluded_fused(rays, self._groups[False])
        if fused is not None:
            return fused
        blocked: Tensor | None = None  # all False until a group blocks something
        valid = stages.valid_mask(rays)
        for group in self._groups[False]:
            blocked = occluded_group(stages, rays, group, valid, blocked)
        return torch.zeros(len(rays), dtype=torch.bool, device=rays.device) if blocked is None else blocked

    def memory_bytes(self) -> MemoryReport:
        """Each unique BLAS once (instancing), plus 2 float32 4x4 matrices and a box per instance."""
        report = MemoryReport({"instances": len(self.instances) * (2 * 64 + 24)})
        for blas in self.unique_blases:
            report = report + blas.memory_bytes()
        return report

    def __repr__(self) -> str:
        return f"SceneAccel({len(self.instances)} instances, {len(self.unique_blases)} unique BLAS)"

"""The scene's top-level accelerator: instances of bottom-level accelerators (BLAS) under transforms.

Broad phase: every ray is tested against every instance's world-space box (slabs, batched).
Narrow phase: the surviving (ray, instance) pairs are grouped by BLAS, so that each BLAS — an
Embree scene or a neural model — runs once per call over all of its rays from all of its
instances; rays are mapped to object space per pair, and the closest hit over all pairs wins.
The integrator only sees `intersect` / `occluded`; it never knows which kind of BLAS answered.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..rays import AABB, Hits, Rays, Transform, ray_box_intervals, valid_ray_mask
from .blas import BLAS, MemoryReport

__all__ = ["Instance", "SceneAccel"]

# Bound on (rays x instances) slab tests held in memory at once.
_BROAD_PHASE_CHUNK = 1 << 23


@dataclass
class Instance:
    """One placed object: a BLAS in object space, its object-to-world transform and materials."""

    blas: BLAS  # answers rays in object space (MeshBLAS, or a neural model)
    transform: Transform  # object -> world
    material_map: Tensor  # [K] int64: BLAS-local material id -> scene material index
    name: str = ""
    camera_blas: BLAS | None = None  # answers camera rays instead of `blas` when set (hybrid mode)
    world_bounds: AABB = field(init=False)

    def __post_init__(self) -> None:
        self.material_map = torch.as_tensor(self.material_map, dtype=torch.int64).reshape(-1)
        if self.material_map.numel() == 0:
            raise ValueError(f"instance {self.name!r}: material_map is empty")
        self.world_bounds = self.blas.bounds.transformed(self.transform)

    def blas_for(self, camera_rays: bool) -> BLAS:
        return self.camera_blas if (camera_rays and self.camera_blas is not None) else self.blas


@dataclass
class _Group:
    """Instances that share one BLAS: intersected together in one call."""

    blas: BLAS
    instance_ids: Tensor  # [G] int64


class SceneAccel:
    """Two-level accelerator over `Instance`s, answering world-space rays.

    ``intersect`` returns world-space `Hits` whose ``instance_id`` indexes ``instances`` and whose
    ``material_id`` is already mapped to the scene's material table. Normals are unit world-space
    vectors, not flipped towards the ray.
    """

    def __init__(self, instances: list[Instance], device="cpu"):
        if not instances:
            raise ValueError("a scene needs at least one instance")
        self.instances = list(instances)
        self.device = torch.device(device)
        dev = self.device
        n_inst = len(self.instances)
        self.box_lo = torch.stack([i.world_bounds.lo for i in self.instances]).float().to(dev)  # [I, 3]
        self.box_hi = torch.stack([i.world_bounds.hi for i in self.instances]).float().to(dev)
        self.bounds = AABB(self.box_lo.min(0).values, self.box_hi.max(0).values)
        # World -> object matrices for rays; their transpose maps object normals back to world.
        self.world_to_object = torch.stack([i.transform.inverse_matrix for i in self.instances]).to(dev)  # [I,4,4]
        max_k = max(i.material_map.numel() for i in self.instances)
        self.material_maps = torch.full((n_inst, max_k), -1, dtype=torch.int64, device=dev)
        for k, inst in enumerate(self.instances):
            self.material_maps[k, : inst.material_map.numel()] = inst.material_map.to(dev)
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
                if b is not None:
                    seen.setdefault(id(b), b)
        return list(seen.values())

    # -- broad phase -----------------------------------------------------------------------------
    def _candidate_pairs(self, rays: Rays, instance_ids: Tensor, t_limit: Tensor) -> tuple[Tensor, Tensor]:
        """(ray index, instance index) of rays whose interval overlaps an instance's world box."""
        n, g = len(rays), instance_ids.numel()
        valid = valid_ray_mask(rays)
        lo, hi = self.box_lo[instance_ids], self.box_hi[instance_ids]
        ray_idx, inst_idx = [], []
        chunk = max(1, _BROAD_PHASE_CHUNK // max(g, 1))
        for start in range(0, n, chunk):
            sl = slice(start, min(n, start + chunk))
            t0, t1 = ray_box_intervals(rays.origins[sl, None], rays.directions[sl, None], lo[None], hi[None])  # [n, G]
            overlap = (t0 <= t1) & (t1 >= rays.t_min[sl, None]) & (t0 <= t_limit[sl, None]) & valid[sl, None]
            r, k = torch.nonzero(overlap, as_tuple=True)
            ray_idx.append(r + start)
            inst_idx.append(instance_ids[k])
        return torch.cat(ray_idx), torch.cat(inst_idx)

    def _object_space_rays(self, rays: Rays, ray_idx: Tensor, inst_idx: Tensor, t_max: Tensor) -> Rays:
        m = self.world_to_object[inst_idx]  # [P, 4, 4]
        o = torch.einsum("pij,pj->pi", m[:, :3, :3], rays.origins[ray_idx]) + m[:, :3, 3]
        d = torch.einsum("pij,pj->pi", m[:, :3, :3], rays.directions[ray_idx])
        return Rays(o, d, rays.t_min[ray_idx], t_max)

    # -- queries ----------------------------------------------------------------------------------
    def intersect(self, rays: Rays, camera_rays: bool = False) -> Hits:
        """Closest world-space hit per ray over all instances."""
        n = len(rays)
        best = Hits.empty(n, rays.device)
        for group in self._groups[camera_rays]:
            # Rays already closer than a box cannot improve: the box test uses the current best t.
            t_limit = torch.minimum(rays.t_max, best.t)
            ray_idx, inst_idx = self._candidate_pairs(rays, group.instance_ids, t_limit)
            if ray_idx.numel() == 0:
                continue
            local = group.blas.intersect(self._object_space_rays(rays, ray_idx, inst_idx, t_limit[ray_idx]))
            closer = local.hit & (local.t < best.t[ray_idx])
            if not closer.any():
                continue
            ray_idx, inst_idx, local = ray_idx[closer], inst_idx[closer], local[closer]
            # Several instances may improve one ray: keep the smallest t per ray.
            best_t = best.t.clone().scatter_reduce_(0, ray_idx, local.t, reduce="amin")
            winner = local.t == best_t[ray_idx]
            ray_idx, inst_idx, local = ray_idx[winner], inst_idx[winner], local[winner]
            self._to_world_(local, inst_idx)
            best.scatter_(ray_idx, local)
        return best

    def _to_world_(self, hits: Hits, inst_idx: Tensor) -> None:
        """Object-space hit records to world space (normals by the inverse transpose), in place."""
        w2o = self.world_to_object[inst_idx, :3, :3]  # normal_world = (M^-1)^T n = n^T M^-1
        hits.normal = torch.nn.functional.normalize(torch.einsum("pj,pji->pi", hits.normal, w2o), dim=-1)
        hits.geometric_normal = torch.nn.functional.normalize(
            torch.einsum("pj,pji->pi", hits.geometric_normal, w2o), dim=-1
        )
        local_mat = hits.material_id.clamp(0, self.material_maps.shape[1] - 1)
        hits.material_id = self.material_maps[inst_idx, local_mat]
        hits.instance_id = inst_idx

    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: does any instance block the ray within (t_min, t_max)?"""
        blocked = torch.zeros(len(rays), dtype=torch.bool, device=rays.device)
        for group in self._groups[False]:
            t_limit = torch.where(blocked, -torch.inf, rays.t_max)  # done rays drop out of the broad phase
            ray_idx, inst_idx = self._candidate_pairs(rays, group.instance_ids, t_limit)
            if ray_idx.numel() == 0:
                continue
            hit = group.blas.occluded(self._object_space_rays(rays, ray_idx, inst_idx, rays.t_max[ray_idx]))
            blocked[ray_idx[hit]] = True
        return blocked

    def memory_bytes(self) -> MemoryReport:
        """Each unique BLAS once (instancing), plus 2 float32 4x4 matrices and a box per instance."""
        report = MemoryReport({"instances": len(self.instances) * (2 * 64 + 24)})
        for blas in self.unique_blases:
            report = report + blas.memory_bytes()
        return report

    def __repr__(self) -> str:
        return f"SceneAccel({len(self.instances)} instances, {len(self.unique_blases)} unique BLAS)"

"""The scene's top-level accelerator: instances of bottom-level accelerators (BLAS) under transforms.

Broad phase: every ray is tested against every instance's world-space box (slabs, batched).
Narrow phase: the surviving (ray, instance) pairs are grouped by BLAS, so that each BLAS — an
Embree scene or a neural model — runs once per call over all of its rays from all of its
instances; rays are mapped to object space per pair, and the closest hit over all pairs wins.
The integrator only sees `intersect` / `occluded`; it never knows which kind of BLAS answered.

On the CPU the broad phase, the ray mapping and the closest-pair choice run as fused numba passes
(`tlas_kernels`) that compute exactly what the torch code (kept for other devices) computes. A
single-instance group that most rays overlap takes every ray as is (no gather, no scatter), and an
identity instance skips the matrix products.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
import torch
from torch import Tensor

from ..rays import AABB, Hits, Rays, Transform, ray_box_intervals, valid_ray_mask
from . import tlas_kernels as kernels
from .blas import BLAS, MemoryReport

__all__ = ["Instance", "SceneAccel"]

# Bound on (rays x instances) slab tests held in memory at once.
_BROAD_PHASE_CHUNK = 1 << 23
# A one-instance group sends every ray to its BLAS (no gather/scatter of pairs) when at least this
# fraction of the rays overlaps its box; the rest get an empty interval.
_EVERY_RAY_FRACTION = 0.5


def _only(t_max: Tensor, overlap: Tensor | None) -> Tensor:
    """``t_max`` where ``overlap``, else -inf (an empty interval); unchanged without a mask."""
    return t_max if overlap is None else torch.where(overlap, t_max, -torch.inf)


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
        # numpy views for the CPU kernels; identity instances skip the ray and normal transforms.
        self._box_lo_np = self.box_lo.cpu().numpy()
        self._box_hi_np = self.box_hi.cpu().numpy()
        self._world_to_object_np = self.world_to_object.cpu().contiguous().numpy()
        self._material_maps_np = self.material_maps.cpu().numpy()
        self._is_identity = np.array([i.transform.is_identity for i in self.instances], np.bool_)

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
    def _candidate_pairs(
        self, rays: Rays, instance_ids: Tensor, t_limit: Tensor, valid: Tensor | None
    ) -> tuple[Tensor | None, Tensor, Tensor | None]:
        """(ray index, instance index, None) of valid rays whose interval (t_min, t_limit) overlaps
        an instance's world box.

        A group of one instance whose box most rays overlap gives ``(None, instance, overlap)``
        instead: every ray, in order, is a pair (no gathering); ``overlap`` [N] bool marks the real
        ones, or is None when all are (the others get an empty interval and cannot hit).
        """
        n, g = len(rays), instance_ids.numel()
        if self._kernels_on(rays.device):
            overlap = np.empty((n, g), np.bool_)
            o, d, t_min, t_max, limit = (x.detach().numpy() for x in (rays.origins, rays.directions, rays.t_min, rays.t_max, t_limit))
            lo, hi = self._box_lo_np[instance_ids.numpy()], self._box_hi_np[instance_ids.numpy()]
            count = kernels.instance_overlaps(o, d, t_min, t_max, limit, lo, hi, overlap)
            if g == 1 and count >= _EVERY_RAY_FRACTION * n:
                return None, instance_ids, None if count == n else torch.from_numpy(overlap[:, 0])
            ray_idx, k = np.nonzero(overlap)
            return torch.from_numpy(ray_idx), instance_ids[torch.from_numpy(k)], None
        if valid is None:
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
        return torch.cat(ray_idx), torch.cat(inst_idx), None

    def _kernels_on(self, device: torch.device) -> bool:
        """CPU data and accelerator: the fused numba passes (same results as the torch ops)."""
        return device.type == "cpu" and self.device.type == "cpu"

    def _object_space_rays(self, rays: Rays, ray_idx: Tensor | None, inst_idx: Tensor, t_max: Tensor) -> Rays:
        """The pairs' rays in their instance's object space, with interval (t_min, ``t_max`` [P]).
        ``ray_idx`` None: every ray, in order, under the one instance ``inst_idx[0]``."""
        if ray_idx is None:
            k = int(inst_idx[0])
            if self._is_identity[k]:
                return Rays(rays.origins, rays.directions, rays.t_min, t_max)
            if self._kernels_on(rays.device):
                o, d = np.empty((len(rays), 3), np.float32), np.empty((len(rays), 3), np.float32)
                kernels.transform_rays(
                    rays.origins.detach().numpy(), rays.directions.detach().numpy(), self._world_to_object_np[k], o, d
                )
                return Rays(torch.from_numpy(o), torch.from_numpy(d), rays.t_min, t_max)
            t_min, ray_idx, inst_idx = rays.t_min, torch.arange(len(rays)), inst_idx.expand(len(rays))
        else:
            t_min = rays.t_min[ray_idx]
        if self._kernels_on(rays.device):
            o, d = np.empty((ray_idx.numel(), 3), np.float32), np.empty((ray_idx.numel(), 3), np.float32)
            kernels.object_space_rays(
                rays.origins.detach().numpy(), rays.directions.detach().numpy(), ray_idx.numpy(), inst_idx.contiguous().numpy(),
                self._world_to_object_np, self._is_identity, o, d,
            )  # fmt: skip
            return Rays(torch.from_numpy(o), torch.from_numpy(d), t_min, t_max)
        m = self.world_to_object[inst_idx]  # [P, 4, 4]
        o = torch.einsum("pij,pj->pi", m[:, :3, :3], rays.origins[ray_idx]) + m[:, :3, 3]
        d = torch.einsum("pij,pj->pi", m[:, :3, :3], rays.directions[ray_idx])
        return Rays(o, d, t_min, t_max)

    # -- queries ----------------------------------------------------------------------------------
    def intersect(self, rays: Rays, camera_rays: bool = False) -> Hits:
        """Closest world-space hit per ray over all instances."""
        n = len(rays)
        if n == 0:
            return Hits.empty(0, rays.device)
        best: Hits | None = None  # Hits.empty(n) until a group hits something
        valid = None if self._kernels_on(rays.device) else valid_ray_mask(rays)  # numba fuses it per group
        for group in self._groups[camera_rays]:
            # Rays already closer than a box cannot improve: the box test uses the current best t.
            t_limit = rays.t_max if best is None else torch.minimum(rays.t_max, best.t)
            ray_idx, inst_idx, overlap = self._candidate_pairs(rays, group.instance_ids, t_limit, valid)
            if ray_idx is None:  # every ray, one instance: no gathers
                local = group.blas.intersect(self._object_space_rays(rays, None, inst_idx, _only(t_limit, overlap)))
                best = self._merge_every_ray(best, local, int(inst_idx[0]), overlap)
            elif ray_idx.numel():
                local = group.blas.intersect(self._object_space_rays(rays, ray_idx, inst_idx, t_limit[ray_idx]))
                best = self._merge_pairs(best, local, ray_idx, inst_idx, n, rays.device)
        return Hits.empty(n, rays.device) if best is None else best

    def _merge_every_ray(self, best: Hits | None, local: Hits, k: int, overlap: Tensor | None) -> Hits:
        """Row ``r`` of ``local`` answers ray ``r`` under instance ``k``: keep it where closer."""
        if self._kernels_on(local.t.device):
            # One pass instead of ~20 torch ops (each a full sweep, and a thread wake-up).
            out = best
            if out is None:  # uninitialised: the kernel writes every row
                template = Hits.empty(0)
                out = Hits(**{f.name: torch.empty((len(local), *getattr(template, f.name).shape[1:]),
                                                  dtype=getattr(template, f.name).dtype) for f in fields(Hits)})  # fmt: skip
            kernels.merge_every_ray(
                *(getattr(local, f.name).detach().contiguous().numpy() for f in fields(Hits) if f.name != "instance_id"),
                np.empty(0, np.bool_) if overlap is None else overlap.numpy(), best is not None,
                k, self._material_maps_np[k], self._world_to_object_np[k], bool(self._is_identity[k]),
                *(getattr(out, f.name).numpy() for f in fields(Hits)),
            )  # fmt: skip
            return out
        closer = local.hit if best is None else local.hit & (local.t < best.t)
        if overlap is not None:
            closer &= overlap  # rows outside the broad phase never count, whatever the BLAS said
        local.material_id = self.material_maps[k, local.material_id.clamp(0, self.material_maps.shape[1] - 1)]
        local.instance_id = torch.full_like(local.material_id, k)
        self._normals_to_world_(local, torch.full_like(local.material_id, k))
        return (Hits.empty(len(local), local.t.device) if best is None else best).where_(closer, local)

    def _merge_pairs(
        self, best: Hits | None, local: Hits, ray_idx: Tensor, inst_idx: Tensor, n: int, device
    ) -> Hits:
        """Scatter each ray's closest improving pair of ``local`` into ``best`` (world space)."""
        if best is None:
            best = Hits.empty(n, device)
        if self._kernels_on(local.t.device):
            winner = np.empty(n, np.int64)
            found = kernels.closest_pair_per_ray(
                ray_idx.numpy(), local.hit.numpy(), local.t.detach().numpy(), best.t.detach().numpy(), winner
            )
            if found == 0:
                return best
            winner_t = torch.from_numpy(winner)
            rays_won = torch.nonzero(winner_t >= 0).squeeze(1)
            pairs = winner_t[rays_won]
            ray_idx, inst_idx, local = rays_won, inst_idx[pairs], local[pairs]
        else:
            closer = local.hit & (local.t < best.t[ray_idx])
            if not closer.any():
                return best
            ray_idx, inst_idx, local = ray_idx[closer], inst_idx[closer], local[closer]
            # Several instances may improve one ray: keep the smallest t per ray.
            best_t = best.t.clone().scatter_reduce_(0, ray_idx, local.t, reduce="amin")
            winner = local.t == best_t[ray_idx]
            ray_idx, inst_idx, local = ray_idx[winner], inst_idx[winner], local[winner]
        self._to_world_(local, inst_idx)
        return best.scatter_(ray_idx, local)

    def _to_world_(self, hits: Hits, inst_idx: Tensor) -> None:
        """Object-space hit records to world space (normals by the inverse transpose), in place."""
        self._normals_to_world_(hits, inst_idx)
        local_mat = hits.material_id.clamp(0, self.material_maps.shape[1] - 1)
        hits.material_id = self.material_maps[inst_idx, local_mat]
        hits.instance_id = inst_idx

    def _normals_to_world_(self, hits: Hits, inst_idx: Tensor) -> None:
        """normal_world = normalize((M^-1)^T n) = normalize(n^T M^-1), M^-1 = world_to_object."""
        if self._kernels_on(hits.normal.device):
            idx = inst_idx.contiguous().numpy()
            for name in ("normal", "geometric_normal"):
                world = np.empty((len(idx), 3), np.float32)
                kernels.normals_to_world(
                    getattr(hits, name).detach().contiguous().numpy(), idx, self._world_to_object_np, self._is_identity, world
                )
                setattr(hits, name, torch.from_numpy(world))
            return
        w2o = self.world_to_object[inst_idx, :3, :3]
        hits.normal = torch.nn.functional.normalize(torch.einsum("pj,pji->pi", hits.normal, w2o), dim=-1)
        hits.geometric_normal = torch.nn.functional.normalize(
            torch.einsum("pj,pji->pi", hits.geometric_normal, w2o), dim=-1
        )

    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: does any instance block the ray within (t_min, t_max)?"""
        if len(rays) == 0:
            return torch.zeros(0, dtype=torch.bool, device=rays.device)
        blocked: Tensor | None = None  # all False until a group blocks something
        valid = None if self._kernels_on(rays.device) else valid_ray_mask(rays)
        for group in self._groups[False]:
            # Done rays drop out of the broad phase.
            t_limit = rays.t_max if blocked is None else torch.where(blocked, -torch.inf, rays.t_max)
            ray_idx, inst_idx, overlap = self._candidate_pairs(rays, group.instance_ids, t_limit, valid)
            if ray_idx is None:  # every ray, one instance: no gathers
                hit = group.blas.occluded(self._object_space_rays(rays, None, inst_idx, _only(rays.t_max, overlap)))
                hit = hit if overlap is None else hit & overlap
                blocked = hit if blocked is None else blocked | hit
                continue
            if ray_idx.numel() == 0:
                continue
            hit = group.blas.occluded(self._object_space_rays(rays, ray_idx, inst_idx, rays.t_max[ray_idx]))
            if blocked is None:
                blocked = torch.zeros(len(rays), dtype=torch.bool, device=rays.device)
            blocked[ray_idx[hit]] = True
        return torch.zeros(len(rays), dtype=torch.bool, device=rays.device) if blocked is None else blocked

    def memory_bytes(self) -> MemoryReport:
        """Each unique BLAS once (instancing), plus 2 float32 4x4 matrices and a box per instance."""
        report = MemoryReport({"instances": len(self.instances) * (2 * 64 + 24)})
        for blas in self.unique_blases:
            report = report + blas.memory_bytes()
        return report

    def __repr__(self) -> str:
        return f"SceneAccel({len(self.instances)} instances, {len(self.unique_blases)} unique BLAS)"

"""The scene TLAS's whole-batch stages, in two implementations with one contract.

`NumbaTLASStages` runs fused numba passes (`tlas_kernels`) on CPU arrays, its broad phase walking
a BVH over a group's instance boxes; `TorchTLASStages` runs torch ops on any device, testing every
box (the same pairs in the same order). `SceneAccel` picks one at construction
(`stages_for(device)`) and never branches on the device again. Both compute the same values in the same float32 order, so a scene
answers bit-identically with either (the tests run both on CPU tensors).

Every stage sees the instance table the accelerator was built with (`InstanceTable`):

- ``valid_mask(rays)``: [N] bool valid rays, or None when `candidate_pairs` tests validity itself.
- ``candidate_pairs(rays, instance_ids, t_limit, valid)``: the (ray, instance) pairs whose ray is
  valid and whose interval ``(t_min, t_limit)`` meets the instance's world box, as
  ``(ray_idx [P], inst_idx [P], None)``; or ``(None, instance_ids, overlap)`` for a one-instance
  group most rays overlap: every ray in order is a pair, ``overlap`` [N] marking the real ones
  (None when all are).
- ``object_space_rays(rays, ray_idx, inst_idx, t_max)``: the pairs' rays in object space with
  interval ``(t_min, t_max)``; ``ray_idx`` None means every ray under instance ``inst_idx[0]``.
- ``merge_every_ray(best, local, k, overlap)``: row r of ``local`` (object space, instance ``k``)
  answers ray r; keep it in world space where it hits (inside ``overlap``) closer than ``best``.
- ``merge_pairs(best, local, ray_idx, inst_idx)``: each ray's closest improving pair of ``local``,
  in world space, written into ``best``; exact ties go to the later pair.
- ``intersect_fused(rays, groups)``: the whole closest-hit query at once where a fused path
  exists (`NumbaTLASStages`, a scene with an untextured Embree mesh among its groups: Embree's
  raw answers merged, the other groups' steps of `intersect_group` in their turn), else None (the
  caller runs `intersect_group` group by group). Same answers, bit for bit.
- ``occluded_fused(rays, groups)``: the same for the shadow-ray query ([N] bool, or None).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from ..geometry.bvh import BVH, build_box_bvh
from ..host_threads import numba_threads
from ..rays import Hits, Rays, ray_box_intervals, valid_ray_mask
from . import tlas_kernels as kernels

__all__ = ["InstanceTable", "NumbaTLASStages", "TorchTLASStages", "stages_for"]

# Bound on (rays x instances) slab tests held in memory at once.
_BROAD_PHASE_CHUNK = 1 << 23
# A one-instance group sends every ray to its BLAS (no gather/scatter of pairs) when at least this
# fraction of the rays overlaps its box; the rest get an empty interval.
_EVERY_RAY_FRACTION = 0.5
# Groups of at least this many instances walk a BVH over their boxes (numba stages); smaller ones
# test every box.
_BVH_MIN_INSTANCES = 4


@dataclass
class InstanceTable:
    """Per-instance data of a scene, on the accelerator's device."""

    box_lo: Tensor  # [I, 3] float32 world box
    box_hi: Tensor  # [I, 3] float32
    world_to_object: Tensor  # [I, 4, 4] float32; its 3x3 transpose maps object normals to world
    material_maps: Tensor  # [I, K] int64 BLAS-local material -> scene material (-1 padding)
    is_identity: Tensor  # [I] bool: identity transform (ray and normal maps are skipped)


def _local_material_index(material_id: Tensor, material_maps: Tensor) -> Tensor:
    """BLAS-local material ids clamped into the map (misses and out-of-range ids map to slot 0 / K-1)."""
    return material_id.clamp(0, material_maps.shape[1] - 1)


def _only_within(t_max: Tensor, overlap: Tensor | None) -> Tensor:
    """``t_max`` where ``overlap``, else -inf (an empty interval); unchanged without a mask."""
    return t_max if overlap is None else torch.where(overlap, t_max, -torch.inf)


def intersect_group(stages, rays: Rays, group, t_limit: Tensor, valid: Tensor | None, best: Hits | None) -> Hits | None:
    """One group's step of the closest-hit query, group by group: its BLAS answers the (ray,
    instance) pairs whose interval ``(t_min, t_limit)`` meets the instance's box, and the closer
    answers are merged into ``best`` (None: nothing hit yet); returns the merged `Hits`."""
    ray_idx, inst_idx, overlap = stages.candidate_pairs(rays, group.instance_ids, t_limit, valid)
    if ray_idx is None:  # every ray, one instance: no gathers
        local = group.blas.intersect(stages.object_space_rays(rays, None, inst_idx, _only_within(t_limit, overlap)))
        return stages.merge_every_ray(best, local, int(inst_idx[0]), overlap)
    if ray_idx.numel() == 0:
        return best
    local = group.blas.intersect(stages.object_space_rays(rays, ray_idx, inst_idx, t_limit[ray_idx]))
    return stages.merge_pairs(Hits.empty(len(rays), rays.device) if best is None else best, local, ray_idx, inst_idx)


def occluded_group(stages, rays: Rays, group, valid: Tensor | None, blocked: Tensor | None) -> Tensor | None:
    """One group's step of the shadow-ray query: ``blocked`` ([N] bool, None: nothing blocked yet)
    with the rays this group's BLAS blocks added; rays already blocked drop out of the broad phase."""
    t_limit = rays.t_max if blocked is None else torch.where(blocked, -torch.inf, rays.t_max)
    ray_idx, inst_idx, overlap = stages.candidate_pairs(rays, group.instance_ids, t_limit, valid)
    if ray_idx is None:  # every ray, one instance: no gathers
        hit = group.blas.occluded(stages.object_space_rays(rays, None, inst_idx, _only_within(rays.t_max, overlap)))
        hit = hit if overlap is None else hit & overlap
        return hit if blocked is None else blocked | hit
    if ray_idx.numel() == 0:
        return blocked
    hit = group.blas.occluded(stages.object_space_rays(rays, ray_idx, inst_idx, rays.t_max[ray_idx]))
    if blocked is None:
        blocked = torch.zeros(len(rays), dtype=torch.bool, device=rays.device)
    blocked[ray_idx[hit]] = True
    return blocked


class TorchTLASStages:
    """The stages as torch ops: any device."""

    def __init__(self, table: InstanceTable):
        self.t = table

    def valid_mask(self, rays: Rays) -> Tensor | None:
        return valid_ray_mask(rays)

    def candidate_pairs(self, rays: Rays, instance_ids: Tensor, t_limit: Tensor, valid: Tensor | None):
        if valid is None:
            valid = valid_ray_mask(rays)
        n, g = len(rays), instance_ids.numel()
        lo, hi = self.t.box_lo[instance_ids], self.t.box_hi[instance_ids]
        empty = torch.zeros(0, dtype=torch.int64, device=rays.device)
        ray_idx, inst_idx = [empty], [empty]  # (no rays: no pairs, as the numba stage answers)
        chunk = max(1, _BROAD_PHASE_CHUNK // max(g, 1))
        for start in range(0, n, chunk):
            sl = slice(start, min(n, start + chunk))
            t0, t1 = ray_box_intervals(rays.origins[sl, None], rays.directions[sl, None], lo[None], hi[None])  # [n, G]
            overlap = (t0 <= t1) & (t1 >= rays.t_min[sl, None]) & (t0 <= t_limit[sl, None]) & valid[sl, None]
            r, k = torch.nonzero(overlap, as_tuple=True)
            ray_idx.append(r + start)
            inst_idx.append(instance_ids[k])
        return torch.cat(ray_idx), torch.cat(inst_idx), None

    def object_space_rays(self, rays: Rays, ray_idx: Tensor | None, inst_idx: Tensor, t_max: Tensor) -> Rays:
        if ray_idx is None:
            if bool(self.t.is_identity[inst_idx[0]]):
                return Rays(rays.origins, rays.directions, rays.t_min, t_max)
            ray_idx, inst_idx = torch.arange(len(rays), device=rays.device), inst_idx[:1].expand(len(rays))
        m = self.t.world_to_object[inst_idx]  # [P, 4, 4]
        o = torch.einsum("pij,pj->pi", m[:, :3, :3], rays.origins[ray_idx]) + m[:, :3, 3]
        d = torch.einsum("pij,pj->pi", m[:, :3, :3], rays.directions[ray_idx])
        return Rays(o, d, rays.t_min[ray_idx], t_max)

    def merge_every_ray(self, best: Hits | None, local: Hits, k: int, overlap: Tensor | None) -> Hits:
        closer = local.hit if best is None else local.hit & (local.t < best.t)
        if overlap is not None:
            closer &= overlap  # rows outside the broad phase never count, whatever the BLAS said
        inst_idx = torch.full_like(local.material_id, k)
        self._to_world_(local, inst_idx)
        return (Hits.empty(len(local), local.t.device) if best is None else best).where_(closer, local)

    def merge_pairs(self, best: Hits, local: Hits, ray_idx: Tensor, inst_idx: Tensor) -> Hits:
        closer = local.hit & (local.t < best.t[ray_idx])
        if not closer.any():
            return best
        ray_idx, inst_idx, local = ray_idx[closer], inst_idx[closer], local[closer]
        # Several instances may improve one ray: keep the smallest t per ray, the later pair on ties.
        best_t = best.t.clone().scatter_reduce_(0, ray_idx, local.t, reduce="amin")
        winner = local.t == best_t[ray_idx]
        ray_idx, inst_idx, local = ray_idx[winner], inst_idx[winner], local[winner]
        # One row per ray before the scatter: with repeated indices a CUDA scatter keeps any of the
        # writes (even different ones per field); the last pair per ray is what the CPU keeps.
        order = torch.arange(len(ray_idx), device=ray_idx.device)
        last = torch.full_like(best.material_id, -1).scatter_reduce_(0, ray_idx, order, reduce="amax")
        kept = order == last[ray_idx]
        ray_idx, inst_idx, local = ray_idx[kept], inst_idx[kept], local[kept]
        self._to_world_(local, inst_idx)
        return best.scatter_(ray_idx, local)

    def intersect_fused(self, rays: Rays, groups) -> Hits | None:
        return None  # no fused path: the stages above, group by group

    def occluded_fused(self, rays: Rays, groups) -> Tensor | None:
        return None

    def _to_world_(self, hits: Hits, inst_idx: Tensor) -> None:
        """Object-space hit records to world space (normals by the inverse transpose), in place."""
        w2o = self.t.world_to_object[inst_idx, :3, :3]  # normal_world = normalize(n^T M^-1)
        hits.normal = torch.nn.functional.normalize(torch.einsum("pj,pji->pi", hits.normal, w2o), dim=-1)
        hits.geometric_normal = torch.nn.functional.normalize(torch.einsum("pj,pji->pi", hits.geometric_normal, w2o), dim=-1)
        hits.material_id = self.t.material_maps[inst_idx, _local_material_index(hits.material_id, self.t.material_maps)]
        hits.instance_id = inst_idx


class NumbaTLASStages:
    """The stages as fused numba passes over CPU arrays (one sweep each instead of chains of ops)."""

    def __init__(self, table: InstanceTable, broad_phase: str = "bvh", fused_meshes: bool = True):
        if broad_phase not in ("bvh", "all_boxes"):
            raise ValueError(f"broad_phase must be 'bvh' or 'all_boxes', got {broad_phase!r}")
        if table.box_lo.device.type != "cpu":
            raise ValueError("NumbaTLASStages needs an instance table on the CPU")
        self.t = table
        self._box_lo = table.box_lo.numpy()
        self._box_hi = table.box_hi.numpy()
        self._world_to_object = table.world_to_object.contiguous().numpy()
        self._material_maps = table.material_maps.numpy()
        self._is_identity = table.is_identity.numpy()
        self.broad_phase = broad_phase  # "all_boxes": every ray against every box (kept to measure against)
        self._bvhs: dict[bytes, BVH] = {}
        # Scenes with Embree meshes answer through `intersect_fused` / `occluded_fused` (False: group
        # by group, each BLAS computing attributes for all its rays, kept to measure against).
        self.fused_meshes = fused_meshes

    def valid_mask(self, rays: Rays) -> Tensor | None:
        return None  # fused into the broad phase

    def candidate_pairs(self, rays: Rays, instance_ids: Tensor, t_limit: Tensor, valid: Tensor | None):
        n, g = len(rays), instance_ids.numel()
        o, d, t_min, t_max, limit = (x.detach().numpy() for x in (rays.origins, rays.directions, rays.t_min, rays.t_max, t_limit))
        ids = instance_ids.numpy()
        if g >= _BVH_MIN_INSTANCES and self.broad_phase == "bvh":
            bvh = self._group_bvh(ids)
            ray_idx, k = kernels.instance_pairs(o, d, t_min, t_max, limit, self._box_lo[ids], self._box_hi[ids], bvh.node_lo,
                                                bvh.node_hi, bvh.children, bvh.leaf_start, bvh.leaf_count, bvh.prim_order)
            return torch.from_numpy(ray_idx), instance_ids[torch.from_numpy(k)], None
        overlap = np.empty((n, g), np.bool_)
        count = kernels.instance_overlaps(o, d, t_min, t_max, limit, self._box_lo[ids], self._box_hi[ids], overlap)
        if g == 1 and count >= _EVERY_RAY_FRACTION * n:
            return None, instance_ids, None if count == n else torch.from_numpy(overlap[:, 0])
        ray_idx, k = np.nonzero(overlap)
        return torch.from_numpy(ray_idx), instance_ids[torch.from_numpy(k)], None

    def _group_bvh(self, ids: np.ndarray) -> BVH:
        """The BVH over these instances' boxes, built on first use (a scene queries a few fixed groups)."""
        key = ids.tobytes()
        bvh = self._bvhs.get(key)
        if bvh is None:
            bvh = self._bvhs[key] = build_box_bvh(self._box_lo[ids], self._box_hi[ids])
        return bvh

    def object_space_rays(self, rays: Rays, ray_idx: Tensor | None, inst_idx: Tensor, t_max: Tensor) -> Rays:
        origins, directions = rays.origins.detach().numpy(), rays.directions.detach().numpy()
        if ray_idx is None:
            k = int(inst_idx[0])
            if self._is_identity[k]:
                return Rays(rays.origins, rays.directions, rays.t_min, t_max)
            o, d = np.empty((len(rays), 3), np.float32), np.empty((len(rays), 3), np.float32)
            kernels.transform_rays(origins, directions, self._world_to_object[k], o, d)
            return Rays(torch.from_numpy(o), torch.from_numpy(d), rays.t_min, t_max)
        o, d = np.empty((ray_idx.numel(), 3), np.float32), np.empty((ray_idx.numel(), 3), np.float32)
        kernels.object_space_rays(origins, directions, ray_idx.numpy(), inst_idx.contiguous().numpy(),
                                  self._world_to_object, self._is_identity, o, d)
        return Rays(torch.from_numpy(o), torch.from_numpy(d), rays.t_min[ray_idx], t_max)

    def merge_every_ray(self, best: Hits | None, local: Hits, k: int, overlap: Tensor | None) -> Hits:
        out = best
        if out is None:  # the kernel writes every row
            out = Hits.uninitialized(len(local))
        kernels.merge_every_ray(
            *(getattr(local, f.name).detach().contiguous().numpy() for f in fields(Hits) if f.name != "instance_id"),
            np.empty(0, np.bool_) if overlap is None else overlap.numpy(), best is not None,
            k, self._material_maps[k], self._world_to_object[k], bool(self._is_identity[k]),
            *(getattr(out, f.name).numpy() for f in fields(Hits)),
        )  # fmt: skip
        return out

    @staticmethod
    def _embree_closest(group) -> bool:
        """Does the fused path answer this group's closest hits itself (an untextured Embree mesh)?"""
        from .mesh_blas import EmbreeMeshBLAS

        return type(group.blas) is EmbreeMeshBLAS and not group.blas.textured

    def intersect_fused(self, rays: Rays, groups) -> Hits | None:
        """Closest hits of a scene with at least one untextured `EmbreeMeshBLAS` group (else None).
        Per such group, one parallel pass does the broad phase, the object-space mapping
        and Embree's preparation (one-instance groups; pairs from `candidate_pairs` otherwise),
        Embree answers, and only (t, triangle, u, v, instance) is merged; hit attributes are
        computed once, for each ray's final hit (`BLAS.intersect` computes them for every ray of
        every group, and merging copies them). Other groups (neural models, textured meshes) take
        their group-by-group step (`intersect_group`) in their turn, merged into the same records.
        The same float32 operations as the group-by-group stages: the same Hits."""
        from .mesh_blas_kernels import embree_workers

        embree = [self._embree_closest(g) for g in groups]
        if not self.fused_meshes or not any(embree):
            return None
        n = len(rays)
        o, d, t_min, t_max = (x.detach().contiguous().numpy() for x in (rays.origins, rays.directions, rays.t_min, rays.t_max))
        out = Hits.uninitialized(n)
        # The running best t and winning instance are the output's own columns: a model's merged
        # answer (complete records) and Embree's raw answers (finished below) share them.
        best_t, best_instance = out.t.numpy(), out.instance_id.numpy()
        best_t.fill(np.inf)
        best_instance.fill(-1)
        best_prim = np.full(n, -1, np.int32)
        best_u, best_v = np.empty(n, np.float32), np.empty(n, np.float32)
        for gi, group in enumerate(groups):
            blas, ids, has_best = group.blas, group.instance_ids.numpy(), gi > 0
            if not embree[gi]:
                t_limit = rays.t_max if not has_best else torch.minimum(rays.t_max, out.t)
                intersect_group(self, rays, group, t_limit, None, out)  # merges into out (as a previous best)
                continue
            if ids.shape[0] == 1:
                k = int(ids[0])
                with numba_threads(blas.threads):
                    kernels.instance_closest_hits(blas.scene_handle, embree_workers(n), o, d, t_min, t_max, has_best,
                                                  self._box_lo[k:k + 1], self._box_hi[k:k + 1], self._world_to_object[k],
                                                  bool(self._is_identity[k]), k, best_t, best_prim, best_u, best_v,
                                                  best_instance)  # fmt: skip
                continue
            t_limit = torch.from_numpy(t_max if not has_best else np.minimum(t_max, best_t))
            ray_idx, inst_idx, _ = self.candidate_pairs(rays, group.instance_ids, t_limit, None)
            if ray_idx is None or ray_idx.numel() == 0:  # (candidate_pairs gives pairs for groups of several instances)
                continue
            ray_np, inst_np, limit = ray_idx.numpy(), inst_idx.contiguous().numpy(), t_limit.numpy()
            p = ray_np.shape[0]
            so, sd, tfar, pair = np.empty((p, 3), np.float32), np.empty((p, 3), np.float32), np.empty(p, np.float32), np.empty(p, np.int64)
            count = kernels.pair_embree_rays(o, d, t_min, limit, ray_np, inst_np, self._world_to_object, self._is_identity,
                                             so, sd, tfar, pair)  # fmt: skip
            prim, tfar_out, u, v = blas.trace_closest(so[:count], sd[:count], tfar[:count])
            kernels.merge_pair_hits(pair[:count], prim, tfar_out, u, v, ray_np, inst_np, t_min, best_t, best_prim, best_u,
                                    best_v, best_instance)  # fmt: skip
        instance_group = np.full(len(self._is_identity), -1, np.int64)
        for gi, group in enumerate(groups):
            instance_group[group.instance_ids.numpy()] = gi
        records = [getattr(out, f.name).numpy() for f in fields(Hits)]
        first = embree.index(True)  # its pass also writes the rows of the rays that hit nothing
        for gi, group in enumerate(groups):
            if not embree[gi]:  # a model's winning rows are complete already
                continue
            with numba_threads(group.blas.threads):
                kernels.finish_hits(best_t, best_prim, best_u, best_v, best_instance, instance_group, gi, gi == first,
                                    *group.blas.surface_tables(), self._material_maps, self._world_to_object, self._is_identity,
                                    *records)  # fmt: skip
        return out

    def occluded_fused(self, rays: Rays, groups) -> Tensor | None:
        """`intersect_fused` for shadow rays, for scenes with at least one `EmbreeMeshBLAS` group:
        per such group, one parallel pass does the broad phase (rays already blocked drop out),
        the mapping and Embree's preparation, then Embree's occlusion query marks the blocked
        rays; other groups take their group-by-group step (`occluded_group`). The same answers as
        the group-by-group stages."""
        from .mesh_blas import EmbreeMeshBLAS
        from .mesh_blas_kernels import embree_workers

        embree = [type(g.blas) is EmbreeMeshBLAS for g in groups]
        if not self.fused_meshes or not any(embree):
            return None
        n = len(rays)
        o, d, t_min, t_max = (x.detach().contiguous().numpy() for x in (rays.origins, rays.directions, rays.t_min, rays.t_max))
        blocked = np.zeros(n, np.bool_)
        for gi, group in enumerate(groups):
            blas, ids = group.blas, group.instance_ids.numpy()
            if not embree[gi]:
                blocked = occluded_group(self, rays, group, None, torch.from_numpy(blocked)).numpy()
                continue
            if ids.shape[0] == 1:
                k = int(ids[0])
                with numba_threads(blas.threads):
                    kernels.instance_occluded(blas.scene_handle, embree_workers(n), o, d, t_min, t_max, blocked,
                                              self._box_lo[k:k + 1], self._box_hi[k:k + 1], self._world_to_object[k],
                                              bool(self._is_identity[k]))  # fmt: skip
                continue
            t_limit = torch.from_numpy(t_max if gi == 0 else np.where(blocked, np.float32(-np.inf), t_max))
            ray_idx, inst_idx, _ = self.candidate_pairs(rays, group.instance_ids, t_limit, None)
            if ray_idx.numel() == 0:
                continue
            ray_np, inst_np = ray_idx.numpy(), inst_idx.contiguous().numpy()
            p = ray_np.shape[0]
            so, sd, tfar, pair = np.empty((p, 3), np.float32), np.empty((p, 3), np.float32), np.empty(p, np.float32), np.empty(p, np.int64)
            # The pairs' own interval (t_min, t_max), as the group-by-group `occluded` passes it.
            count = kernels.pair_embree_rays(o, d, t_min, t_max, ray_np, inst_np, self._world_to_object, self._is_identity,
                                             so, sd, tfar, pair)  # fmt: skip
            kernels.mark_blocked(ray_np[pair[:count]], blas.trace_occluded(so[:count], sd[:count], tfar[:count]), blocked)
        return torch.from_numpy(blocked)

    def merge_pairs(self, best: Hits, local: Hits, ray_idx: Tensor, inst_idx: Tensor) -> Hits:
        kernels.merge_pairs(
            ray_idx.contiguous().numpy(), inst_idx.contiguous().numpy(),
            *(getattr(local, f.name).detach().contiguous().numpy() for f in fields(Hits) if f.name != "instance_id"),
            self._material_maps, self._world_to_object, self._is_identity,
            *(getattr(best, f.name).numpy() for f in fields(Hits)),
        )  # fmt: skip
        return best


def stages_for(table: InstanceTable) -> NumbaTLASStages | TorchTLASStages:
    """The implementation for the table's device: numba on the CPU, torch elsewhere."""
    return NumbaTLASStages(table) if table.box_lo.device.type == "cpu" else TorchTLASStages(table)

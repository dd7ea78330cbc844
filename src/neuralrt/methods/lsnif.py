"""LSNIF: a neural intersector for one object (Fujieda et al. 2025, Sec. 3 and 5).

Pipeline for a batch of rays in object space::

    object space --(inflated AABB -> [0,1]^3)--> unit-box rays
      --featurize_rays--> first H voxel-boundary points in ray order   (lsnif_features, numba DDA)
      --SparseHashGrid--> concatenated features [N, H*L*F]              (neural.sparse_hash_grid)
      --MLP------------> occlusion, local distance, normal, albedo, material logits
      --decode---------> Hits in object space

Rays that cross no occupied voxel are certain misses (the voxelization is exact and
conservative) and never reach the network, in training or inference. The affine map to the unit
box keeps the ray parameter ``t`` unchanged (directions are not renormalised), so the model's
distances are object-space distances.

Normals are learned in object space from targets turned to face the incoming ray (open meshes
have either side) and returned as predicted, not flipped afterwards, so an undertrained model may
return some that face away (``eval``'s ``normal_backfacing_fraction``; `Hits.normal`);
``Hits.geometric_normal`` carries the same vector.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..accel.blas import MemoryReport
from ..geometry.mesh import Mesh
from ..geometry.voxelize import pack_occupancy, unpack_occupancy, voxelize_triangles
from ..neural.mlp import MLP, padded_rows
from ..neural.sparse_hash_grid import SparseHashGrid
from ..rays import AABB, Hits, Rays
from ..training.step import StepResult
from .base import NeuralBLAS, material_table, prefixed_parameters
from .lsnif_config import LSNIFConfig
from .lsnif_loss import training_loss
from .lsnif_features import (RayFeaturePoints, featurize_rays, point_local_distances, select_network_rays, select_network_rows,
                             unit_box_rays)  # fmt: skip

__all__ = ["LSNIFConfig", "LSNIFModel", "LSNIFBLAS", "METHOD"]

METHOD = "lsnif"

# Output layout of the MLP: 8 fixed channels, then one logit per material.
_OCC, _DIST, _NORMAL, _ALBEDO, _MAT = 0, 1, slice(2, 5), slice(5, 8), 8


@dataclass
class _UnitRays:
    """Valid rays mapped into the unit box, origins moved to ``t_min`` (all on the model's device)."""

    index: Tensor  # [K] long: which rays of the batch are valid
    origins: Tensor  # [K, 3] unit-box origins
    directions: Tensor  # [K, 3] unit-box directions (not renormalised: t is unchanged)
    t_offset: Tensor  # [K] the t_min shift applied to the origins


@dataclass
class _Prepared:
    """Rays mapped to the unit box, featurized; ``active`` rows go to the network."""

    active: Tensor  # [M] long indices into the batch
    features: RayFeaturePoints  # rows of the active rays only
    t_offset: Tensor  # [M] t_min shift applied to the origins
    truncated: Tensor  # scalar: valid rays with more boundary points than H
    origins: Tensor  # [M, 3] unit-box origins (moved to t_min) of the active rays
    directions: Tensor  # [M, 3] unit-box directions of the active rays
    distances: Tensor | None = None  # [M, H] `point_local_distances` (with ``features.point_distances``)


@dataclass
class _TrainingRows:
    """What a training step needs of its batch before the network (`LSNIFModel.prepare_training_batch`):
    the batch's voxel-boundary points and, for the rays that reach the network, their index into
    the points and the batch, t shift, box interval and point distances."""

    features: RayFeaturePoints  # every valid ray's points (the encoder reads rows ``keep``)
    keep: Tensor  # [M] long: the network rays' rows of ``features``
    active: Tensor  # [M] long: the network rays' indices into the batch
    t_offset: Tensor  # [M]
    t_enter: Tensor  # [M]
    t_exit: Tensor  # [M]
    distances: Tensor | None  # [M, H] point distances (with ``features.point_distances``)
    truncated: Tensor  # scalar: valid rays with more boundary points than H


class LSNIFModel(NeuralBLAS):
    """A trained (or training) LSNIF for one object; implements the `BLAS` protocol.

    Args:
        config: the full configuration (`LSNIFConfig.preset("hq")` by default).
        bounds: the object's tight AABB in object space.
        occupancy: [V, V, V] bool occupancy over the inflated box.
        materials: the material table, ``[{"name": str, "base_color": [r, g, b]}, ...]``.
    """

    METHOD: ClassVar[str] = METHOD
    TITLE: ClassVar[str] = "LSNIF"
    CONFIG: ClassVar[type[LSNIFConfig]] = LSNIFConfig

    def __init__(self, config: LSNIFConfig, bounds: AABB, occupancy: Tensor | np.ndarray, materials: list[dict] | None = None):
        super().__init__(config, bounds, materials)
        box = self.bounds.inflated(config.voxel.box_inflation)
        # Never flat: a planar object still gets a box with thickness.
        pad = torch.clamp(1e-3 * max(box.diagonal, 1e-12) - box.extent, min=0) * 0.5
        self.register_buffer("box_lo", (box.lo - pad).float())
        self.register_buffer("box_hi", (box.hi + pad).float())
        occ = torch.as_tensor(np.asarray(occupancy), dtype=torch.bool)
        v = config.voxel.resolution
        if occ.shape != (v, v, v):
            raise ValueError(f"occupancy has shape {tuple(occ.shape)}, expected ({v}, {v}, {v})")
        self.register_buffer("occupancy", occ)
        learned = self._learned_modules(config, self.num_materials)
        self.encoder, self.network = learned["encoder"], learned["network"]
        # Training: the encoder reads the network rays through their index (True) or a copy of their
        # points is made first (False: the earlier path, kept to measure against); not stored in models.
        self.training_rows_by_index = True
        # CPU featurization (training, `_prepare`) from the 16-lane float32 walk the fused pass
        # walks, where it applies (`lsnif_features_simd.applies`): the points inference encodes,
        # in a third of the float64 walk's time. False: the float64 walk; not stored in models.
        self.float32_walk = True

    # -- construction ----------------------------------------------------------------------------
    @classmethod
    def _learned_modules(cls, config: LSNIFConfig, num_materials: int) -> dict[str, nn.Module]:
        enc, net = config.encoding, config.network
        encoder = SparseHashGrid(
            resolutions=tuple(enc.resolutions), features_per_level=enc.features_per_level,
            log2_table_size=enc.log2_table_size, init_scale=enc.init_scale, seed=config.training.seed,
        )
        network = MLP(
            _network_inputs(config, encoder), 8 + num_materials, net.hidden_width, net.hidden_layers, net.leaky_relu_slope,
            generator=torch.Generator().manual_seed(config.training.seed),
        )
        return {"encoder": encoder, "network": network}

    @classmethod
    def from_mesh(cls, mesh: Mesh, config: LSNIFConfig | None = None) -> "LSNIFModel":
        """An untrained model for ``mesh``: box, exact voxelization, material table."""
        config = config or LSNIFConfig.preset("hq")
        lo, hi = mesh.bounds
        bounds = AABB(torch.as_tensor(np.array(lo, copy=True)), torch.as_tensor(np.array(hi, copy=True)))
        model = cls(config, bounds, np.zeros((config.voxel.resolution,) * 3, bool), material_table(mesh))
        unit = (mesh.triangles().astype(np.float64) - model.box_lo.double().numpy()) / model.box_extent.double().numpy()
        model.occupancy.copy_(torch.from_numpy(voxelize_triangles(unit, config.voxel.resolution)))
        model._remember_mesh(mesh)
        return model

    @classmethod
    def _from_arrays(cls, config: LSNIFConfig, bounds: AABB, materials: list[dict], arrays: dict[str, Tensor]) -> "LSNIFModel":
        occ = unpack_occupancy(arrays["occupancy_bits"].numpy(), config.voxel.resolution)
        model = cls(config, bounds, occ, materials)
        cls._load_parameters(model._stored_parameters(), arrays)
        return model

    # -- properties ----------------------------------------------------------------------------------
    @property
    def box(self) -> AABB:
        """The inflated box the model lives in (object space)."""
        return AABB(self.box_lo, self.box_hi)

    @property
    def box_extent(self) -> Tensor:
        return self.box_hi - self.box_lo

    def _unit_rays(self, rays: Rays) -> _UnitRays:
        """The one map from object space to the unit box: ``(p - box_lo) / box_extent`` (t unchanged)."""
        return _UnitRays(*unit_box_rays(rays, self.box_lo, self.box_extent))

    # -- featurization -----------------------------------------------------------------------------
    def _prepare(self, rays: Rays) -> _Prepared:
        """Map valid rays to the unit box (origins moved to t_min) and featurize them, on the model's device."""
        unit = self._unit_rays(rays)
        fp = self._featurize(unit.origins, unit.directions)
        keep, kept, origins, directions, distances = select_network_rays(fp, unit.origins, unit.directions, self.config.features.point_distances)
        return _Prepared(unit.index[keep], kept, unit.t_offset[keep], fp.truncated.sum(), origins, directions, distances)

    def _featurize(self, origins: Tensor, directions: Tensor) -> RayFeaturePoints:
        from . import lsnif_features_simd

        fc = self.config.features
        simd = self.float32_walk and origins.device.type == "cpu" and lsnif_features_simd.applies(self.occupancy.shape[0])
        featurize = lsnif_features_simd.featurize_rays_simd if simd else featurize_rays
        return featurize(
            origins, directions, self.occupancy, fc.max_points,
            origin_point=fc.origin_point, share_boundary_points=fc.share_boundary_points,
        )

    @property
    def network_inputs(self) -> int:
        """MLP input width: H*L*F encoded features (+ H point distances with ``features.point_distances``)."""
        return _network_inputs(self.config, self.encoder)

    def network_input(self, prep: _Prepared, dtype: torch.dtype = torch.float32) -> Tensor:
        """[M, network_inputs] in ``dtype``: encoded features of the active rays' points, in ray order."""
        fp = prep.features
        distances = None
        if self.config.features.point_distances:
            distances = prep.distances if prep.distances is not None else point_local_distances(fp, prep.origins, prep.directions)
        return self.encoder(fp.points, fp.face_axis, distances, dtype)

    def _raw_outputs(self, prep: _Prepared, compute_dtype: torch.dtype) -> Tensor:
        return self.network(self.network_input(prep), compute_dtype)

    # -- training ------------------------------------------------------------------------------------
    def prepare_training_batch(self, rays: Rays) -> _TrainingRows | None:
        """The unit-box map, the voxel walk and the network rays' selection of a batch: they depend on
        the batch, the box and the occupancy alone, so the training loop computes them with the
        batch on its drawing thread (None on the earlier copy-the-points path)."""
        return self._training_rows(rays)

    def _training_rows(self, rays: Rays) -> _TrainingRows | None:
        if not self.training_rows_by_index:
            return None
        unit = self._unit_rays(rays)
        fp = self._featurize(unit.origins, unit.directions)
        keep, t_enter, t_exit, distances = select_network_rows(fp, unit.origins, unit.directions, self.config.features.point_distances)
        return _TrainingRows(fp, keep, unit.index[keep], unit.t_offset[keep], t_enter, t_exit, distances, fp.truncated.sum())

    def training_step(self, rays: Rays, truth: Hits, prepared: _TrainingRows | None = None) -> StepResult:
        """Loss of one batch against exact hits (paper Sec. 5.3); certain misses are skipped.
        ``prepared``: `prepare_training_batch` of these rays, when the loop computed it ahead."""
        n = len(rays)
        dtype = self.compute_dtype(training=True)
        rows = prepared if prepared is not None else self._training_rows(rays)
        if rows is not None:
            # The encoder reads the network rays' points through their index: no copy of the batch's points.
            active, t_offset, truncated, t_enter, t_exit = rows.active, rows.t_offset, rows.truncated, rows.t_enter, rows.t_exit
            # The encoder writes the GEMMs' zero padding rows too (`padded_rows`): the MLP copies nothing.
            features = self.encoder(rows.features.points, rows.features.face_axis, rows.distances, dtype, rows=rows.keep,
                                    out_rows=padded_rows(len(rows.keep), rows.keep.device))  # fmt: skip
        else:  # the network rays' points copied first (`_prepare`), kept to measure against
            prep = self._prepare(rays)
            active, t_offset, truncated = prep.active, prep.t_offset, prep.truncated
            t_enter, t_exit = prep.features.t_enter, prep.features.t_exit
            features = self.network_input(prep, dtype)
        # The encoder hands the MLP its input in the hidden layers' dtype (bf16 on the CPU: written so,
        # no cast); the loss runs the output layer (on the CPU in the same pass as the loss terms).
        hidden = self.network.hidden_forward(features, dtype)
        terms = training_loss(hidden, self.network.output, active, t_offset, t_enter, t_exit, rays.directions,
                              truth, self.config.loss, self.num_materials, _logit(self.config.inference.occlusion_threshold),
                              truncated)  # fmt: skip
        correct = n - terms.wrong_network - terms.missed_outside
        return StepResult(terms.loss, terms.parts, correct, n, len(active), {"truncated": terms.truncated})

    # -- inference ---------------------------------------------------------------------------------
    def rays_per_chunk(self, device: torch.device) -> int:
        """``inference.chunk_size``; on the CPU's fused pass `lsnif_fused_cpu.rays_per_chunk` of it
        (at least 2^17 rays per thread, up to 2^18)."""
        from . import lsnif_fused_cpu

        chunk = super().rays_per_chunk(device)
        if device.type == "cpu" and lsnif_fused_cpu.WRITE_HITS:
            return lsnif_fused_cpu.rays_per_chunk(chunk)
        return chunk

    def _chunk_records(self, n: int, device: torch.device) -> Hits:
        """Uninitialised records where the CPU's fused pass writes every row (`lsnif_fused_cpu.fused_hits_cpu`;
        a fill of 73 bytes a ray before the pass took ~5% of a 2^17-ray `intersect`), else all misses."""
        from . import lsnif_fused_cpu

        if torch.device(device).type == "cpu" and lsnif_fused_cpu.WRITE_HITS:
            return Hits.uninitialized(n, device)
        return Hits.empty(n, device)

    def _intersect_chunk(self, rays: Rays) -> Hits:
        hits = self._chunk_records(len(rays), rays.device)
        self._intersect_chunk_into(rays, hits)
        return hits

    def _intersect_chunk_into(self, rays: Rays, hits: Hits) -> None:
        """The chunk's answers written into ``hits`` (`_chunk_records`, possibly views of a larger batch's rows)."""
        if self._network_answers_as_hits(rays, hits):  # where a fused pass decodes the hits itself (CPU, CUDA)
            return
        act, out, t_enter, t_exit, t_offset = self._network_answers(rays)
        if len(act) == 0:
            return
        t = t_offset + t_enter + torch.sigmoid(out[:, _DIST]) * (t_exit - t_enter)
        hit = (out[:, _OCC] > _logit(self.config.inference.occlusion_threshold)) & (t <= rays.t_max[act]) & (t >= rays.t_min[act])
        normal = F.normalize(out[:, _NORMAL], dim=-1)
        hits.hit[act] = hit
        hits.t[act] = torch.where(hit, t, torch.full_like(t, float("inf")))
        normal = normal * hit[:, None]
        hits.normal[act] = normal
        hits.geometric_normal[act] = normal
        hits.albedo[act] = torch.where(hit[:, None], torch.sigmoid(out[:, _ALBEDO]), hits.albedo[act])
        material = out[:, _MAT:].argmax(-1) if self.num_materials > 1 else torch.zeros_like(act)
        hits.material_id[act] = torch.where(hit, material, torch.full_like(material, -1))

    def _network_answers(self, rays: Rays) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """(indices, raw outputs, t_enter, t_exit, t_offset) of the rays that reach the network, from
        one fused pass per chunk (walk + encoding (+ first layer) per ray): a Triton kernel on CUDA
        (`lsnif_fused`), a numba kernel on the CPU (`lsnif_fused_cpu`); elsewhere featurize -> encode -> MLP."""
        answer = {"cuda": self._network_answers_fused, "cpu": self._network_answers_fused_cpu}.get(rays.device.type)
        if answer is not None:
            return answer(rays)
        return self._network_answers_unfused(rays)

    def _network_answers_unfused(self, rays: Rays) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        prep = self._prepare(rays)
        out = self._raw_outputs(prep, self.compute_dtype())
        return prep.active, out, prep.features.t_enter, prep.features.t_exit, prep.t_offset

    def _network_answers_fused_cpu(self, rays: Rays) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        from .lsnif_fused_cpu import fused_network_outputs_cpu

        unit = self._unit_rays(rays)
        fc = self.config.features
        fused = fused_network_outputs_cpu(
            unit.origins, unit.directions, self.occupancy, self.encoder, self.network,
            max_points=fc.max_points, origin_point=fc.origin_point, share_boundary_points=fc.share_boundary_points,
            point_distances=fc.point_distances, compute_dtype=self.compute_dtype(),
        )  # fmt: skip
        act = fused.active
        return unit.index[act], fused.values, fused.t_enter[act], fused.t_exit[act], unit.t_offset[act]

    def _network_answers_fused(self, rays: Rays) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        from .lsnif_fused import fused_network_outputs  # imports triton: CUDA only

        unit = self._unit_rays(rays)
        fc = self.config.features
        fused = fused_network_outputs(
            unit.origins, unit.directions, self.occupancy, self.encoder, self.network,
            max_points=fc.max_points, origin_point=fc.origin_point, share_boundary_points=fc.share_boundary_points,
            point_distances=fc.point_distances, compute_dtype=self.compute_dtype(),
        )  # fmt: skip
        keep = torch.nonzero(fused.count > 0).squeeze(1)
        return unit.index[keep], fused.values[keep], fused.t_enter[keep], fused.t_exit[keep], unit.t_offset[keep]

    def _network_answers_as_hits(self, rays: Rays, hits: Hits) -> bool:
        """Where a fused pass decodes the hits itself (CUDA with ``lsnif_fused.DEFAULT_LAUNCH
        ["write_hits"]``, the CPU with ``lsnif_fused_cpu.WRITE_HITS``), it writes the chunk's
        answers into ``hits``; returns whether it did."""
        if rays.device.type == "cpu":
            from . import lsnif_fused_cpu

            if not lsnif_fused_cpu.WRITE_HITS:
                return False
            self._network_answers_fused_cpu_hits(rays, hits)
            return True
        if rays.device.type != "cuda":
            return False
        from .lsnif_fused import DEFAULT_LAUNCH  # imports triton: CUDA only

        if not DEFAULT_LAUNCH["write_hits"]:
            return False
        self._network_answers_fused_hits(rays, hits)
        return True

    def _fused_cpu_arguments(self, rays: Rays) -> tuple[tuple, dict]:
        """The arguments `lsnif_fused_cpu.fused_hits_cpu` / `fused_occluded_cpu` share for a chunk
        (the pass maps the rays into the unit box itself, as `_unit_rays`)."""
        fc = self.config.features
        return (rays.origins, rays.directions, self.occupancy, self.encoder, self.network), dict(
            box_lo=self.box_lo, box_extent=self.box_extent, t_min=rays.t_min, t_max=rays.t_max,
            occlusion_logit=_logit(self.config.inference.occlusion_threshold),
            max_points=fc.max_points, origin_point=fc.origin_point, share_boundary_points=fc.share_boundary_points,
            point_distances=fc.point_distances, compute_dtype=self.compute_dtype(),
        )  # fmt: skip

    def _network_answers_fused_cpu_hits(self, rays: Rays, hits: Hits) -> None:
        """The decoded answers of `_intersect_chunk`, written into ``hits`` by `lsnif_fused_cpu.fused_hits_cpu`."""
        from .lsnif_fused_cpu import fused_hits_cpu

        args, kwargs = self._fused_cpu_arguments(rays)
        fused_hits_cpu(*args, hits=hits, num_materials=self.num_materials, **kwargs)

    @torch.no_grad()
    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: the model predicts a hit within [t_min, t_max], the same decision as
        `intersect`. On the CPU (``lsnif_fused_cpu.WRITE_HITS``) only that decision is decoded
        (`lsnif_fused_cpu.fused_occluded_cpu`: no normals, albedo or materials)."""
        from . import lsnif_fused_cpu

        self._check_device(rays)
        if rays.device.type != "cpu" or not lsnif_fused_cpu.WRITE_HITS:
            return super().occluded(rays)
        n = len(rays)
        hit = torch.empty(n, dtype=torch.bool)  # (the pass writes every row)
        chunk = self.rays_per_chunk(rays.device)
        for start in range(0, n, chunk):
            part = rays if n <= chunk else rays[slice(start, start + chunk)]
            args, kwargs = self._fused_cpu_arguments(part)
            lsnif_fused_cpu.fused_occluded_cpu(*args, hit=hit[start : start + len(part)], **kwargs)
        return hit

    def _network_answers_fused_hits(self, rays: Rays, hits: Hits) -> None:
        """The decoded answers of `_intersect_chunk`, written into ``hits`` by `lsnif_fused.fused_hits`."""
        from .lsnif_fused import fused_hits  # imports triton: CUDA only

        unit = self._unit_rays(rays)
        fc = self.config.features
        fused_hits(
            unit.origins, unit.directions, self.occupancy, self.encoder, self.network,
            index=unit.index, t_offset=unit.t_offset, t_min=rays.t_min, t_max=rays.t_max, hits=hits,
            occlusion_logit=_logit(self.config.inference.occlusion_threshold), num_materials=self.num_materials,
            max_points=fc.max_points, origin_point=fc.origin_point, share_boundary_points=fc.share_boundary_points,
            point_distances=fc.point_distances, compute_dtype=self.compute_dtype(),
        )  # fmt: skip

    @torch.no_grad()
    def feature_statistics(self, rays: Rays, truth: Hits) -> dict:
        """How the H-point cut-off and the voxel skip behave on ``rays`` with exact hits ``truth``.

        ``network_fraction``: rays that cross an occupied voxel (the rest skip the network);
        ``truncated_fraction``: of those, rays with more boundary points than H;
        ``hit_beyond_last_point_fraction``: of those, rays whose exact hit lies past the last kept
        point (unlearnable from the features); ``hit_in_skipped_rays``: exact hits on rays that
        skipped the network (0 when the voxelization is conservative).
        """
        self._check_device(rays)
        unit = self._unit_rays(rays)
        o, d = unit.origins, unit.directions
        fp = self._featurize(o, d)
        hit = truth.hit[unit.index]
        t_true = truth.t[unit.index] - unit.t_offset
        net = fp.count > 0
        last = fp.points[torch.arange(len(fp.count), device=o.device), (fp.count.long() - 1).clamp(min=0)]
        t_last = ((last - o) * d).sum(-1) / (d * d).sum(-1).clamp(min=1e-30)
        beyond = hit & net & fp.truncated & (t_true > t_last)
        n_net, n_valid = int(net.sum()), len(unit.index)
        return {
            "rays": n_valid,
            "network_fraction": n_net / max(n_valid, 1),
            "truncated_fraction": float((fp.truncated & net).sum()) / max(n_net, 1),
            "hit_beyond_last_point_fraction": float(beyond.sum()) / max(n_net, 1),
            "hit_in_skipped_rays": int((hit & ~net).sum()),
            "mean_points": float(fp.count[net].float().mean()) if n_net else 0.0,
        }

    # -- memory and files ------------------------------------------------------------------------------
    def memory_bytes(self) -> MemoryReport:
        """Run-time bytes at the storage precision: voxel bits, hash tables, MLP weights and biases."""
        v = self.config.voxel.resolution
        return MemoryReport({
            "voxels": (v**3 + 7) // 8,
            "encoder": self.encoder.table.numel() * self.storage_bytes,
            "mlp": self.parameter_bytes(self.network),
        })

    def _stored_parameters(self) -> dict[str, torch.nn.Parameter]:
        return prefixed_parameters({"encoder": self.encoder, "network": self.network})

    def _arrays(self) -> dict[str, Tensor]:
        occupancy_bits = torch.from_numpy(pack_occupancy(self.occupancy.cpu().numpy()))
        return {"occupancy_bits": occupancy_bits, **self._stored(self._stored_parameters())}

    def __repr__(self) -> str:
        c = self.config
        return (
            f"LSNIFModel({self.mesh_name!r}, V={c.voxel.resolution}, H={c.features.max_points}, "
            f"mlp={c.network.hidden_layers}x{c.network.hidden_width}, {self.memory_bytes().total} bytes)"
        )


# LSNIFModel already is a BLAS (bounds, secondary_offset, intersect, occluded, memory_bytes).
LSNIFBLAS = LSNIFModel


def _network_inputs(config: LSNIFConfig, encoder: SparseHashGrid) -> int:
    h = config.features.max_points
    return encoder.output_dim(h) + (h if config.features.point_distances else 0)


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))

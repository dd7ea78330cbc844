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

Normals are learned and returned in object space, turned to face the incoming ray (open meshes
have either side); ``Hits.geometric_normal`` carries the same vector.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..accel.blas import MemoryReport
from ..errors import ModelFileError
from ..geometry.mesh import Mesh
from ..geometry.voxelize import pack_occupancy, unpack_occupancy, voxelize_triangles
from ..io.model_file import read_model_file, write_model_file
from ..neural.sparse_hash_grid import SparseHashGrid
from ..rays import AABB, Hits, Rays, valid_ray_mask
from .lsnif_config import LSNIFConfig
from .lsnif_features import RayFeaturePoints, featurize_rays

__all__ = ["LSNIFConfig", "LSNIFModel", "LSNIFBLAS", "LSNIFNetwork", "StepResult", "METHOD", "cpu_has_native_bf16"]

METHOD = "lsnif"
_BYTES = {"fp16": 2, "fp32": 4}
_DTYPES = {"fp16": torch.float16, "fp32": torch.float32}

# Output layout of the MLP: 8 fixed channels, then one logit per material.
_OCC, _DIST, _NORMAL, _ALBEDO, _MAT = 0, 1, slice(2, 5), slice(5, 8), 8


def cpu_has_native_bf16() -> bool:
    """Whether this CPU does bf16 arithmetic natively (AVX512-BF16 or AMX): then bf16 matmul pays off."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = f.read()
    except OSError:
        return False
    return " avx512_bf16" in flags or " amx_bf16" in flags


class LSNIFNetwork(nn.Module):
    """The paper's MLP: ``hidden_layers`` leaky-ReLU layers of ``hidden_width``, Kaiming init, linear output."""

    def __init__(self, in_features: int, out_features: int, hidden_width: int = 128, hidden_layers: int = 2, slope: float = 0.01,
                 generator: torch.Generator | None = None):
        super().__init__()
        widths = [in_features] + [hidden_width] * hidden_layers
        self.hidden = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.output = nn.Linear(widths[-1], out_features)
        self.slope = slope
        for layer in self.hidden:
            nn.init.kaiming_uniform_(layer.weight, a=slope, nonlinearity="leaky_relu", generator=generator)
            nn.init.zeros_(layer.bias)
        nn.init.kaiming_uniform_(self.output.weight, a=1.0, nonlinearity="linear", generator=generator)
        nn.init.zeros_(self.output.bias)

    def forward(self, x: Tensor, compute_dtype: torch.dtype = torch.float32) -> Tensor:
        """Outputs in fp32. With ``compute_dtype=torch.bfloat16`` the hidden layers run in bf16
        (about 2x faster on CPUs with native bf16); the small output layer always runs in fp32,
        so the distance output keeps fp32 resolution."""
        if compute_dtype != torch.float32 and not torch.is_grad_enabled():
            # Inference: reuse bf16 copies of the weights instead of casting them every call.
            x = x.to(compute_dtype)
            for w, b in self._cast_weights(compute_dtype):
                x = F.leaky_relu(F.linear(x, w, b), self.slope)
            return self.output(x.float())
        with torch.autocast(device_type=x.device.type, dtype=compute_dtype, enabled=compute_dtype != torch.float32):
            for layer in self.hidden:
                x = F.leaky_relu(layer(x), self.slope)
        return self.output(x.float())

    def _cast_weights(self, dtype: torch.dtype) -> list[tuple[Tensor, Tensor]]:
        # Keyed on each parameter's storage and version counter: any update (optimizer step,
        # load, rounding) invalidates the copies.
        key = (dtype, tuple((p.data_ptr(), p._version) for p in self.hidden.parameters()))
        if getattr(self, "_cast_key", None) != key:
            self._cast = [(layer.weight.detach().to(dtype), layer.bias.detach().to(dtype)) for layer in self.hidden]
            self._cast_key = key
        return self._cast


@dataclass
class StepResult:
    """One training step's loss and statistics (over all rays of the batch)."""

    loss: Tensor
    parts: dict[str, float] = field(default_factory=dict)
    correct: int = 0  # rays whose hit/miss the model gets right (certain misses count as right)
    count: int = 0  # rays in the batch
    network_rays: int = 0  # rays that reached the network
    truncated: int = 0  # rays with more boundary points than H


@dataclass
class _Prepared:
    """Rays mapped to the unit box, featurized; ``active`` rows go to the network."""

    active: Tensor  # [M] long indices into the batch
    features: RayFeaturePoints  # rows of the active rays only
    t_offset: Tensor  # [M] t_min shift applied to the origins
    truncated_total: int
    origins: Tensor  # [M, 3] unit-box origins (moved to t_min) of the active rays, CPU
    directions: Tensor  # [M, 3] unit-box directions of the active rays, CPU


class LSNIFModel(nn.Module):
    """A trained (or training) LSNIF for one object; implements the `BLAS` protocol.

    Args:
        config: the full configuration (`LSNIFConfig.preset("hq")` by default).
        bounds: the object's tight AABB in object space.
        occupancy: [V, V, V] bool occupancy over the inflated box.
        materials: the material table, ``[{"name": str, "base_color": [r, g, b]}, ...]``.
    """

    def __init__(self, config: LSNIFConfig, bounds: AABB, occupancy: Tensor | np.ndarray, materials: list[dict] | None = None):
        super().__init__()
        self.config = config
        self.materials = list(materials) if materials else [{"name": "default", "base_color": [1.0, 1.0, 1.0]}]
        self.training_record: dict = {}
        self.mesh_hash: str | None = None
        self.mesh_name: str | None = None
        lo, hi = bounds.lo.float().cpu(), bounds.hi.float().cpu()
        self.bounds = AABB(lo, hi)
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
        enc = config.encoding
        self.encoder = SparseHashGrid(
            resolutions=tuple(enc.resolutions), features_per_level=enc.features_per_level,
            log2_table_size=enc.log2_table_size, init_scale=enc.init_scale, seed=config.training.seed,
        )
        net = config.network
        self.network = LSNIFNetwork(
            self.network_inputs, 8 + self.num_materials, net.hidden_width, net.hidden_layers, net.leaky_relu_slope,
            generator=torch.Generator().manual_seed(config.training.seed),
        )
        self._occupancy_np: np.ndarray | None = None
        self._occupancy_key = None

    # -- construction ----------------------------------------------------------------------------
    @staticmethod
    def from_mesh(mesh: Mesh, config: LSNIFConfig | None = None) -> "LSNIFModel":
        """An untrained model for ``mesh``: box, exact voxelization, material table."""
        config = config or LSNIFConfig.preset("hq")
        lo, hi = mesh.bounds
        bounds = AABB(torch.from_numpy(lo.copy()), torch.from_numpy(hi.copy()))
        model = LSNIFModel(config, bounds, np.zeros((config.voxel.resolution,) * 3, bool), _material_table(mesh))
        unit = (mesh.triangles().astype(np.float64) - model.box_lo.double().numpy()) / model.box_extent.double().numpy()
        model.occupancy.copy_(torch.from_numpy(voxelize_triangles(unit, config.voxel.resolution)))
        model.mesh_hash, model.mesh_name = mesh.content_hash(), mesh.name
        return model

    # -- properties ----------------------------------------------------------------------------------
    @property
    def num_materials(self) -> int:
        return len(self.materials)

    @property
    def box(self) -> AABB:
        """The inflated box the model lives in (object space)."""
        return AABB(self.box_lo, self.box_hi)

    @property
    def box_extent(self) -> Tensor:
        return self.box_hi - self.box_lo

    @property
    def secondary_offset(self) -> float:
        """Origin offset (object-space units, along the normal) for rays leaving a neural hit."""
        return float(self.config.inference.secondary_offset * self.box.diagonal)

    @property
    def device(self) -> torch.device:
        return self.box_lo.device

    def _occupancy_cpu(self) -> np.ndarray:
        """The occupancy as a contiguous numpy array for the CPU kernels (re-made if the buffer changed)."""
        key = (self.occupancy.data_ptr(), self.occupancy._version)
        if self._occupancy_np is None or self._occupancy_key != key:
            self._occupancy_np = np.ascontiguousarray(self.occupancy.cpu().numpy())
            self._occupancy_key = key
        return self._occupancy_np

    # -- featurization -----------------------------------------------------------------------------
    def _prepare(self, rays: Rays) -> _Prepared:
        """Map valid rays to the unit box (origins moved to t_min) and featurize them on the CPU."""
        valid = valid_ray_mask(rays)
        t_off = torch.where(torch.isfinite(rays.t_min) & (rays.t_min > 0), rays.t_min, torch.zeros_like(rays.t_min))
        lo, ext = self.box_lo.to(rays.device), self.box_extent.to(rays.device)
        o = (rays.origins + t_off[:, None] * rays.directions - lo) / ext
        d = rays.directions / ext
        idx = torch.nonzero(valid).squeeze(1)
        o, d = o[idx].cpu().contiguous(), d[idx].cpu().contiguous()
        fp = self._featurize(o, d)
        keep = torch.nonzero(fp.count > 0).squeeze(1)
        truncated = int(fp.truncated.sum())
        active = idx[keep.to(idx.device)]
        return _Prepared(active, fp[keep], t_off[active], truncated, o[keep], d[keep])

    def _featurize(self, origins: Tensor, directions: Tensor) -> RayFeaturePoints:
        fc = self.config.features
        return featurize_rays(
            origins, directions, self._occupancy_cpu(), fc.max_points,
            origin_point=fc.origin_point, share_boundary_points=fc.share_boundary_points,
        )

    @property
    def network_inputs(self) -> int:
        """MLP input width: H*L*F encoded features (+ H point distances with ``features.point_distances``)."""
        h = self.config.features.max_points
        return self.encoder.output_dim(h) + (h if self.config.features.point_distances else 0)

    def network_input(self, prep: _Prepared) -> Tensor:
        """[M, network_inputs]: encoded features of the active rays' points, in ray order."""
        dev, fp = self.device, prep.features
        x = self.encoder(fp.points.to(dev), fp.face_axis.to(dev))
        if self.config.features.point_distances:
            x = torch.cat([x, point_local_distances(fp, prep.origins, prep.directions).to(dev)], dim=1)
        return x

    def _raw_outputs(self, prep: _Prepared, compute_dtype: torch.dtype) -> Tensor:
        return self.network(self.network_input(prep), compute_dtype)

    def _compute_dtype(self, training: bool = False) -> torch.dtype:
        choice = (self.config.training if training else self.config.inference).compute_precision
        if choice == "auto":
            return torch.bfloat16 if (self.device.type == "cuda" or cpu_has_native_bf16()) else torch.float32
        return torch.bfloat16 if choice == "bf16" else torch.float32

    # -- training ------------------------------------------------------------------------------------
    def training_step(self, rays: Rays, truth: Hits) -> StepResult:
        """Loss of one batch against exact hits (paper Sec. 5.3); certain misses are skipped."""
        n = len(rays)
        prep = self._prepare(rays)
        fp, act = prep.features, prep.active
        dev = self.device
        out = self._raw_outputs(prep, self._compute_dtype(training=True))
        tr = truth[act.to(truth.hit.device)].to(dev)
        hit = tr.hit
        w = self.config.loss
        occ_loss = F.binary_cross_entropy_with_logits(out[:, _OCC], hit.float()) if len(act) else out.sum() * 0
        loss = w.occlusion * occ_loss
        parts = {"occlusion": occ_loss.item()}
        if bool(hit.any()):
            o = out[hit]
            t_enter, t_exit = fp.t_enter.to(dev)[hit], fp.t_exit.to(dev)[hit]
            t_local = (tr.t[hit] - prep.t_offset.to(dev)[hit] - t_enter) / torch.clamp(t_exit - t_enter, min=1e-12)
            dist_loss = (torch.sigmoid(o[:, _DIST]) - t_local.clamp(0, 1)).abs().mean()
            d = rays.directions[act.to(rays.device)].to(dev)[hit]
            n_true = tr.normal[hit]
            n_true = torch.where(((n_true * d).sum(-1) > 0)[:, None], -n_true, n_true)  # face the ray
            normal_loss = (1 - F.cosine_similarity(o[:, _NORMAL], n_true, dim=-1, eps=1e-8)).mean()
            albedo = torch.sigmoid(o[:, _ALBEDO])
            albedo_loss = ((albedo - tr.albedo[hit]) ** 2 / (albedo.detach() ** 2 + 1e-2)).mean()
            loss = loss + w.distance * dist_loss + w.normal * normal_loss + w.albedo * albedo_loss
            parts.update(distance=dist_loss.item(), normal=normal_loss.item(), albedo=albedo_loss.item())
            if self.num_materials > 1:
                mat_loss = F.cross_entropy(o[:, _MAT:], tr.material_id[hit].clamp(0, self.num_materials - 1))
                loss = loss + w.material * mat_loss
                parts["material"] = mat_loss.item()
        with torch.no_grad():
            predicted = out[:, _OCC] > _logit(self.config.inference.occlusion_threshold)
            wrong_net = int((predicted != hit).sum())
            # Certain misses are right unless the exact tracer hit there (impossible with exact voxels).
            missed_outside = int(truth.hit.sum()) - int(hit.sum())
        return StepResult(loss, parts, n - wrong_net - missed_outside, n, len(act), prep.truncated_total)

    # -- inference ---------------------------------------------------------------------------------
    @torch.no_grad()
    def intersect(self, rays: Rays) -> Hits:
        """Closest hit per ray in object space (neural): hit, t, normal (facing the ray), albedo, material."""
        n = len(rays)
        out = Hits.empty(n, rays.device)
        chunk = self.config.inference.chunk_size
        for start in range(0, n, chunk):
            part = rays[slice(start, start + chunk)] if n > chunk else rays
            hits = self._intersect_chunk(part)
            if n > chunk:
                out.scatter_(torch.arange(start, start + len(part), device=rays.device), hits)
            else:
                out = hits
        return out

    def _intersect_chunk(self, rays: Rays) -> Hits:
        n = len(rays)
        hits = Hits.empty(n, rays.device)
        prep = self._prepare(rays)
        if len(prep.active) == 0:
            return hits
        fp, act = prep.features, prep.active.to(rays.device)
        out = self._raw_outputs(prep, self._compute_dtype()).to(rays.device)
        t_enter, t_exit = fp.t_enter.to(rays.device), fp.t_exit.to(rays.device)
        t = prep.t_offset.to(rays.device) + t_enter + torch.sigmoid(out[:, _DIST]) * (t_exit - t_enter)
        hit = (out[:, _OCC] > _logit(self.config.inference.occlusion_threshold)) & (t < rays.t_max[act]) & (t > rays.t_min[act])
        normal = F.normalize(out[:, _NORMAL], dim=-1)
        hits.hit[act] = hit
        hits.t[act] = torch.where(hit, t, torch.full_like(t, float("inf")))
        normal = normal * hit[:, None]
        hits.normal[act] = normal
        hits.geometric_normal[act] = normal
        hits.albedo[act] = torch.where(hit[:, None], torch.sigmoid(out[:, _ALBEDO]), hits.albedo[act])
        material = out[:, _MAT:].argmax(-1) if self.num_materials > 1 else torch.zeros_like(act)
        hits.material_id[act] = torch.where(hit, material, torch.full_like(material, -1))
        return hits

    @torch.no_grad()
    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: the model predicts a hit within (t_min, t_max) (same decision as `intersect`)."""
        return self.intersect(rays).hit

    @torch.no_grad()
    def feature_statistics(self, rays: Rays, truth: Hits) -> dict:
        """How the H-point cut-off and the voxel skip behave on ``rays`` with exact hits ``truth``.

        ``network_fraction``: rays that cross an occupied voxel (the rest skip the network);
        ``truncated_fraction``: of those, rays with more boundary points than H;
        ``hit_beyond_last_point_fraction``: of those, rays whose exact hit lies past the last kept
        point (unlearnable from the features); ``hit_in_skipped_rays``: exact hits on rays that
        skipped the network (0 when the voxelization is conservative).
        """
        valid = valid_ray_mask(rays)
        t_off = torch.where(torch.isfinite(rays.t_min) & (rays.t_min > 0), rays.t_min, torch.zeros_like(rays.t_min))
        lo, ext = self.box_lo.to(rays.device), self.box_extent.to(rays.device)
        o = ((rays.origins + t_off[:, None] * rays.directions - lo) / ext)[valid].cpu()
        d = (rays.directions / ext)[valid].cpu()
        fp = self._featurize(o.contiguous(), d.contiguous())
        hit = truth.hit[valid].cpu()
        t_true = (truth.t[valid].cpu() - t_off[valid].cpu())
        net = fp.count > 0
        last = fp.points[torch.arange(len(fp.count)), (fp.count.long() - 1).clamp(min=0)]
        t_last = ((last - o) * d).sum(-1) / (d * d).sum(-1).clamp(min=1e-30)
        beyond = hit & net & fp.truncated & (t_true > t_last)
        n_net = int(net.sum())
        return {
            "rays": int(valid.sum()),
            "network_fraction": n_net / max(int(valid.sum()), 1),
            "truncated_fraction": float((fp.truncated & net).sum()) / max(n_net, 1),
            "hit_beyond_last_point_fraction": float(beyond.sum()) / max(n_net, 1),
            "hit_in_skipped_rays": int((hit & ~net).sum()),
            "mean_points": float(fp.count[net].float().mean()) if n_net else 0.0,
        }

    # -- memory ---------------------------------------------------------------------------------------
    def memory_bytes(self) -> MemoryReport:
        """Run-time bytes at the storage precision: voxel bits, hash tables, MLP weights and biases."""
        b = _BYTES[self.config.inference.storage_precision]
        v = self.config.voxel.resolution
        return MemoryReport({
            "voxels": (v**3 + 7) // 8,
            "encoder": self.encoder.table.numel() * b,
            "mlp": sum(p.numel() for p in self.network.parameters()) * b,
        })

    def round_to_storage_precision_(self) -> "LSNIFModel":
        """Round parameters to the stored precision in place, so the model in memory answers exactly as its file."""
        dt = _DTYPES[self.config.inference.storage_precision]
        with torch.no_grad():
            for p in self.parameters():
                p.copy_(p.to(dt).float())
        return self

    # -- files ----------------------------------------------------------------------------------------
    def _arrays(self) -> dict[str, Tensor]:
        dt = _DTYPES[self.config.inference.storage_precision]
        arrays = {"occupancy_bits": torch.from_numpy(pack_occupancy(self._occupancy_cpu()))}
        for key, p in self._stored_parameters():
            arrays[key] = p.detach().cpu().to(dt)
        return arrays

    def _stored_parameters(self) -> list[tuple[str, nn.Parameter]]:
        """(file key, parameter) of everything the file stores besides the voxels."""
        return [(f"encoder.{k}", p) for k, p in self.encoder.named_parameters()] + [
            (f"network.{k}", p) for k, p in self.network.named_parameters()
        ]

    def header(self) -> dict:
        return {
            "config": self.config.model_dump(mode="json"),
            "bounds": self.bounds.tolist(),
            "box": self.box.tolist(),
            "materials": self.materials,
            "training": self.training_record,
            "mesh_sha256": self.mesh_hash,
            "mesh_name": self.mesh_name,
            "memory_bytes": self.memory_bytes().as_dict(),
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write the model to ``path`` (atomically; suggested suffix ``.nrt``)."""
        return write_model_file(path, METHOD, self.header(), self._arrays())

    @staticmethod
    def load(path: str | os.PathLike, device: str | torch.device = "cpu") -> "LSNIFModel":
        """Load a model file; bad, truncated, corrupted, newer or other-method files raise `ModelFileError`."""
        f = read_model_file(path, method=METHOD)
        h = f.header
        try:
            config = LSNIFConfig.model_validate(h["config"])
            bounds = AABB(torch.tensor(h["bounds"][0], dtype=torch.float32), torch.tensor(h["bounds"][1], dtype=torch.float32))
            v = config.voxel.resolution
            occ = unpack_occupancy(f.arrays["occupancy_bits"].numpy(), v)
            model = LSNIFModel(config, bounds, occ, h["materials"])
        except ModelFileError:
            raise
        except Exception as exc:  # missing key, invalid config value, wrong array shape
            msg = str(exc).replace("\n", " ")
            raise ModelFileError(f"{path}: invalid LSNIF model ({type(exc).__name__}: {msg[:300]})") from None
        with torch.no_grad():
            for key, p in model._stored_parameters():
                if key not in f.arrays:
                    raise ModelFileError(f"{path}: invalid LSNIF model (array '{key}' missing)")
                if tuple(f.arrays[key].shape) != tuple(p.shape):
                    raise ModelFileError(
                        f"{path}: invalid LSNIF model (array '{key}' has shape {tuple(f.arrays[key].shape)}, expected {tuple(p.shape)})"
                    )
                p.copy_(f.arrays[key].float())
        model.training_record = dict(h.get("training") or {})
        model.mesh_hash, model.mesh_name = h.get("mesh_sha256"), h.get("mesh_name")
        return model.to(device).eval()

    def __repr__(self) -> str:
        c = self.config
        return (
            f"LSNIFModel({self.mesh_name!r}, V={c.voxel.resolution}, H={c.features.max_points}, "
            f"mlp={c.network.hidden_layers}x{c.network.hidden_width}, {self.memory_bytes().total} bytes)"
        )


# LSNIFModel already is a BLAS (bounds, secondary_offset, intersect, occluded, memory_bytes).
LSNIFBLAS = LSNIFModel


def point_local_distances(fp: RayFeaturePoints, origins: Tensor, directions: Tensor) -> Tensor:
    """[M, H] each point's ray parameter as a fraction of the ray's box interval (0 for padding)."""
    t = ((fp.points - origins[:, None]) * directions[:, None]).sum(-1) / (directions * directions).sum(-1, keepdim=True)
    span = (fp.t_exit - fp.t_enter).clamp(min=1e-12)
    local = ((t - fp.t_enter[:, None]) / span[:, None]).clamp(0, 1)
    return torch.where(fp.face_axis >= 0, local, torch.zeros_like(local))


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _material_table(mesh: Mesh) -> list[dict]:
    return [{"name": m.name, "base_color": [float(c) for c in np.asarray(m.base_color).reshape(-1)[:3]]} for m in mesh.materials]

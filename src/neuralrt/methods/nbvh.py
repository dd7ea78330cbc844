"""N-BVH: neural queries over an error-driven BVH cut (Weier et al., SIGGRAPH 2024).

Pipeline for a batch of rays in object space::

    object space --(cube around the grown box -> [0,1]^3, unit directions)--> unit rays
      --list_leaves (nbvh_traversal)--> each ray's leaves of the cut, front to back
      --wavefront steps: the next leaf of every active ray, one batched query, compaction:
          chord points (3, in the leaf's box) --HashGrid (one table)--> [96] --MLP 4x64--> 8 outputs
      --decode (LocalT)--> closest accepted hit over all leaves (leaves overlap)

Outputs: visibility (sigmoid; 1 = hit, the code's polarity), depth (sigmoid, the paper's LocalT:
t = t0 + depth * (len + 1e-3)), normal (linear, in [-1, 1], facing the chord), albedo (sigmoid).
A ray whose origin lies inside a leaf asks for the REVERSED chord (exit to entry) and accepts the
answer only beyond 0.2 * len (METHODS-SPEC A4: it skips the surface the ray just left).

Training (`NBVHRayDistribution`, `training_step`, `after_training_step`) grows the cut from the
root by the split schedule of `nbvh_cut` and registers up to 7 LoDs; the model file stores only
the registered cuts (`nbvh_cut.compact`), the hash table and the MLP.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..accel.blas import MemoryReport
from ..errors import ConfigError
from ..geometry.mesh import Mesh
from ..neural.hash_grid import HashGrid
from ..neural.mlp import MLP
from ..rays import AABB, Hits, Rays, face_forward, valid_ray_mask
from ..training.step import StepResult
from .base import NeuralBLAS, material_table, prefixed_parameters
from .nbvh_config import NBVHConfig
from .nbvh_cut import base_tree, choose_splits, compact, kept_nodes, lod_to_register, split_count
from .nbvh_rays import NBVHRayDistribution
from .nbvh_wavefront_cpu import answers_cpu, closest_hits_cpu
from .nbvh_traversal import NO_LOD, CutArrays, LeafList, first_leaves, list_leaves

__all__ = ["NBVHModel", "NBVHConfig", "METHOD"]

METHOD = "nbvh"
# Output layout: 8 fixed channels, then one logit per material when the mesh has several.
_VIS, _DEPTH, _NORMAL, _ALBEDO, _MAT = 0, 1, slice(2, 5), slice(5, 8), 8
_DEPTH_PAD = 1e-3  # LocalT: depth is relative to (chord length + 1e-3)
_REVERSED_MIN = 0.2  # reversed chords accept hits beyond 0.2 * len + 1e-5
_NODE_BYTES = 3 * 4 + 3 * 4 + 2 * 4 + 1  # lo, hi (fp32), two child indices (int32), LoD (int8)
_EQUIDISTANT = (0.0, 0.5, 1.0)
_STRATA_CENTRES = (1 / 6, 1 / 2, 5 / 6)


MAX_LODS = 7  # levels of detail a model can register (`CutConfig.lods` <= 7, as in the paper)


def _tree_problem(lo: Tensor, hi: Tensor, children: Tensor, lod: Tensor) -> str | None:
    """What makes these arrays no tree the traversal can walk (None if they are one): a leaf is
    (-1, -1), an inner node's children are two adjacent nodes after it (so no walk loops), boxes
    are finite and ordered, LoDs are registered levels or `NO_LOD`."""
    m = len(children)
    first, second = children[:, 0].long(), children[:, 1].long()
    inner = first >= 0
    if m == 0:
        return "node arrays are empty"
    if ((first < -1) | ((~inner) & (second != -1))).any():
        return "leaf rows must be (-1, -1)"
    nodes = torch.arange(m, device=children.device)  # (a checkpoint's tree is on the training device)
    if (inner & ((first <= nodes) | (second != first + 1) | (second >= m))).any():
        return f"child indices must be two adjacent nodes after their parent, below {m}"
    if not (torch.isfinite(lo).all() and torch.isfinite(hi).all() and (lo <= hi).all()):
        return "node boxes must be finite with lo <= hi"
    if (((lod < 0) | (lod >= MAX_LODS)) & (lod != NO_LOD)).any():
        return f"LoDs must lie in [0, {MAX_LODS}) or be {NO_LOD}"
    return None


class NBVHModel(NeuralBLAS):
    """A trained (or training) N-BVH of one object; implements the `BLAS` protocol.

    Args:
        config: the full configuration (`NBVHConfig.preset("cpu")` by default).
        bounds: the object's tight AABB in object space.
        lo, hi, children, lod: the tree (unit cube; see `nbvh_traversal.CutArrays`).
        materials: the material table.
    """

    METHOD: ClassVar[str] = METHOD
    TITLE: ClassVar[str] = "N-BVH"
    CONFIG: ClassVar[type[NBVHConfig]] = NBVHConfig

    def __init__(self, config: NBVHConfig, bounds: AABB, lo, hi, children, lod, materials: list[dict] | None = None):
        super().__init__(config, bounds, materials)
        unit_lo, unit_scale = unit_cube(self.bounds, config.query.scene_box_dilation)
        self.register_buffer("unit_lo", unit_lo, persistent=False)
        self.unit_scale = unit_scale
        self.register_buffer("unit_center", (self.bounds.center.float() - unit_lo) / unit_scale, persistent=False)
        self.register_buffer("unit_extent", self.bounds.extent.float() / unit_scale, persistent=False)
        m = len(lo)
        self.register_buffer("node_lo", torch.as_tensor(np.asarray(lo), dtype=torch.float32))
        self.register_buffer("node_hi", torch.as_tensor(np.asarray(hi), dtype=torch.float32))
        self.register_buffer("node_children", torch.as_tensor(np.asarray(children), dtype=torch.int32))
        self.register_buffer("node_lod", torch.as_tensor(np.asarray(lod), dtype=torch.int8))
        if self.node_lo.shape != (m, 3) or self.node_hi.shape != (m, 3) or self.node_children.shape != (m, 2) or self.node_lod.shape != (m,):
            raise ValueError(f"inconsistent tree arrays for {m} nodes")
        self._check_tree()
        # Training state (checkpointed; not in the model file).
        self.register_buffer("live", torch.zeros(m, dtype=torch.bool))
        self.register_buffer("loss_sum", torch.zeros(m, dtype=torch.float64))
        self.register_buffer("samples", torch.zeros(m, dtype=torch.float64))
        self.register_buffer("alive_steps", torch.zeros(m, dtype=torch.float64))
        self.register_buffer("h_max", torch.zeros((), dtype=torch.float64))
        self.register_buffer("registered", torch.tensor([bool((self.node_lod == lvl).any()) for lvl in range(MAX_LODS)]))
        learned = self._learned_modules(config, self.num_materials)
        self.encoder, self.network = learned["encoder"], learned["network"]
        self._batch: tuple[Tensor, Tensor | None] | None = None  # (leaf per sample, chord fractions) of the batch being trained
        self._batch_losses: Tensor | None = None
        self._h: Tensor | None = None

    def _check_tree(self) -> None:
        """A ValueError unless the node arrays are a tree the traversal can walk: the kernels index
        by them without bounds checks, so a bad index reads outside the arrays."""
        problem = _tree_problem(self.node_lo, self.node_hi, self.node_children, self.node_lod)
        if problem:
            raise ValueError(f"the tree's {problem}")

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """As `nn.Module`'s, then the tree checked as a model file's is (a checkpoint's tree too)."""
        result = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self._check_tree()
        return result

    def _apply(self, fn, recurse=True):
        # .to() / .cuda() move the buffers; h, cached from them, is recomputed where they now are.
        self._h = None
        return super()._apply(fn, recurse)

    # -- construction ----------------------------------------------------------------------------
    @classmethod
    def from_mesh(cls, mesh: Mesh, config: NBVHConfig | None = None) -> "NBVHModel":
        """An untrained model of ``mesh``: its binary SAH BVH, the cut = the root."""
        config = config or NBVHConfig.preset("cpu")
        lo, hi = mesh.bounds
        bounds = AABB(torch.as_tensor(np.array(lo, copy=True)), torch.as_tensor(np.array(hi, copy=True)))
        unit_lo, scale = unit_cube(AABB(bounds.lo.float(), bounds.hi.float()), config.query.scene_box_dilation)
        tri = (mesh.triangles().astype(np.float64) - unit_lo.double().numpy()) / scale
        node_lo, node_hi, children = base_tree(tri, config.cut.max_leaf_size)
        model = cls(config, bounds, node_lo, node_hi, children, np.full(len(node_lo), NO_LOD, np.int8), material_table(mesh))
        model.live[0] = True
        model._remember_mesh(mesh)
        return model

    @classmethod
    def _learned_modules(cls, config: NBVHConfig, num_materials: int) -> dict[str, nn.Module]:
        enc, net = config.encoding, config.network
        encoder = HashGrid(enc.levels, enc.base_resolution, enc.features_per_level, enc.log2_table_size, enc.init_scale,
                           seed=config.training.seed)
        network = MLP(encoder.output_dim(3), 8 + _material_logits(num_materials), net.hidden_width, net.hidden_layers, 0.0,
                      generator=torch.Generator().manual_seed(config.training.seed))
        return {"encoder": encoder, "network": network}

    @classmethod
    def _from_arrays(cls, config: NBVHConfig, bounds: AABB, materials: list[dict], arrays: dict[str, Tensor]) -> "NBVHModel":
        model = cls(config, bounds, arrays["cut.lo"].float(), arrays["cut.hi"].float(), arrays["cut.children"].int(),
                    arrays["cut.lod"].to(torch.int8), materials)  # fmt: skip
        cls._load_parameters(model._stored_parameters(), arrays)
        return model

    # -- the cut -------------------------------------------------------------------------------------
    @property
    def material_logits(self) -> int:
        """Material outputs of the MLP: one per material slot, none for a single-material mesh."""
        return _material_logits(self.num_materials)

    def cut_arrays(self) -> CutArrays:
        return CutArrays(self.node_lo, self.node_hi, self.node_children, self.node_lod, self.live)

    def leaf_list(self, origins: Tensor, directions: Tensor, t_max: Tensor, level: Tensor, dilation: Tensor) -> LeafList:
        """Leaves each unit-cube ray crosses (level -1 = the live cut of training)."""
        return list_leaves(origins, directions, t_max, self.cut_arrays(), level, dilation)

    def first_leaf(self, origins: Tensor, directions: Tensor, t_max: Tensor, level: Tensor, dilation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(node (-1: none), t0, t1) of the first leaf each unit-cube ray crosses (what training samples)."""
        return first_leaves(origins, directions, t_max, self.cut_arrays(), level, dilation)

    def node_heuristic(self) -> Tensor:
        """[M] h = loss_sum / sqrt(samples * alive_steps) (0 for nodes never sampled or never alive)."""
        den = torch.sqrt(self.samples * self.alive_steps)
        return torch.where(den > 0, self.loss_sum / den.clamp(min=1e-300), torch.zeros_like(den))

    def acceptance(self, node: Tensor) -> Tensor:
        """Probability of keeping a training sample of each leaf: max(h / h_max, min_acceptance); 1 if never sampled."""
        if self._h is None:  # h changes only after a step: computed once per step
            self._h = self.node_heuristic()
        h = self._h[node]
        h_max = float(self.h_max)
        p = (h / h_max).clamp(min=self.config.training.min_acceptance, max=1.0) if h_max > 0 else torch.ones_like(h)
        return torch.where(self.samples[node] > 0, p, torch.ones_like(p)).float()

    def training_levels(self) -> Tensor:
        """Cuts training draws from, uniformly: the registered LoDs, and the live cut (-1) until LoD 0 exists."""
        levels = [lvl for lvl in range(MAX_LODS) if bool(self.registered[lvl])]
        if not bool(self.registered[0]):
            levels.append(-1)
        return torch.tensor(levels, dtype=torch.int8, device=self.device)

    def remember_batch_leaves(self, node: Tensor, fractions: Tensor | None = None) -> None:
        """Called by the ray distribution: the leaf (and stratified chord fractions) of each sample it hands out."""
        self._batch = (node, fractions)

    @property
    def num_nodes(self) -> int:
        """Nodes the model file stores (every registered LoD's cut and their ancestors)."""
        return int(kept_nodes(self.node_children.cpu().numpy(), self.node_lod.cpu().numpy()).sum()) if bool(self.registered.any()) else 1

    def live_nodes(self) -> int:
        return 2 * int(self.live.sum()) - 1

    # -- levels of detail in a scene -----------------------------------------------------------------
    def registered_lods(self) -> list[int]:
        return [lvl for lvl in range(MAX_LODS) if bool(self.registered[lvl])]

    def at_lod(self, lod: int) -> "NBVHModel":
        """This model answering rays with the cut of LoD ``lod``: `with_inference` (``lod=lod``), a
        view sharing every parameter and buffer, made once per setting (instances of one model share it)."""
        lods = self.config.cut.lods
        if isinstance(lod, bool) or not isinstance(lod, int) or not 0 <= lod < lods:
            raise ConfigError(f"N-BVH level of detail: expected an integer in 0..{lods - 1} (cut.lods = {lods}), got {lod!r}")
        return self if lod == self.config.inference.lod else self.with_inference(lod=lod)

    def views_for_rays(self) -> tuple["NBVHModel", "NBVHModel"]:
        """(this model, the view at ``inference.secondary_lod``): camera rays get the configured cut,
        every other ray the coarsest registered LoD up to ``secondary_lod`` (never finer than ``lod``)."""
        inf = self.config.inference
        if inf.secondary_lod is None or inf.secondary_lod <= inf.lod:
            return self, self
        coarser = [lvl for lvl in self.registered_lods() if inf.lod < lvl <= inf.secondary_lod]
        return (self, self.at_lod(max(coarser))) if coarser else (self, self)

    # -- network -------------------------------------------------------------------------------------
    def _query(self, origins: Tensor, directions: Tensor, a: Tensor, b: Tensor, fractions: Tensor, compute_dtype) -> Tensor:
        """Raw outputs [K, 8 + material logits] for the chords from ``o + a d`` to ``o + b d`` (unit cube) at ``fractions``."""
        t = a[:, None] + fractions * (b - a)[:, None]  # [K, 3]
        points = origins[:, None, :] + t[..., None] * directions[:, None, :]
        return self.network(self.encoder(points), compute_dtype)

    def _fractions(self, n: int, device) -> Tensor:
        pts = _EQUIDISTANT if self.config.query.chord_points == "equidistant" else _STRATA_CENTRES
        return torch.tensor(pts, device=device).expand(n, 3)

    # -- training ------------------------------------------------------------------------------------
    def progress_fields(self) -> dict[str, str]:
        return {"nodes": str(self.live_nodes())}

    def curve_states(self) -> dict[str, float]:
        return {"BVH cut nodes": float(self.live_nodes())}

    def training_rays(self, truth, device: torch.device) -> NBVHRayDistribution:
        return NBVHRayDistribution(self, truth, device)

    def training_step(self, rays: Rays, truth: Hits) -> StepResult:
        """Loss of one batch of leaf chords (rays from `NBVHRayDistribution`) against exact hits (paper Sec. 5.2)."""
        n = len(rays)
        start = (rays.origins - self.unit_lo) / self.unit_scale
        length = rays.t_max / self.unit_scale
        fractions = self._batch[1] if self._batch is not None and self._batch[1] is not None else self._fractions(n, start.device)
        out = self._query(start, rays.directions, torch.zeros_like(length), length, fractions, self.compute_dtype(training=True))
        hit = truth.hit
        hitf = hit.float()
        vis = torch.sigmoid(out[:, _VIS]).clamp(1e-5, 1 - 1e-5)
        bce = -(hitf * torch.log(vis) + (1 - hitf) * torch.log(1 - vis))
        t_hit = torch.where(hit, truth.t, torch.zeros_like(truth.t)) / self.unit_scale
        depth = (torch.sigmoid(out[:, _DEPTH]) - t_hit / (length + _DEPTH_PAD)).abs() * hitf
        normal_true = face_forward(truth.normal, rays.directions)
        normal = (out[:, _NORMAL] - normal_true).abs().sum(-1) * hitf
        albedo = torch.sigmoid(out[:, _ALBEDO])
        rel = ((albedo - truth.albedo) ** 2 / (albedo.detach() ** 2 + 1e-2)).sum(-1) * hitf
        w = self.config.loss
        # Means over all samples (misses count as 0 for the hit-only losses), per channel.
        parts = {"visibility": bce.mean(), "depth": depth.mean(), "normal": normal.mean() / 3, "albedo": rel.mean() / 3}
        loss = w.visibility * parts["visibility"] + w.depth * parts["depth"] + w.normal * parts["normal"] + w.albedo * parts["albedo"]
        if self.material_logits and bool(hit.any()):  # not in the paper (one BSDF there): the slot of the hit
            parts["material"] = F.cross_entropy(out[hit, _MAT:], truth.material_id[hit].clamp(0, self.num_materials - 1))
            loss = loss + w.material * parts["material"]
        self._batch_losses = (bce + depth + normal + rel).detach()  # the sample's 8 channel losses, summed
        with torch.no_grad():
            # One device-to-host read for every figure (float64 holds each float32 part and the count exactly).
            correct = ((out[:, _VIS] > 0) == hit).sum()
            figures = torch.stack([v.detach().double() for v in parts.values()] + [correct.double()]).tolist()
        return StepResult(loss, dict(zip(parts, figures[:-1])), int(figures[-1]), n, n, {})

    @torch.no_grad()
    def after_training_step(self, step: int, optimizer: torch.optim.Optimizer) -> None:
        """Node statistics, then the schedule's splits and LoD registration (METHODS-SPEC A3)."""
        if self._batch is not None and self._batch_losses is not None:
            node = self._batch[0]
            self.loss_sum.index_add_(0, node, self._batch_losses.double())
            self.samples.index_add_(0, node, torch.full((len(node),), 8.0, dtype=torch.float64, device=node.device))
        # Alive = a leaf of a cut training draws from (the live one or a registered LoD), so that
        # samples / alive_steps stays a sampling rate for nodes of coarse LoDs too.
        self.alive_steps += (self.live | (self.node_lod < NO_LOD)).double()
        h = self.node_heuristic()
        cut, steps = self.config.cut, self.config.training.steps
        count = split_count(step, cut, steps)
        if count > 0 and cut.target_nodes is not None:  # (live_nodes reads the device: only on split steps)
            count = min(count, (cut.target_nodes - self.live_nodes()) // 2)
        if count > 0:
            chosen = choose_splits(h, self.live, self.node_children[:, 0] >= 0, count)
            kids = self.node_children[chosen].long()
            self.live[chosen] = False
            self.live[kids.reshape(-1)] = True
        lod = lod_to_register(step, cut, steps)
        if lod is not None:
            # LoDs are registered coarse to fine; finer values left by an earlier, shorter run are stale.
            self.node_lod[self.node_lod <= lod] = NO_LOD
            self.node_lod[self.live] = lod
            self.registered[: lod + 1] = False
            self.registered[lod] = True
        if self._batch is not None:
            # Over the leaves just trained: nodes split long ago keep their early, large h frozen.
            # (On the device, read by the next draw there: no host sync.)
            if len(self._batch[0]):
                self.h_max.copy_(h[self._batch[0]].max())
            else:
                self.h_max.zero_()
        self._batch, self._batch_losses, self._h = None, None, None

    # -- inference ---------------------------------------------------------------------------------
    def _unit_rays(self, rays: Rays):
        """Valid rays in the unit cube: (index, origins moved to t_min, unit directions, t_max, unit-t -> ray-t factor, t offset)."""
        valid = valid_ray_mask(rays)
        idx = torch.nonzero(valid).squeeze(1)
        t_off = torch.where(torch.isfinite(rays.t_min) & (rays.t_min > 0), rays.t_min, torch.zeros_like(rays.t_min))[idx]
        d = rays.directions[idx]
        norm = torch.linalg.norm(d, dim=-1)
        o = (rays.origins[idx] + t_off[:, None] * d - self.unit_lo) / self.unit_scale
        to_ray_t = self.unit_scale / norm
        # One float32 step wider in unit t, so that t_max equal to a hit's own t keeps it after the
        # round trip ray t -> unit t -> ray t (the interval includes its end); answers are clamped to t_max.
        t_max = torch.nextafter((rays.t_max[idx] - t_off) / to_ray_t, torch.tensor(float("inf"), device=t_off.device))
        return idx, o.contiguous(), (d / norm[:, None]).contiguous(), t_max.contiguous(), to_ray_t, t_off

    def _closest(self, o: Tensor, d: Tensor, t_max: Tensor, any_hit: bool) -> tuple[Tensor, Tensor]:
        """Wavefront over the cut: (t [K] unit, inf where missed; raw outputs of the accepted hit).
        The per-step work runs in Triton kernels on CUDA (`nbvh_wavefront_triton`), in numba passes
        on the CPU (`nbvh_wavefront_cpu`); `_closest_torch` is the same loop in torch ops (the reference)."""
        if o.device.type == "cuda":
            from .nbvh_wavefront_triton import closest_hits_triton

            return closest_hits_triton(self, o, d, t_max, any_hit)
        return closest_hits_cpu(self, o, d, t_max, any_hit)

    def _closest_torch(self, o: Tensor, d: Tensor, t_max: Tensor, any_hit: bool) -> tuple[Tensor, Tensor]:
        k, dev = len(o), o.device
        inf = self.config.inference
        leaves = self.leaf_list(o, d, t_max, torch.full((k,), inf.lod, dtype=torch.int8, device=dev),
                                torch.full((k,), inf.box_dilation, device=dev))  # fmt: skip
        ptr, end = leaves.start[:-1].clone(), leaves.start[1:]
        best_t = torch.full((k,), float("inf"), device=dev)
        best_out = torch.zeros(k, 8 + self.material_logits, device=dev)
        threshold = math.log(inf.occlusion_threshold / (1 - inf.occlusion_threshold))
        dtype = self.compute_dtype()
        active = torch.nonzero(ptr < end).squeeze(1)
        for _ in range(inf.max_steps):
            if len(active) == 0:
                break
            e = ptr[active]
            t0, t1 = leaves.t0[e], leaves.t1[e]
            ahead = t0 < best_t[active]  # leaves come sorted by t0: past the best hit, a ray is done
            active, e, t0, t1 = active[ahead], e[ahead], t0[ahead], t1[ahead]
            if len(active) == 0:
                break
            inside = t0 < 0
            length = t1 - t0
            a, b = torch.where(inside, t1, t0), torch.where(inside, t0, t1)
            out = self._query(o[active], d[active], a, b, self._fractions(len(active), dev), dtype)
            depth = torch.sigmoid(out[:, _DEPTH]) * (length + _DEPTH_PAD)
            t = torch.where(inside, t1 - depth, t0 + depth)
            ok = (out[:, _VIS] > threshold) & (t > 0) & (t <= t_max[active])
            ok &= ~inside | (t > _REVERSED_MIN * length + 1e-5)
            better = ok & (t < best_t[active])
            rows = active[better]
            best_t[rows] = t[better]
            best_out[rows] = out[better]  # normals: turned to face the ray when decoded
            ptr[active] += 1
            more = ptr[active] < end[active]
            if any_hit:
                more &= ~ok
            active = active[more]
        return best_t, best_out

    def _answer(self, rays: Rays, any_hit: bool) -> Hits:
        """The records of ``rays``' closest (``any_hit``: first accepted) hits: numba passes
        throughout on the CPU (`answers_cpu`), torch ops around the wavefront elsewhere."""
        if rays.device.type == "cpu":
            return answers_cpu(self, rays, any_hit)
        return self._answer_torch(rays, any_hit)

    def _answer_torch(self, rays: Rays, any_hit: bool) -> Hits:
        hits = Hits.empty(len(rays), rays.device)
        idx, o, d, t_max, to_ray_t, t_off = self._unit_rays(rays)
        if len(idx) == 0:
            return hits
        t, out = self._closest(o, d, t_max, any_hit)
        hit = torch.isfinite(t)
        hits.hit[idx] = hit
        hits.t[idx] = torch.where(hit, torch.minimum(t_off + t * to_ray_t, rays.t_max[idx]), torch.full_like(t, float("inf")))
        normal = F.normalize(face_forward(out[:, _NORMAL], d), dim=-1) * hit[:, None]
        hits.normal[idx] = normal
        hits.geometric_normal[idx] = normal
        hits.albedo[idx] = torch.where(hit[:, None], torch.sigmoid(out[:, _ALBEDO]), hits.albedo[idx])
        material = out[:, _MAT:].argmax(-1) if self.material_logits else torch.zeros_like(idx)
        hits.material_id[idx] = torch.where(hit, material, torch.full_like(idx, -1))
        return hits

    def _intersect_chunk(self, rays: Rays) -> Hits:
        return self._answer(rays, any_hit=False)

    @torch.no_grad()
    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: a hit within [t_min, t_max]; each ray stops at its first accepted hit."""
        self._check_device(rays)
        chunk = self.rays_per_chunk(rays.device)
        parts = [self._answer(rays[slice(s, s + chunk)], any_hit=True).hit for s in range(0, len(rays), chunk)]
        return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.bool, device=rays.device)

    # -- memory and files ------------------------------------------------------------------------------
    def memory_bytes(self) -> MemoryReport:
        """Run-time bytes at the storage precision: hash table rows, MLP, cut nodes (what the file stores)."""
        return MemoryReport({
            "hash_table": self.encoder.table.numel() * self.storage_bytes,
            "mlp": self.parameter_bytes(self.network),
            "nodes": self.num_nodes * _NODE_BYTES,
        })

    def _stored_parameters(self) -> dict[str, torch.nn.Parameter]:
        return prefixed_parameters({"encoder": self.encoder, "network": self.network})

    def _arrays(self) -> dict[str, Tensor]:
        lo, hi, children, lod = compact(self.node_lo.cpu().numpy(), self.node_hi.cpu().numpy(), self.node_children.cpu().numpy(),
                                        self.node_lod.cpu().numpy())  # fmt: skip
        tree = {"cut.lo": lo, "cut.hi": hi, "cut.children": children, "cut.lod": lod}
        return {**{k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in tree.items()}, **self._stored(self._stored_parameters())}

    def __repr__(self) -> str:
        c = self.config
        return (f"NBVHModel({self.mesh_name!r}, nodes={self.num_nodes}, table=2^{c.encoding.log2_table_size}, "
                f"mlp={c.network.hidden_layers}x{c.network.hidden_width}, {self.memory_bytes().total} bytes)")


def _material_logits(num_materials: int) -> int:
    return num_materials if num_materials > 1 else 0


def unit_cube(bounds: AABB, dilation: float) -> tuple[Tensor, float]:
    """(lo [3], side) of the cube the model works in: the object's box grown by ``dilation`` x its
    largest extent on each side, centred in a cube (uniform scale: unit directions stay unit)."""
    extent = bounds.extent.float()
    largest = max(float(extent.max()), 1e-12)
    side = largest * (1 + 2 * dilation)
    lo = bounds.center.float() - 0.5 * side
    return lo, side

"""LSNIF's training loss (paper Sec. 5.3) over the network's raw outputs, with the step's figures.

Five terms, each weighted by `LossConfig`: occlusion BCE with logits over the network rays;
over the network rays that hit, distance L1 between the sigmoid output and the hit's fraction of
the ray's box interval, normal ``1 - cos`` against the exact normal turned towards the ray,
albedo relative L2 (``(a - y)^2 / (a^2 + 0.01)``, the denominator held constant) and, with more
than one material, material cross-entropy.

Two implementations, chosen once by device (`training_loss`): torch ops (`training_loss_torch`,
any device: the reference and the CUDA path) and, on the CPU, one numba pass
(`training_loss_numba`) that computes the terms, the figures and d loss / d outputs together;
its autograd function's backward only scales that stored gradient. The two agree within fp32
rounding (the numba pass sums in float64; tested against each other).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..rays import Hits, face_forward
from .lsnif_config import LossConfig

__all__ = ["TrainingLoss", "training_loss", "training_loss_torch", "training_loss_numba"]

# Output layout of the MLP (as in lsnif.py): 8 fixed channels, then one logit per material.
_OCC, _DIST, _NORMAL, _ALBEDO, _MAT = 0, 1, slice(2, 5), slice(5, 8), 8
_TERMS = ("occlusion", "distance", "normal", "albedo", "material")


@dataclass
class TrainingLoss:
    loss: Tensor  # scalar, differentiable in the raw outputs
    parts: dict[str, float]  # each term's value (the terms that apply to this batch)
    wrong_network: int  # network rays whose predicted hit/miss is wrong
    missed_outside: int  # exact hits on rays that skipped the network (0 with exact voxels)
    truncated: int  # the ``truncated`` count handed in, read back with the rest


def training_loss(out: Tensor, active: Tensor, t_offset: Tensor, t_enter: Tensor, t_exit: Tensor, directions: Tensor,
                  truth: Hits, weights: LossConfig, num_materials: int, occlusion_logit: float,
                  truncated: Tensor) -> TrainingLoss:  # fmt: skip
    """The loss of the network rays ``active`` (rows of the batch) with raw outputs ``out [M, 8 +
    materials]``; ``t_offset``/``t_enter``/``t_exit [M]`` place each ray's box interval, ``directions``
    and ``truth`` are the whole batch's. On the CPU one numba pass, elsewhere torch ops."""
    implementation = training_loss_numba if out.device.type == "cpu" else training_loss_torch
    return implementation(out, active, t_offset, t_enter, t_exit, directions, truth, weights, num_materials,
                          occlusion_logit, truncated)  # fmt: skip


def training_loss_torch(out: Tensor, active: Tensor, t_offset: Tensor, t_enter: Tensor, t_exit: Tensor, directions: Tensor,
                        truth: Hits, weights: LossConfig, num_materials: int, occlusion_logit: float,
                        truncated: Tensor) -> TrainingLoss:  # fmt: skip
    """`training_loss` as torch ops (any device); one device->host read-back for all figures."""
    w = weights
    hit = truth.hit[active]
    occ_loss = F.binary_cross_entropy_with_logits(out[:, _OCC], hit.float()) if len(active) else out.sum() * 0
    loss = w.occlusion * occ_loss
    parts = {"occlusion": occ_loss}
    # Rows of the active rays that hit (one device sync here, instead of one per masked tensor).
    hit_rows = torch.nonzero(hit).squeeze(1)
    if len(hit_rows):
        ray_rows = active[hit_rows]  # the same rays as rows of the batch
        o = out[hit_rows]
        te, tx = t_enter[hit_rows], t_exit[hit_rows]
        t_local = (truth.t[ray_rows] - t_offset[hit_rows] - te) / torch.clamp(tx - te, min=1e-12)
        dist_loss = (torch.sigmoid(o[:, _DIST]) - t_local.clamp(0, 1)).abs().mean()
        n_true = face_forward(truth.normal[ray_rows], directions[ray_rows])
        normal_loss = (1 - F.cosine_similarity(o[:, _NORMAL], n_true, dim=-1, eps=1e-8)).mean()
        albedo = torch.sigmoid(o[:, _ALBEDO])
        albedo_loss = ((albedo - truth.albedo[ray_rows]) ** 2 / (albedo.detach() ** 2 + 1e-2)).mean()
        loss = loss + w.distance * dist_loss + w.normal * normal_loss + w.albedo * albedo_loss
        parts.update(distance=dist_loss, normal=normal_loss, albedo=albedo_loss)
        if num_materials > 1:
            mat_loss = F.cross_entropy(o[:, _MAT:], truth.material_id[ray_rows].clamp(0, num_materials - 1))
            loss = loss + w.material * mat_loss
            parts["material"] = mat_loss
    with torch.no_grad():
        predicted = out[:, _OCC] > occlusion_logit
        # Certain misses are right unless the exact tracer hit there (impossible with exact voxels).
        counts = torch.stack([(predicted != hit).sum(), truth.hit.sum() - hit.sum(), truncated]).tolist()
        values = torch.stack([v.detach().float() for v in parts.values()]).tolist()  # one device->host copy each
    return TrainingLoss(loss, dict(zip(parts, values)), *counts)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _sigmoid(x):
    return np.float32(1.0) / (np.float32(1.0) + np.exp(-x))


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _loss_kernel(out, active, t_offset, t_enter, t_exit, directions, hit, t_true, normal, albedo, material, weights,
                 num_materials, occlusion_logit, grad, sums, counts):  # fmt: skip
    """One pass over the network rays: ``sums[term]`` (float64, not yet divided by the ray count),
    ``counts = (network rays that hit, wrong predictions, all hits of the batch)`` and ``grad [M, C]``
    = d (weighted total) / d out, with the same formulas as `training_loss_torch`."""
    one, zero = np.float32(1.0), np.float32(0.0)
    n_net = out.shape[0]
    n_hit = 0
    for i in range(n_net):
        n_hit += hit[active[i]]
    all_hits = 0
    for r in range(hit.shape[0]):
        all_hits += hit[r]
    wrong = 0
    g_occ = np.float32(weights[0] / max(n_net, 1))
    g_dist = np.float32(weights[1] / max(n_hit, 1))
    g_normal = np.float32(weights[2] / max(n_hit, 1))
    g_albedo = np.float32(weights[3] / max(3 * n_hit, 1))
    g_mat = np.float32(weights[4] / max(n_hit, 1))
    for i in range(n_net):
        r = active[i]
        row = out[i]
        g = grad[i]
        g[:] = zero
        y = hit[r]
        x = row[0]
        # BCE with logits, stable form: max(x, 0) - x y + log(1 + exp(-|x|)).
        sums[0] += max(x, zero) - (x if y else zero) + np.log1p(np.exp(-abs(x)))
        g[0] = (_sigmoid(x) - (one if y else zero)) * g_occ
        wrong += (x > occlusion_logit) != y
        if not y:
            continue
        # Distance: L1 between sigmoid(out) and the hit's fraction of [t_enter, t_exit].
        te, tx = t_enter[i], t_exit[i]
        t_local = (t_true[r] - t_offset[i] - te) / max(tx - te, np.float32(1e-12))
        t_local = min(max(t_local, zero), one)
        s = _sigmoid(row[1])
        d = s - t_local
        sums[1] += abs(d)
        g[1] = (one if d > 0 else (-one if d < 0 else zero)) * s * (one - s) * g_dist
        # Normal: 1 - cos(out, exact normal facing the ray); norms clamped at eps as torch does.
        nx, ny, nz = normal[r, 0], normal[r, 1], normal[r, 2]
        if nx * directions[r, 0] + ny * directions[r, 1] + nz * directions[r, 2] > 0:
            nx, ny, nz = -nx, -ny, -nz
        px, py, pz = row[2], row[3], row[4]
        eps = np.float32(1e-8)
        p_norm = max(np.sqrt(px * px + py * py + pz * pz), eps)
        n_norm = max(np.sqrt(nx * nx + ny * ny + nz * nz), eps)
        ux, uy, uz = nx / n_norm, ny / n_norm, nz / n_norm
        cos = (px / p_norm) * ux + (py / p_norm) * uy + (pz / p_norm) * uz
        sums[2] += one - cos
        # d cos / d p = (u - cos p / |p|) / |p| (the clamped norm is constant below eps).
        shrink = cos / p_norm if p_norm > eps else zero
        g[2] = -(ux - shrink * px) / p_norm * g_normal
        g[3] = -(uy - shrink * py) / p_norm * g_normal
        g[4] = -(uz - shrink * pz) / p_norm * g_normal
        # Albedo: relative L2, the denominator held constant.
        for c in range(3):
            a = _sigmoid(row[5 + c])
            diff = a - albedo[r, c]
            den = a * a + np.float32(1e-2)
            sums[3] += diff * diff / den
            g[5 + c] = np.float32(2.0) * diff / den * a * (one - a) * g_albedo
        if num_materials > 1:
            target = min(max(material[r], 0), num_materials - 1)
            m = row[8]
            for k in range(1, num_materials):
                m = max(m, row[8 + k])
            total = np.float64(0.0)
            for k in range(num_materials):
                total += np.exp(np.float64(row[8 + k] - m))
            lse = np.float64(m) + np.log(total)
            sums[4] += lse - row[8 + target]
            for k in range(num_materials):
                p = np.float32(np.exp(np.float64(row[8 + k]) - lse))
                g[8 + k] = (p - (one if k == target else zero)) * g_mat
    counts[0], counts[1], counts[2] = n_hit, wrong, all_hits


class _LossFromGradient(torch.autograd.Function):
    """A loss whose gradient in ``out`` was computed with it (the numba pass): backward scales it."""

    @staticmethod
    def forward(ctx, out: Tensor, value: float, grad: Tensor) -> Tensor:
        ctx.save_for_backward(grad)
        return out.new_tensor(value)

    @staticmethod
    def backward(ctx, g: Tensor):
        (grad,) = ctx.saved_tensors
        return grad * g, None, None


def _array(t: Tensor, dtype=None) -> np.ndarray:
    t = t.detach()
    return (t if dtype is None else t.to(dtype)).contiguous().numpy()


def training_loss_numba(out: Tensor, active: Tensor, t_offset: Tensor, t_enter: Tensor, t_exit: Tensor, directions: Tensor,
                        truth: Hits, weights: LossConfig, num_materials: int, occlusion_logit: float,
                        truncated: Tensor) -> TrainingLoss:  # fmt: skip
    """`training_loss` on CPU tensors: one numba pass (terms, figures and the gradient together)."""
    w = np.array([weights.occlusion, weights.distance, weights.normal, weights.albedo, weights.material], np.float64)
    grad = np.empty(tuple(out.shape), np.float32)
    sums = np.zeros(5, np.float64)
    counts = np.zeros(3, np.int64)
    _loss_kernel(_array(out, torch.float32), _array(active, torch.int64), _array(t_offset), _array(t_enter), _array(t_exit),
                 _array(directions), _array(truth.hit), _array(truth.t), _array(truth.normal), _array(truth.albedo),
                 _array(truth.material_id, torch.int64), w, num_materials, np.float32(occlusion_logit), grad, sums,
                 counts)  # fmt: skip
    n_net, (n_hit, wrong, all_hits) = len(active), counts.tolist()
    terms = ["occlusion"]
    if n_hit:
        terms += ["distance", "normal", "albedo"] + (["material"] if num_materials > 1 else [])
    means = {"occlusion": sums[0] / n_net if n_net else 0.0}
    if n_hit:
        means.update(distance=sums[1] / n_hit, normal=sums[2] / n_hit, albedo=sums[3] / (3 * n_hit), material=sums[4] / n_hit)
    # Each term as the fp32 value torch's mean would give (to rounding); the total from those.
    parts = {k: float(np.float32(means[k])) for k in terms}
    value = sum(float(w[_TERMS.index(k)]) * parts[k] for k in terms)
    loss = _LossFromGradient.apply(out, value, torch.from_numpy(grad))
    return TrainingLoss(loss, parts, wrong, all_hits - n_hit, int(truncated))

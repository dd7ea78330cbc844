"""LSNIF's training loss (paper Sec. 5.3) from the MLP's last hidden layer, with the step's figures.

Five terms, each weighted by `LossConfig`: occlusion BCE with logits over the network rays;
over the network rays that hit, distance L1 between the sigmoid output and the hit's fraction of
the ray's box interval, normal ``1 - cos`` against the exact normal turned towards the ray,
albedo relative L2 (``(a - y)^2 / (a^2 + 0.01)``, the denominator held constant) and, with more
than one material, material cross-entropy.

The loss takes the last hidden activations and the (fp32) output layer, so that the CPU can run
the output layer and the loss as one pass. Two implementations, chosen once by device
(`training_loss`): torch ops (`training_loss_torch`, any device: the output layer as
`MLP.forward` runs it, then the terms; the reference and the CUDA path) and, on the CPU, one
numba pass (`training_loss_numba`) that computes per ray the outputs (16-lane fp32 FMAs), the
terms and figures, and the gradients of the hidden activations and of the output layer's weight
and bias; its autograd function's backward only scales those. The numba passes run fixed
1,024-row chunks on the host's threads (the chunks' partial sums added in chunk order: the same
result on any thread count). The two agree to fp32 rounding (sums in another order; the hidden
gradient to one bf16 rounding step; tested against each other).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch
import torch.nn.functional as F
from numba import types
from numba.extending import overload
from torch import Tensor, nn

from ..neural.bf16_dot import as_fp32, bf16_bits, fma16, load16, load_bf16x16, store16, store_bf16x16, zeros16
from ..rays import Hits, face_forward
from .lsnif_config import LossConfig
from .lsnif_features import MIN_SPAN

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


def training_loss(hidden: Tensor, output_layer: nn.Linear, active: Tensor, t_offset: Tensor, t_enter: Tensor, t_exit: Tensor,
                  directions: Tensor, truth: Hits, weights: LossConfig, num_materials: int, occlusion_logit: float,
                  truncated: Tensor) -> TrainingLoss:  # fmt: skip
    """The loss of the network rays ``active`` (rows of the batch) whose last hidden activations are
    the first M rows of ``hidden [>= M, W]`` (fp32 or bf16; rows past M, the MLP's row padding,
    get a zero gradient); ``output_layer`` (fp32) maps them to the raw outputs ``[M, 8 +
    materials]`` (as `MLP.forward`). ``t_offset``/``t_enter``/``t_exit [M]`` place each ray's box
    interval, ``directions`` and ``truth`` are the whole batch's. On the CPU one numba pass for the
    output layer and the loss, elsewhere torch ops."""
    implementation = training_loss_numba if hidden.device.type == "cpu" else training_loss_torch
    return implementation(hidden, output_layer, active, t_offset, t_enter, t_exit, directions, truth, weights, num_materials,
                          occlusion_logit, truncated)  # fmt: skip


def training_loss_torch(hidden: Tensor, output_layer: nn.Linear, active: Tensor, t_offset: Tensor, t_enter: Tensor,
                        t_exit: Tensor, directions: Tensor, truth: Hits, weights: LossConfig, num_materials: int,
                        occlusion_logit: float, truncated: Tensor) -> TrainingLoss:  # fmt: skip
    """`training_loss` as torch ops (any device); one device->host read-back for all figures."""
    out = output_layer(hidden[: len(active)].float())  # the output layer in fp32, as `MLP.forward`
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
        t_local = (truth.t[ray_rows] - t_offset[hit_rows] - te) / torch.clamp(tx - te, min=MIN_SPAN)
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


def _narrow(dst, i, j, value):
    """``dst[i, j] = value`` in ``dst``'s precision: fp32 as is, bf16 bits rounded as torch's cast."""
    raise NotImplementedError("_narrow is for numba kernels (an @overload)")


@overload(_narrow, inline="always")
def _narrow_overload(dst, i, j, value):
    if dst.dtype == types.uint16:

        def store_bf16(dst, i, j, value):
            dst[i, j] = np.uint16(bf16_bits(value))

        return store_bf16

    def store(dst, i, j, value):
        dst[i, j] = value

    return store


def _load_row16(row, start):
    """``row[start : start + 16]`` as fp32 lanes: fp32 as is, bf16 bits widened exactly."""
    raise NotImplementedError("_load_row16 is for numba kernels (an @overload)")


@overload(_load_row16, inline="always")
def _load_row16_overload(row, start):
    if row.dtype == types.uint16:
        return lambda row, start: load_bf16x16(row, start)
    return lambda row, start: load16(row, start)


def _store_row16(row, start, value):
    """``row[start : start + 16] = value`` in ``row``'s precision (bf16 bits rounded as `_narrow`)."""
    raise NotImplementedError("_store_row16 is for numba kernels (an @overload)")


@overload(_store_row16, inline="always")
def _store_row16_overload(row, start, value):
    if row.dtype == types.uint16:
        return lambda row, start, value: store_bf16x16(row, start, value)
    return lambda row, start, value: store16(row, start, value)


@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _row_loss(row, sig, softplus, y, t_local, nx, ny, nz, ax, ay, az, target, num_materials, occlusion_logit, scale, g,
              sums):  # fmt: skip
    """One network ray's terms added into ``sums`` and d (weighted total) / d outputs written into
    ``g`` (``scale[term]`` = weight / ray count of the term); returns whether the hit/miss
    prediction is wrong. ``row``: the outputs, ``sig``: their sigmoids, ``softplus``: log(1 +
    exp(-|row[0]|)); ``y``: the ray hits; the rest is read only when it does."""
    one, zero = np.float32(1.0), np.float32(0.0)
    x = row[0]
    # BCE with logits, stable form: max(x, 0) - x y + log(1 + exp(-|x|)).
    sums[0] += max(x, zero) - (x if y else zero) + softplus
    g[0] = (sig[0] - (one if y else zero)) * scale[0]
    wrong = (x > occlusion_logit) != y
    if not y:
        return wrong
    # Distance: L1 between sigmoid(out) and the hit's fraction of [t_enter, t_exit].
    s = sig[1]
    d = s - t_local
    sums[1] += abs(d)
    g[1] = (one if d > 0 else (-one if d < 0 else zero)) * s * (one - s) * scale[1]
    # Normal: 1 - cos(out, exact normal facing the ray); norms clamped at eps as torch does.
    px, py, pz = row[2], row[3], row[4]
    eps = np.float32(1e-8)
    p_norm = max(np.sqrt(px * px + py * py + pz * pz), eps)
    n_norm = max(np.sqrt(nx * nx + ny * ny + nz * nz), eps)
    ux, uy, uz = nx / n_norm, ny / n_norm, nz / n_norm
    cos = (px / p_norm) * ux + (py / p_norm) * uy + (pz / p_norm) * uz
    sums[2] += one - cos
    # d cos / d p = (u - cos p / |p|) / |p| (the clamped norm is constant below eps).
    shrink = cos / p_norm if p_norm > eps else zero
    g[2] = -(ux - shrink * px) / p_norm * scale[2]
    g[3] = -(uy - shrink * py) / p_norm * scale[2]
    g[4] = -(uz - shrink * pz) / p_norm * scale[2]
    # Albedo: relative L2, the denominator held constant.
    for c in range(3):
        a = sig[5 + c]
        diff = a - (ax if c == 0 else (ay if c == 1 else az))
        den = a * a + np.float32(1e-2)
        sums[3] += diff * diff / den
        g[5 + c] = np.float32(2.0) * diff / den * a * (one - a) * scale[3]
    if num_materials > 1:
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
            g[8 + k] = (p - (one if k == target else zero)) * scale[4]
    return wrong


# Rows per task of the two passes below. Fixed, not per thread: the chunk partials of the loss
# pass are summed in chunk order, so the sums are the same whatever the thread count. Passed to
# the kernels, not a compile-time global, so benchmarks can try other sizes: 256 (more tasks for
# 16 threads at a 2^13 batch's ~5,400 network rays) measured no faster in whole training, on 16
# threads or on 2 (`bench_training.py --pair loss_chunks`, docs/lsnif.md).
CHUNK_ROWS = 1024


@numba.njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _output_layer_kernel(hidden, weight_t, bias, out, chunk_rows):
    """``out [M, C] = hidden @ W^T + b`` in fp32, ``hidden [M, W]`` fp32 or bf16 bits (uint16),
    ``weight_t`` W^T zero-padded to ``[Wp, Cp]`` (multiples of 16) and flattened. 4 rows at once
    (4 independent FMA chains; each row's sum in j order), 16 outputs at a time; past the last row
    of a chunk the last one repeats. Rows in chunks of ``chunk_rows`` over the threads."""
    n_net, width = hidden.shape
    n_out = bias.shape[0]
    padded_out = weight_t.shape[0] // (-(-width // 16) * 16)
    for chunk in numba.prange(-(-n_net // chunk_rows)):
        lo = chunk * chunk_rows
        hi = min(lo + chunk_rows, n_net)
        h32 = np.zeros((4, width), np.float32)
        group_out = np.zeros((4, padded_out), np.float32)
        for first in range(lo, hi, 4):
            for p in range(4):
                row_index = min(first + p, hi - 1)
                for j in range(width):
                    h32[p, j] = as_fp32(hidden[row_index, j])
            h0, h1, h2, h3 = h32[0], h32[1], h32[2], h32[3]
            for cb in range(0, padded_out, 16):
                a0, a1, a2, a3 = zeros16(), zeros16(), zeros16(), zeros16()
                for j in range(width):
                    at = j * padded_out + cb
                    a0, a1 = fma16(a0, h0[j], weight_t, at), fma16(a1, h1[j], weight_t, at)
                    a2, a3 = fma16(a2, h2[j], weight_t, at), fma16(a3, h3[j], weight_t, at)
                store16(group_out[0], cb, a0), store16(group_out[1], cb, a1)
                store16(group_out[2], cb, a2), store16(group_out[3], cb, a3)
            for p in range(min(4, hi - first)):
                for k in range(n_out):
                    out[first + p, k] = group_out[p, k] + bias[k]


@numba.njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _head_loss_kernel(hidden, weight, out, sig, softplus, active, t_offset, t_enter, t_exit, directions, hit, t_true, normal,
                      albedo, material, weights, num_materials, occlusion_logit, grad_hidden, grad_weight, grad_bias, sums,
                      counts, chunk_rows):  # fmt: skip
    """The loss and the gradients from the output layer's outputs ``out [M, C]`` (their sigmoids
    ``sig`` and the BCE's ``softplus`` = log(1 + exp(-|out[:, 0]|)) computed beforehand, vectorized):
    the terms of `training_loss_torch` summed into ``sums`` (float64, not divided by the counts),
    ``counts`` = (network rays that hit, wrong predictions, all hits of the batch); d loss / d
    hidden into ``grad_hidden`` (hidden's dtype, rounded as torch's cast), d loss / d W
    (``grad_weight``, ``[C, Wp]`` flattened, ``weight`` the same layout) and d loss / d b.
    Rows in chunks of ``chunk_rows`` over the threads; each chunk's sums, d W and d b are partials
    (float64) added up in chunk order afterwards."""
    n_net, width = hidden.shape
    n_out = out.shape[1]
    padded_width = weight.shape[0] // n_out
    full_width = width // 16 * 16  # hidden units written 16 at a time; the rest one by one
    n_hit = 0
    for i in range(n_net):
        n_hit += hit[active[i]]
    all_hits = 0
    for r in range(hit.shape[0]):
        all_hits += hit[r]
    scale = np.empty(5, np.float32)
    scale[0] = weights[0] / max(n_net, 1)
    scale[1] = weights[1] / max(n_hit, 1)
    scale[2] = weights[2] / max(n_hit, 1)
    scale[3] = weights[3] / max(3 * n_hit, 1)
    scale[4] = weights[4] / max(n_hit, 1)
    n_chunks = -(-n_net // chunk_rows)
    chunk_sums = np.zeros((n_chunks, 5), np.float64)
    chunk_wrong = np.zeros(n_chunks, np.int64)
    chunk_bias = np.zeros((n_chunks, n_out), np.float64)
    chunk_weight = np.zeros((n_chunks, n_out * padded_width), np.float32)
    one, zero = np.float32(1.0), np.float32(0.0)
    for chunk in numba.prange(n_chunks):
        row32 = np.zeros(padded_width, np.float32)
        g = np.zeros(n_out, np.float32)
        dh = np.zeros(padded_width, np.float32)
        part_sums, part_weight, part_bias = chunk_sums[chunk], chunk_weight[chunk], chunk_bias[chunk]
        wrong = 0
        for i in range(chunk * chunk_rows, min((chunk + 1) * chunk_rows, n_net)):
            r = active[i]
            y = hit[r]
            t_local = zero
            nx = ny = nz = ax = ay = az = zero
            target = 0
            if y:
                te, tx = t_enter[i], t_exit[i]
                t_local = min(max((t_true[r] - t_offset[i] - te) / max(tx - te, np.float32(MIN_SPAN)), zero), one)
                nx, ny, nz = normal[r, 0], normal[r, 1], normal[r, 2]
                if nx * directions[r, 0] + ny * directions[r, 1] + nz * directions[r, 2] > 0:
                    nx, ny, nz = -nx, -ny, -nz
                ax, ay, az = albedo[r, 0], albedo[r, 1], albedo[r, 2]
                target = min(max(material[r], 0), num_materials - 1)
            g[:] = zero
            wrong += _row_loss(out[i], sig[i], softplus[i], y, t_local, nx, ny, nz, ax, ay, az, target, num_materials,
                               occlusion_logit, scale, g, part_sums)  # fmt: skip
            # d hidden = g @ W, 16 hidden units at a time. A miss's only nonzero g is the occlusion's:
            # one branch per row, not one per product (those, mispredicted with hits and misses mixed,
            # made the pass 1.18x slower: 0.394 against 0.333 ms for 5,632 rows x 128 units, 2 threads).
            for jb in range(0, padded_width, 16):
                acc = fma16(zeros16(), g[0], weight, jb)
                if y:
                    for k in range(1, n_out):
                        acc = fma16(acc, g[k], weight, k * padded_width + jb)
                store16(dh, jb, acc)
            hidden_row, grad_row = hidden[i], grad_hidden[i]
            for jb in range(0, full_width, 16):
                _store_row16(grad_row, jb, load16(dh, jb))
                store16(row32, jb, _load_row16(hidden_row, jb))
            for j in range(full_width, width):
                _narrow(grad_hidden, i, j, dh[j])
                row32[j] = as_fp32(hidden_row[j])
            # d W += g^T h over the nonzero g.
            for k in range(n_out):
                gk = g[k]
                if gk != zero:
                    part_bias[k] += gk
                    for jb in range(0, padded_width, 16):
                        at = k * padded_width + jb
                        store16(part_weight, at, fma16(load16(part_weight, at), gk, row32, jb))
        chunk_wrong[chunk] = wrong
    weight_sum = np.zeros(n_out * padded_width, np.float64)
    bias_sum = np.zeros(n_out, np.float64)
    wrong = 0
    for chunk in range(n_chunks):
        for t in range(5):
            sums[t] += chunk_sums[chunk, t]
        for k in range(n_out):
            bias_sum[k] += chunk_bias[chunk, k]
        for a in range(n_out * padded_width):
            weight_sum[a] += chunk_weight[chunk, a]
        wrong += chunk_wrong[chunk]
    for a in range(n_out * padded_width):
        grad_weight[a] = weight_sum[a]
    for k in range(n_out):
        grad_bias[k] = bias_sum[k]
    counts[0], counts[1], counts[2] = n_hit, wrong, all_hits


class _HeadLoss(torch.autograd.Function):
    """The output layer plus the loss, whose gradients in the hidden activations and the output
    layer's weight and bias were computed with it (the numba pass): backward only scales them."""

    @staticmethod
    def forward(ctx, hidden: Tensor, weight: Tensor, bias: Tensor, value: float, grad_hidden: Tensor, grad_weight: Tensor,
                grad_bias: Tensor) -> Tensor:  # fmt: skip
        ctx.save_for_backward(grad_hidden, grad_weight, grad_bias)
        return hidden.new_tensor(value, dtype=torch.float32)

    @staticmethod
    def backward(ctx, g: Tensor):
        grads = ctx.saved_tensors
        if float(g) != 1.0:  # (the training loop's backward() hands in 1: no pass over [M, W])
            grads = [t * g for t in grads]
        return (*grads, None, None, None, None)


def _array(t: Tensor, dtype=None) -> np.ndarray:
    t = t.detach()
    return (t if dtype is None else t.to(dtype)).contiguous().numpy()


def _padded16(n: int) -> int:
    return -(-n // 16) * 16


def training_loss_numba(hidden: Tensor, output_layer: nn.Linear, active: Tensor, t_offset: Tensor, t_enter: Tensor,
                        t_exit: Tensor, directions: Tensor, truth: Hits, weights: LossConfig, num_materials: int,
                        occlusion_logit: float, truncated: Tensor) -> TrainingLoss:  # fmt: skip
    """`training_loss` on CPU tensors: the output layer and the loss in one numba pass (outputs,
    terms, figures and the gradients of the hidden activations and the output layer together)."""
    w = np.array([weights.occlusion, weights.distance, weights.normal, weights.albedo, weights.material], np.float64)
    n_net, width = len(active), hidden.shape[1]
    n_out = output_layer.out_features
    padded_width, padded_out = _padded16(width), _padded16(n_out)
    weight = output_layer.weight.detach()
    weight_t = np.zeros((padded_width, padded_out), np.float32)
    weight_t[:width, :n_out] = weight.t().numpy()
    weight_rows = np.zeros((n_out, padded_width), np.float32)
    weight_rows[:, :width] = weight.numpy()
    low = hidden.dtype == torch.bfloat16
    hidden_np = hidden.detach().contiguous().view(torch.int16).numpy().view(np.uint16) if low else _array(hidden, torch.float32)
    hidden_np = hidden_np[:n_net]
    # d loss / d hidden for all of hidden's rows: zeros past the network rays' (the padding's gradient
    # goes to the MLP's backward as it is, no copy there)
    padded_grad_hidden = np.empty((len(hidden), width), hidden_np.dtype)
    padded_grad_hidden[n_net:] = 0
    grad_hidden = padded_grad_hidden[:n_net]
    grad_weight = np.empty(n_out * padded_width, np.float32)
    grad_bias = np.empty(n_out, np.float32)
    out = np.empty((n_net, n_out), np.float32)
    bias = _array(output_layer.bias)
    _output_layer_kernel(hidden_np, weight_t.reshape(-1), bias, out, CHUNK_ROWS)
    # The sigmoids and the BCE's softplus as vectorized torch ops (numba has no vector exp here).
    out_t = torch.from_numpy(out)
    sig = torch.sigmoid(out_t).numpy()
    softplus = torch.log1p(torch.exp(-out_t[:, 0].abs())).numpy()
    sums = np.zeros(5, np.float64)
    counts = np.zeros(3, np.int64)
    _head_loss_kernel(hidden_np, weight_rows.reshape(-1), out, sig, softplus, _array(active, torch.int64), _array(t_offset),
                      _array(t_enter), _array(t_exit), _array(directions), _array(truth.hit), _array(truth.t),
                      _array(truth.normal), _array(truth.albedo), _array(truth.material_id, torch.int64), w, num_materials,
                      np.float32(occlusion_logit), grad_hidden, grad_weight, grad_bias, sums, counts, CHUNK_ROWS)  # fmt: skip
    n_hit, wrong, all_hits = counts.tolist()
    terms = ["occlusion"]
    if n_hit:
        terms += ["distance", "normal", "albedo"] + (["material"] if num_materials > 1 else [])
    means = {"occlusion": sums[0] / n_net if n_net else 0.0}
    if n_hit:
        means.update(distance=sums[1] / n_hit, normal=sums[2] / n_hit, albedo=sums[3] / (3 * n_hit), material=sums[4] / n_hit)
    # Each term as the fp32 value torch's mean would give (to rounding); the total from those.
    parts = {k: float(np.float32(means[k])) for k in terms}
    value = sum(float(w[_TERMS.index(k)]) * parts[k] for k in terms)
    grad_hidden_t = torch.from_numpy(padded_grad_hidden)
    if low:
        grad_hidden_t = grad_hidden_t.view(torch.bfloat16)
    grad_weight_t = torch.from_numpy(grad_weight.reshape(n_out, padded_width)[:, :width].copy())
    loss = _HeadLoss.apply(hidden, output_layer.weight, output_layer.bias, value, grad_hidden_t, grad_weight_t,
                           torch.from_numpy(grad_bias))  # fmt: skip
    return TrainingLoss(loss, parts, wrong, all_hits - n_hit, int(truncated))

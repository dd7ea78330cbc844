"""N-BVH's wavefront inference on the CPU: per step one numba pass for the network, one to decode.

The same loop as `NBVHModel._closest_torch` and `nbvh_wavefront_triton` (each ray's leaf list
made once, then per step the next leaf of every active ray, one batched query, the closest
accepted hit kept, compaction), with the per-step torch ops (about 40 gathers, masks and
scatters a step) folded into numba passes:

- `_step_outputs_kernel` (parallel, 8 rays a block): each active ray's current leaf entry, its
  chord (reversed when the origin is inside the leaf), the 3 chord points, all 8 levels encoded by
  the hash grid's `encode_group` (a block's rows prefetched before any is read), rounded to bf16
  and through the MLP (`neural/mlp_rows_cpu`: bf16 hidden layers, fp32 output layer) into the
  ray's raw outputs. Where the model computes in fp32, or the CPU has AMX (`MLP_IN_PASS`),
  `_step_inputs_kernel` writes the encoded input rows instead and torch's GEMMs run the MLP;
- `_step_decode` (one thread: a few loads and compares a ray, against a parallel launch's cost):
  LocalT decoding, the acceptance rules, the best hit and its output row updated in place, the
  ray's list pointer advanced, and the ray kept for the next step when it has more leaves, no
  accepted hit for `occluded`, and its next leaf is entered before its best hit; the kept rays
  are written in order as the next step's active list.

Same answers as the torch loop: the chord points and features bit for bit, the decoding up to
`sigmoid`'s rounding, the in-pass MLP within bf16 rounding of torch's bf16 GEMMs (tests/test_nbvh.py).
Bunny, 2 cores (docs/nbvh.md, session 38): 0.49x the torch loop's time.

Around the loop, `answers_cpu` is `NBVHModel._answer` on the CPU: the valid rays moved into the
unit cube before it and the hit records decoded after it, each one numba pass (the same records
as `_answer_torch`'s torch ops; session 39: 0.82x the time of a bunny `intersect`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from ..neural.bf16_dot import bf16_bits, dot_rows_bf16, fma_f32
from ..neural.hash_grid import PREFETCH_GROUP, encode_group
from ..neural.mlp_rows_cpu import (
    BLOCK_ROWS, HOST_HAS_AMX, bias_leaky_bf16, hidden_layer_pairs, hidden_layers_bf16, layer_pairs, output_layer_columns, output_rows,
    sigmoid, widen_rows_bf16,
)  # fmt: skip
from ..rays import Hits, Rays
from ..rays_kernels import valid_ray, write_miss
from ..task_queue import task_count

__all__ = ["closest_hits_cpu", "answers_cpu"]


@numba.njit(cache=True, inline="always")
def _chord_points(active, first, stop, ptr, t0s, t1s, origins, directions, fractions, points):
    """``points[k - first]`` ([P, 3]): active ray ``active[k]``'s chord points in its current leaf, k in [first, stop)."""
    for k in range(first, stop):
        ray = active[k]
        e = ptr[ray]
        t0, t1 = t0s[e], t1s[e]
        inside = t0 < 0  # a ray starting inside the leaf asks for the reversed chord
        a = t1 if inside else t0
        b = t0 if inside else t1
        for j in range(fractions.shape[0]):
            t = a + fractions[j] * (b - a)  # as torch: a + fractions * (b - a), then o + t * d
            for axis in range(3):
                points[k - first, j, axis] = origins[ray, axis] + t * directions[ray, axis]


@numba.njit(parallel=True, cache=True)
def _step_inputs_kernel(active, ptr, t0s, t1s, origins, directions, fractions, table, resolutions, sizes, offsets, n_chunks, x):
    """Row ``k`` of ``x`` [K, P * L * F]: active ray ``active[k]``'s chord through its current leaf, encoded."""
    n, n_points = active.shape[0], fractions.shape[0]
    per_ray = n_points * resolutions.shape[0] * 8
    for chunk in numba.prange(n_chunks):
        points = np.empty((PREFETCH_GROUP, n_points, 3), np.float32)
        rows = np.empty(PREFETCH_GROUP * per_ray, np.int64)
        weights = np.empty(PREFETCH_GROUP * per_ray, np.float32)
        acc = np.empty(table.shape[1], np.float32)
        last = (chunk + 1) * n // n_chunks
        for first in range(chunk * n // n_chunks, last, PREFETCH_GROUP):
            stop = min(first + PREFETCH_GROUP, last)
            _chord_points(active, first, stop, ptr, t0s, t1s, origins, directions, fractions, points)
            encode_group(points, 0, stop - first, table, resolutions, sizes, offsets, rows, weights, acc, x, first)


@numba.njit(parallel=True, cache=True)
def _step_outputs_kernel(active, ptr, t0s, t1s, origins, directions, fractions, table, resolutions, sizes, offsets,
                         w1_pairs, b1, hidden_pairs, hidden_bias, slope, wo_flat, bo, n_chunks, out):  # fmt: skip
    """Row ``k`` of ``out`` [K, outputs]: the network's raw outputs for active ray ``active[k]``'s
    chord through its current leaf, `BLOCK_ROWS` rays at a time: their chord points encoded
    (`encode_group`), rounded to bf16 pairs, the first layer (``w1_pairs``/``b1``, `layer_pairs`),
    the later hidden layers (`hidden_layers_bf16`) and the fp32 output layer (`output_rows`)."""
    n, n_points = active.shape[0], fractions.shape[0]
    per_ray = n_points * resolutions.shape[0] * 8
    in_half = (n_points * resolutions.shape[0] * table.shape[1] + 1) // 2
    width = b1.shape[0]
    n_padded, n_out = bo.shape[0], out.shape[1]
    for chunk in numba.prange(n_chunks):
        points = np.empty((BLOCK_ROWS, n_points, 3), np.float32)
        rows = np.empty(BLOCK_ROWS * per_ray, np.int64)
        weights = np.empty(BLOCK_ROWS * per_ray, np.float32)
        acc = np.empty(table.shape[1], np.float32)
        x = np.zeros((BLOCK_ROWS, 2 * in_half), np.float32)  # (an odd input count: a zero last column)
        x_pairs = np.zeros((BLOCK_ROWS, in_half), np.uint32)
        xp = np.zeros((BLOCK_ROWS, width // 2), np.uint32)
        xp_bf16 = xp.reshape(-1).view(np.uint16)
        quad = np.empty(4, np.int64)
        dots = np.empty(4 * width, np.float32)
        hidden = np.empty(BLOCK_ROWS * width, np.float32)
        outs = np.empty(BLOCK_ROWS * n_padded, np.float32)
        last = (chunk + 1) * n // n_chunks
        for first in range(chunk * n // n_chunks, last, BLOCK_ROWS):
            stop = min(first + BLOCK_ROWS, last)
            _chord_points(active, first, stop, ptr, t0s, t1s, origins, directions, fractions, points)
            # (a short block leaves its last rows' earlier values: computed, never written out)
            encode_group(points, 0, stop - first, table, resolutions, sizes, offsets, rows, weights, acc, x, 0)
            for b in range(BLOCK_ROWS):
                for q in range(in_half):
                    x_pairs[b, q] = bf16_bits(x[b, 2 * q]) | (bf16_bits(x[b, 2 * q + 1]) << np.uint32(16))
            for g in range(0, BLOCK_ROWS, 4):
                for i in range(4):
                    quad[i] = g + i
                dot_rows_bf16(x_pairs, quad, in_half, w1_pairs, 0, width, dots)
                for i in range(4):
                    bias_leaky_bf16(dots, i * width, b1, 0, width, slope, xp_bf16, (g + i) * width)
            hidden_layers_bf16(hidden_pairs, hidden_bias, slope, xp, xp_bf16, quad, dots)
            widen_rows_bf16(xp_bf16, hidden)
            output_rows(hidden, wo_flat, bo, n_padded, n_padded, outs)
            for b in range(stop - first):
                for j in range(n_out):
                    out[first + b, j] = outs[b * n_padded + j]


@numba.njit(cache=True)
def _step_decode(active, ptr, start, t0s, t1s, t_max, out, threshold, depth_pad, reversed_min, any_hit, best_t, best_out, kept):
    """Decode row ``k`` of ``out`` for ray ``active[k]``; the rays that go on into ``kept``; returns their count."""
    m = 0
    for k in range(active.shape[0]):
        ray = active[k]
        e = ptr[ray]
        t0, t1 = t0s[e], t1s[e]
        inside = t0 < 0
        length = t1 - t0
        depth = sigmoid(out[k, 1]) * (length + depth_pad)
        t = t1 - depth if inside else t0 + depth
        accept = out[k, 0] > threshold and t > 0 and t <= t_max[ray]
        accept = accept and (not inside or t > reversed_min * length + np.float32(1e-5))  # skip the surface a ray starts on
        best = best_t[ray]
        if accept and t < best:
            best = t
            best_t[ray] = t
            best_out[ray, :] = out[k, :]
        nxt = e + 1
        ptr[ray] = nxt
        # Lists are sorted by entry: a next leaf entered beyond the best hit cannot hold a closer one.
        if nxt < start[ray + 1] and not (any_hit and accept) and t0s[nxt] < best:
            kept[m] = ray
            m += 1
    return m


# The MLP inside the step pass (`_step_outputs_kernel`: numba's bf16 layers, `mlp_rows_cpu`) where
# the model computes in bf16, its width is a multiple of 16 and the CPU has no AMX (oneDNN's AMX
# GEMMs win there, as for LSNIF); False: torch's GEMMs on the inputs the pass writes
# (`_step_inputs_kernel`), as in fp32; None: that default. The pass differs from torch's bf16
# GEMMs within bf16 rounding (summation order, one rounding of negative activations).
MLP_IN_PASS: bool | None = None


def mlp_in_pass(network, compute_dtype: torch.dtype) -> bool:
    """Whether the step runs ``network`` inside its numba pass (see MLP_IN_PASS)."""
    if compute_dtype != torch.bfloat16 or network.hidden[0].weight.shape[0] % 16:
        return False
    return not HOST_HAS_AMX if MLP_IN_PASS is None else MLP_IN_PASS


def _network_arrays(network) -> tuple:
    """(first layer pairs, its bias, the later hidden layers' pairs and biases, output weights, output bias)
    for `_step_outputs_kernel`, kept on ``network`` until a parameter changes (keyed as `MLP._cast_weights`)."""
    key = tuple((t.data_ptr(), t._version, t.shape) for t in network.parameters())
    cached = getattr(network, "_nbvh_cpu_arrays", None)
    if cached is None or cached[0] != key:
        w1, b1 = layer_pairs(*network._cast_weights(torch.bfloat16)[0])
        hidden_pairs, hidden_bias = hidden_layer_pairs(network)
        wo, bo = output_layer_columns(network)
        cached = (key, (w1, b1, hidden_pairs, hidden_bias, np.float32(network.slope), wo.reshape(-1), bo))
        network._nbvh_cpu_arrays = cached
    return cached[1]


@torch.no_grad()
def closest_hits_cpu(model, o: Tensor, d: Tensor, t_max: Tensor, any_hit: bool) -> tuple[Tensor, Tensor]:
    """`NBVHModel._closest` with the per-step numba passes: (t [K] unit, inf where missed; raw outputs of the accepted hit)."""
    from .nbvh import _DEPTH_PAD, _REVERSED_MIN

    k = len(o)
    inf = model.config.inference
    leaves = model.leaf_list(o, d, t_max, torch.full((k,), inf.lod, dtype=torch.int8), torch.full((k,), inf.box_dilation))
    start = leaves.start.numpy()
    ptr = start[:-1].copy()
    t0s, t1s = leaves.t0.float().contiguous().numpy(), leaves.t1.float().contiguous().numpy()
    outputs = 8 + model.material_logits
    best_t = np.full(k, np.inf, np.float32)
    best_out = np.zeros((k, outputs), np.float32)
    threshold = np.float32(math.log(inf.occlusion_threshold / (1 - inf.occlusion_threshold)))
    dtype = model.compute_dtype()
    grid = model.encoder
    table = grid.table.detach().float().contiguous().numpy()
    res, sizes, offsets = grid.layout.arrays()
    fractions = model._fractions(1, "cpu")[0].float().contiguous().numpy()
    width = grid.output_dim(len(fractions))
    origins, directions = o.float().contiguous().numpy(), d.float().contiguous().numpy()
    t_max_np = t_max.float().contiguous().numpy()
    in_pass = mlp_in_pass(model.network, dtype)
    weights = _network_arrays(model.network) if in_pass else ()
    active = np.nonzero(ptr < start[1:])[0]
    kept = np.empty(k, np.int64)
    for _ in range(inf.max_steps):
        n = len(active)
        if n == 0:
            break
        tasks = task_count(n, BLOCK_ROWS)
        if in_pass:
            out = np.empty((n, outputs), np.float32)
            _step_outputs_kernel(active, ptr, t0s, t1s, origins, directions, fractions, table, res, sizes, offsets, *weights, tasks, out)
        else:
            x = np.empty((n, width), np.float32)
            _step_inputs_kernel(active, ptr, t0s, t1s, origins, directions, fractions, table, res, sizes, offsets, tasks, x)
            out = model.network(torch.from_numpy(x), dtype).float().contiguous().numpy()
        m = _step_decode(active, ptr, start, t0s, t1s, t_max_np, out, threshold, np.float32(_DEPTH_PAD), np.float32(_REVERSED_MIN),
                         any_hit, best_t, best_out, kept)  # fmt: skip
        active = kept[:m].copy()
    return torch.from_numpy(best_t), torch.from_numpy(best_out)


# ---------------------------------------------------------------------------------------------
# Before and after the wavefront: `NBVHModel._unit_rays` and `NBVHModel._answer_torch`'s decoding
# as two numba passes (on the bunny's 2^16 rays their ~30 torch ops took ~4.5 ms, 14% of an
# `intersect`)


@numba.njit(parallel=True, cache=True)
def _valid_kernel(origins, directions, t_min, t_max, valid):
    for i in numba.prange(origins.shape[0]):
        valid[i] = valid_ray(origins, directions, t_min, t_max, i)


@numba.njit(parallel=True, cache=True)
def _unit_rays_kernel(idx, origins, directions, t_min, t_max, unit_lo, unit_scale, o, d, t_max_unit, to_ray_t, t_off):
    """Rays ``idx`` (valid) moved to their ``t_min`` (where positive and finite) in the unit cube,
    with unit directions: `NBVHModel._unit_rays`' float32 operations in its order (the norm's
    fused multiply-adds, ``scale / norm`` as torch's reciprocal times the scale), the same bits."""
    zero, one = np.float32(0.0), np.float32(1.0)
    for k in numba.prange(idx.shape[0]):
        i = idx[k]
        tm = t_min[i]
        off = tm if np.isfinite(tm) and tm > zero else zero
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        norm = np.sqrt(fma_f32(dz, dz, fma_f32(dy, dy, dx * dx)))
        for a in range(3):
            da = directions[i, a]
            o[k, a] = ((origins[i, a] + off * da) - unit_lo[a]) / unit_scale
            d[k, a] = da / norm
        scale = (one / norm) * unit_scale
        to_ray_t[k], t_off[k] = scale, off
        t_max_unit[k] = np.nextafter((t_max[i] - off) / scale, np.float32(np.inf))  # (`NBVHModel._unit_rays`)


@numba.njit(parallel=True, cache=True)
def _answer_kernel(idx, t, out, d, t_off, to_ray_t, t_max, n_logits, hit, t_hit, normal, geometric_normal, uv, albedo, material,
                   primitive_id, instance_id):  # fmt: skip
    """Every row of the records (`Hits`' fields) written: a miss, then for ray ``idx[k]`` with a
    hit (``t[k]`` finite, unit t; ``out[k]`` its raw outputs) the answer, decoded as
    `NBVHModel._answer_torch` decodes it (normal turned to face ``d[k]``, then normalised; albedo
    through the sigmoid; the first largest of ``n_logits`` material logits, or material 0)."""
    for r in numba.prange(hit.shape[0]):
        write_miss(r, hit, t_hit, normal, geometric_normal, uv, albedo, material, primitive_id, instance_id)
    for k in numba.prange(idx.shape[0]):
        if not np.isfinite(t[k]):
            continue
        r = idx[k]
        hit[r] = True
        t_hit[r] = min(t_off[k] + t[k] * to_ray_t[k], t_max[r])  # (`NBVHModel._answer_torch`)
        nx, ny, nz = out[k, 2], out[k, 3], out[k, 4]
        if (nx * d[k, 0] + ny * d[k, 1]) + nz * d[k, 2] > 0:  # `face_forward`
            nx, ny, nz = -nx, -ny, -nz
        norm = max(np.sqrt(fma_f32(nz, nz, fma_f32(ny, ny, nx * nx))), np.float32(1e-12))  # as F.normalize
        normal[r, 0], normal[r, 1], normal[r, 2] = nx / norm, ny / norm, nz / norm
        geometric_normal[r, 0], geometric_normal[r, 1], geometric_normal[r, 2] = normal[r, 0], normal[r, 1], normal[r, 2]
        for c in range(3):
            albedo[r, c] = sigmoid(out[k, 5 + c])
        best = 0
        for j in range(1, n_logits):
            if out[k, 8 + j] > out[k, 8 + best]:
                best = j
        material[r] = best


@torch.no_grad()
def answers_cpu(model, rays: Rays, any_hit: bool) -> Hits:
    """`NBVHModel._answer` on the CPU: the unit rays, `closest_hits_cpu`, the records, each a numba pass."""
    n = len(rays)
    origins, directions = rays.origins.float().contiguous().numpy(), rays.directions.float().contiguous().numpy()
    t_min, t_max = rays.t_min.float().contiguous().numpy(), rays.t_max.float().contiguous().numpy()
    valid = np.empty(n, np.bool_)
    _valid_kernel(origins, directions, t_min, t_max, valid)
    idx = np.flatnonzero(valid)
    k = len(idx)
    o, d = np.empty((k, 3), np.float32), np.empty((k, 3), np.float32)
    t_max_unit, to_ray_t, t_off = np.empty(k, np.float32), np.empty(k, np.float32), np.empty(k, np.float32)
    unit_lo = model.unit_lo.float().contiguous().numpy()
    _unit_rays_kernel(idx, origins, directions, t_min, t_max, unit_lo, np.float32(model.unit_scale), o, d, t_max_unit, to_ray_t, t_off)
    hits = Hits.uninitialized(n)
    t, out = closest_hits_cpu(model, torch.from_numpy(o), torch.from_numpy(d), torch.from_numpy(t_max_unit), any_hit)
    records = (hits.hit, hits.t, hits.normal, hits.geometric_normal, hits.uv, hits.albedo, hits.material_id, hits.primitive_id,
               hits.instance_id)  # (`write_miss`' order)
    _answer_kernel(idx, t.numpy(), out.numpy(), d, t_off, to_ray_t, t_max, model.material_logits, *(c.numpy() for c in records))
    return hits

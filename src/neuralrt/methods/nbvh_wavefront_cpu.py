"""N-BVH's wavefront inference on the CPU: two numba passes around the MLP per step.

The same loop as `NBVHModel._closest_torch` and `nbvh_wavefront_triton` (each ray's leaf list
made once, then per step the next leaf of every active ray, one batched query, the closest
accepted hit kept, compaction), with the per-step torch ops (about 40 gathers, masks and
scatters a step) folded into two passes:

- `_step_inputs_kernel` (parallel): the ray's current leaf entry, its chord (reversed when the
  origin is inside the leaf), the 3 chord points, all 8 levels encoded by the hash grid's
  `encode_group` (a group's rows prefetched before any is read), written as the network's input row;
- the MLP as torch GEMMs (`MLP.forward`, bf16 where the CPU has it);
- `_step_decode` (one thread: a few loads and compares a ray, against a parallel launch's cost):
  LocalT decoding, the acceptance rules, the best hit and its output row updated in place, the
  ray's list pointer advanced, and the ray kept for the next step when it has more leaves, no
  accepted hit for `occluded`, and its next leaf is entered before its best hit; the kept rays
  are written in order as the next step's active list.

Same answers as the torch loop: the chord points and features bit for bit, the decoding up to
`sigmoid`'s rounding (tests/test_nbvh.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from ..neural.hash_grid import FORWARD_GROUP, encode_group
from ..task_queue import task_count

__all__ = ["closest_hits_cpu"]


@numba.njit(parallel=True, cache=True)
def _step_inputs_kernel(active, ptr, t0s, t1s, origins, directions, fractions, table, resolutions, sizes, offsets, n_chunks, x):
    """Row ``k`` of ``x`` [K, P * L * F]: active ray ``active[k]``'s chord through its current leaf, encoded."""
    n, n_points = active.shape[0], fractions.shape[0]
    per_ray = n_points * resolutions.shape[0] * 8
    for chunk in numba.prange(n_chunks):
        points = np.empty((FORWARD_GROUP, n_points, 3), np.float32)
        rows = np.empty(FORWARD_GROUP * per_ray, np.int64)
        weights = np.empty(FORWARD_GROUP * per_ray, np.float32)
        acc = np.empty(table.shape[1], np.float32)
        last = (chunk + 1) * n // n_chunks
        for first in range(chunk * n // n_chunks, last, FORWARD_GROUP):
            stop = min(first + FORWARD_GROUP, last)
            for k in range(first, stop):
                ray = active[k]
                e = ptr[ray]
                t0, t1 = t0s[e], t1s[e]
                inside = t0 < 0  # a ray starting inside the leaf asks for the reversed chord
                a = t1 if inside else t0
                b = t0 if inside else t1
                for j in range(n_points):
                    t = a + fractions[j] * (b - a)  # as torch: a + fractions * (b - a), then o + t * d
                    for axis in range(3):
                        points[k - first, j, axis] = origins[ray, axis] + t * directions[ray, axis]
            encode_group(points, 0, stop - first, table, resolutions, sizes, offsets, rows, weights, acc, x, first)


@numba.njit(cache=True)
def _step_decode(active, ptr, start, t0s, t1s, t_max, out, threshold, depth_pad, reversed_min, any_hit, best_t, best_out, kept):
    """Decode row ``k`` of ``out`` for ray ``active[k]``; the rays that go on into ``kept``; returns their count."""
    one = np.float32(1.0)
    m = 0
    for k in range(active.shape[0]):
        ray = active[k]
        e = ptr[ray]
        t0, t1 = t0s[e], t1s[e]
        inside = t0 < 0
        length = t1 - t0
        depth = one / (one + np.exp(-out[k, 1])) * (length + depth_pad)
        t = t1 - depth if inside else t0 + depth
        accept = out[k, 0] > threshold and t > 0 and t < t_max[ray]
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
    active = np.nonzero(ptr < start[1:])[0]
    kept = np.empty(k, np.int64)
    for _ in range(inf.max_steps):
        n = len(active)
        if n == 0:
            break
        x = np.empty((n, width), np.float32)
        _step_inputs_kernel(active, ptr, t0s, t1s, origins, directions, fractions, table, res, sizes, offsets,
                            task_count(n, FORWARD_GROUP), x)  # fmt: skip
        out = model.network(torch.from_numpy(x), dtype).float().contiguous().numpy()
        m = _step_decode(active, ptr, start, t0s, t1s, t_max_np, out, threshold, np.float32(_DEPTH_PAD), np.float32(_REVERSED_MIN),
                         any_hit, best_t, best_out, kept)  # fmt: skip
        active = kept[:m].copy()
    return torch.from_numpy(best_t), torch.from_numpy(best_out)

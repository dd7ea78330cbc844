"""N-BVH's wavefront inference on CUDA: two Triton kernels around the MLP per step.

The same loop as `NBVHModel._closest_torch` (each ray's leaf list made once, then per step the
next leaf of every active ray, one batched query, the closest accepted hit kept, compaction),
with the per-step torch ops folded into two kernels, one active ray per lane:

- `_step_input_kernel`: the ray's current leaf entry, its chord (reversed when the origin is
  inside the leaf), the 3 chord points, all 8 levels of each encoded in the hash grid
  (`encode_level`, one point per lane), written straight as the network input row in the compute dtype
  (the points and the fp32 features never go to global memory);
- the MLP as torch GEMMs (`MLP.forward`, bf16 on CUDA);
- `_step_decode_kernel`: LocalT decoding, the acceptance rules, the best hit and its output row
  updated in place, the ray's list pointer advanced, and whether the ray goes on: more leaves,
  no accepted hit for `occluded`, and its next leaf entered before its best hit (the check the
  torch loop makes at the start of the next step).

Then one boolean index compacts the active rays. Same answers as the torch loop up to float
rounding (`sigmoid`, and fused multiply-adds when compiled); under the interpreter the chord
points and features are the torch path's bit for bit.
"""

from __future__ import annotations

import math

import torch
import triton
import triton.language as tl
from torch import Tensor

from ..neural.hash_grid_triton import encode_level, layout_tensors

__all__ = ["closest_hits_triton"]

_BLOCK = 64
_WARPS = _BLOCK // 32  # one ray per thread (more warps would hold each lane twice)


@triton.jit
def _step_input_kernel(active_ptr, ptr_ptr, t0_ptr, t1_ptr, o_ptr, d_ptr, table_ptr, res_ptr, size_ptr, offset_ptr, dense_ptr,
                       x_ptr, n_active, frac0, frac1, frac2,
                       L: tl.constexpr, F: tl.constexpr, FP: tl.constexpr, BLOCK: tl.constexpr):  # fmt: skip
    k = (tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)).to(tl.int64)
    ok = k < n_active
    ray = tl.load(active_ptr + k, mask=ok, other=0)
    e = tl.load(ptr_ptr + ray, mask=ok, other=0)
    t0 = tl.load(t0_ptr + e, mask=ok, other=0.0)
    t1 = tl.load(t1_ptr + e, mask=ok, other=0.0)
    inside = t0 < 0.0
    a = tl.where(inside, t1, t0)  # a ray starting inside the leaf asks for the reversed chord
    b = tl.where(inside, t0, t1)
    ox = tl.load(o_ptr + ray * 3, mask=ok, other=0.0)
    oy = tl.load(o_ptr + ray * 3 + 1, mask=ok, other=0.0)
    oz = tl.load(o_ptr + ray * 3 + 2, mask=ok, other=0.0)
    dx = tl.load(d_ptr + ray * 3, mask=ok, other=0.0)
    dy = tl.load(d_ptr + ray * 3 + 1, mask=ok, other=0.0)
    dz = tl.load(d_ptr + ray * 3 + 2, mask=ok, other=0.0)
    feats = tl.arange(0, FP)
    mask = ok[:, None] & (feats < F)[None, :]
    row = x_ptr + k[:, None] * (3 * L * F) + feats[None, :]
    for j in tl.static_range(3):
        if j == 0:
            frac = frac0
        elif j == 1:
            frac = frac1
        else:
            frac = frac2
        t = a + frac * (b - a)  # as torch: a + fractions * (b - a), then o + t * d
        px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
        for lvl in tl.static_range(L):
            res, size = tl.load(res_ptr + lvl), tl.load(size_ptr + lvl)
            offset, dense = tl.load(offset_ptr + lvl), tl.load(dense_ptr + lvl) != 0
            x = encode_level(px, py, pz, ok, table_ptr, res, size, offset, dense, F, FP)
            tl.store(row + (j * L + lvl) * F, x.to(x_ptr.dtype.element_ty), mask=mask)


@triton.jit
def _step_decode_kernel(active_ptr, ptr_ptr, start_ptr, t0_ptr, t1_ptr, t_max_ptr, out_ptr, best_t_ptr, best_out_ptr, keep_ptr,
                        n_active, threshold, depth_pad, reversed_min,
                        OUTPUTS: tl.constexpr, OP: tl.constexpr, ANY_HIT: tl.constexpr, BLOCK: tl.constexpr):  # fmt: skip
    k = (tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)).to(tl.int64)
    ok = k < n_active
    ray = tl.load(active_ptr + k, mask=ok, other=0)
    e = tl.load(ptr_ptr + ray, mask=ok, other=0)
    t0 = tl.load(t0_ptr + e, mask=ok, other=0.0)
    t1 = tl.load(t1_ptr + e, mask=ok, other=0.0)
    inside = t0 < 0.0
    length = t1 - t0
    vis = tl.load(out_ptr + k * OUTPUTS, mask=ok, other=-float("inf"))
    depth = tl.sigmoid(tl.load(out_ptr + k * OUTPUTS + 1, mask=ok, other=0.0)) * (length + depth_pad)
    t = tl.where(inside, t1 - depth, t0 + depth)
    best = tl.load(best_t_ptr + ray, mask=ok, other=0.0)
    accept = ok & (vis > threshold) & (t > 0.0) & (t <= tl.load(t_max_ptr + ray, mask=ok, other=0.0))
    accept = accept & (~inside | (t > reversed_min * length + 1e-5))  # skip the surface a ray starts on
    better = accept & (t < best)
    tl.store(best_t_ptr + ray, t, mask=better)
    o = tl.arange(0, OP)
    row_mask = (o < OUTPUTS)[None, :]
    vals = tl.load(out_ptr + k[:, None] * OUTPUTS + o[None, :], mask=better[:, None] & row_mask, other=0.0)
    tl.store(best_out_ptr + ray[:, None] * OUTPUTS + o[None, :], vals, mask=better[:, None] & row_mask)
    nxt = e + 1
    tl.store(ptr_ptr + ray, nxt, mask=ok)
    more = ok & (nxt < tl.load(start_ptr + ray + 1, mask=ok, other=0))
    if ANY_HIT:
        more = more & ~accept
    # Lists are sorted by entry: a next leaf entered beyond the best hit cannot hold a closer one.
    next_t0 = tl.load(t0_ptr + nxt, mask=more, other=0.0)
    more = more & (next_t0 < tl.where(better, t, best))
    tl.store(keep_ptr + k, more.to(tl.int8), mask=ok)


def closest_hits_triton(model, o: Tensor, d: Tensor, t_max: Tensor, any_hit: bool) -> tuple[Tensor, Tensor]:
    """`NBVHModel._closest` with the per-step kernels: (t [K] unit, inf where missed; raw outputs of the accepted hit)."""
    from .nbvh import _DEPTH_PAD, _REVERSED_MIN

    k, dev = len(o), o.device
    inf = model.config.inference
    leaves = model.leaf_list(o, d, t_max, torch.full((k,), inf.lod, dtype=torch.int8, device=dev),
                             torch.full((k,), inf.box_dilation, device=dev))  # fmt: skip
    ptr = leaves.start[:-1].clone()
    outputs = 8 + model.material_logits
    best_t = torch.full((k,), float("inf"), device=dev)
    best_out = torch.zeros(k, outputs, device=dev)
    threshold = math.log(inf.occlusion_threshold / (1 - inf.occlusion_threshold))
    dtype = model.compute_dtype()
    grid = model.encoder
    table = grid.table.detach()
    if table.dtype != torch.float32 or not table.is_contiguous():
        table = table.float().contiguous()
    res, sizes, offsets, dense = layout_tensors(grid.layout, dev)
    levels, feats = len(grid.layout.resolutions), grid.features_per_level
    fractions = [float(f) for f in model._fractions(1, "cpu")[0].tolist()]
    o, d, t_max = o.float().contiguous(), d.float().contiguous(), t_max.float().contiguous()
    active = torch.nonzero(ptr < leaves.start[1:]).squeeze(1)
    for _ in range(inf.max_steps):
        n = len(active)
        if n == 0:
            break
        x = torch.empty(n, 3 * levels * feats, dtype=dtype, device=dev)
        blocks = (triton.cdiv(n, _BLOCK),)
        _step_input_kernel[blocks](active, ptr, leaves.t0, leaves.t1, o, d, table, res, sizes, offsets, dense, x, n, *fractions,
                                   L=levels, F=feats, FP=triton.next_power_of_2(feats),
                                   BLOCK=_BLOCK, num_warps=_WARPS)  # fmt: skip
        out = model.network(x, dtype).float().contiguous()
        keep = torch.empty(n, dtype=torch.int8, device=dev)
        _step_decode_kernel[blocks](active, ptr, leaves.start, leaves.t0, leaves.t1, t_max, out, best_t, best_out, keep, n,
                                    threshold, _DEPTH_PAD, _REVERSED_MIN, OUTPUTS=outputs, OP=triton.next_power_of_2(outputs),
                                    ANY_HIT=any_hit, BLOCK=_BLOCK, num_warps=_WARPS)  # fmt: skip
        active = active[keep.bool()]
    return best_t, best_out

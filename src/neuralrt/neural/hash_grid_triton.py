"""Multiresolution hash grid on CUDA: Triton forward (gather) and backward (atomic scatter).

Same contract and arithmetic as the numba kernels in `hash_grid` (float32, a point at
``clamp(x, 0, 1) * (res - 1) + 0.5`` in vertex units, corner ``c`` at ``+ (c & 1, c >> 1 & 1,
c >> 2 & 1)`` clamped to ``res - 1``, weight ``((wx * wy) * wz)``, corners summed in order 0..7
from zero), dense rows ``x + y res + z res^2`` where a level fits, the instant-ngp hash above.
The hash keeps only the low log2(T) <= 26 bits, which 32-bit wrap-around products preserve, so
it runs in uint32 (numba uses int64: same bits).

Lanes are points (a ray's P points are P consecutive lanes), one point per lane: levels are an
unrolled loop (their sizes read as scalars), the F features of a corner one contiguous row (a
16-byte load for F = 4), so a thread holds one point's F accumulators. (A first version tiled
[points, levels, features]: ptxas for sm_90 reported 6.8 KB of spills in the forward kernel and
255 registers with spills in the backward.)

Under ``TRITON_INTERPRET=1`` (numpy, no fused multiply-add) the forward pass is bit-identical to
numba; compiled, the GPU may fuse multiply-adds (float32 rounding differences). The backward
pass adds with relaxed atomics, so its summation order (and last bits) vary from run to run.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch import Tensor

from .hash_grid import HASH_PRIMES, HashGridLayout

__all__ = ["hash_grid_triton", "encode_level", "level_cell", "level_rows_weights", "layout_tensors"]

_P1, _P2 = (tl.constexpr(p) for p in HASH_PRIMES[1:])  # Triton reads globals only as constexpr; _P0 == 1


@triton.jit
def _axis(x, res):
    """Base vertex (int32) and trilinear fraction of coordinates [B] at a level of ``res`` vertices."""
    f = tl.minimum(tl.maximum(x, 0.0), 1.0) * (res - 1).to(tl.float32) + 0.5
    base = tl.floor(f)
    return base.to(tl.int32), f - base


@triton.jit
def level_cell(px, py, pz, res):
    """The cell of points [B] at a level: base vertex and fractions per axis."""
    ix, wx = _axis(px, res)
    iy, wy = _axis(py, res)
    iz, wz = _axis(pz, res)
    return ix, iy, iz, wx, wy, wz


@triton.jit
def level_rows_weights(cell, res, size, dense, C: tl.constexpr):
    """Table row (within the level) and weight [B] of corner C (x fastest) of a `level_cell`."""
    ix, iy, iz, wx, wy, wz = cell
    if C & 1:
        cx, fx = tl.minimum(ix + 1, res - 1), wx
    else:
        cx, fx = ix, 1.0 - wx
    if (C >> 1) & 1:
        cy, fy = tl.minimum(iy + 1, res - 1), wy
    else:
        cy, fy = iy, 1.0 - wy
    if (C >> 2) & 1:
        cz, fz = tl.minimum(iz + 1, res - 1), wz
    else:
        cz, fz = iz, 1.0 - wz
    if dense:
        idx = cx + cy * res + cz * (res * res)
    else:
        idx = ((cx.to(tl.uint32) ^ (cy.to(tl.uint32) * _P1) ^ (cz.to(tl.uint32) * _P2)) & (size - 1).to(tl.uint32)).to(tl.int32)
    return idx, fx * fy * fz


@triton.jit
def encode_level(px, py, pz, valid, table_ptr, res, size, offset, dense, F: tl.constexpr, FP: tl.constexpr):
    """Features [B, FP] (float32; zero past F and for invalid lanes) of points [B] at one level:
    one lane per point, its F features one contiguous row per corner (a vector load)."""
    feats = tl.arange(0, FP)
    mask = valid[:, None] & (feats < F)[None, :]
    acc = tl.zeros([px.shape[0], FP], tl.float32)
    cell = level_cell(px, py, pz, res)
    for c in tl.static_range(8):
        idx, w = level_rows_weights(cell, res, size, dense, c)
        vals = tl.load(table_ptr + (offset + idx)[:, None] * F + feats[None, :], mask=mask, other=0.0)
        acc += w[:, None] * vals.to(tl.float32)
    return acc


@triton.jit
def _load_points(pts_ptr, n_points, BLOCK: tl.constexpr):
    p = (tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)).to(tl.int64)
    ok = p < n_points
    px = tl.load(pts_ptr + p * 3 + 0, mask=ok, other=0.0)
    py = tl.load(pts_ptr + p * 3 + 1, mask=ok, other=0.0)
    pz = tl.load(pts_ptr + p * 3 + 2, mask=ok, other=0.0)
    return p, ok, px, py, pz


@triton.jit
def _forward_kernel(pts_ptr, table_ptr, res_ptr, size_ptr, offset_ptr, dense_ptr, out_ptr, n_points,
                    L: tl.constexpr, F: tl.constexpr, FP: tl.constexpr, BLOCK: tl.constexpr):  # fmt: skip
    p, ok, px, py, pz = _load_points(pts_ptr, n_points, BLOCK)
    feats = tl.arange(0, FP)
    mask = ok[:, None] & (feats < F)[None, :]
    for lvl in tl.static_range(L):
        res, size = tl.load(res_ptr + lvl), tl.load(size_ptr + lvl)
        offset, dense = tl.load(offset_ptr + lvl), tl.load(dense_ptr + lvl) != 0
        acc = encode_level(px, py, pz, ok, table_ptr, res, size, offset, dense, F, FP)
        tl.store(out_ptr + p[:, None] * (L * F) + lvl * F + feats[None, :], acc, mask=mask)


@triton.jit
def _backward_kernel(pts_ptr, grad_out_ptr, res_ptr, size_ptr, offset_ptr, dense_ptr, grad_table_ptr, n_points,
                     L: tl.constexpr, F: tl.constexpr, FP: tl.constexpr, BLOCK: tl.constexpr):  # fmt: skip
    p, ok, px, py, pz = _load_points(pts_ptr, n_points, BLOCK)
    feats = tl.arange(0, FP)
    mask = ok[:, None] & (feats < F)[None, :]
    for lvl in tl.static_range(L):
        res, size = tl.load(res_ptr + lvl), tl.load(size_ptr + lvl)
        offset, dense = tl.load(offset_ptr + lvl), tl.load(dense_ptr + lvl) != 0
        g = tl.load(grad_out_ptr + p[:, None] * (L * F) + lvl * F + feats[None, :], mask=mask, other=0.0).to(tl.float32)
        cell = level_cell(px, py, pz, res)
        for c in tl.static_range(8):
            idx, w = level_rows_weights(cell, res, size, dense, c)
            # relaxed: a sum needs no ordering (the default acq_rel orders every add)
            tl.atomic_add(grad_table_ptr + (offset + idx)[:, None] * F + feats[None, :], w[:, None] * g, mask=mask, sem="relaxed")


def _pow2(n: int) -> int:
    return triton.next_power_of_2(max(int(n), 1))


def layout_tensors(layout: HashGridLayout, device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(resolutions, sizes, offsets, dense flags) as int32 tensors on ``device`` (the kernels' arguments)."""
    arrays = (layout.resolutions, layout.sizes, layout.offsets, [int(d) for d in layout.dense])
    return tuple(torch.tensor(v, dtype=torch.int32, device=device) for v in arrays)


class _HashGridTritonFunction(torch.autograd.Function):
    """Triton forward/backward; differentiable in the table only (points are data)."""

    @staticmethod
    def forward(ctx, points: Tensor, table: Tensor, layout: HashGridLayout, block: int):
        n, n_points = points.shape[:2]
        n_levels, n_feat = len(layout.resolutions), table.shape[1]
        pts = points.detach().to(torch.float32).contiguous()
        res, sizes, offsets, dense = layout_tensors(layout, table.device)
        out = torch.empty((n, n_points * n_levels * n_feat), dtype=torch.float32, device=table.device)
        m = n * n_points
        if m:
            _forward_kernel[(triton.cdiv(m, block),)](
                pts, table.detach().contiguous(), res, sizes, offsets, dense, out, m,
                L=n_levels, F=n_feat, FP=_pow2(n_feat), BLOCK=block, num_warps=max(1, block // 32),
            )  # fmt: skip
        ctx.save_for_backward(pts, res, sizes, offsets, dense)
        ctx.table_shape, ctx.table_dtype, ctx.block = tuple(table.shape), table.dtype, block
        return out

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        if not ctx.needs_input_grad[1]:
            return None, None, None, None
        pts, res, sizes, offsets, dense = ctx.saved_tensors
        n_levels, n_feat = len(res), ctx.table_shape[1]
        grad = torch.zeros(ctx.table_shape, dtype=torch.float32, device=pts.device)
        m = pts.shape[0] * pts.shape[1]
        if m:
            _backward_kernel[(triton.cdiv(m, ctx.block),)](
                pts, grad_out.to(torch.float32).contiguous(), res, sizes, offsets, dense, grad, m,
                L=n_levels, F=n_feat, FP=_pow2(n_feat), BLOCK=ctx.block, num_warps=max(1, ctx.block // 32),
            )  # fmt: skip
        return None, grad.to(ctx.table_dtype), None, None


def hash_grid_triton(points: Tensor, table: Tensor, layout: HashGridLayout, block: int = 128) -> Tensor:
    """`HashGrid.forward` on the table's device with Triton kernels (autograd in the table).

    ``points [N, P, 3]`` (on the table's device), ``table [rows, F]`` -> ``[N, P * L * F]`` float32.
    """
    if table.numel() >= 2**31:
        raise ValueError(f"hash table of {table.numel()} entries is too large for 32-bit offsets")
    if table.shape[0] != layout.rows:
        raise ValueError(f"hash table has {table.shape[0]} rows, the layout {layout.rows}")
    return _HashGridTritonFunction.apply(points, table, layout, block)

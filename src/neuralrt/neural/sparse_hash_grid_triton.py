"""Sparse hash grid encoding on CUDA: Triton forward (gather) and backward (atomic scatter).

Same contract and arithmetic as the numba kernels in `sparse_hash_grid` (float32 weights, the
instant-ngp hash, ``rint`` onto the face plane, ``floor`` in the plane, corners summed in the
same order). One formula serves face and origin points: the trilinear weights of a point on a
face plane are 0 for the 4 corners off the plane and exactly the bilinear weights for the other
4, so face points read 4 entries (the off-plane loads are masked) and origin points 8.

Lanes are points; levels and features are the second and third tile dimensions (padded to
powers of two), so all levels of a point are encoded in one pass. `encode_point` is shared with
the fused LSNIF inference kernel. Under ``TRITON_INTERPRET=1`` the forward pass is bit-identical
to numba; compiled, the GPU may fuse multiply-adds (float32 rounding differences). The backward
pass adds with atomics, so its summation order (and last bits) vary from run to run.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import triton
import triton.language as tl
from torch import Tensor

from .sparse_hash_grid import HASH_PRIMES

__all__ = ["sparse_hash_grid_triton", "encode_point", "encode_point_level_feature"]

_P0, _P1, _P2 = (tl.constexpr(p) for p in HASH_PRIMES)  # Triton reads globals only as constexpr


@triton.jit
def _rint(f):
    """Round half to even (np.rint, torch.round) without the ``floor(f + 0.5)`` rounding trap."""
    r = tl.floor(f)
    frac = f - r
    odd = (r - 2.0 * tl.floor(r * 0.5)) != 0.0
    return tl.where((frac > 0.5) | ((frac == 0.5) & odd), r + 1.0, r)


@triton.jit
def _axis_terms(p, fixed, resf, prime):
    """[B, LP] hashed terms of vertex i and i + 1 and the weight of i + 1 along one axis, all
    levels at once (``p``, ``fixed``: [B]; ``resf``: [LP] level resolutions as float32)."""
    f = p[:, None] * resf[None, :]
    on_plane = tl.minimum(tl.maximum(_rint(f), 0.0), resf[None, :])
    in_cell = tl.minimum(tl.maximum(tl.floor(f), 0.0), resf[None, :] - 1.0)
    i = tl.where(fixed[:, None], on_plane, in_cell)
    w = tl.where(fixed[:, None], 0.0, f - i)
    # 32-bit products: the hash keeps only the low log2(T) <= 24 bits, which wrap-around preserves.
    iu = i.to(tl.uint32)
    h0 = iu * prime
    h1 = tl.where(fixed[:, None], h0, (iu + 1) * prime)
    return h0, h1, w


@triton.jit
def _level_terms(px, py, pz, code, res_ptr, L: tl.constexpr, LP: tl.constexpr):
    levels = tl.arange(0, LP)
    resf = tl.load(res_ptr + levels, mask=levels < L, other=1).to(tl.float32)
    x0, x1, wx = _axis_terms(px, code == 0, resf, _P0)
    y0, y1, wy = _axis_terms(py, code == 1, resf, _P1)
    z0, z1, wz = _axis_terms(pz, code == 2, resf, _P2)
    return x0, x1, wx, y0, y1, wy, z0, z1, wz


@triton.jit
def _corner(terms, code, valid, table_size, C: tl.constexpr, L: tl.constexpr, LP: tl.constexpr):
    """Table rows [B, LP] (levels stacked), weights [B, LP] and load mask of corner C (x fastest)."""
    x0, x1, wx, y0, y1, wy, z0, z1, wz = terms
    if C & 1:
        hx, fx, on_x = x1, wx, code != 0
    else:
        hx, fx, on_x = x0, 1.0 - wx, valid
    if (C >> 1) & 1:
        hy, fy, on_y = y1, wy, code != 1
    else:
        hy, fy, on_y = y0, 1.0 - wy, valid
    if (C >> 2) & 1:
        hz, fz, on_z = z1, wz, code != 2
    else:
        hz, fz, on_z = z0, 1.0 - wz, valid
    levels = tl.arange(0, LP)
    row = levels[None, :] * table_size + ((hx ^ hy ^ hz) & (table_size - 1)).to(tl.int32)
    needed = (valid & on_x & on_y & on_z)[:, None] & (levels < L)[None, :]
    return row, fx * fy * fz, needed


@triton.jit
def encode_point(px, py, pz, code, valid, table_ptr, res_ptr, table_size,
                 L: tl.constexpr, F: tl.constexpr, LP: tl.constexpr, FP: tl.constexpr):  # fmt: skip
    """Features [B, LP, FP] (float32; zero outside L x F and for invalid lanes) of points [B]."""
    terms = _level_terms(px, py, pz, code, res_ptr, L, LP)
    feats = tl.arange(0, FP)
    acc = tl.zeros([px.shape[0], LP, FP], tl.float32)
    for c in tl.static_range(8):
        row, w, needed = _corner(terms, code, valid, table_size, c, L, LP)
        mask = needed[:, :, None] & (feats < F)[None, None, :]
        vals = tl.load(table_ptr + row[:, :, None] * F + feats[None, None, :], mask=mask, other=0.0)
        acc += w[:, :, None] * vals.to(tl.float32)
    return acc


@triton.jit
def _lane_axis_terms(p, fixed, resf, prime):
    """`_axis_terms` of one level (``resf`` a float32 scalar): every value is a [B] lane vector."""
    f = p * resf
    on_plane = tl.minimum(tl.maximum(_rint(f), 0.0), resf)
    in_cell = tl.minimum(tl.maximum(tl.floor(f), 0.0), resf - 1.0)
    i = tl.where(fixed, on_plane, in_cell)
    w = tl.where(fixed, 0.0, f - i)
    iu = i.to(tl.uint32)
    h0 = iu * prime
    h1 = tl.where(fixed, h0, (iu + 1) * prime)
    return h0, h1, w


@triton.jit
def encode_point_level_feature(px, py, pz, code, valid, table_ptr, resf, level, table_size, f, F: tl.constexpr):
    """Feature ``f`` of level ``level`` (resolution ``resf``) of points [B]: a [B] float32 vector,
    the same arithmetic as `encode_point` (corners summed in the same order) without its padded
    [B, LP, FP] tile, so a lane holds one point and nothing else. The hash terms do not depend on
    ``f``: called for each ``f`` in an unrolled loop, the compiler computes them once."""
    x0, x1, wx = _lane_axis_terms(px, code == 0, resf, _P0)
    y0, y1, wy = _lane_axis_terms(py, code == 1, resf, _P1)
    z0, z1, wz = _lane_axis_terms(pz, code == 2, resf, _P2)
    base = level * table_size
    acc = tl.zeros(px.shape, tl.float32)
    for c in tl.static_range(8):
        if c & 1:
            hx, fx, on_x = x1, wx, code != 0
        else:
            hx, fx, on_x = x0, 1.0 - wx, valid
        if (c >> 1) & 1:
            hy, fy, on_y = y1, wy, code != 1
        else:
            hy, fy, on_y = y0, 1.0 - wy, valid
        if (c >> 2) & 1:
            hz, fz, on_z = z1, wz, code != 2
        else:
            hz, fz, on_z = z0, 1.0 - wz, valid
        row = base + ((hx ^ hy ^ hz) & (table_size - 1)).to(tl.int32)
        vals = tl.load(table_ptr + row * F + f, mask=valid & on_x & on_y & on_z, other=0.0)
        acc += fx * fy * fz * vals.to(tl.float32)
    return acc


@triton.jit
def _load_points(pts_ptr, axes_ptr, n_points, BLOCK: tl.constexpr):
    p = (tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)).to(tl.int64)
    ok = p < n_points
    px = tl.load(pts_ptr + p * 3 + 0, mask=ok, other=0.0)
    py = tl.load(pts_ptr + p * 3 + 1, mask=ok, other=0.0)
    pz = tl.load(pts_ptr + p * 3 + 2, mask=ok, other=0.0)
    code = tl.load(axes_ptr + p, mask=ok, other=-1).to(tl.int32)
    valid = ok & (code >= 0) & (code <= 3)
    return p, ok, px, py, pz, code, valid


@triton.jit
def _out_offsets(p, L: tl.constexpr, F: tl.constexpr, LP: tl.constexpr, FP: tl.constexpr):
    """Point-major output columns ``p * L * F + level * F + feature`` and their mask."""
    levels = tl.arange(0, LP)
    feats = tl.arange(0, FP)
    offs = p[:, None, None] * (L * F) + levels[None, :, None] * F + feats[None, None, :]
    inside = (levels < L)[None, :, None] & (feats < F)[None, None, :]
    return offs, inside


@triton.jit
def _forward_kernel(pts_ptr, axes_ptr, table_ptr, res_ptr, out_ptr, n_points, table_size,
                    L: tl.constexpr, F: tl.constexpr, LP: tl.constexpr, FP: tl.constexpr,
                    BLOCK: tl.constexpr):  # fmt: skip
    p, ok, px, py, pz, code, valid = _load_points(pts_ptr, axes_ptr, n_points, BLOCK)
    acc = encode_point(px, py, pz, code, valid, table_ptr, res_ptr, table_size, L, F, LP, FP)
    offs, inside = _out_offsets(p, L, F, LP, FP)
    tl.store(out_ptr + offs, acc, mask=ok[:, None, None] & inside)


@triton.jit
def _backward_kernel(pts_ptr, axes_ptr, grad_out_ptr, res_ptr, grad_table_ptr, n_points, table_size,
                     L: tl.constexpr, F: tl.constexpr, LP: tl.constexpr, FP: tl.constexpr,
                     BLOCK: tl.constexpr):  # fmt: skip
    p, ok, px, py, pz, code, valid = _load_points(pts_ptr, axes_ptr, n_points, BLOCK)
    offs, inside = _out_offsets(p, L, F, LP, FP)
    g = tl.load(grad_out_ptr + offs, mask=valid[:, None, None] & inside, other=0.0).to(tl.float32)
    terms = _level_terms(px, py, pz, code, res_ptr, L, LP)
    feats = tl.arange(0, FP)
    for c in tl.static_range(8):
        row, w, needed = _corner(terms, code, valid, table_size, c, L, LP)
        mask = needed[:, :, None] & (feats < F)[None, None, :]
        tl.atomic_add(grad_table_ptr + row[:, :, None] * F + feats[None, None, :], w[:, :, None] * g, mask=mask)


def _pow2(n: int) -> int:
    return triton.next_power_of_2(max(int(n), 1))


class _SparseHashGridTritonFunction(torch.autograd.Function):
    """Triton forward/backward; differentiable in the table only (points are data)."""

    @staticmethod
    def forward(ctx, points: Tensor, face_axis: Tensor, table: Tensor, resolutions: Tensor, block: int):
        n_rays, n_points = face_axis.shape
        levels, table_size, n_feat = table.shape
        pts = points.detach().to(torch.float32).contiguous()
        axes = face_axis.to(torch.int8).contiguous()
        out = torch.empty((n_rays, n_points * levels * n_feat), dtype=torch.float32, device=points.device)
        m = n_rays * n_points
        if m:
            _forward_kernel[(triton.cdiv(m, block),)](
                pts, axes, table.detach().contiguous(), resolutions, out, m, table_size,
                L=levels, F=n_feat, LP=_pow2(levels), FP=_pow2(n_feat), BLOCK=block,
            )  # fmt: skip
        ctx.save_for_backward(pts, axes, resolutions)
        ctx.table_shape, ctx.table_dtype, ctx.block = tuple(table.shape), table.dtype, block
        return out

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        grad_table = None
        if ctx.needs_input_grad[2]:
            pts, axes, resolutions = ctx.saved_tensors
            levels, table_size, n_feat = ctx.table_shape
            grad = torch.zeros(ctx.table_shape, dtype=torch.float32, device=pts.device)
            m = axes.numel()
            if m:
                _backward_kernel[(triton.cdiv(m, ctx.block),)](
                    pts, axes, grad_out.to(torch.float32).contiguous(), resolutions, grad, m, table_size,
                    L=levels, F=n_feat, LP=_pow2(levels), FP=_pow2(n_feat), BLOCK=ctx.block,
                )  # fmt: skip
            grad_table = grad.to(ctx.table_dtype)
        return None, None, grad_table, None, None


def sparse_hash_grid_triton(
    points: Tensor, face_axis: Tensor, table: Tensor, resolutions: Sequence[int] | Tensor, block: int = 128
) -> Tensor:
    """`SparseHashGrid.forward` on the table's device with Triton kernels (autograd in the table).

    ``points [N, H, 3]``, ``face_axis [N, H]``, ``table [L, T, F]`` -> ``[N, H * L * F]`` float32.
    """
    if table.numel() >= 2**31:
        raise ValueError(f"hash table of {table.numel()} entries is too large for 32-bit offsets")
    res = torch.as_tensor(resolutions, dtype=torch.int32).to(table.device)
    return _SparseHashGridTritonFunction.apply(points, face_axis, table, res, block)

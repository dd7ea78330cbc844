"""Dense-then-hashed multiresolution grid encoding (instant-ngp; N-BVH, Weier et al. 2024, Sec. 6).

``L`` levels of resolution ``base * 2**l`` (N-BVH: 8 levels, 8^3 .. 1024^3), ``F`` features per
vertex (4), trilinear interpolation of the 8 vertices around a point. tiny-cuda-nn's conventions
(which the N-BVH code uses): a level's scale is ``s = res - 1`` and a point ``x`` in [0, 1]
sits at ``x * s + 0.5`` in vertex units; a level whose ``res**3`` vertices fit in the table size
``T`` is stored densely (index ``x + y*res + z*res^2``), coarser ones first; finer levels hash
``(x*1) ^ (y*2654435761) ^ (z*805459861) mod T``. All levels live in one table of
``sum_l min(res_l**3, T)`` rows (`HashGridLayout`), initialised U(-1e-4, 1e-4).

A query encodes P points at once (N-BVH: the 3 chord points of a ray in a leaf) with the same
table, giving ``[N, P * L * F]`` features, point-major (point 0's levels, then point 1's, ...).

One contract, implementations chosen once by the table's device: fused numba kernels on the CPU
(forward parallel over rays; the backward scatters into one gradient table per thread, then sums
them: no atomics), Triton kernels on CUDA (`hash_grid_triton`: gather forward, atomic-add
backward), vectorized torch elsewhere (`hash_grid_torch`, autograd through indexing).
`hash_grid_reference` is a slow scalar transcription of the definition above, for the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch
from llvmlite import ir
from numba import types
from numba.extending import intrinsic
from torch import Tensor, nn

from ..simd import broadcast, contiguous_1d, element_pointer, prefetch, vector_pointer
from ..task_queue import task_count, task_workers

__all__ = ["HashGridLayout", "HashGrid", "hash_grid_torch", "hash_grid_reference", "HASH_PRIMES", "encode_group", "PREFETCH_GROUP"]

HASH_PRIMES = (1, 2654435761, 805459861)  # instant-ngp's spatial hash
_P0, _P1, _P2 = HASH_PRIMES


@dataclass(frozen=True)
class HashGridLayout:
    """Where each level lives in the shared table.

    ``resolutions[l]`` vertices per axis, rows ``offsets[l] : offsets[l] + sizes[l]``; a level is
    dense when ``sizes[l] == resolutions[l]**3``, else hashed into ``sizes[l] == T`` rows.
    """

    resolutions: tuple[int, ...]
    sizes: tuple[int, ...]
    offsets: tuple[int, ...]

    @staticmethod
    def create(levels: int = 8, base_resolution: int = 8, log2_table_size: int = 18) -> "HashGridLayout":
        if levels < 1 or base_resolution < 2 or not 1 <= log2_table_size <= 26:
            raise ValueError(f"hash grid: need levels >= 1, base_resolution >= 2, 1 <= log2_table_size <= 26 "
                             f"(got {levels}, {base_resolution}, {log2_table_size})")
        res = tuple(base_resolution * 2**lvl for lvl in range(levels))
        sizes = tuple(min(r**3, 2**log2_table_size) for r in res)
        offsets = tuple(int(x) for x in np.concatenate([[0], np.cumsum(sizes)[:-1]]))
        return HashGridLayout(res, sizes, offsets)

    @property
    def rows(self) -> int:
        return int(sum(self.sizes))

    @property
    def dense(self) -> tuple[bool, ...]:
        return tuple(s == r**3 for r, s in zip(self.resolutions, self.sizes))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(resolutions, sizes, offsets) as int64 numpy arrays (the numba kernels' arguments)."""
        return (np.asarray(self.resolutions, np.int64), np.asarray(self.sizes, np.int64), np.asarray(self.offsets, np.int64))


# ---------------------------------------------------------------------------------------------
# numba kernels (CPU)


@numba.njit(cache=True, inline="always")
def _cell(x, y, z, res):
    """A point's cell ``ix, iy, iz`` (int64) and fractions ``wx, wy, wz`` (float32) at resolution ``res``."""
    scale = np.float32(res - 1)
    half = np.float32(0.5)
    one = np.float32(1.0)
    px = min(max(x, np.float32(0.0)), one) * scale + half
    py = min(max(y, np.float32(0.0)), one) * scale + half
    pz = min(max(z, np.float32(0.0)), one) * scale + half
    fx, fy, fz = np.floor(px), np.floor(py), np.floor(pz)
    return np.int64(fx), np.int64(fy), np.int64(fz), px - fx, py - fy, pz - fz


_F32X4 = ir.VectorType(ir.FloatType(), 4)


def _rows4_typing(table_flat, rows, weights, at, out_flat, col) -> bool:
    """`read_rows4` / `add_rows4`'s argument types: flat float32 table (or gradient), int64 rows,
    float32 weights, flat float32 features, integer offsets."""
    return (contiguous_1d(table_flat, types.float32) and contiguous_1d(rows, types.int64) and contiguous_1d(weights, types.float32)
            and contiguous_1d(out_flat, types.float32) and isinstance(at, types.Integer) and isinstance(col, types.Integer))  # fmt: skip


def _corner_rows4(context, builder, sig, args):
    """Per corner c of a point, in corner order (IR): its row's first float in a 4-feature table
    (``rows[at + c] * 4``) and its weight (``weights[at + c]``); ``args`` as `read_rows4`'s."""
    at_value = context.cast(builder, args[3], sig.args[3], types.intp)
    four = ir.Constant(ir.IntType(64), 4)
    for c in range(8):
        i = builder.add(at_value, ir.Constant(at_value.type, c))
        row = builder.load(element_pointer(context, builder, sig.args[1], args[1], i))
        weight = builder.load(element_pointer(context, builder, sig.args[2], args[2], i))
        yield builder.mul(row, four), weight


@intrinsic
def read_rows4(typingctx, table_flat, rows, weights, at, out_flat, col):
    """``out_flat[col : col + 4] = sum_c weights[at + c] * table[rows[at + c]]`` over a point's 8
    corners, for a table of 4 features (``table_flat`` its flat float32 data): one vector load per
    row; per lane products, then sums from 0 in corner order (the scalar loop's operations and
    bits; 0.75x its time, measured on the forward kernel)."""
    if not _rows4_typing(table_flat, rows, weights, at, out_flat, col):
        return None

    def codegen(context, builder, sig, args):
        table, out = args[0], args[4]
        col_value = context.cast(builder, args[5], sig.args[5], types.intp)
        acc = ir.Constant(_F32X4, [0.0] * 4)
        for start, weight in _corner_rows4(context, builder, sig, args):
            values = builder.load(vector_pointer(context, builder, sig.args[0], table, start, _F32X4), align=4)
            acc = builder.fadd(acc, builder.fmul(broadcast(builder, weight, _F32X4), values))
        builder.store(acc, vector_pointer(context, builder, sig.args[4], out, col_value, _F32X4), align=4)
        return context.get_dummy_value()

    return types.void(table_flat, rows, weights, at, out_flat, col), codegen


@intrinsic
def add_rows4(typingctx, grad_flat, rows, weights, at, grad_out_flat, col):
    """``grad[rows[at + c]] += weights[at + c] * grad_out_flat[col : col + 4]`` for a point's 8
    corners in corner order, for a table of 4 features (``grad_flat`` its flat float32 data): one
    vector load, multiply, add and store per row (the scalar loop's operations in its order, so
    the same bits; a row two corners share gets both adds, one after the other)."""
    if not _rows4_typing(grad_flat, rows, weights, at, grad_out_flat, col):
        return None

    def codegen(context, builder, sig, args):
        grad, grad_out = args[0], args[4]
        col_value = context.cast(builder, args[5], sig.args[5], types.intp)
        upstream = builder.load(vector_pointer(context, builder, sig.args[4], grad_out, col_value, _F32X4), align=4)
        for start, weight in _corner_rows4(context, builder, sig, args):
            target = vector_pointer(context, builder, sig.args[0], grad, start, _F32X4)
            total = builder.fadd(builder.load(target, align=4), builder.fmul(broadcast(builder, weight, _F32X4), upstream))
            builder.store(total, target, align=4)
        return context.get_dummy_value()

    return types.void(grad_flat, rows, weights, at, grad_out_flat, col), codegen


_I64 = ir.IntType(64)
_I64X8 = ir.VectorType(_I64, 8)
_F32X8 = ir.VectorType(ir.FloatType(), 8)
_LANE = ir.IntType(32)


@intrinsic
def corner_rows8(typingctx, ix, iy, iz, wx, wy, wz, res, size, offset, rows, weights, at, table_flat, n_feat):
    """A point's 8 corners at one level at once, lane c holding corner c (x fastest; AVX-512: 8
    int64 lanes), from its cell ``ix, iy, iz`` and fractions ``wx, wy, wz`` (`_cell`): the table
    rows (``offset`` + the dense index or the hash, as the module docstring defines them) into
    ``rows[at : at + 8]``, the trilinear weights (``w`` or ``1 - w`` per axis, multiplied x, y, z
    in that order, as `hash_grid_reference`) into ``weights[at : at + 8]``, and each row's cache
    line prefetched from ``table_flat`` (``n_feat`` floats a row). Scalar, with a bounds-checked
    index each, the corners took 78% of the forward kernel."""
    integers = (ix, iy, iz, res, size, offset, at, n_feat)
    if not (all(isinstance(a, types.Integer) for a in integers) and wx == wy == wz == types.float32
            and contiguous_1d(rows, types.int64) and contiguous_1d(weights, types.float32) and contiguous_1d(table_flat, types.float32)):  # fmt: skip
        return None

    def codegen(context, builder, sig, args):
        def int64(k):
            return context.cast(builder, args[k], sig.args[k], types.int64)

        def splat(value, vector_type=_I64X8):
            return broadcast(builder, value, vector_type)

        ix_, iy_, iz_, res_, size_, offset_, at_, n_feat_ = (int64(k) for k in (0, 1, 2, 6, 7, 8, 11, 13))
        last = splat(builder.sub(res_, _I64(1)))

        def corner(i, axis):  # min(i + bit, res - 1)
            v = builder.add(splat(i), ir.Constant(_I64X8, [(c >> axis) & 1 for c in range(8)]))
            return builder.select(builder.icmp_signed("<", v, last), v, last)

        cx, cy, cz = corner(ix_, 0), corner(iy_, 1), corner(iz_, 2)
        plane = builder.mul(res_, res_)
        dense_index = builder.add(builder.add(cx, builder.mul(cy, splat(res_))), builder.mul(cz, splat(plane)))
        primes = [ir.Constant(_I64X8, [p] * 8) for p in HASH_PRIMES]
        hashed = builder.xor(builder.xor(builder.mul(cx, primes[0]), builder.mul(cy, primes[1])), builder.mul(cz, primes[2]))
        hashed = builder.and_(hashed, splat(builder.sub(size_, _I64(1))))
        dense = builder.icmp_signed("==", size_, builder.mul(plane, res_))
        row = builder.add(splat(offset_), builder.select(dense, dense_index, hashed))
        builder.store(row, vector_pointer(context, builder, sig.args[9], args[9], at_, _I64X8), align=8)
        one = ir.Constant(ir.FloatType(), 1.0)

        def factor(w, axis):  # w where the corner's bit is set, else 1 - w
            bit = ir.Constant(ir.VectorType(ir.IntType(1), 8), [bool((c >> axis) & 1) for c in range(8)])
            return builder.select(bit, splat(w, _F32X8), splat(builder.fsub(one, w), _F32X8))

        weight = builder.fmul(builder.fmul(factor(args[3], 0), factor(args[4], 1)), factor(args[5], 2))
        builder.store(weight, vector_pointer(context, builder, sig.args[10], args[10], at_, _F32X8), align=4)
        for c in range(8):
            start = builder.mul(builder.extract_element(row, _LANE(c)), n_feat_)
            prefetch(builder, element_pointer(context, builder, sig.args[12], args[12], start))
        return context.get_dummy_value()

    return types.void(ix, iy, iz, wx, wy, wz, res, size, offset, rows, weights, at, table_flat, n_feat), codegen


@numba.njit(cache=True, inline="always")
def _corners(x, y, z, res, size, offset, rows, weights, at, table_flat, n_feat):
    """Rows and weights of point ``(x, y, z)`` at one level into ``rows``/``weights[at : at + 8]``
    (`corner_rows8`), each row prefetched from ``table_flat``."""
    ix, iy, iz, wx, wy, wz = _cell(x, y, z, res)
    corner_rows8(ix, iy, iz, wx, wy, wz, res, size, offset, rows, weights, at, table_flat, n_feat)


# Rays whose rows (every point and level) are found and prefetched before any is read (the
# forward, `encode_group`) or added to (the backward, `scatter_group`): the accesses then overlap
# instead of waiting on one cache miss after another (N-BVH's tables, ~6 MB at its `cpu` preset,
# do not fit in L2). 2 cores, Zen 5, N-BVH `intersect` (session 37) and training (session 39):
# see docs/nbvh.md.
PREFETCH_GROUP = 8


@numba.njit(cache=True, inline="always")
def _group_corners(points, first, stop, resolutions, sizes, offsets, rows, weights, table_flat, n_feat):
    """Every point and level of ``points[first:stop]``: its 8 rows and weights into ``rows``/``weights``
    (8 entries each, in ray, point, level order), each row prefetched from ``table_flat``."""
    at = 0
    for i in range(first, stop):
        for p in range(points.shape[1]):
            for lvl in range(resolutions.shape[0]):
                _corners(points[i, p, 0], points[i, p, 1], points[i, p, 2], resolutions[lvl], sizes[lvl], offsets[lvl], rows, weights,
                         at, table_flat, n_feat)  # fmt: skip
                at += 8


@numba.njit(cache=True, inline="always")
def encode_group(points, first, stop, table, resolutions, sizes, offsets, rows, weights, acc, out, out_first):
    """Encode ``points[first:stop]`` ([N, P, 3]) into ``out[out_first + i - first]`` ([P * L * F]
    each): the group's rows (every point and level) found and prefetched, then read.
    ``rows``/``weights``: scratch of ``(stop - first) * P * L * 8``; ``acc``: of F."""
    n_points, n_levels, n_feat = points.shape[1], resolutions.shape[0], table.shape[1]
    table_flat, out_flat, n_columns = table.reshape(-1), out.reshape(-1), out.shape[1]
    _group_corners(points, first, stop, resolutions, sizes, offsets, rows, weights, table_flat, n_feat)
    at = 0
    for i in range(first, stop):
        o = out_first + i - first
        for p in range(n_points):
            for lvl in range(n_levels):
                col = (p * n_levels + lvl) * n_feat
                if n_feat == 4:  # (N-BVH's): a row per vector load
                    read_rows4(table_flat, rows, weights, at, out_flat, o * n_columns + col)
                else:
                    acc[:] = np.float32(0.0)
                    for c in range(8):  # corner-major: one table row at a time, sums in a local array
                        r, w = rows[at + c], weights[at + c]
                        for f in range(n_feat):
                            acc[f] += w * table[r, f]
                    for f in range(n_feat):
                        out[o, col + f] = acc[f]
                at += 8


@numba.njit(parallel=True, cache=True)
def _forward_kernel(points, table, resolutions, sizes, offsets, n_chunks, out):
    """``points`` [N, P, 3], ``table`` [R, F] -> ``out`` [N, P * L * F]."""
    n, n_points = points.shape[0], points.shape[1]
    per_ray = n_points * resolutions.shape[0] * 8  # rows a ray reads
    for chunk in numba.prange(n_chunks):
        rows = np.empty(PREFETCH_GROUP * per_ray, np.int64)
        weights = np.empty(PREFETCH_GROUP * per_ray, np.float32)
        acc = np.empty(table.shape[1], np.float32)
        last = (chunk + 1) * n // n_chunks
        for first in range(chunk * n // n_chunks, last, PREFETCH_GROUP):
            encode_group(points, first, min(first + PREFETCH_GROUP, last), table, resolutions, sizes, offsets, rows, weights, acc,
                         out, first)  # fmt: skip


@numba.njit(cache=True, inline="always")
def scatter_group(points, first, stop, grad_out, resolutions, sizes, offsets, rows, weights, grad):
    """Add ``grad_out[i]`` ([P * L * F] each) of ``points[first:stop]`` into ``grad`` ([R, F]) at
    their rows, weighted: `encode_group`'s transpose, with the group's rows found and prefetched
    before any is added to (the same adds in the same order as one point at a time, so the same
    bits: 0.26x the time on N-BVH's 8-level grid, 8192 samples, docs/nbvh.md)."""
    n_points, n_levels, n_feat = points.shape[1], resolutions.shape[0], grad.shape[1]
    grad_flat, grad_out_flat, n_columns = grad.reshape(-1), grad_out.reshape(-1), grad_out.shape[1]
    _group_corners(points, first, stop, resolutions, sizes, offsets, rows, weights, grad_flat, n_feat)
    at = 0
    for i in range(first, stop):
        for p in range(n_points):
            for lvl in range(n_levels):
                col = (p * n_levels + lvl) * n_feat
                if n_feat == 4:  # (N-BVH's): a row per vector
                    add_rows4(grad_flat, rows, weights, at, grad_out_flat, i * n_columns + col)
                else:
                    for c in range(8):
                        r, w = rows[at + c], weights[at + c]
                        for f in range(n_feat):
                            grad[r, f] += w * grad_out[i, col + f]
                at += 8


@numba.njit(parallel=True, cache=True)
def _backward_kernel(points, grad_out, resolutions, sizes, offsets, grad_tables):
    """Scatter ``grad_out`` [N, P * L * F] into ``grad_tables[chunk]`` ([R, F] each, one per thread)."""
    n, n_points = points.shape[0], points.shape[1]
    n_chunks = grad_tables.shape[0]
    per_ray = n_points * resolutions.shape[0] * 8  # rows a ray adds to
    for chunk in numba.prange(n_chunks):
        rows = np.empty(PREFETCH_GROUP * per_ray, np.int64)
        weights = np.empty(PREFETCH_GROUP * per_ray, np.float32)
        last = (chunk + 1) * n // n_chunks
        for first in range(chunk * n // n_chunks, last, PREFETCH_GROUP):
            scatter_group(points, first, min(first + PREFETCH_GROUP, last), grad_out, resolutions, sizes, offsets, rows, weights,
                          grad_tables[chunk])  # fmt: skip


class _HashGridFunction(torch.autograd.Function):
    """Fused numba forward/backward; differentiable in the table only (points are data)."""

    @staticmethod
    def forward(ctx, points: Tensor, table: Tensor, layout: HashGridLayout):
        pts = points.detach().float().contiguous().numpy()
        res, sizes, offsets = layout.arrays()
        n, n_points = pts.shape[:2]
        n_feat = table.shape[1]
        out = np.empty((n, n_points * len(res) * n_feat), np.float32)
        if n:
            _forward_kernel(pts, table.detach().contiguous().numpy(), res, sizes, offsets, task_count(n), out)
        ctx.save_for_backward(points)
        ctx.layout, ctx.table_shape = layout, tuple(table.shape)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        if not ctx.needs_input_grad[1]:
            return None, None, None
        (points,) = ctx.saved_tensors
        res, sizes, offsets = ctx.layout.arrays()
        threads = task_workers(len(points))  # a gradient table per worker
        tables = np.zeros((threads, *ctx.table_shape), np.float32)
        if len(points):
            _backward_kernel(points.detach().float().contiguous().numpy(), grad_out.float().contiguous().numpy(),
                             res, sizes, offsets, tables)  # fmt: skip
        grad = tables[0] if threads == 1 else tables.sum(0)
        return None, torch.from_numpy(grad), None


# ---------------------------------------------------------------------------------------------
# torch (any device), and the slow reference

_CORNER_BITS = torch.tensor([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])  # [8, 3]


def hash_grid_torch(points: Tensor, table: Tensor, layout: HashGridLayout) -> Tensor:
    """Vectorized torch encoding, same contract as `HashGrid.forward` (autograd through indexing)."""
    n, n_points = points.shape[:2]
    p = points.reshape(-1, 3).float().clamp(0.0, 1.0)
    bits = _CORNER_BITS.to(p.device)
    primes = torch.tensor(HASH_PRIMES, device=p.device)
    per_level = []
    for res, size, offset in zip(layout.resolutions, layout.sizes, layout.offsets):
        pos = p * float(res - 1) + 0.5
        cell = torch.floor(pos)
        w = pos - cell
        vertex = (cell.long()[:, None, :] + bits[None]).clamp(max=res - 1)  # [M, 8, 3]
        if size == res**3:
            idx = vertex[..., 0] + vertex[..., 1] * res + vertex[..., 2] * (res * res)
        else:
            idx = ((vertex[..., 0] * primes[0]) ^ (vertex[..., 1] * primes[1]) ^ (vertex[..., 2] * primes[2])) & (size - 1)
        weight = torch.where(bits[None].bool(), w[:, None, :], 1 - w[:, None, :]).prod(-1)  # [M, 8]
        per_level.append((weight[..., None] * table[offset + idx]).sum(1))
    return torch.stack(per_level, 1).reshape(n, n_points * len(layout.resolutions) * table.shape[1])


def hash_grid_reference(points: np.ndarray, table: np.ndarray, layout: HashGridLayout) -> np.ndarray:
    """Scalar float64 transcription of the encoding (slow; tests only): [N, P, 3] -> [N, P * L * F]."""
    points, table = np.asarray(points, np.float64), np.asarray(table, np.float64)
    n, n_points, n_feat = points.shape[0], points.shape[1], table.shape[1]
    out = np.zeros((n, n_points, len(layout.resolutions), n_feat))
    for i in range(n):
        for p in range(n_points):
            for lvl, (res, size, offset) in enumerate(zip(layout.resolutions, layout.sizes, layout.offsets)):
                pos = [min(max(x, 0.0), 1.0) * (res - 1) + 0.5 for x in points[i, p]]
                base = [int(np.floor(x)) for x in pos]
                for c in range(8):
                    corner = [min(base[a] + ((c >> a) & 1), res - 1) for a in range(3)]
                    weight = 1.0
                    for a in range(3):
                        frac = pos[a] - base[a]
                        weight *= frac if (c >> a) & 1 else 1.0 - frac
                    if size == res**3:
                        idx = corner[0] + corner[1] * res + corner[2] * res * res
                    else:
                        idx = (corner[0] * _P0 ^ corner[1] * _P1 ^ corner[2] * _P2) % size
                    out[i, p, lvl] += weight * table[offset + idx]
    return out.reshape(n, -1)


# ---------------------------------------------------------------------------------------------


class HashGrid(nn.Module):
    """Multiresolution hash grid over the unit cube; ``forward(points [N, P, 3]) -> [N, P * L * F]``.

    Defaults are N-BVH's: 8 levels from 8^3 to 1024^3, 4 features, ``2**18`` rows per hashed
    level, features U(-init_scale, init_scale) drawn from a generator seeded with ``seed``.
    Points outside [0, 1] are clamped onto the cube.
    """

    def __init__(self, levels: int = 8, base_resolution: int = 8, features_per_level: int = 4, log2_table_size: int = 18,
                 init_scale: float = 1e-4, seed: int = 0):
        super().__init__()
        self.layout = HashGridLayout.create(levels, base_resolution, log2_table_size)
        self.features_per_level = int(features_per_level)
        generator = torch.Generator().manual_seed(seed)
        init = (torch.rand(self.layout.rows, self.features_per_level, generator=generator) * 2 - 1) * init_scale
        self.table = nn.Parameter(init)  # [rows, F]

    def output_dim(self, points_per_query: int) -> int:
        return points_per_query * len(self.layout.resolutions) * self.features_per_level

    def forward(self, points: Tensor) -> Tensor:
        if points.ndim != 3 or points.shape[-1] != 3:
            raise ValueError(f"expected points [N, P, 3], got {tuple(points.shape)}")
        if self.table.device.type == "cpu" and self.table.dtype == torch.float32:
            return _HashGridFunction.apply(points, self.table, self.layout)
        if self.table.device.type == "cuda":
            from .hash_grid_triton import hash_grid_triton

            return hash_grid_triton(points, self.table, self.layout)
        return hash_grid_torch(points, self.table, self.layout)

    def extra_repr(self) -> str:
        lay = self.layout
        return f"resolutions={lay.resolutions[0]}..{lay.resolutions[-1]}, rows={lay.rows}, features={self.features_per_level}"

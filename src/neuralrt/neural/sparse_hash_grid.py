"""Sparse multi-resolution hash grid encoding (LSNIF, Sec. 3.2).

LSNIF only ever queries points on voxel faces (the boundary points of `lsnif_features`), so only
grid vertices on voxel faces need features. A point on a face perpendicular to axis ``a`` is
interpolated *bilinearly* from the 4 vertices of its 2D cell on that face plane (4 table reads
instead of the 8 of a dense trilinear grid). Each level has its own hash table of ``2**17``
entries, indexed by the instant-ngp spatial hash of the integer vertex coordinates
``(x * 1) ^ (y * 2654435761) ^ (z * 805459861) mod T`` (Müller et al. 2022). A vertex shared by
faces of different orientations (edges, corners) is the same entry, so features are continuous
across voxel edges.

Point codes follow `neuralrt.methods.lsnif_features`: ``face_axis`` 0/1/2 = on a face plane
perpendicular to x/y/z (bilinear), 3 = a ray origin inside a voxel (trilinear from the 8
vertices of its cell; the only reads of interior vertices), -1 = padding (zero features).

Level resolutions must be multiples of the voxel resolution, so that every voxel face plane is
a grid plane of every level (`check_resolutions`).

One contract, implementations chosen once by the table's device: on the CPU (fp32 table), fused
numba kernels (the forward parallel over rays; the backward parallel over table rows: each thread
owns a range of one level's rows and adds the contributions that land there, so there are no
atomics, no per-thread tables to sum, and the sums are the serial ones; on hosts with many threads
per level the contributions are first bucketed by row range, so that the work still divides); on
CUDA, Triton kernels (`sparse_hash_grid_triton`:
gather forward, atomic-add backward); elsewhere the vectorized pure-torch
`sparse_hash_grid_reference`, which is also the reference the tests compare the kernels against.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np
import torch
import torch.nn.functional as F
from llvmlite import ir
from numba import types
from numba.extending import intrinsic
from torch import Tensor, nn

from ..simd import broadcast, contiguous_1d, element_pointer, numba_targets, prefetch_row, vector_pointer
from ..task_queue import take_task, task_count, task_workers
from .bf16_dot import as_fp32, bf16_bits

__all__ = [
    "SparseHashGrid",
    "sparse_hash_grid_reference",
    "count_stored_entries",
    "check_resolutions",
    "HASH_PRIMES",
]

HASH_PRIMES = (1, 2654435761, 805459861)  # instant-ngp's spatial hash
_P0, _P1, _P2 = HASH_PRIMES
_ORIGIN_POINT = 3


def check_resolutions(resolutions: Sequence[int], voxel_resolution: int) -> None:
    """Raise ValueError unless every level resolution is a positive multiple of the voxel one."""
    bad = [r for r in resolutions if r < 1 or r % voxel_resolution]
    if bad or voxel_resolution < 1:
        raise ValueError(
            f"hash grid resolutions {tuple(resolutions)} must be positive multiples of the voxel "
            f"resolution {voxel_resolution} (voxel faces must lie on grid planes)"
        )


# ---------------------------------------------------------------------------------------------
# numba kernels (CPU)


@numba.njit(cache=True, inline="always")
def _axis_terms(p, res, fixed, prime):
    """Hashed coordinate terms (vertex i, vertex i + 1) and the weight of i + 1 along one axis.

    The hash is ``x*P0 ^ y*P1 ^ z*P2``, so each axis contributes its own term. On the fixed
    (face-normal) axis the point lies on a grid plane: round onto it, both terms equal, weight 0.
    """
    f = p * np.float32(res)  # float32 throughout: exact for power-of-two resolutions, and faster
    if fixed:
        i = min(max(int(np.rint(f)), 0), res)
        h = np.int64(i) * prime
        return h, h, np.float32(0.0)
    i = min(max(int(np.floor(f)), 0), res - 1)
    return np.int64(i) * prime, np.int64(i + 1) * prime, f - np.float32(i)


@numba.njit(cache=True, inline="always")
def corner_rows(a, u0, u1, wu, v0, v1, wv, base, mask):
    """The 4 rows and bilinear weights of a face point as (s0, s1, s2, s3, w0, w1, w2, w3), from the
    fixed axis's hash term ``a`` and the in-plane axes' corner terms (u0, u1, v0, v1) and
    fractions (wu, wv)."""
    one = np.float32(1.0)
    return (base + ((a ^ u0 ^ v0) & mask), base + ((a ^ u1 ^ v0) & mask), base + ((a ^ u0 ^ v1) & mask),
            base + ((a ^ u1 ^ v1) & mask), (one - wu) * (one - wv), wu * (one - wv), (one - wu) * wv, wu * wv)


@numba.njit(cache=True, inline="always")
def face_corners(a, u0, u1, wu, v0, v1, wv, base, mask, slots, weights):
    """`corner_rows` written into ``slots``/``weights``; returns 4."""
    slots[0], slots[1], slots[2], slots[3], weights[0], weights[1], weights[2], weights[3] = corner_rows(
        a, u0, u1, wu, v0, v1, wv, base, mask)
    return 4


@numba.njit(cache=True, inline="always")
def face_rows(px, py, pz, code, res, mask, base):
    """The 4 rows (offset by ``base``) and bilinear weights of a face point (code 0/1/2) as a tuple
    (s0, s1, s2, s3, w0, w1, w2, w3), without branches on the face axis (it changes from point to
    point along a ray, so branches on it mispredict): a loop of these over many points compiles to
    SIMD code. Same rows and weights as `_point_level`."""
    r = np.float32(res)
    pa = px if code == 0 else (py if code == 1 else pz)  # on the face plane
    pu = py if code == 0 else px  # the two in-plane axes, in x, y, z order
    pv = py if code == 2 else pz
    prime_a = _P0 if code == 0 else (_P1 if code == 1 else _P2)
    prime_u = _P1 if code == 0 else _P0
    prime_v = _P1 if code == 2 else _P2
    a = np.int64(min(max(int(np.rint(pa * r)), 0), res)) * prime_a
    fu = pu * r
    iu = min(max(int(np.floor(fu)), 0), res - 1)
    wu = fu - np.float32(iu)
    fv = pv * r
    iv = min(max(int(np.floor(fv)), 0), res - 1)
    wv = fv - np.float32(iv)
    u0, u1 = np.int64(iu) * prime_u, np.int64(iu + 1) * prime_u
    v0, v1 = np.int64(iv) * prime_v, np.int64(iv + 1) * prime_v
    return corner_rows(a, u0, u1, wu, v0, v1, wv, base, mask)


@numba.njit(cache=True, inline="always")
def origin_corner(c, x0, x1, wx, y0, y1, wy, z0, z1, wz, base, mask):
    """Corner ``c`` (x fastest) of an origin point's cell: its row and trilinear weight, from the
    axes' `_axis_terms`."""
    one = np.float32(1.0)
    hx, fx = (x1, wx) if c & 1 else (x0, one - wx)
    hy, fy = (y1, wy) if c & 2 else (y0, one - wy)
    hz, fz = (z1, wz) if c & 4 else (z0, one - wz)
    return base + ((hx ^ hy ^ hz) & mask), fx * fy * fz


@numba.njit(cache=True, inline="always")
def origin_rows(px, py, pz, res, mask, base, slots, weights, i):
    """The 8 rows and trilinear weights of an origin point (`_point_level`'s), written to
    ``slots[c, i]``/``weights[c, i]``, without branches: a loop of these over many points compiles
    to SIMD code."""
    x0, x1, wx = _axis_terms(px, res, False, _P0)
    y0, y1, wy = _axis_terms(py, res, False, _P1)
    z0, z1, wz = _axis_terms(pz, res, False, _P2)
    for c in range(8):
        slots[c, i], weights[c, i] = origin_corner(c, x0, x1, wx, y0, y1, wy, z0, z1, wz, base, mask)


@numba.njit(cache=True, inline="always")
def face_point_level(px, py, pz, code, res, mask, base, slots, weights):
    """`face_rows` written into ``slots``/``weights``; returns 4."""
    slots[0], slots[1], slots[2], slots[3], weights[0], weights[1], weights[2], weights[3] = face_rows(
        px, py, pz, code, res, mask, base)
    return 4


@numba.njit(cache=True, inline="always")
def _point_level(px, py, pz, code, res, mask, base, slots, weights):
    """Fill ``slots``/``weights`` with the table rows (offset by ``base``) a point reads; returns
    how many: 4 (bilinear on the face cell) for face points, 8 (trilinear) for origin points."""
    x0, x1, wx = _axis_terms(px, res, code == 0, _P0)
    y0, y1, wy = _axis_terms(py, res, code == 1, _P1)
    z0, z1, wz = _axis_terms(pz, res, code == 2, _P2)
    if code == _ORIGIN_POINT:
        for c in range(8):
            slots[c], weights[c] = origin_corner(c, x0, x1, wx, y0, y1, wy, z0, z1, wz, base, mask)
        return 8
    # Face point: (a, u0, u1, wu, v0, v1, wv) = fixed axis term and the two in-plane axes.
    if code == 0:
        a, u0, u1, wu, v0, v1, wv = x0, y0, y1, wy, z0, z1, wz
    elif code == 1:
        a, u0, u1, wu, v0, v1, wv = y0, x0, x1, wx, z0, z1, wz
    else:
        a, u0, u1, wu, v0, v1, wv = z0, x0, x1, wx, y0, y1, wy
    return face_corners(a, u0, u1, wu, v0, v1, wv, base, mask, slots, weights)


# Rays whose table rows are found (and prefetched) before any is read: the reads of a group are
# then independent and overlap, instead of waiting on one cache miss after another (the 2 x 1.5
# MiB tables do not fit in L2). Since the rows are found for all of a group's points at once
# (session 46), 64 rays: the forward 0.77-0.98x the time of 16 (four in-process A/Bs, Zen 4).
_GROUP = 64


@numba.njit(cache=True, inline="always")
def _rows_of(px, py, pz, code, res, mask, base, slots, weights):
    """`_point_level` with the branch-free face-point variant (same slots and weights)."""
    if code == _ORIGIN_POINT:
        return _point_level(px, py, pz, code, res, mask, base, slots, weights)
    return face_point_level(px, py, pz, code, res, mask, base, slots, weights)


@numba.njit(cache=True, inline="always")
def read_face_rows(table, s0, s1, s2, s3, c0, c1, c2, c3, out, col):
    """``out[col + f] = sum_c c_c * table[s_c, f]`` over a face point's 4 rows, summed in row order
    from 0, the 4 reads of a feature written out together."""
    for f in range(table.shape[1]):
        out[col + f] = (((np.float32(0.0) + c0 * table[s0, f]) + c1 * table[s1, f]) + c2 * table[s2, f]) + c3 * table[s3, f]


_F32X4 = ir.VectorType(ir.FloatType(), 4)
_F16X4 = ir.VectorType(ir.HalfType(), 4)
_F32X2 = ir.VectorType(ir.FloatType(), 2)


def padded_table(table: Tensor) -> np.ndarray:
    """``table``'s values and one float after them, flat float32 (`read_rows3`'s ``table_flat``): a
    view of its storage where the table has that spare float (a `SparseHashGrid`'s, on the CPU in
    float32: no copy), else a copy with a zero after it."""
    t = table.detach()
    n = t.numel()
    if (t.dtype == torch.float32 and t.device.type == "cpu" and t.is_contiguous()
            and t.untyped_storage().nbytes() >= (t.storage_offset() + n + 1) * 4):  # fmt: skip
        return torch.empty(0).set_(t.untyped_storage(), t.storage_offset(), (n + 1,)).numpy()
    flat = np.zeros(n + 1, np.float32)
    flat[:-1] = t.float().reshape(-1).cpu().numpy()
    return flat


# Where numba targets F16C, whose instruction widens float16 (`read_rows3` on `half_table`s): without
# it LLVM calls a conversion routine numba's JIT does not provide (a crash, measured with
# NUMBA_CPU_NAME=generic), so there the tables stay float32.
HALF_READS = numba_targets("f16c")


def half_table(table: Tensor) -> np.ndarray | None:
    """``table``'s values as flat float16 bits (uint16: numba's CPU target has no float16 arrays)
    with one more after them (`read_rows3`'s ``table_flat`` at half the bytes) where float16 holds
    every value exactly (a model rounded to its fp16 storage precision, as `train` returns and a
    model file loads) and `HALF_READS`, else None."""
    if not HALF_READS:
        return None
    t = table.detach().cpu().float().reshape(-1)
    half = t.to(torch.float16)
    if not torch.equal(half.float(), t):
        return None
    flat = np.zeros(t.numel() + 1, np.uint16)
    flat[:-1] = half.view(torch.int16).numpy().view(np.uint16)
    return flat


def _rows3_typing(table_flat, slots, weights, out, col) -> bool:
    table_ok = contiguous_1d(table_flat, types.float32) or (HALF_READS and contiguous_1d(table_flat, types.uint16))
    return (table_ok and contiguous_1d(out, types.float32) and isinstance(col, types.Integer)
            and isinstance(slots, types.UniTuple) and isinstance(slots.dtype, types.Integer)
            and isinstance(weights, types.UniTuple) and weights.dtype == types.float32 and len(slots) == len(weights))  # fmt: skip


def _rows3_sum(context, builder, sig, args):
    """The weighted sum of the rows, 4 lanes (the fourth: the value after each row, unused) (IR)."""
    table_type, slots_type = sig.args[0], sig.args[1]
    acc = ir.Constant(_F32X4, [0.0] * 4)
    three = ir.Constant(ir.IntType(64), 3)
    for k in range(len(slots_type)):
        slot = context.cast(builder, builder.extract_value(args[1], k), slots_type.dtype, types.int64)
        if table_type.dtype == types.uint16:
            row = builder.load(vector_pointer(context, builder, table_type, args[0], builder.mul(slot, three), _F16X4), align=2)
            row = builder.fpext(row, _F32X4)
        else:
            row = builder.load(vector_pointer(context, builder, table_type, args[0], builder.mul(slot, three), _F32X4), align=4)
        acc = builder.fadd(acc, builder.fmul(broadcast(builder, builder.extract_value(args[2], k), _F32X4), row))
    return acc


@intrinsic
def read_rows3(typingctx, table_flat, slots, weights, out, col):
    """`read_rows` for 3 features per row and the rows ``slots`` (a tuple of integers) with
    ``weights`` (as many float32s), one row per vector load: ``table_flat`` is the table's flat
    float32 data (or float16 bits as uint16, `half_table`: each row widened to float32 exactly) with
    at least one element after it (each load takes 4 values from ``3 * slot``); per lane the same
    operations (products, then sums from 0 in row order, no fused multiply-adds), so the same bits;
    ``out[col : col + 3]`` written, nothing after it."""
    if not _rows3_typing(table_flat, slots, weights, out, col):
        return None

    def codegen(context, builder, sig, args):
        acc = _rows3_sum(context, builder, sig, args)
        out_type, col = sig.args[3], context.cast(builder, args[4], sig.args[4], types.intp)
        first_two = builder.shuffle_vector(acc, ir.Constant(_F32X4, None), ir.Constant(ir.VectorType(ir.IntType(32), 2), [0, 1]))
        builder.store(first_two, vector_pointer(context, builder, out_type, args[3], col, _F32X2), align=4)
        third = element_pointer(context, builder, out_type, args[3], builder.add(col, ir.Constant(col.type, 2)))
        builder.store(builder.extract_element(acc, ir.Constant(ir.IntType(32), 2)), third)
        return context.get_dummy_value()

    return types.void(table_flat, slots, weights, out, col), codegen


@intrinsic
def read_rows3_then(typingctx, table_flat, slots, weights, out, col, then):
    """`read_rows3`, and ``out[col + 3] = then`` (a float32) in the same vector store."""
    if not (_rows3_typing(table_flat, slots, weights, out, col) and then == types.float32):
        return None

    def codegen(context, builder, sig, args):
        acc = builder.insert_element(_rows3_sum(context, builder, sig, args), args[5], ir.Constant(ir.IntType(32), 3))
        col = context.cast(builder, args[4], sig.args[4], types.intp)
        builder.store(acc, vector_pointer(context, builder, sig.args[3], args[3], col, _F32X4), align=4)
        return context.get_dummy_value()

    return types.void(table_flat, slots, weights, out, col, types.float32), codegen


@numba.njit(cache=True, inline="always")
def read_rows(table, slots, weights, k, out, col):
    """``out[col + f] = sum_c weights[c] * table[slots[c], f]`` over the point's ``k`` rows, summed
    in row order from 0. Face points (k = 4) have their rows and weights loaded once and the 4
    reads of a feature written out together (measured ~2x faster than the loop, same bits)."""
    n_feat = table.shape[1]
    if k == 4:
        read_face_rows(table, slots[0], slots[1], slots[2], slots[3], weights[0], weights[1], weights[2], weights[3], out, col)
        return
    for f in range(n_feat):
        acc = np.float32(0.0)  # padding points (k = 0): zero features
        for c in range(k):
            acc += weights[c] * table[slots[c], f]
        out[col + f] = acc


@numba.njit(cache=True)
def face_rows_of_points(point_x, point_y, point_z, point_code, n, res, mask, base, slots, weights):
    """`face_rows` of points ``[0, n)`` into ``slots``/``weights`` ``[4, >= n]``: a function of its own
    so that the loop compiles to SIMD code (its arrays are arguments, not a parallel kernel's
    locals). Origin points get face rows too, which their callers do not use."""
    for i in range(n):
        slots[0, i], slots[1, i], slots[2, i], slots[3, i], weights[0, i], weights[1, i], weights[2, i], weights[3, i] = face_rows(
            point_x[i], point_y[i], point_z[i], point_code[i], res, mask, base)


@numba.njit(parallel=True, cache=True)
def _forward_kernel(points, axes, rows, table, table_flat, resolutions, n_chunks, n_workers, extra, out, out_bf16, point_offsets,
                    saved_slots, saved_weights):  # fmt: skip
    """``table`` is ``[L * T, F]`` (levels stacked), ``table_flat`` its `padded_table`; ``out`` is
    ``[>= N, H * L * F + E]`` fp32, or, when ``out_bf16`` has rows, ``out_bf16`` is (uint16 bf16
    bits, rounded as torch's cast) and ``out`` is unused; row n's last E columns are ``extra [N,
    E]`` (E may be 0), the same cast. Per group of `_GROUP` rays: the valid points listed, every
    face point's rows and weights found for a level at once (`face_rows_of_points`, SIMD code) and
    prefetched, then the reads (origin points' 8 rows found as they are read). When
    ``saved_slots``/``saved_weights`` (``[L, P, 4]``) have rows, each face point's 4 rows and
    weights are kept there for the backward, packed: ray n's j-th valid point at
    ``point_offsets[n] + j`` (origin points, 8 rows, are recomputed).
    Output row n encodes the points of input row ``rows[n]`` (the caller's selection, no copy)."""
    n_rays, n_points = rows.shape[0], axes.shape[1]
    n_levels = resolutions.shape[0]
    n_feat = table.shape[1]
    table_size = table.shape[0] // n_levels
    mask = np.int64(table_size - 1)
    stride = n_levels * n_feat
    low_precision = out_bf16.shape[0] > 0
    save = point_offsets.shape[0] > 0
    next_chunk = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):  # chunks handed out one at a time (`task_queue`)
        # The group's valid points, one entry each (structure of arrays: SIMD code in `face_rows_of_points`)
        point_x = np.empty(_GROUP * n_points, np.float32)
        point_y = np.empty(_GROUP * n_points, np.float32)
        point_z = np.empty(_GROUP * n_points, np.float32)
        point_code = np.empty(_GROUP * n_points, np.int32)
        entry = np.empty(_GROUP * n_points, np.int64)  # per slot of a ray, to its last valid one: its point, or -1
        face_slots = np.empty((n_levels, 4, _GROUP * n_points), np.int32)  # (table rows < 2^31)
        face_weights = np.empty((n_levels, 4, _GROUP * n_points), np.float32)
        slots8 = np.empty(8, np.int64)  # an origin point's rows, or a face point's for `read_rows`
        weights8 = np.empty(8, np.float32)
        scratch = np.empty(n_points * stride, np.float32)  # one ray's fp32 features before rounding
        used = np.empty(_GROUP, np.int64)  # per ray of the group: slots up to its last valid point
        while True:
            chunk = take_task(next_chunk)
            if chunk >= n_chunks:
                break
            stop = (chunk + 1) * n_rays // n_chunks
            for first in range(chunk * n_rays // n_chunks, stop, _GROUP):
                last = min(first + _GROUP, stop)
                q = 0  # points listed
                e = 0  # slots walked
                for n in range(first, last):
                    src = rows[n]
                    # Rays fill their slots from the first (`featurize_rays`); the padding after the
                    # last valid point (~2/3 of a bunny ray's 18 slots) is written as zeros at once.
                    h_used = n_points
                    while h_used > 0 and not (0 <= axes[src, h_used - 1] <= _ORIGIN_POINT):
                        h_used -= 1
                    used[n - first] = h_used
                    for h in range(h_used):
                        code = axes[src, h]
                        entry[e] = -1
                        if 0 <= code <= _ORIGIN_POINT:
                            point_x[q], point_y[q], point_z[q], point_code[q] = points[src, h, 0], points[src, h, 1], points[src, h, 2], code
                            entry[e] = q
                            q += 1
                        e += 1
                for lvl in range(n_levels):
                    face_rows_of_points(point_x, point_y, point_z, point_code, q, resolutions[lvl], mask, lvl * table_size,
                                        face_slots[lvl], face_weights[lvl])  # fmt: skip
                    for i in range(q):
                        if point_code[i] != _ORIGIN_POINT:
                            for c in range(4):
                                prefetch_row(table, face_slots[lvl, c, i])
                if save:
                    e = 0
                    for n in range(first, last):
                        p = point_offsets[n]
                        for h in range(used[n - first]):
                            i = entry[e]
                            e += 1
                            if i < 0:
                                continue
                            if point_code[i] != _ORIGIN_POINT:
                                for lvl in range(n_levels):
                                    for c in range(4):
                                        saved_slots[lvl, p, c] = face_slots[lvl, c, i]
                                        saved_weights[lvl, p, c] = face_weights[lvl, c, i]
                            p += 1
                e = 0
                for n in range(first, last):
                    row = scratch if low_precision else out[n]
                    h_used = used[n - first]
                    for h in range(h_used):
                        i = entry[e]
                        e += 1
                        for lvl in range(n_levels):
                            col = h * stride + lvl * n_feat
                            if i < 0:  # padding between points: zero features
                                for f in range(n_feat):
                                    row[col + f] = np.float32(0.0)
                            elif point_code[i] == _ORIGIN_POINT:
                                _point_level(point_x[i], point_y[i], point_z[i], _ORIGIN_POINT, resolutions[lvl], mask, lvl * table_size,
                                             slots8, weights8)  # fmt: skip
                                if n_feat == 3:  # a row per vector load (`read_rows3`: the same sums)
                                    read_rows3(table_flat, (slots8[0], slots8[1], slots8[2], slots8[3], slots8[4], slots8[5], slots8[6],
                                                            slots8[7]),
                                               (weights8[0], weights8[1], weights8[2], weights8[3], weights8[4], weights8[5], weights8[6],
                                                weights8[7]), row, col)  # fmt: skip
                                else:
                                    read_rows(table, slots8, weights8, 8, row, col)
                            elif n_feat == 3:
                                s, w = face_slots[lvl], face_weights[lvl]
                                read_rows3(table_flat, (s[0, i], s[1, i], s[2, i], s[3, i]), (w[0, i], w[1, i], w[2, i], w[3, i]), row, col)
                            else:
                                for c in range(4):
                                    slots8[c], weights8[c] = face_slots[lvl, c, i], face_weights[lvl, c, i]
                                read_rows(table, slots8, weights8, 4, row, col)
                    if low_precision:
                        for j in range(h_used * stride):
                            out_bf16[n, j] = bf16_bits(scratch[j])
                        for j in range(h_used * stride, n_points * stride):
                            out_bf16[n, j] = 0  # bf16_bits(0.0)
                    else:
                        for j in range(h_used * stride, n_points * stride):
                            out[n, j] = np.float32(0.0)
                    for j in range(extra.shape[1]):
                        if low_precision:
                            out_bf16[n, n_points * stride + j] = bf16_bits(extra[n, j])
                        else:
                            out[n, n_points * stride + j] = extra[n, j]


@numba.njit(parallel=True, cache=True)
def _backward_kernel(points, axes, grad_out, resolutions, grad_tables):
    """Scatter ``grad_out`` into ``grad_tables[chunk]`` (``[L * T, F]`` each): one private table
    per chunk (thread), so no atomics are needed."""
    n_rays, n_points = axes.shape
    n_chunks = grad_tables.shape[0]
    n_levels = resolutions.shape[0]
    n_feat = grad_tables.shape[2]
    table_size = grad_tables.shape[1] // n_levels
    mask = np.int64(table_size - 1)
    stride = n_levels * n_feat
    for chunk in numba.prange(n_chunks):
        grad = grad_tables[chunk]
        slots = np.empty(8, np.int64)
        weights = np.empty(8, np.float32)
        for n in range(chunk * n_rays // n_chunks, (chunk + 1) * n_rays // n_chunks):
            for h in range(n_points):
                code = axes[n, h]
                if code < 0 or code > _ORIGIN_POINT:
                    continue
                for lvl in range(n_levels):
                    k = _point_level(points[n, h, 0], points[n, h, 1], points[n, h, 2], code,
                                     resolutions[lvl], mask, lvl * table_size, slots, weights)  # fmt: skip
                    col = h * stride + lvl * n_feat
                    for f in range(n_feat):
                        g = grad_out[n, col + f]
                        for c in range(k):
                            grad[slots[c], f] += weights[c] * g


@numba.njit(parallel=True, cache=True)
def _backward_rows_kernel(points, axes, rows, grad_out, resolutions, ranges_per_level, grad_table):
    """Scatter ``grad_out`` into the one ``grad_table`` (``[L * T, F]``) with no atomics and no
    per-thread copies: task (level, r) owns rows ``r/R .. (r+1)/R`` of that level's table
    (``R = ranges_per_level``), zeroes them, and adds every point's contributions that land there.
    Each row sums its contributions in ray order, whatever R and the thread count: the result is
    the serial scatter's, bit for bit. With R > 1 every task of a level recomputes that level's
    rows for all points (the price of owning rows). (Prefetching the rows a group of rays ahead,
    as the forward does, measured slower here.) Gradient row n belongs to input row ``rows[n]``
    (no copy of the selected rays)."""
    n_rays, n_points = rows.shape[0], axes.shape[1]
    n_levels = resolutions.shape[0]
    n_feat = grad_table.shape[1]
    table_size = grad_table.shape[0] // n_levels
    mask = np.int64(table_size - 1)
    stride = n_levels * n_feat
    for task in numba.prange(n_levels * ranges_per_level):
        lvl, r = task // ranges_per_level, task % ranges_per_level
        base = lvl * table_size
        row_lo = base + r * table_size // ranges_per_level
        row_hi = base + (r + 1) * table_size // ranges_per_level
        grad_table[row_lo:row_hi] = 0.0
        slots = np.empty(8, np.int64)
        weights = np.empty(8, np.float32)
        res = resolutions[lvl]
        for n in range(n_rays):
            i = rows[n]
            for h in range(n_points):
                code = axes[i, h]
                if code < 0 or code > _ORIGIN_POINT:
                    continue
                k = _rows_of(points[i, h, 0], points[i, h, 1], points[i, h, 2], code, res, mask, base, slots, weights)
                col = h * stride + lvl * n_feat
                for c in range(k):
                    row = slots[c]
                    if row_lo <= row < row_hi:
                        w = weights[c]
                        for f in range(n_feat):
                            grad_table[row, f] += w * as_fp32(grad_out[n, col + f])


@numba.njit(parallel=True, cache=True)
def _backward_saved_kernel(points, axes, rows, grad_out, resolutions, ranges_per_level, saved_slots, saved_weights, grad_table):
    """`_backward_rows_kernel` reading each face point's rows and weights as the forward saved them
    (``[L, P, 4]``, the valid points packed in ray order) instead of hashing the point again; origin
    points (8 rows) are recomputed; gradient row n belongs to input row ``rows[n]``.
    Same contributions in the same order: the same gradient, bit for bit."""
    n_rays, n_points = axes.shape
    n_levels = resolutions.shape[0]
    n_feat = grad_table.shape[1]
    table_size = grad_table.shape[0] // n_levels
    mask = np.int64(table_size - 1)
    stride = n_levels * n_feat
    for task in numba.prange(n_levels * ranges_per_level):
        lvl, r = task // ranges_per_level, task % ranges_per_level
        base = lvl * table_size
        row_lo = base + r * table_size // ranges_per_level
        row_hi = base + (r + 1) * table_size // ranges_per_level
        grad_table[row_lo:row_hi] = 0.0
        slots = np.empty(8, np.int64)
        weights = np.empty(8, np.float32)
        res = resolutions[lvl]
        level_slots, level_weights = saved_slots[lvl], saved_weights[lvl]
        p = -1
        for n in range(rows.shape[0]):
            src = rows[n]
            for h in range(n_points):
                code = axes[src, h]
                if code < 0 or code > _ORIGIN_POINT:
                    continue
                p += 1
                col = h * stride + lvl * n_feat
                if code == _ORIGIN_POINT:
                    k = _point_level(points[src, h, 0], points[src, h, 1], points[src, h, 2], code, res, mask, base, slots, weights)
                    for c in range(k):
                        row = slots[c]
                        if row_lo <= row < row_hi:
                            w = weights[c]
                            for f in range(n_feat):
                                grad_table[row, f] += w * as_fp32(grad_out[n, col + f])
                    continue
                for c in range(4):
                    row = level_slots[p, c]
                    if row_lo <= row < row_hi:
                        w = level_weights[p, c]
                        for f in range(n_feat):
                            grad_table[row, f] += w * as_fp32(grad_out[n, col + f])


@numba.njit(cache=True, inline="always")
def _bucket_chunk(first, last, points, axes, rows, grad_out, resolutions, ranges_per_level, table_size, mask, at, write,
                  entry_rows, entry_values):  # fmt: skip
    """Rays ``first..last`` (output rows; input rows ``rows[n]``) of one chunk, their contributions
    in order of ray, point, level, corner, each into the bucket of the row range it lands in:
    ``at[bucket] += 1`` per contribution, and with ``write`` the row and ``w * grad`` stored at
    the entry ``at[bucket]`` held before (so ``at`` counts, or, starting from the chunk's
    offsets, places)."""
    n_levels, n_points = resolutions.shape[0], axes.shape[1]
    n_feat = entry_values.shape[1]
    stride = n_levels * n_feat
    slots = np.empty(8, np.int64)
    weights = np.empty(8, np.float32)
    for n in range(first, last):
        src = rows[n]
        for h in range(n_points):
            code = axes[src, h]
            if code < 0 or code > _ORIGIN_POINT:
                continue
            for lvl in range(n_levels):
                base = lvl * table_size
                k = _rows_of(points[src, h, 0], points[src, h, 1], points[src, h, 2], code, resolutions[lvl], mask, base,
                             slots, weights)  # fmt: skip
                col = h * stride + lvl * n_feat
                for c in range(k):
                    b = lvl * ranges_per_level + (slots[c] - base) * ranges_per_level // table_size
                    e = at[b]
                    at[b] = e + 1
                    if write:
                        entry_rows[e] = slots[c]
                        for f in range(n_feat):
                            entry_values[e, f] = weights[c] * as_fp32(grad_out[n, col + f])


@numba.njit(parallel=True, cache=True)
def _backward_buckets_kernel(points, axes, rows, grad_out, resolutions, ranges_per_level, n_chunks, grad_table):
    """`_backward_rows_kernel`'s result (bit for bit) with work that shrinks with the thread count:
    each of ``n_chunks`` chunks of rays counts, then writes, its contributions ``w * grad`` into the
    bucket of the row range they land in (`_bucket_chunk`, twice, hashing the points each time;
    buckets keep ray order: chunk order, then ray, point, corner), and each (level, range) task
    zeroes its rows and adds its bucket in that order. The rows-owned-by-a-task scatter instead
    hashes every point of its level in every task: with R ranges per level R times the work, so it
    gains nothing past one task per level (2 levels: 2 threads). Gradient row n belongs to input
    row ``rows[n]`` (no copy of the selected rays)."""
    n_rays = rows.shape[0]
    n_levels = resolutions.shape[0]
    n_feat = grad_table.shape[1]
    table_size = grad_table.shape[0] // n_levels
    mask = np.int64(table_size - 1)
    n_buckets = n_levels * ranges_per_level
    per_chunk = -(-n_rays // n_chunks)
    no_rows, no_values = np.empty(0, np.int64), np.empty((0, n_feat), np.float32)
    counts = np.zeros((n_chunks, n_buckets), np.int64)
    for chunk in numba.prange(n_chunks):
        _bucket_chunk(chunk * per_chunk, min((chunk + 1) * per_chunk, n_rays), points, axes, rows, grad_out, resolutions,
                      ranges_per_level, table_size, mask, counts[chunk], False, no_rows, no_values)  # fmt: skip
    # Bucket-major offsets: bucket b holds chunk 0's entries of b, then chunk 1's, ...
    starts = np.empty(n_buckets + 1, np.int64)
    cursor = np.empty((n_chunks, n_buckets), np.int64)
    total = 0
    for b in range(n_buckets):
        starts[b] = total
        for chunk in range(n_chunks):
            cursor[chunk, b] = total
            total += counts[chunk, b]
    starts[n_buckets] = total
    entry_rows = np.empty(total, np.int64)
    entry_values = np.empty((total, n_feat), np.float32)
    for chunk in numba.prange(n_chunks):
        _bucket_chunk(chunk * per_chunk, min((chunk + 1) * per_chunk, n_rays), points, axes, rows, grad_out, resolutions,
                      ranges_per_level, table_size, mask, cursor[chunk], True, entry_rows, entry_values)  # fmt: skip
    for b in numba.prange(n_buckets):
        lvl, r = b // ranges_per_level, b % ranges_per_level
        base = lvl * table_size
        # Range r is the rows x (from base) with x * R // T == r: from ceil(r T / R) on.
        lo = base + (r * table_size + ranges_per_level - 1) // ranges_per_level
        hi = base + ((r + 1) * table_size + ranges_per_level - 1) // ranges_per_level
        grad_table[lo:hi] = 0.0
        for e in range(starts[b], starts[b + 1]):
            row = entry_rows[e]
            for f in range(n_feat):
                grad_table[row, f] += entry_values[e, f]


def _numpy(t: Tensor, dtype) -> np.ndarray:
    return t.detach().to(dtype).contiguous().numpy()


class _SparseHashGridFunction(torch.autograd.Function):
    """Fused numba forward/backward; differentiable in the table only (points are data). With
    ``dtype=torch.bfloat16`` the features come out rounded to bf16 (as ``.to(torch.bfloat16)`` of
    the fp32 ones: same bits) and the backward reads the bf16 output gradient as it is."""

    @staticmethod
    def forward(ctx, points: Tensor, face_axis: Tensor, rows: Tensor | None, table: Tensor, resolutions: np.ndarray,
                backward_scatter: str, extra: Tensor | None, dtype: torch.dtype, out_rows: int):  # fmt: skip
        pts = _numpy(points, torch.float32)
        axes = _numpy(face_axis, torch.int8)
        # Output row n encodes input row rows[n] (all rows in order without ``rows``).
        index = np.arange(len(axes), dtype=np.int64) if rows is None else _numpy(rows, torch.int64)
        n_rays, n_points = len(index), axes.shape[1]
        levels, _, n_feat = table.shape
        width = n_points * levels * n_feat
        extra_np = np.empty((n_rays, 0), np.float32) if extra is None else _numpy(extra, torch.float32)
        # The extra columns are written by the kernel: no concatenation after, no slice of the gradient
        # before the backward. Rows past the rays' are zeros (a GEMM's row padding, `MLP`: no copy).
        shape = (max(out_rows, n_rays), width + extra_np.shape[1])
        if dtype == torch.bfloat16:
            out, bits = np.empty((0, shape[1]), np.float32), np.empty(shape, np.uint16)
            bits[n_rays:] = 0
        else:
            out, bits = np.empty(shape, np.float32), np.empty((0, shape[1]), np.uint16)
            out[n_rays:] = 0
        # "saved_rows": the backward scatters from the rows and weights the forward found (int32 +
        # fp32, 4 per valid point and level, packed: 32 * L bytes a point; a bunny hq step's
        # ~30,000 points of 5,400 rays: ~1.9 MiB). (The caller decides: grad mode is off here.)
        save = backward_scatter == "saved_rows"
        offsets = np.zeros(n_rays + 1 if save else 0, np.int64)
        if save:
            selected = axes if rows is None else axes[index]
            np.cumsum(np.count_nonzero((selected >= 0) & (selected <= _ORIGIN_POINT), axis=1), out=offsets[1:])
        saved_shape = (levels, int(offsets[-1]) if save else 0, 4)
        saved_slots, saved_weights = np.empty(saved_shape, np.int32), np.empty(saved_shape, np.float32)
        if n_rays:
            n_chunks = task_count(n_rays)
            flat = _numpy(table, torch.float32).reshape(-1, n_feat)
            _forward_kernel(pts, axes, index, flat, padded_table(table), resolutions, n_chunks, task_workers(n_chunks), extra_np, out,
                            bits, offsets, saved_slots, saved_weights)  # fmt: skip
        ctx.saved_rows = (saved_slots, saved_weights) if save else None
        ctx.index = index
        ctx.save_for_backward(points, face_axis)
        ctx.resolutions = resolutions
        ctx.table_shape = tuple(table.shape)
        ctx.backward_scatter = backward_scatter
        return torch.from_numpy(bits).view(torch.bfloat16) if dtype == torch.bfloat16 else torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        grad_table = None
        if ctx.needs_input_grad[3]:
            points, face_axis = ctx.saved_tensors
            levels, size, n_feat = ctx.table_shape
            if grad_out.dtype == torch.bfloat16:
                grad = grad_out.contiguous().view(torch.int16).numpy().view(np.uint16)
            else:
                grad = _numpy(grad_out, torch.float32)
            grad = grad[: len(ctx.index)]  # (rows past the rays': padding, no gradient to scatter)
            pts, axes = _numpy(points, torch.float32), _numpy(face_axis, torch.int8)
            threads = numba.get_num_threads()
            if ctx.saved_rows is not None:
                table_grad = np.empty((levels * size, n_feat), np.float32)
                _backward_saved_kernel(pts, axes, ctx.index, grad, ctx.resolutions, -(-threads // levels), *ctx.saved_rows,
                                       table_grad)  # fmt: skip
                ctx.saved_rows = None
            elif ctx.backward_scatter == "buckets":
                table_grad = np.empty((levels * size, n_feat), np.float32)
                n_chunks = max(1, min(len(ctx.index), 4 * threads))
                _backward_buckets_kernel(pts, axes, ctx.index, grad, ctx.resolutions, -(-2 * threads // levels), n_chunks,
                                         table_grad)  # fmt: skip
            elif ctx.backward_scatter in ("row_ranges", "saved_rows"):
                table_grad = np.empty((levels * size, n_feat), np.float32)
                _backward_rows_kernel(pts, axes, ctx.index, grad, ctx.resolutions, -(-threads // levels), table_grad)
            else:  # "thread_tables": the earlier scatter, kept to measure against; it takes the selected rows
                if len(ctx.index) != len(axes) or not np.array_equal(ctx.index, np.arange(len(axes))):
                    pts, axes = pts[ctx.index], axes[ctx.index]
                n_threads = max(1, min(len(axes), threads))
                tables = np.zeros((n_threads, levels * size, n_feat), np.float32)
                if len(axes):
                    _backward_kernel(pts, axes, _numpy(grad_out, torch.float32)[: len(axes)], ctx.resolutions, tables)
                table_grad = tables[0] if n_threads == 1 else tables.sum(0)
            grad_table = torch.from_numpy(table_grad.reshape(ctx.table_shape))
        return None, None, None, grad_table, None, None, None, None, None


# ---------------------------------------------------------------------------------------------
# Pure torch (any device): the reference, and the CUDA path.

_CORNERS = torch.tensor([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])  # [8, 3]


def sparse_hash_grid_reference(
    points: Tensor, face_axis: Tensor, table: Tensor, resolutions: Sequence[int]
) -> Tensor:
    """Vectorized torch version of `SparseHashGrid.forward` (autograd through indexing)."""
    n_rays, n_points = face_axis.shape
    levels, table_size, n_feat = table.shape
    p = points.reshape(-1, 3).to(table.dtype)
    code = face_axis.reshape(-1).long()
    valid = (code >= 0) & (code <= _ORIGIN_POINT)
    fixed = nn.functional.one_hot(code.clamp(0, 3), 4)[:, :3].bool() & valid[:, None]  # [M, 3]
    corners = _CORNERS.to(p.device)
    primes = torch.tensor(HASH_PRIMES, device=p.device)
    per_level = []
    for lvl, res in enumerate(resolutions):
        f = p * res
        cell = torch.floor(f).long().clamp(0, res - 1)
        w = f - cell
        cell = torch.where(fixed, torch.round(f).long().clamp(0, res), cell)
        w = torch.where(fixed, torch.zeros_like(w), w)  # face points: no weight off the plane
        vertex = cell[:, None, :] + corners[None]  # [M, 8, 3]
        weight = torch.where(corners[None].bool(), w[:, None, :], 1 - w[:, None, :]).prod(-1)
        slot = (vertex[..., 0] * primes[0]) ^ (vertex[..., 1] * primes[1]) ^ (vertex[..., 2] * primes[2])
        slot = slot & (table_size - 1)
        feats = table[lvl][slot]  # [M, 8, F]
        per_level.append((weight[..., None] * feats).sum(1) * valid[:, None])
    return torch.stack(per_level, 1).reshape(n_rays, n_points * levels * n_feat)


# ---------------------------------------------------------------------------------------------


# The encoder backward alone (bench_scaling.py --scatters, 16-core host, hq, 2 levels), ms, row
# ranges vs buckets: 2 threads 1.76 vs 3.71 (2^13 rays), 27.9 vs 64.6 (2^17); 16 threads 2.17 vs
# 1.19, 31.3 vs 20.5. Between 2 and 16 unmeasured: buckets from 4 threads per level (8 for 2 levels).
BUCKETS_FROM_THREADS_PER_LEVEL = 4


class SparseHashGrid(nn.Module):
    """Multi-resolution hash grid over voxel faces; features of H points concatenated per ray.

    Defaults are the paper's: levels 64^3 and 128^3, 3 features per entry, ``2**17`` entries per
    level, features initialised ``U(-1e-4, 1e-4)``.
    """

    def __init__(
        self,
        resolutions: Sequence[int] = (64, 128),
        features_per_level: int = 3,
        log2_table_size: int = 17,
        init_scale: float = 1e-4,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if not resolutions or min(resolutions) < 1:
            raise ValueError(f"hash grid resolutions must be positive, got {tuple(resolutions)}")
        if features_per_level < 1 or not 1 <= log2_table_size <= 30:
            raise ValueError(
                f"need features_per_level >= 1 and 1 <= log2_table_size <= 30, got "
                f"{features_per_level} and {log2_table_size}"
            )
        self.resolutions = tuple(int(r) for r in resolutions)
        self.features_per_level = int(features_per_level)
        self.log2_table_size = int(log2_table_size)
        generator = torch.Generator().manual_seed(seed)
        shape = (len(self.resolutions), 2**self.log2_table_size, self.features_per_level)
        init = (torch.rand(shape, generator=generator) * 2 - 1) * init_scale
        # One spare float after the table in its storage: the fused CPU pass loads each row of 3
        # features as 4 floats (`read_rows3`), so the last row may read it (`padded_table`).
        storage = torch.zeros(init.numel() + 1)
        storage[:-1] = init.reshape(-1)
        self.table = nn.Parameter(storage[:-1].view(shape))  # [L, T, F]
        self._resolutions_np = np.asarray(self.resolutions, np.int64)
        # CPU backward: "auto" (the default: "buckets" on hosts of at least BUCKETS_FROM_THREADS_PER_LEVEL
        # threads per level, else "row_ranges"), "row_ranges" (threads own table rows, hashing each point
        # again: R row ranges per level cost R times the hashing, so no gain past one thread per level),
        # "buckets" (the contributions bucketed by row range first: twice the work on 2 threads, but it
        # shrinks with threads), "saved_rows" (as row_ranges, from the rows and weights the forward saved:
        # the backward ~0.8 ms faster, the forward ~0.4 ms slower, no gain in the step on 2 cores,
        # docs/lsnif.md) or "thread_tables" (a private table per thread, summed); the last two kept to
        # measure against. All but thread_tables give the serial scatter's bits. Not stored in models.
        self.backward_scatter = "auto"
        # CPU forward with ``dtype=torch.bfloat16``: the kernel writes bf16 (True) or fp32 that is
        # then cast (False: the earlier path, kept to measure against); same values either way.
        self.low_precision_output = True

    def output_dim(self, max_points: int) -> int:
        return max_points * len(self.resolutions) * self.features_per_level

    def forward(self, points: Tensor, face_axis: Tensor, extra: Tensor | None = None, dtype: torch.dtype = torch.float32,
                rows: Tensor | None = None, out_rows: int | None = None) -> Tensor:  # fmt: skip
        """``points [N, H, 3]`` unit-box, ``face_axis [N, H]`` -> features ``[N, H * L * F]``.

        Layout is point-major: point 0 level 0 features, point 0 level 1, ..., point 1 ...;
        padding points give zeros. ``extra [N, E]`` (data, no gradient) is appended as E more
        columns (on the CPU written into the same output, instead of a concatenation). ``dtype``:
        the output's, the fp32 features cast to it (the CPU kernel writes bf16 itself, no fp32
        copy, with ``low_precision_output``). ``rows [M]`` (long): encode only those rays, in that
        order, as ``points[rows], face_axis[rows]`` would (``extra`` then has M rows); the CPU kernels
        read the points through the index (no copy). ``out_rows`` (>= M): the output has that many
        rows, those past the rays' zeros (the row padding `MLP` gives its GEMMs, written here
        instead of copied there).
        """
        if points.ndim != 3 or points.shape[-1] != 3 or face_axis.shape != points.shape[:2]:
            raise ValueError(
                f"expected points [N, H, 3] and face_axis [N, H], got {tuple(points.shape)} and "
                f"{tuple(face_axis.shape)}"
            )
        n_out = len(points) if rows is None else len(rows)
        if extra is not None and (extra.ndim != 2 or len(extra) != n_out):
            raise ValueError(f"expected extra columns [N, E] for {n_out} rays, got {tuple(extra.shape)}")
        if out_rows is not None and out_rows < n_out:
            raise ValueError(f"out_rows ({out_rows}) must be at least the {n_out} rays")
        if rows is not None and (rows.ndim != 1 or (len(rows) and not 0 <= int(rows.min()) <= int(rows.max()) < len(points))):
            raise ValueError(f"rows must be a 1-D index into the {len(points)} rays")
        cpu_kernels = self.table.device.type == "cpu" and self.table.dtype == torch.float32
        if rows is not None and not cpu_kernels:
            points, face_axis = points[rows], face_axis[rows]
        if self.table.device.type == "cuda":
            from .sparse_hash_grid_triton import sparse_hash_grid_triton

            features = sparse_hash_grid_triton(points, face_axis, self.table, self._resolutions_on(self.table.device))
        elif cpu_kernels:
            kernel_dtype = torch.bfloat16 if dtype == torch.bfloat16 and self.low_precision_output else torch.float32
            scatter = self.backward_scatter
            if scatter == "auto":
                scatter = "buckets" if numba.get_num_threads() >= BUCKETS_FROM_THREADS_PER_LEVEL * len(self.resolutions) else "row_ranges"
            if scatter == "saved_rows" and not (torch.is_grad_enabled() and self.table.requires_grad):
                scatter = "row_ranges"  # no backward to come: nothing to save
            features = _SparseHashGridFunction.apply(points, face_axis, rows, self.table, self._resolutions_np, scatter,
                                                     extra, kernel_dtype, out_rows or n_out)  # fmt: skip
            return features.to(dtype)
        else:
            features = sparse_hash_grid_reference(points, face_axis, self.table, self.resolutions)
        features = (features if extra is None else torch.cat([features, extra.to(features.dtype)], dim=1)).to(dtype)
        return features if out_rows is None or out_rows == n_out else F.pad(features, (0, 0, 0, out_rows - n_out))

    def _resolutions_on(self, device: torch.device) -> Tensor:
        """The level resolutions as an int32 tensor on ``device`` (made once per device: no copy per call)."""
        cached = getattr(self, "_resolutions_dev", None)
        if cached is None or cached.device != device:
            cached = self._resolutions_dev = torch.tensor(self.resolutions, dtype=torch.int32, device=device)
        return cached

    def extra_repr(self) -> str:
        return (
            f"resolutions={self.resolutions}, features_per_level={self.features_per_level}, "
            f"log2_table_size={self.log2_table_size}"
        )


def count_stored_entries(
    occupancy: Tensor | np.ndarray, resolutions: Sequence[int] = (64, 128), log2_table_size: int = 17
) -> dict:
    """How many grid vertices the sparse grid actually uses, per level, vs a dense grid.

    ``face_vertices``: distinct vertices on faces of occupied voxels (what face points read);
    ``interior_vertices``: vertices strictly inside occupied voxels (read only by trilinear ray
    origins); ``dense_vertices``: ``(R + 1)^3``; ``*_slots_used``: distinct hash-table slots those
    vertex sets occupy in a table of ``2**log2_table_size`` entries (the rest collide).
    """
    occ = occupancy.detach().cpu().numpy() if isinstance(occupancy, Tensor) else np.asarray(occupancy)
    occ = occ.astype(bool)
    if occ.ndim != 3 or len(set(occ.shape)) != 1:
        raise ValueError(f"occupancy must be a cubic [V, V, V] array, got shape {occ.shape}")
    voxel_res = occ.shape[0]
    check_resolutions(resolutions, voxel_res)
    table_size = 2**log2_table_size
    occupied = np.argwhere(occ)
    levels = []
    for res in resolutions:
        s = res // voxel_res  # grid cells per voxel edge
        on_face = np.zeros((res + 1,) * 3, bool)
        inside = np.zeros((res + 1,) * 3, bool)
        for i, j, k in occupied * s:
            for axis in range(3):
                for plane in (0, s):
                    sl = [slice(i, i + s + 1), slice(j, j + s + 1), slice(k, k + s + 1)]
                    sl[axis] = (i, j, k)[axis] + plane
                    on_face[tuple(sl)] = True
            inside[i + 1 : i + s, j + 1 : j + s, k + 1 : k + s] = True

        def slots(mask: np.ndarray) -> int:
            v = np.argwhere(mask).astype(np.int64)
            h = (v[:, 0] * _P0 ^ v[:, 1] * _P1 ^ v[:, 2] * _P2) & (table_size - 1)
            return int(np.unique(h).size)

        levels.append(
            {
                "resolution": int(res),
                "face_vertices": int(on_face.sum()),
                "interior_vertices": int(inside.sum()),
                "dense_vertices": (res + 1) ** 3,
                "table_size": table_size,
                "face_slots_used": slots(on_face),
                "dense_slots_used": slots(np.ones_like(on_face)),
            }
        )
    return {"voxel_resolution": voxel_res, "occupied_voxels": int(len(occupied)), "levels": levels}

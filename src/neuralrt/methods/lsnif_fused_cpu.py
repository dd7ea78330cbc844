"""LSNIF inference on the CPU with one fused numba pass per ray chunk.

For each ray, one numba kernel maps it into the model's unit box (`lsnif_features.unit_box_ray`),
walks the voxels (the 3D-DDA of `lsnif_features`, float64; where numba targets AVX-512 and V is a
power of two, sixteen rays at a time in float32 with the same decisions, `lsnif_walk_simd`),
encodes each boundary point in the sparse hash grid (`sparse_hash_grid.face_rows` and
`origin_rows`: `_point_level`'s rows and weights, float32, the same sums as its forward kernel; a
group's rows are read a group after its walk, each with one vector load, `read_rows3`) and adds
the point's contribution to the first MLP layer at once:
the network input is the concatenation of per-point blocks, so ``x @ W1^T`` is the sum over
points of ``x_h @ W1[:, block h]^T`` and padding points contribute nothing. The kernel writes
the first hidden layer's activations (bias, leaky ReLU, rounded to the compute dtype); the other
hidden layers run as torch GEMMs with the model's own weights (or in the decoding pass,
`HIDDEN_LAYERS_IN_DECODE`) and the output layer in the decoding pass; where those later layers
run in numba, the pass itself runs them and the decoding, a group of rays after its first layer
(`DECODE_IN_PASS`). A table whose values are all float16 numbers (a model at fp16 storage
precision) is read from a float16 copy (`HALF_TABLE`), the same bits from half the bytes. Nothing of size [rays,
points, features] is ever in memory; a ray's points live in a per-thread scratch row of H entries.
The exception, chosen for speed: where the CPU has AMX the first layer is a torch GEMM too
(`FIRST_LAYER_IN_PASS`), and the pass writes each network ray's H * (L * F + 1) inputs in bf16
(2 bytes each: for `hq`, 126 inputs, the size of the 128 activations it writes otherwise; never
more than `GEMM_INPUTS_PER_WIDTH` times the width by default).

Rays that cross no occupied voxel (``count == 0``) are certain misses and never reach the GEMMs.

Same answers as the unfused path (`featurize_rays` -> `SparseHashGrid` -> `MLP`) up to the
compute precision: the first layer accumulates in fp32 from fp32 features here (unfused: a bf16
GEMM where the compute dtype is bf16); in fp32 the two differ only by summation order.

The CUDA counterpart is `lsnif_fused` (Triton); `LSNIFModel._network_answers` picks one by device.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..neural.bf16_dot import bf16_bits, bf16_pairs, bf16_value, dot_rows_bf16, first_lanes16, fma_f32, load16, store_bf16x16
from ..neural.mlp import MLP, padded_rows
from ..neural.mlp_rows_cpu import (
    BLOCK_ROWS, HOST_HAS_AMX, bias_leaky_bf16, hidden_layer_pairs, hidden_layers_bf16, output_layer_columns, output_rows, sigmoid,
    widen_rows_bf16,
)  # fmt: skip
from ..neural.sparse_hash_grid import SparseHashGrid, half_table, padded_table
from ..neural.sparse_hash_grid import face_rows_of_points as _face_rows_of_points
from ..neural.sparse_hash_grid import origin_rows as _origin_rows
from ..neural.sparse_hash_grid import read_rows3 as _read_rows3
from ..neural.sparse_hash_grid import read_rows3_then as _read_rows3_then
from ..neural.sparse_hash_grid import read_rows as _read_rows
from ..simd import HAS_AVX512
from ..simd16 import (
    bits16, compress16_f32, compress16_i32, lane_index16, load16_i32, popcount16, splat_i32, store16_i32,
)  # fmt: skip
from ..rays_kernels import valid_ray, write_miss
from ..task_queue import take_task, task_count, task_workers
from .lsnif_features import ORIGIN_POINT, _check_rays, local_distance, unit_box_ray, walk_ray
from .lsnif_walk_simd import float32_walk_applies, occupancy_bits, walk_group, walk_scratch

__all__ = ["FusedCPUOutputs", "fused_network_outputs_cpu", "fused_hits_cpu", "fused_occluded_cpu", "first_layer_blocks"]



@dataclass
class FusedCPUOutputs:
    """Per ray of the batch: ``count``, ``t_enter``, ``t_exit`` (as `featurize_rays`); per ray that
    reached the network (``active``, indices into the batch, ascending): the MLP's raw ``values``."""

    active: Tensor  # [M] long
    values: Tensor  # [M, outputs] fp32
    count: Tensor  # [N] int32
    t_enter: Tensor  # [N] float32
    t_exit: Tensor  # [N] float32


@numba.njit(cache=True, fastmath={"contract"})
def _add_inputs(acc, w1, xs, n_inputs):
    """``acc += xs[:n] @ w1[:n]``, eight inputs per pass over ``acc`` (it stays in registers for
    eight products; fused multiply-adds allowed here only, not in the walk)."""
    width = acc.shape[0]
    i = 0
    while i + 8 <= n_inputs:
        x0, x1, x2, x3, x4, x5, x6, x7 = xs[i], xs[i + 1], xs[i + 2], xs[i + 3], xs[i + 4], xs[i + 5], xs[i + 6], xs[i + 7]
        for j in range(width):
            acc[j] += ((x0 * w1[i, j] + x1 * w1[i + 1, j]) + (x2 * w1[i + 2, j] + x3 * w1[i + 3, j])) + (
                (x4 * w1[i + 4, j] + x5 * w1[i + 5, j]) + (x6 * w1[i + 6, j] + x7 * w1[i + 7, j]))
        i += 8
    while i + 2 <= n_inputs:
        x0, x1 = xs[i], xs[i + 1]
        for j in range(width):
            acc[j] += x0 * w1[i, j] + x1 * w1[i + 1, j]
        i += 2
    if i < n_inputs:
        x0 = xs[i]
        for j in range(width):
            acc[j] += x0 * w1[i, j]


@numba.njit(cache=True, inline="always")
def _input_pairs(xs_row, n_inputs, out_row):
    """A ray's first ``n_inputs`` network inputs rounded to bf16 and packed two per word (input
    2p in the low half) into ``out_row``, zero past them."""
    used = (n_inputs + 1) // 2
    for p in range(used):
        lo, hi = 2 * p, 2 * p + 1
        x_hi = xs_row[hi] if hi < n_inputs else np.float32(0.0)
        out_row[p] = bf16_bits(xs_row[lo]) | (bf16_bits(x_hi) << np.uint32(16))
    for p in range(used, out_row.shape[0]):
        out_row[p] = 0


@numba.njit(cache=True, inline="always")
def _inputs_bf16(xs_row, n_inputs, n_out, out_row):
    """A ray's first ``n_inputs`` network inputs rounded to bf16 (`bf16_bits`) into ``out_row[:n_out]``
    (uint16; as uint32, the pairs of `_input_pairs`), zero past them; 16 per instruction (``n_out``
    a multiple of 16, at most the length of ``xs_row``)."""
    for c in range(0, n_out, 16):
        store_bf16x16(out_row, c, first_lanes16(load16(xs_row, c), min(max(n_inputs - c, 0), 16)))


@numba.njit(cache=True)
def _first_layer_pairs(xs, xp, group_count, n_group, block, w1_pairs, b1, slope, order, buckets, rows, dots, hidden_flat, start):
    """The first layer of a group's rays in bf16 (`dot_rows_bf16`), 4 rays per weight pass:
    each ray's inputs rounded to bf16 pairs (`_inputs_bf16`; zero up to the group's longest, so
    that a pass reads zeros past a ray's own), the rays with points ordered by point count (most
    first) so that the 4 of a pass need about as many pairs; bias, leaky ReLU and the rounding to
    bf16 in fp32 as the per-ray path; writes ray g's row at ``(start + g) * W`` of ``hidden_flat``
    (flat ``[N * W]`` uint16) and returns the number m of rays with points (``order[:m]``).
    ``xs [G, K]`` fp32 and ``xp [G, K / 2]`` uint32, K a multiple of 16."""
    width = b1.shape[0]
    longest = 0
    for g in range(n_group):
        longest = max(longest, group_count[g])
    n_out = (longest * block + 15) // 16 * 16
    xp_bf16 = xp.view(np.uint16)  # [G, K]: pair p of a row is its inputs 2p (low half: little-endian), 2p + 1
    # order: a counting sort by count, descending, stable (rays with more points first)
    ahead = buckets[: longest + 2]
    ahead[:] = 0
    for g in range(n_group):
        ahead[longest - group_count[g] + 1] += 1  # ahead[k + 1]: rays with count longest - k
    for k in range(1, longest + 2):
        ahead[k] += ahead[k - 1]  # ahead[k]: rays with more points than longest - k
    for g in range(n_group):
        count = group_count[g]
        if count == 0:
            continue
        _inputs_bf16(xs[g], count * block, n_out, xp_bf16[g])
        k = longest - count
        order[ahead[k]] = g
        ahead[k] += 1
    m = ahead[longest - 1] if longest > 0 else 0  # (rays with count 0 come last and are not ordered)
    for q in range(0, m, 4):
        n_rows = min(4, m - q)
        for i in range(4):
            rows[i] = order[q + min(i, n_rows - 1)]  # a short pass repeats its last ray
        dot_rows_bf16(xp, rows, (group_count[rows[0]] * block + 1) // 2, w1_pairs, 0, width, dots)
        for i in range(n_rows):
            bias_leaky_bf16(dots, i * width, b1, 0, width, slope, hidden_flat, (start + rows[i]) * width)
    return m


@numba.njit(cache=True)
def _origin_rows_of_points(origin_x, origin_y, origin_z, n, res, mask, base, slots, weights):
    """`origin_rows` of origin points ``[0, n)`` into ``slots``/``weights`` ``[8, >= n]`` (SIMD code,
    as `_face_rows_of_points`)."""
    for i in range(n):
        _origin_rows(origin_x[i], origin_y[i], origin_z[i], res, mask, base, slots, weights, i)


@numba.njit(cache=True, inline="always")
def _list_points(point_ray, point_slot, point_code, point_x, point_y, point_z, e, first_row, row_stride, block, point_column,
                 origin_entry, origin_x, origin_y, origin_z):  # fmt: skip
    """Points ``[0, e)`` of a group, 16 per instruction: each point's inputs' first column in
    ``xs_flat`` (row ``first_row`` + its ray, ``row_stride`` wide; ``block`` per slot) into
    ``point_column``, and the origin points' entries and coordinates appended to ``origin_*`` (their
    rows are found with the face points'); returns the number of origin points. (The point arrays
    hold a multiple of 16 entries: the lanes past ``e`` read and write unused entries.)"""
    n_origin = 0
    origin_code, lane = splat_i32(ORIGIN_POINT), lane_index16()
    for i in range(0, e, 16):
        ray, slot = load16_i32(point_ray, i), load16_i32(point_slot, i)
        store16_i32(point_column, i, (splat_i32(first_row) + ray) * splat_i32(row_stride) + slot * splat_i32(block))
        is_origin = (lane < splat_i32(e - i)) & (load16_i32(point_code, i) == origin_code)
        if bits16(is_origin) != 0:
            compress16_i32(origin_entry, n_origin, lane + splat_i32(i), is_origin)
            compress16_f32(origin_x, n_origin, load16(point_x, i), is_origin)
            compress16_f32(origin_y, n_origin, load16(point_y, i), is_origin)
            compress16_f32(origin_z, n_origin, load16(point_z, i), is_origin)
            n_origin += popcount16(is_origin)
    return n_origin


# Rays walked before their points are encoded. A group's table rows are found after its walk and
# read after the next group's walk. Zen 5, hairball(6): with `walk_ray` and the rows prefetched,
# 32 rays beat 8, 16, 64 and 128 (the one-group lead took the `hq` pass from 36-37 to 33 ms per
# 2^17 rays); with the SIMD walk, whose 8 lanes idle while a group's last rays finish (81% of lane
# steps used with 32 rays, 94% with 128), 64 beat 32 by 2-4% (`intersect`, both presets). Since
# each row is read with one vector load, prefetching the rows no longer pays (A/B: `intersect`
# 0.98-1.005x, `occluded` 0.95-1.01x without), and the lead still measures 0-6% faster for `lq`
# (mean ~2%) than reading a group's rows right after its walk. Without the prefetches, 128 rays
# beat 64 (A/B, `intersect`: `lq` 0.965-0.989x in three runs, `hq` 0.98-1.02x) and 96, 192 and
# 256 did not (`lq` 1.01x, 1.01x, 1.005x) (session 31). With the 16-lane float32 walk (session
# 32), 64 and 256 measured 1.024x and 1.000x (`lq`). On the Zen 4 (session 46; in-process A/B of
# two copies of this module on the same rays, medians of 50 rounds; an identical copy measured
# 0.994-1.005x): 256 rays 0.98-0.985x the time of 128 (`lq` `intersect` in four runs, `hq` in one;
# `occluded` 0.98-1.006x), 192 0.99-1.00x, 64 1.05x.
_GROUP = 256

# Many small chunks handed out one at a time (`task_queue`): rays vary in length, and on a shared
# machine one thread may be descheduled; with numba's static split of a prange (its OpenMP layer)
# the other waits for it. 2 threads, hairball(6), 2^17 rays in two chunks (session 35): the
# threads' sums of task times were 11.8 and 11.9 ms of a 12.9 ms call with the static split
# (the second half of the rays costs more); `intersect` 0.968x / 0.984x the time with the queue
# (A/B, same records), `occluded` 0.963x / 0.966x, `hq` 0.990x; one 2^17-ray chunk, 1.18x the time
# of two 2^16 with the static split, 0.99x with the queue. 32, 64, 128 or 256 chunks a thread:
# the same within noise.
_CHUNKS_PER_THREAD = 32

# The fused pass's chunks from the task queue; False: numba's split of the prange, one chunk per
# iteration, its scratch allocated per chunk (the code before session 35, for comparisons:
# `bench_scaling.py --switches DYNAMIC_CHUNKS=False`).
DYNAMIC_CHUNKS = True


@numba.njit(parallel=True, cache=True, nogil=True)
def _fused_kernel(
    origins, directions, t_min, t_max, box_lo, box_extent, occ, occ_bits, simd_walk, planes, table, table_flat, resolutions,
    w1, w1_pairs, b1, slope, max_points, origin_point, share, point_distances, to_bf16, pairs, write_inputs, n_chunks, n_workers,
    dynamic, hidden_f32, hidden_bf16, input_pairs, counts, t_enter, t_exit, t_offset,
    decode_here, hidden_pairs, hidden_bias, wo, bo, occlusion_logit, n_materials, occlusion_only, write_every_row,
    hit, t_hit, normal, geometric_normal, albedo, material, uv, primitive_id, instance_id,
):  # fmt: skip
    """The rays (``origins``/``directions`` fp32, ``t_min``/``t_max``) are mapped into the unit box
    (``box_lo``, ``box_extent``) a group at a time, as `unit_box_rays` maps them (``t_offset[n]``
    the shift); an invalid ray gets a zero direction and so no points. ``w1 [H * (L * F + 1), W]``:
    the first layer's weights, input-major, point slot h's rows at ``h * (L * F + 1)`` (its L * F
    features, then its point distance), so a ray's nonzero inputs are the first
    ``count * (L * F + 1)`` rows; writes ``hidden_f32`` or (``to_bf16``) ``hidden_bf16`` (bf16
    bits) rows of the rays with points; other rows are left as they were.
    With ``pairs`` (bf16, width a multiple of 16) the first layer is `dot_rows_bf16` over the
    group's rays, 4 at a time, from the bf16 pairs ``w1_pairs`` (``w1`` rounded, flat
    ``[ceil(rows / 2) * W]`` uint32) and the inputs rounded to bf16; else fp32 per ray from ``w1``.
    With ``pairs`` and ``decode_here`` the rest of the network and the decoding follow at once, per
    group (`_decode_rows`: ``hidden_pairs`` ... ``material`` as `_decode_kernel`'s, the chunk's ray n
    at row n of the records), and nothing is written to ``hidden_bf16``. With ``write_every_row`` every
    ray's row of the records (``hit`` ... ``instance_id``, `neuralrt.rays.Hits`' fields; ``hit``
    alone with ``occlusion_only``) first gets a miss (`write_miss`), which the decoding overwrites
    for the rays that reach the network (here or in `_decode_kernel`): the records need no fill
    before the call.
    With ``write_inputs`` no layer runs here: each ray's inputs, rounded to bf16 pairs (zero past
    its points), go to ``input_pairs [N, ceil(rows / 2)]`` uint32 for a GEMM (`first_layer_in_pass`).
    Per chunk, groups of `_GROUP` rays go through two stages one group apart (a software
    pipeline with two buffers): walk (``simd_walk``: `walk_group`, 16 lanes, the points unordered,
    ``occ_bits`` the occupancy as bits, `occupancy_bits`; else `walk_ray` per ray), list the points and find
    their rows (`face_rows`, SIMD); then read the rows and run the first layer. The rays are cut
    into ``n_chunks`` chunks, which ``n_workers`` workers take from a task queue (`task_queue`);
    without ``dynamic``, worker i runs chunk i alone (``n_workers = n_chunks``)."""
    n_rays = origins.shape[0]
    n_levels = resolutions.shape[0]
    n_feat = table.shape[1]
    table_size = table.shape[0] // n_levels
    mask = np.int64(table_size - 1)
    width = b1.shape[0]
    block = n_levels * n_feat + 1  # weight rows per point slot
    wo_flat = wo.reshape(-1)
    next_chunk = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):  # chunks handed out one at a time (`task_queue`)
        pts = np.empty((_GROUP, max_points, 3), np.float32)
        axes = np.empty((_GROUP, max_points), np.int8)
        # Two groups in flight: one is walked and its rows found while the other's rows are read
        group_count = np.empty((2, _GROUP), np.int64)
        group_truncated = np.empty(_GROUP, np.int32)  # (not needed here; `walk_group` writes it)
        # The group's points, one entry each (structure of arrays, so step 2 compiles to SIMD code)
        point_x = np.empty(_GROUP * max_points, np.float32)
        point_y = np.empty(_GROUP * max_points, np.float32)
        point_z = np.empty(_GROUP * max_points, np.float32)
        point_local = np.empty((2, _GROUP * max_points), np.float32)  # each point's local distance
        point_code = np.empty((2, _GROUP * max_points), np.int32)
        point_column = np.empty((2, _GROUP * max_points), np.int32)  # its features' first index in xs_flat
        face_slots = np.empty((2, n_levels, 4, _GROUP * max_points), np.int32)  # (table rows < 2^31)
        face_weights = np.empty((2, n_levels, 4, _GROUP * max_points), np.float32)
        group_points = np.empty(2, np.int64)
        point_ray = np.empty(_GROUP * max_points, np.int32)  # each point's ray in the group and slot in its list
        point_slot = np.empty(_GROUP * max_points, np.int32)
        queue, queue_i, rays8, lane_terms, redo = walk_scratch(_GROUP)
        group_origins = np.empty(2, np.int64)
        unit_o = np.empty((_GROUP, 3), np.float32)  # the group's rays in the unit box
        unit_d = np.empty((_GROUP, 3), np.float32)
        # Origin points (at most one per ray, the first): 8 rows per level
        origin_entry = np.empty((2, _GROUP), np.int32)
        origin_x = np.empty(_GROUP, np.float32)
        origin_y = np.empty(_GROUP, np.float32)
        origin_z = np.empty(_GROUP, np.float32)
        origin_slots = np.empty((2, n_levels, 8, _GROUP), np.int32)
        origin_weights = np.empty((2, n_levels, 8, _GROUP), np.float32)
        n_inputs = (max_points * block + 15) // 16 * 16  # (a multiple of 16 for `_inputs_bf16`)
        xs = np.empty((2, _GROUP, n_inputs), np.float32)  # the rays' nonzero network inputs
        xs_flat = xs.reshape(-1)
        acc = np.empty(width, np.float32)
        xp = np.empty((_GROUP, n_inputs // 2), np.uint32)  # the inputs as bf16 pairs (pairs path)
        order = np.empty(_GROUP, np.int64)  # the group's rays with points, most points first
        buckets = np.empty(max_points + 2, np.int64)
        rows = np.empty(4, np.int64)
        dots = np.empty(4 * width, np.float32)
        # decode_here: the group's first hidden layer (row g: ray start + g), then `_decode_rows`' scratch
        group_hidden = np.empty((_GROUP if decode_here else 0, width), np.uint16)
        layer_out = (group_hidden if decode_here else hidden_bf16).reshape(-1)  # (flat: `_first_layer_pairs` writes at offsets)
        rows8, outs, xp8, xp8_bf16 = _decode_scratch(width, wo.shape[1], decode_here)
        while True:
            chunk = take_task(next_chunk) if dynamic else np.int64(worker)  # (the prange index is unsigned)
            if chunk >= n_chunks:
                break
            first, last = chunk * n_rays // n_chunks, (chunk + 1) * n_rays // n_chunks
            n_groups = (last - first + _GROUP - 1) // _GROUP
            for step in range(n_groups + 1):
                if step < n_groups:  # walk group `step`; find its rows
                    b = step & 1
                    start = first + step * _GROUP
                    stop = min(start + _GROUP, last)
                    # 0. the rays into the unit box
                    for g in range(stop - start):
                        n = start + g
                        t_offset[n] = unit_box_ray(origins, directions, t_min, box_lo, box_extent, n, g, unit_o, unit_d)
                        if not valid_ray(origins, directions, t_min, t_max, n):
                            unit_d[g, 0] = unit_d[g, 1] = unit_d[g, 2] = np.float32(0.0)
                    if write_every_row and occlusion_only:
                        for n in range(start, stop):
                            hit[n] = False
                    elif write_every_row:  # (row by row: a column at a time measured slower; the rows the group's
                        # decoding overwrites are still in cache then)
                        for n in range(start, stop):
                            write_miss(n, hit, t_hit, normal, geometric_normal, uv, albedo, material, primitive_id, instance_id)
                    # 1. walk; list the points
                    e = 0
                    if simd_walk:  # sixteen rays at a time, the points unordered
                        e = walk_group(unit_o, unit_d, 0, stop - start, occ, occ_bits, planes, max_points, origin_point, share,
                                       queue, queue_i, rays8, lane_terms, redo, pts, axes, point_x, point_y, point_z, point_local[b],
                                       point_code[b], point_ray, point_slot, group_count[b], group_truncated, t_enter[start:stop],
                                       t_exit[start:stop])  # fmt: skip
                        for g in range(stop - start):
                            counts[start + g] = group_count[b, g]
                    else:
                        for g in range(stop - start):
                            n = start + g
                            ox32, oy32, oz32 = unit_o[g, 0], unit_o[g, 1], unit_o[g, 2]
                            dx32, dy32, dz32 = unit_d[g, 0], unit_d[g, 1], unit_d[g, 2]
                            count, _, t0, t1 = walk_ray(np.float64(ox32), np.float64(oy32), np.float64(oz32),
                                                        np.float64(dx32), np.float64(dy32), np.float64(dz32),
                                                        occ, planes, max_points, origin_point, share, pts, axes, g)  # fmt: skip
                            counts[n] = count
                            t_enter[n] = t0
                            t_exit[n] = t1
                            group_count[b, g] = count
                            for h in range(count):
                                px, py, pz = pts[g, h, 0], pts[g, h, 1], pts[g, h, 2]
                                point_x[e], point_y[e], point_z[e], point_code[b, e] = px, py, pz, axes[g, h]
                                point_ray[e], point_slot[e] = g, h
                                point_local[b, e] = local_distance(px, py, pz, ox32, oy32, oz32, dx32, dy32, dz32, np.float32(t0),
                                                                   np.float32(t1))  # fmt: skip
                                e += 1
                    # list the points: their inputs' columns; the origin points
                    n_origin = _list_points(point_ray, point_slot, point_code[b], point_x, point_y, point_z, e, b * _GROUP, xs.shape[2],
                                            block, point_column[b], origin_entry[b], origin_x, origin_y, origin_z)  # fmt: skip
                    # 2. every point's face rows and weights, per level (origin points' are computed and
                    # unused), and the origin points' 8 rows
                    for lvl in range(n_levels):
                        res, base = resolutions[lvl], lvl * table_size
                        _face_rows_of_points(point_x, point_y, point_z, point_code[b], e, res, mask, base, face_slots[b, lvl],
                                             face_weights[b, lvl])  # fmt: skip
                        _origin_rows_of_points(origin_x, origin_y, origin_z, n_origin, res, mask, base, origin_slots[b, lvl],
                                               origin_weights[b, lvl])  # fmt: skip
                    group_points[b] = e
                    group_origins[b] = n_origin
                if step > 0:  # read group `step - 1`'s rows, then its first layer
                    b = (step - 1) & 1
                    start = first + (step - 1) * _GROUP
                    stop = min(start + _GROUP, last)
                    # 3. the table reads, all independent, and the points' local distances (with n_feat = 3, the
                    # default: a row per vector load, the distance stored with the last level's features)
                    top = n_levels - 1  # the last level
                    for i in range(group_points[b]):
                        if point_code[b, i] == ORIGIN_POINT:
                            continue
                        col = point_column[b, i]
                        local = point_local[b, i] if point_distances else np.float32(0.0)
                        if n_feat == 3:
                            for lvl in range(top):
                                s, c = face_slots[b, lvl, :, i], face_weights[b, lvl, :, i]
                                _read_rows3(table_flat, (s[0], s[1], s[2], s[3]), (c[0], c[1], c[2], c[3]), xs_flat, col + lvl * 3)
                            s, c = face_slots[b, top, :, i], face_weights[b, top, :, i]
                            _read_rows3_then(table_flat, (s[0], s[1], s[2], s[3]), (c[0], c[1], c[2], c[3]), xs_flat, col + top * 3, local)
                        else:
                            xs_flat[col + block - 1] = local
                            for lvl in range(n_levels):
                                _read_rows(table, face_slots[b, lvl, :, i], face_weights[b, lvl, :, i], 4, xs_flat, col + lvl * n_feat)
                    for k in range(group_origins[b]):
                        col = point_column[b, origin_entry[b, k]]
                        local = point_local[b, origin_entry[b, k]] if point_distances else np.float32(0.0)
                        if n_feat == 3:
                            for lvl in range(top):
                                s, c = origin_slots[b, lvl, :, k], origin_weights[b, lvl, :, k]
                                _read_rows3(table_flat, (s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]),
                                            (c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]), xs_flat, col + lvl * 3)  # fmt: skip
                            s, c = origin_slots[b, top, :, k], origin_weights[b, top, :, k]
                            _read_rows3_then(table_flat, (s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]),
                                             (c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]), xs_flat, col + top * 3, local)  # fmt: skip
                        else:
                            xs_flat[col + block - 1] = local
                            for lvl in range(n_levels):
                                _read_rows(table, origin_slots[b, lvl, :, k], origin_weights[b, lvl, :, k], 8, xs_flat, col + lvl * n_feat)
                    # 4. the first layer, or its inputs
                    if write_inputs:
                        for g in range(stop - start):
                            if group_count[b, g] > 0:
                                _input_pairs(xs[b, g], group_count[b, g] * block, input_pairs[start + g])
                        continue
                    if pairs:
                        m = _first_layer_pairs(xs[b], xp, group_count[b], stop - start, block, w1_pairs, b1, slope, order, buckets, rows,
                                               dots, layer_out, 0 if decode_here else start)  # fmt: skip
                        if decode_here:
                            _decode_rows(group_hidden.view(np.uint32), order, m, start, hidden_pairs, hidden_bias, slope, wo_flat, bo,
                                         rows8, outs, xp8, xp8_bf16, rows, dots, t_enter, t_exit, t_offset, t_min, t_max, occlusion_logit,
                                         n_materials, occlusion_only, hit, t_hit, normal, geometric_normal, albedo, material)  # fmt: skip
                        continue
                    for g in range(stop - start):
                        count = group_count[b, g]
                        if count == 0:
                            continue
                        for j in range(width):
                            acc[j] = b1[j]
                        _add_inputs(acc, w1, xs[b, g], count * block)
                        for j in range(width):
                            y = acc[j]
                            acc[j] = y if y >= 0 else y * slope
                        n = start + g
                        if to_bf16:
                            for j in range(width):
                                hidden_bf16[n, j] = np.uint16(bf16_bits(acc[j]))
                        else:
                            for j in range(width):
                                hidden_f32[n, j] = acc[j]
            if not dynamic:
                break


# The voxel walk sixteen rays at a time (`lsnif_walk_simd`) where numba compiles for AVX-512 and
# the grid's V is a power of two (`float32_walk_applies`); False: `walk_ray` per ray (elsewhere LLVM
# would turn the vector code into slower scalar loops).
SIMD_WALK = HAS_AVX512

# The bf16 first layer from bf16 pairs (`dot_rows_bf16`) where the compute dtype is bf16 and the
# layer runs in the pass (`first_layer_in_pass`); False: the fp32 per-ray first layer
# (`_add_inputs`) in the pass for every dtype (for comparisons and tests).
BF16_DOT_FIRST_LAYER = True

# The fused pass reads the hash table's rows from a float16 copy where float16 holds every value
# exactly (`half_table`: models rounded to their fp16 storage precision, as `train` returns them and
# model files load), so the same bits from half the bytes: hairball(6)'s 2 x 2^17 x 3 table is
# 1.5 MiB instead of 3, against a 1 MiB L2 per core; False: the float32 table always.
HALF_TABLE = True

_scratch = threading.local()
_KEPT_BYTES = 64 << 20  # larger buffers are allocated per call rather than kept by the thread


def _hidden_buffer(rows: int, width: int, dtype, purpose: str = "first") -> np.ndarray:
    """A ``[rows, width]`` buffer for one use (``purpose``) in a call, reused across calls on this
    thread: a fresh one costs a page fault per 4 KiB on first touch (measured: ~25% of a call);
    nothing outside a call keeps a reference to it (the last layer's output is a fresh tensor)."""
    if rows * width * np.dtype(dtype).itemsize > _KEPT_BYTES:  # e.g. 2^20-ray chunks: not kept
        return np.empty((rows, width), dtype)
    key = (purpose, width, np.dtype(dtype).str)
    buffer = getattr(_scratch, "buffers", {}).get(key)
    if buffer is None or buffer.shape[0] < rows:
        _scratch.buffers = {**getattr(_scratch, "buffers", {}), key: np.empty((rows, width), dtype)}
        buffer = _scratch.buffers[key]
    return buffer[:rows]


def _buffer_tensor(rows: int, width: int, dtype: torch.dtype, purpose: str) -> Tensor:
    """`_hidden_buffer` as a torch tensor of ``dtype`` (fp32 or bf16)."""
    if dtype == torch.bfloat16:
        return torch.from_numpy(_hidden_buffer(rows, width, np.uint16, purpose)).view(torch.bfloat16)
    return torch.from_numpy(_hidden_buffer(rows, width, np.float32, purpose))


def first_layer_blocks(network: MLP, max_points: int, block: int, point_distances: bool) -> tuple[np.ndarray, np.ndarray]:
    """The first hidden layer as ``w1 [H * (block + 1), W]`` fp32, input-major: point slot h's
    ``block`` = L * F encoded inputs, then its point distance (a zero row without distances), and
    the bias ``[W]`` fp32."""
    weight = network.hidden[0].weight.detach().float()  # [W, H * block (+ H)]
    features = weight[:, : max_points * block].T.reshape(max_points, block, -1)
    if point_distances:
        distances = weight[:, max_points * block :].T.reshape(max_points, 1, -1)
    else:
        distances = torch.zeros(max_points, 1, weight.shape[0])
    rows = torch.cat([features, distances], dim=1).reshape(max_points * (block + 1), -1)
    return rows.contiguous().numpy(), network.hidden[0].bias.detach().float().contiguous().numpy()


def hidden_layers(network: MLP, hidden: Tensor, active: Tensor, compute_dtype: torch.dtype,
                  first_layer: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """The MLP's hidden layers after the first on rows ``active`` of ``hidden`` (activations in
    ``compute_dtype``; with ``first_layer`` = (weight, bias), the network inputs in the pass's
    order, and that layer first) -> the last hidden layer's activations ``[M, W]`` in ``compute_dtype``, in a
    per-thread buffer (valid until the next call on this thread): the same operations and bits as
    `MLP.forward` in inference, but every intermediate written into a per-thread buffer and the
    leaky ReLU applied in place: fresh [M, W] tensors cost a page fault per 4 KiB and an
    out-of-place activation another pass (measured on hairball(6) `hq`, one thread: 800 -> 340 ns
    per network ray)."""
    if compute_dtype == torch.float32:
        layers = [(layer.weight, layer.bias) for layer in network.hidden[1:]]
    else:
        layers = network._cast_weights(compute_dtype)[1:]  # bf16 copies cached by the MLP
    if first_layer is not None:
        layers = [first_layer, *layers]
    m = len(active)
    # Padded as `MLP.forward` pads its bf16 rows (the same bits): few GEMM shapes, one oneDNN kernel each.
    rows = m if compute_dtype == torch.float32 else padded_rows(m, hidden.device)
    x = _buffer_tensor(rows, hidden.shape[1], hidden.dtype, "gathered")
    torch.index_select(hidden, 0, active, out=x[:m])
    x[m:] = 0
    for i, (w, b) in enumerate(layers):
        x = torch.addmm(b, x, w.t(), out=_buffer_tensor(rows, w.shape[0], x.dtype, f"layer {i % 2}"))
        F.leaky_relu_(x, network.slope)
    return x[:m]


def rest_of_network(network: MLP, hidden: Tensor, active: Tensor, compute_dtype: torch.dtype,
                    first_layer: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """`hidden_layers` then the output layer -> [M, outputs] fp32 (a fresh tensor), the same
    operations and bits as `MLP.forward` in inference (from the first layer's activations)."""
    x = hidden_layers(network, hidden, active, compute_dtype, first_layer)
    if x.dtype != torch.float32:
        x = _buffer_tensor(len(active), x.shape[1], torch.float32, "fp32").copy_(x)
    return network.output(x)  # a fresh tensor: the caller keeps it


@dataclass
class _Pass:
    """What the fused pass and the decoding need besides the rays, prepared once per call."""

    network: MLP
    compute_dtype: torch.dtype
    occ: np.ndarray
    planes: np.ndarray
    table: np.ndarray  # [L * T, F] fp32 (a view of the table's storage where it can be)
    # the rows `read_rows3` reads: the table's values and one float after them (`padded_table`), or
    # their float16 bits where that is exact (`half_table`, `HALF_TABLE`)
    table_flat: np.ndarray
    resolutions: np.ndarray
    w1: np.ndarray
    w1_pairs: np.ndarray
    b1: np.ndarray
    hidden_pairs: np.ndarray  # flat [(L - 1) * W / 2 * W] uint32: the later hidden layers as bf16 pairs (pairs path), else empty
    hidden_bias: np.ndarray  # flat [(L - 1) * W] fp32: their biases, rounded to bf16 as torch's cast weights
    wo: np.ndarray  # [W, P] fp32 and bo [P]: the output layer (`output_layer_columns`)
    bo: np.ndarray
    occ_bits: np.ndarray  # [ceil(V^3 / 32)] int32: occ as bits for the SIMD walk's gathers (`occupancy_bits`)
    first_layer: tuple[Tensor, Tensor] | None  # bf16 (weight [W, 2 * ceil(rows / 2)] in w1's input order, bias): a GEMM, not in the pass
    max_points: int
    origin_point: bool
    share: bool
    point_distances: bool
    pairs: bool


def _prepare_pass(occupancy: Tensor, encoder: SparseHashGrid, network: MLP, *, max_points: int, origin_point: bool,
                  share_boundary_points: bool, point_distances: bool, compute_dtype: torch.dtype) -> _Pass:  # fmt: skip
    """The `_Pass` of these tensors and settings, kept on ``network`` until one of them changes:
    keyed, as `MLP._cast_weights`, on each tensor's storage and version counter (an optimizer
    step, a load or a move invalidates it) and on the module's switches. Building one takes
    ~0.3 ms (weight layouts, the int32 occupancy), paid per chunk before."""
    tensors = (occupancy, encoder.table, *network.parameters())
    key = (tuple((t.data_ptr(), t._version, t.shape) for t in tensors), max_points, origin_point, share_boundary_points,
           point_distances, compute_dtype, BF16_DOT_FIRST_LAYER, FIRST_LAYER_IN_PASS, GEMM_INPUTS_PER_WIDTH, HOST_HAS_AMX,
           HALF_TABLE)  # fmt: skip
    cached = getattr(network, "_fused_cpu_pass", None)
    if cached is not None and cached[0] == key:
        return cached[1]
    p = _build_pass(occupancy, encoder, network, max_points=max_points, origin_point=origin_point,
                    share_boundary_points=share_boundary_points, point_distances=point_distances, compute_dtype=compute_dtype)  # fmt: skip
    network._fused_cpu_pass = (key, p)
    return p


def _build_pass(occupancy: Tensor, encoder: SparseHashGrid, network: MLP, *, max_points: int, origin_point: bool,
                share_boundary_points: bool, point_distances: bool, compute_dtype: torch.dtype) -> _Pass:  # fmt: skip
    if compute_dtype not in (torch.float32, torch.bfloat16):
        raise ValueError(f"compute dtype must be float32 or bfloat16, got {compute_dtype}")
    occ = occupancy.detach().contiguous().numpy()
    if occ.ndim != 3 or len(set(occ.shape)) != 1:
        raise ValueError(f"occupancy must be a cubic [V, V, V] array, got shape {occ.shape}")
    levels, _, n_feat = encoder.table.shape
    table_flat = padded_table(encoder.table)  # (one float after the rows: `read_rows3` loads 4 from any row)
    table = table_flat[:-1].reshape(-1, n_feat)
    if table.shape[0] >= 1 << 31:  # the pass keeps a group's table rows as int32
        raise ValueError(f"hash table of {table.shape[0]} rows: the CPU pass handles fewer than 2^31")
    w1, b1 = first_layer_blocks(network, max_points, levels * n_feat, point_distances)
    in_pass = compute_dtype == torch.float32 or not BF16_DOT_FIRST_LAYER or first_layer_in_pass(*w1.shape)
    pairs = in_pass and BF16_DOT_FIRST_LAYER and compute_dtype == torch.bfloat16 and b1.shape[0] % 16 == 0  # else fp32 per ray
    w1_pairs = bf16_pairs(w1).reshape(-1) if pairs else np.zeros(0, np.uint32)
    if compute_dtype != torch.float32:
        network._cast_weights(compute_dtype)  # the cached bf16 weights, made here once rather than in several threads
    hidden_pairs, hidden_bias = hidden_layer_pairs(network) if pairs else (np.zeros(0, np.uint32), np.zeros(0, np.float32))
    first_layer = None if in_pass else first_layer_gemm(network, w1, compute_dtype)
    planes = np.arange(occ.shape[0] + 1) / occ.shape[0]  # k / V, as featurize_rays computes them
    occ_bits = occupancy_bits(occ)
    wo, bo = output_layer_columns(network)
    table_half = half_table(encoder.table) if HALF_TABLE and n_feat == 3 else None
    if table_half is not None:  # `read_rows3` reads these rows instead
        table_flat = table_half
    return _Pass(network, compute_dtype, occ, planes, table, table_flat, encoder._resolutions_np, w1, w1_pairs, b1, hidden_pairs,
                 hidden_bias, wo, bo, occ_bits, first_layer, int(max_points), bool(origin_point), bool(share_boundary_points),
                 bool(point_distances), pairs)  # fmt: skip


def first_layer_gemm(network: MLP, w1: np.ndarray, compute_dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """The first layer for torch's GEMM on the pass's inputs: ``w1`` (`first_layer_blocks`, fp32
    values of the layer's weights, reordered) rounded to ``compute_dtype`` as `MLP._cast_weights`
    rounds them, as ``[W, rows]`` plus a zero column for an odd row count; its cast bias."""
    rows = w1.shape[0] + w1.shape[0] % 2
    weight = torch.zeros(w1.shape[1], rows, dtype=compute_dtype)
    weight[:, : w1.shape[0]] = torch.from_numpy(w1).T.to(compute_dtype)
    return weight, network._cast_weights(compute_dtype)[0][1]


@dataclass
class _Rays:
    """A chunk's rays for the fused pass as numpy arrays: ``origins``/``directions`` ``[N, 3]``
    fp32, ``t_min``/``t_max`` ``[N]`` fp32, and the box the pass maps them from (``box_lo``,
    ``box_extent`` ``[3]`` fp32; 0 and 1 for rays already in the unit box)."""

    origins: np.ndarray
    directions: np.ndarray
    t_min: np.ndarray
    t_max: np.ndarray
    box_lo: np.ndarray
    box_extent: np.ndarray

    def __len__(self) -> int:
        return self.origins.shape[0]


@dataclass
class _Decoding:
    """A chunk's hit records and how to decode into them: ``records`` (`_decode_row`'s hit, t,
    normal, geometric normal, albedo, material) and ``miss_records`` (uv, primitive and instance id,
    which a neural model leaves at their miss values). The fused pass writes every ray's miss
    first; with ``in_pass`` (`decodes_in_pass`) it decodes the answers itself too."""

    occlusion_logit: float
    num_materials: int
    occlusion_only: bool
    records: tuple[np.ndarray, ...]
    miss_records: tuple[np.ndarray, ...]
    in_pass: bool


_NO_RECORDS = (np.zeros(0, np.bool_), np.zeros(0, np.float32), *(np.zeros((0, 3), np.float32),) * 3, np.zeros(0, np.int64))
_NO_MISS_RECORDS = (np.zeros((0, 2), np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64))
_NO_DECODING = _Decoding(0.0, 0, True, _NO_RECORDS, _NO_MISS_RECORDS, False)


def _first_hidden_layer(p: _Pass, rays: _Rays, decoding: _Decoding | None = None,
                        ) -> tuple[Tensor, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The fused pass on ``rays``: (first hidden layer ``[N, W]`` in the compute dtype -- with
    ``p.first_layer``, the network inputs in bf16 instead --, valid in the rows with points; per
    ray ``count``, ``t_enter``, ``t_exit`` and the unit-box map's ``t_offset`` as numpy arrays).
    With ``decoding`` the pass writes every ray's miss record into its records; where
    ``decoding.in_pass``, it decodes the answers itself too and the first hidden layer returned
    is empty."""
    n, width = len(rays), p.b1.shape[0]
    to_bf16 = p.compute_dtype == torch.bfloat16
    write_inputs = p.first_layer is not None
    write_every_row = decoding is not None
    decoding = decoding or _NO_DECODING
    decode_here = decoding.in_pass
    # One output buffer is used, the others stay empty: numba compiles one kernel for every case.
    hidden_f32 = _hidden_buffer(0 if to_bf16 else n, width, np.float32, "first")
    hidden_bf16 = _hidden_buffer(n if to_bf16 and not write_inputs and not decode_here else 0, width, np.uint16, "first")
    input_pairs = _hidden_buffer(n if write_inputs else 0, (p.w1.shape[0] + 1) // 2, np.uint32, "inputs")
    counts, t_offset = np.empty(n, np.int32), np.empty(n, np.float32)  # (the pass writes every ray's)
    t_enter, t_exit = np.empty(n, np.float32), np.empty(n, np.float32)
    if n:
        # A task allocates scratch for a group: one task per ray made a 64-ray call 2.2x slower
        # (lq, 227 vs 103 us; 1,024 rays 315 vs 184 us; ad hoc, 2 threads, session 34).
        n_chunks = task_count(n, _GROUP, _CHUNKS_PER_THREAD)
        simd_walk = SIMD_WALK and float32_walk_applies(p.occ.shape[0])
        n_workers = task_workers(n_chunks) if DYNAMIC_CHUNKS else n_chunks
        _fused_kernel(rays.origins, rays.directions, rays.t_min, rays.t_max, rays.box_lo, rays.box_extent, p.occ, p.occ_bits,
                      simd_walk, p.planes, p.table, p.table_flat, p.resolutions, p.w1, p.w1_pairs, p.b1, np.float32(p.network.slope),
                      p.max_points, p.origin_point, p.share, p.point_distances, to_bf16, p.pairs, write_inputs, n_chunks, n_workers,
                      DYNAMIC_CHUNKS, hidden_f32, hidden_bf16, input_pairs, counts, t_enter, t_exit, t_offset, decode_here,
                      p.hidden_pairs, p.hidden_bias, p.wo, p.bo, np.float32(decoding.occlusion_logit), int(decoding.num_materials),
                      decoding.occlusion_only, write_every_row, *decoding.records, *decoding.miss_records)  # fmt: skip
    if write_inputs:
        hidden = torch.from_numpy(input_pairs).view(torch.bfloat16)  # [N, 2 * pairs]: input 2p in the low half
    else:
        hidden = torch.from_numpy(hidden_bf16).view(torch.bfloat16) if to_bf16 else torch.from_numpy(hidden_f32)
    return hidden, counts, t_enter, t_exit, t_offset


def _numpy_f32(x: Tensor) -> np.ndarray:
    return x.detach().to(torch.float32).contiguous().numpy()


def _rays_numpy(origins: Tensor, directions: Tensor, max_points: int, t_min: Tensor | None = None, t_max: Tensor | None = None,
                box_lo: Tensor | None = None, box_extent: Tensor | None = None) -> _Rays:  # fmt: skip
    """The pass's `_Rays`; without ``t_min``/``t_max`` and the box, unit-box rays on [0, inf)."""
    _check_rays(origins, directions, max_points)
    o, d = _numpy_f32(origins), _numpy_f32(directions)
    if box_lo is None:
        return _Rays(o, d, np.zeros(len(o), np.float32), np.full(len(o), np.inf, np.float32), np.zeros(3, np.float32),
                     np.ones(3, np.float32))  # fmt: skip
    return _Rays(o, d, _numpy_f32(t_min), _numpy_f32(t_max), _numpy_f32(box_lo), _numpy_f32(box_extent))


@torch.no_grad()
def fused_network_outputs_cpu(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor,
    encoder: SparseHashGrid,
    network: MLP,
    *,
    max_points: int,
    origin_point: bool = True,
    share_boundary_points: bool = True,
    point_distances: bool = True,
    compute_dtype: torch.dtype = torch.float32,
) -> FusedCPUOutputs:
    """Raw MLP outputs of unit-box rays (``origins``/``directions`` ``[N, 3]`` fp32 CPU), with the
    walk, the encoding and the first layer fused in one numba pass; see the module docstring."""
    rays = _rays_numpy(origins, directions, max_points)
    p = _prepare_pass(occupancy, encoder, network, max_points=max_points, origin_point=origin_point,
                      share_boundary_points=share_boundary_points, point_distances=point_distances,
                      compute_dtype=compute_dtype)  # fmt: skip
    hidden, counts, t_enter, t_exit, _ = _first_hidden_layer(p, rays)
    count = torch.from_numpy(counts)
    active = torch.nonzero(count > 0).squeeze(1)
    values = rest_of_network(network, hidden, active, compute_dtype, p.first_layer)
    return FusedCPUOutputs(active, values, count, torch.from_numpy(t_enter), torch.from_numpy(t_exit))


# A chunk's rays cross several parallel regions (the fused pass; on AMX hosts also torch's GEMMs
# and the decoding pass), and each pays for starting its threads and for its tail, where threads
# wait for the last; with a fixed chunk that share grows with the thread count. So a chunk holds at
# least this many rays per numba thread (2^17 on one thread, 2^18 on more; a larger
# `InferenceConfig.chunk_size` wins). A 16-core Intel Xeon (AMX; session 34, hairball(6), untrained,
# 2^18 rays, `bench_scaling.py --switches`, two runs, chunks split statically): the 2^18 rays in
# one chunk over four of 2^16: `intersect` 1.22x / 1.25x (`hq`), 1.07x / 1.32x (`lq`), `occluded`
# 1.07-1.26x; in two of 2^17: 1.10-1.17x; in 16 of 2^14: 0.49-0.60x. 2 threads, Zen 5, with the
# task queue (session 35, same run, medians of 15 alternating rounds): 2^17 rays in one chunk
# 0.957x / 0.960x the time of two of 2^16 (`lq`), 0.967x (`hq`); 2^18 rays in one chunk 0.946x
# the time of four of 2^16, two of 2^17 0.974x (each chunk also pays ~0.3 ms of Python and array
# set-up between its parallel regions). (Before the queue, one 2^17 chunk took 1.18x the time on 2
# threads: the second half of those rays costs more and one thread ran it.) The rule stops at the
# 2^18 rays measured (a chunk's buffers grow with it: on AMX hosts up to ~1 KiB a ray).
MIN_RAYS_PER_THREAD = 1 << 17
MAX_RAYS_BY_THREADS = 1 << 18


def rays_per_chunk(configured: int) -> int:
    """Rays per chunk of the fused CPU pass: ``configured``, or `MIN_RAYS_PER_THREAD` per numba
    thread (at most `MAX_RAYS_BY_THREADS`) where that is more."""
    return max(configured, min(MIN_RAYS_PER_THREAD * numba.get_num_threads(), MAX_RAYS_BY_THREADS))


# `LSNIFModel.intersect` on the CPU decodes in `fused_hits_cpu` (numba) and `occluded` decodes only
# the decision (`fused_occluded_cpu`); False: the raw outputs of `fused_network_outputs_cpu`
# decoded by torch ops in `LSNIFModel._intersect_chunk` (the reference; comparisons and tests).
WRITE_HITS = True

# The output layer inside the decoding pass (`_decode_kernel`, fp32 from the last hidden layer's
# activations as they are); False: torch's addmm (`network.output`) on an fp32 copy, then the
# decoding pass from its raw outputs (for comparisons and tests).
OUTPUT_LAYER_IN_DECODE = True


# With the bf16 pairs path (bf16, width a multiple of 16) and the output layer in the pass, the
# hidden layers after the first run there too (`_later_hidden_rows`: 4 rays per weight pass, no
# [M, W] gather or GEMM output; not torch's summation order or its double rounding of negative
# activations, so answers differ from it within bf16 rounding); False: torch's bf16 GEMMs
# (`hidden_layers`); None (the default): in the pass unless the CPU has AMX (`later_layers_in_pass`).
# Hairball(6) `hq` render rays, the layer alone (ad hoc, AMD Zen 4): 177 vs 265 ns per network ray
# on one thread, 99 vs 156 on two. Where the CPU has AMX, oneDNN runs torch's bf16 GEMMs on the
# tiles and they win: a 2-core Intel Xeon (session 23, docs/lsnif.md), hairball(6), 2^17 rays,
# same-run ratios of the pass over torch's GEMMs 0.76-0.99 (`hq`), 0.73-0.99 (`lq`) in 7 runs.
HIDDEN_LAYERS_IN_DECODE: bool | None = None


# The first layer in the fused pass (`dot_rows_bf16`, AVX-512 bf16 dot products) or (False) as a
# bf16 GEMM of torch's on the network inputs, which the pass then writes ([N, H * (L * F + 1)] bf16:
# the size of the first hidden layer's activations for `hq`). None: a GEMM where the CPU has AMX
# (oneDNN's AMX tiles) and the inputs are at most GEMM_INPUTS_PER_WIDTH times the layer's width
# (the inputs' buffer stays within that many times the activations'), else in the pass. On the
# Intel Xeon (AMX) of session 24, hairball(6) `hq`, 2^17 rays, 2 threads: the first layer took ~21
# ms of the pass's ~67 (ad hoc), its GEMM on the same rows ~4-5 ms; end to end +5% `intersect`,
# +15-19% `occluded` (interleaved medians, docs/lsnif.md), where the layer's dot products had
# overlapped the table reads' cache misses.
FIRST_LAYER_IN_PASS: bool | None = None
GEMM_INPUTS_PER_WIDTH = 4


def first_layer_in_pass(inputs: int, width: int) -> bool:
    """Whether the bf16 first layer (``inputs`` -> ``width``) runs in the fused pass (see FIRST_LAYER_IN_PASS)."""
    if FIRST_LAYER_IN_PASS is not None:
        return FIRST_LAYER_IN_PASS
    return not HOST_HAS_AMX or inputs > GEMM_INPUTS_PER_WIDTH * width


def later_layers_in_pass() -> bool:
    """Whether the hidden layers after the first run in the decoding pass (see HIDDEN_LAYERS_IN_DECODE)."""
    if HIDDEN_LAYERS_IN_DECODE is not None:
        return HIDDEN_LAYERS_IN_DECODE
    return not HOST_HAS_AMX


@numba.njit(cache=True, inline="always")
def _later_hidden_rows(first_pairs, active, block, n_rows, hidden_pairs, hidden_bias, slope, xp, xp_bf16, quad, dots, rows):
    """`BLOCK_ROWS` rows (block ``block`` of ``active``; a short block repeats its last row) through
    the hidden layers after the first, in bf16 (`dot_rows_bf16`, 4 rows per weight pass; fp32 sums,
    bias, leaky ReLU, then one rounding to bf16): from the first layer's bf16 pairs
    ``first_pairs[active[i]]`` to the last hidden layer's activations, widened into ``rows`` (flat
    ``[8 * W]`` fp32). ``hidden_pairs``/``hidden_bias``: `hidden_layer_pairs`' flat arrays; ``xp``
    ``[8, W / 2]`` and ``xp_bf16``, the same memory as flat ``[8 * W]`` uint16 (pair q of a row is
    its columns 2q (low half: little-endian), 2q + 1)."""
    half = first_pairs.shape[1]
    for b in range(BLOCK_ROWS):
        src = active[block + min(b, n_rows - 1)]
        for q in range(half):
            xp[b, q] = first_pairs[src, q]
    hidden_layers_bf16(hidden_pairs, hidden_bias, slope, xp, xp_bf16, quad, dots)
    widen_rows_bf16(xp_bf16, rows)


@numba.njit(cache=True, inline="always")
def _decode_scratch(width, n_padded, needed):
    """Per-thread scratch of `_decode_rows` (empty where not ``needed``): the last hidden layer's
    `BLOCK_ROWS` rows (flat ``[8 * W]`` fp32), their outputs (flat ``[8 * P]`` fp32), and bf16 pairs
    ``[8, W / 2]`` with the same memory as flat ``[8 * W]`` uint16."""
    rows = BLOCK_ROWS if needed else 0
    xp = np.empty((rows, width // 2), np.uint32)
    return np.empty(rows * width, np.float32), np.empty(rows * n_padded, np.float32), xp, xp.reshape(-1).view(np.uint16)


@numba.njit(cache=True, inline="always")
def _decode_row(out, o, r, t_enter, t_exit, t_offset, t_min, t_max, occlusion_logit, n_materials, occlusion_only,
                hit, t_hit, normal, geometric_normal, albedo, material):  # fmt: skip
    """Ray r's record from its raw outputs ``out[o:]``: the same operations as
    the torch decoding, in fp32; the norm of the normal is torch's (fused multiply-adds from x^2);
    the sigmoid differs from torch's by <= 3 ulp. ``occlusion_only`` writes ``hit`` alone.
    (The records are separate arguments: numba 0.68 lost the writes to arrays unpacked from a tuple
    argument inside an inlined function in a prange loop.)"""
    te = t_enter[r]
    t = (t_offset[r] + te) + sigmoid(out[o + 1]) * (t_exit[r] - te)
    h = out[o] > occlusion_logit and t <= t_max[r] and t >= t_min[r]  # [t_min, t_max], both ends included
    hit[r] = h
    if occlusion_only:
        return
    t_hit[r] = t if h else np.float32(np.inf)
    nx, ny, nz = out[o + 2], out[o + 3], out[o + 4]
    norm = max(np.sqrt(fma_f32(nz, nz, fma_f32(ny, ny, nx * nx))), np.float32(1e-12))
    zero = np.float32(0.0)
    nx, ny, nz = (nx / norm, ny / norm, nz / norm) if h else (zero, zero, zero)
    normal[r, 0], normal[r, 1], normal[r, 2] = nx, ny, nz
    geometric_normal[r, 0], geometric_normal[r, 1], geometric_normal[r, 2] = nx, ny, nz
    if h:
        for c in range(3):
            albedo[r, c] = sigmoid(out[o + 5 + c])
    best = 0
    for j in range(1, n_materials):  # argmax: the first of equal logits
        if out[o + 8 + j] > out[o + 8 + best]:
            best = j
    material[r] = best if h else -1


# (Inlined: at most 30 arguments, as any function numba inlines: CPython passes more as one tuple,
# which numba's inliner rejects.)
@numba.njit(cache=True, inline="always")
def _decode_rows(first_pairs, active, m, shift, hidden_pairs, hidden_bias, slope, wo_flat, bo, rows, outs, xp, xp_bf16, quad, dots,
                 t_enter, t_exit, t_offset, t_min, t_max, occlusion_logit, n_materials, occlusion_only,
                 hit, t_hit, normal, geometric_normal, albedo, material):  # fmt: skip
    """Rays ``r = shift + active[i]``, i < m, from their first hidden layer's bf16 pairs
    ``first_pairs[active[i]]`` through the later hidden layers (`_later_hidden_rows`) and the output
    layer (``wo_flat``, `output_rows`' flat weights, and ``bo``; only its first 16 columns with
    ``occlusion_only``) into records row r (`_decode_row`), `BLOCK_ROWS` rays at a time (scratch:
    `_decode_scratch`, and ``quad``/``dots`` as `dot_rows_bf16`'s)."""
    n_padded = bo.shape[0]
    columns = 16 if occlusion_only else n_padded
    for block in range(0, m, BLOCK_ROWS):
        n_rows = min(BLOCK_ROWS, m - block)
        _later_hidden_rows(first_pairs, active, block, n_rows, hidden_pairs, hidden_bias, slope, xp, xp_bf16, quad, dots, rows)
        output_rows(rows, wo_flat, bo, n_padded, columns, outs)
        for b in range(n_rows):
            r = shift + active[block + b]
            _decode_row(outs, b * n_padded, r, t_enter, t_exit, t_offset, t_min, t_max, occlusion_logit, n_materials, occlusion_only,
                        hit, t_hit, normal, geometric_normal, albedo, material)  # fmt: skip


_DECODE_TASK_ROWS = 8 * BLOCK_ROWS


@numba.njit(parallel=True, cache=True, nogil=True)
def _decode_kernel(
    x_f32, x_bf16, first_pairs, hidden_pairs, hidden_bias, slope, wo, bo, output_layer, active, t_enter, t_exit,
    t_offset, t_min, t_max, occlusion_logit, n_materials, occlusion_only, n_chunks, n_workers,
    hit, t_hit, normal, geometric_normal, albedo, material,
):  # fmt: skip
    """`LSNIFModel._intersect_chunk`'s decoding of the rays that reached the network (`_decode_row`),
    written into the hit records at rows ``active[i]`` (``t_*`` are the chunk's, indexed the same):
    row i of ``x_f32``/``x_bf16`` (the other is empty) is the last hidden layer
    (``output_layer``: the output layer ``wo``/``bo`` is applied here, fp32, `BLOCK_ROWS` rows at a
    time) or the raw outputs; or, where ``first_pairs`` (the first hidden layer's bf16 activations
    as pairs, ``[N, W / 2]`` uint32, rows ``active[i]``) is not empty, the later hidden layers run
    here too (`_decode_rows`). ``occlusion_only`` writes ``hit`` alone (the other records may be
    empty arrays) and computes only the first 16 outputs. The rows are cut into ``n_chunks`` chunks,
    which ``n_workers`` workers take from a task queue (`task_queue`)."""
    m = active.shape[0]
    width, n_padded = wo.shape
    to_f32 = x_bf16.shape[0] > 0
    wo_flat = wo.reshape(-1)
    columns = 16 if occlusion_only else n_padded
    next_chunk = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):  # chunks handed out one at a time (`task_queue`)
        rows, outs, xp, xp_bf16 = _decode_scratch(width, n_padded, True)
        quad = np.empty(4, np.int64)
        dots = np.empty(4 * width, np.float32)
        while True:
            chunk = take_task(next_chunk)
            if chunk >= n_chunks:
                break
            first, last = chunk * m // n_chunks, (chunk + 1) * m // n_chunks
            if first_pairs.shape[0] > 0:
                _decode_rows(first_pairs, active[first:last], last - first, 0, hidden_pairs, hidden_bias, slope, wo_flat, bo, rows,
                             outs, xp, xp_bf16, quad, dots, t_enter, t_exit, t_offset, t_min, t_max, occlusion_logit, n_materials,
                             occlusion_only, hit, t_hit, normal, geometric_normal, albedo, material)  # fmt: skip
                continue
            for block in range(first, last, BLOCK_ROWS):
                n_rows = min(BLOCK_ROWS, last - block)
                if output_layer:
                    for b in range(BLOCK_ROWS):
                        i = block + min(b, n_rows - 1)  # a short block repeats its last row
                        if to_f32:
                            for k in range(width):
                                rows[b * width + k] = bf16_value(x_bf16[i, k])
                        else:
                            for k in range(width):
                                rows[b * width + k] = x_f32[i, k]
                    output_rows(rows, wo_flat, bo, n_padded, columns, outs)
                else:
                    for b in range(n_rows):
                        for j in range(x_f32.shape[1]):
                            outs[b * n_padded + j] = x_f32[block + b, j]
                for b in range(n_rows):
                    r = active[block + b]
                    _decode_row(outs, b * n_padded, r, t_enter, t_exit, t_offset, t_min, t_max, occlusion_logit, n_materials,
                                occlusion_only, hit, t_hit, normal, geometric_normal, albedo, material)  # fmt: skip


# The rest of the network and the decoding run in the fused pass, a group of rays after their
# first layer (`_decode_rows`), where the later layers would run in the decoding pass
# (`later_layers_in_pass`): no [N, W] first hidden layer written and read back, one parallel
# kernel per chunk instead of two; False: the decoding pass (`_decode_kernel`), same bits.
DECODE_IN_PASS = True


def _numba_after_first_layer(p: _Pass) -> bool:
    """Whether every layer after the first and the output layer run in numba (`_decode_rows`)."""
    return p.pairs and later_layers_in_pass() and OUTPUT_LAYER_IN_DECODE


def decodes_in_pass(p: _Pass) -> bool:
    """Whether the fused pass decodes the answers itself (see DECODE_IN_PASS)."""
    return DECODE_IN_PASS and _numba_after_first_layer(p)


def _decode(p: _Pass, hidden: Tensor, counts: np.ndarray, t_enter: np.ndarray, t_exit: np.ndarray,
            t_offset: np.ndarray, t_min: np.ndarray, t_max: np.ndarray, occlusion_logit: float, num_materials: int,
            records: tuple[np.ndarray, ...], occlusion_only: bool) -> None:  # fmt: skip
    """The layers after the first on the rays with points, then `_decode_kernel` into ``records``
    (ray i of these arrays, ``t_min`` and ``t_max`` the chunk's, is row i of the records)."""
    active = np.flatnonzero(counts > 0)
    if len(active) == 0:
        return
    x_f32, x_bf16 = np.zeros((0, 1), np.float32), np.zeros((0, 1), np.uint16)
    first_pairs = np.zeros((0, max(p.b1.shape[0] // 2, 1)), np.uint32)
    if _numba_after_first_layer(p):  # all layers after the first in the decoding pass
        first_pairs = hidden.view(torch.int16).numpy().view(np.uint16).view(np.uint32)
    else:
        x = hidden_layers(p.network, hidden, torch.from_numpy(active), p.compute_dtype, p.first_layer)
        if not OUTPUT_LAYER_IN_DECODE:
            x = p.network.output(x.float())  # raw outputs: the decoding pass only decodes
        if x.dtype == torch.bfloat16:
            x_bf16 = x.view(torch.int16).numpy().view(np.uint16)
        else:
            x_f32 = x.numpy()
    # Tasks of at least _DECODE_TASK_ROWS rows: a worker's scratch serves many blocks
    n_chunks = task_count(len(active), _DECODE_TASK_ROWS)
    _decode_kernel(x_f32, x_bf16, first_pairs, p.hidden_pairs, p.hidden_bias, np.float32(p.network.slope), p.wo, p.bo,
                   OUTPUT_LAYER_IN_DECODE, active, t_enter, t_exit, t_offset, t_min, t_max, np.float32(occlusion_logit),
                   int(num_materials), occlusion_only, n_chunks, task_workers(n_chunks), *records)  # fmt: skip


def _hits_pass(origins: Tensor, directions: Tensor, occupancy: Tensor, encoder: SparseHashGrid, network: MLP, *,
               box_lo: Tensor, box_extent: Tensor, t_min: Tensor, t_max: Tensor, occlusion_logit: float,
               num_materials: int, records: tuple[np.ndarray, ...], miss_records: tuple[np.ndarray, ...], occlusion_only: bool,
               max_points: int, origin_point: bool, share_boundary_points: bool, point_distances: bool,
               compute_dtype: torch.dtype) -> None:  # fmt: skip
    """Every row of ``records`` and ``miss_records`` (`_Decoding`'s) written: the fused pass writes
    misses, then it or `_decode` decodes the rays that reach the network."""
    rays = _rays_numpy(origins, directions, max_points, t_min, t_max, box_lo, box_extent)
    p = _prepare_pass(occupancy, encoder, network, max_points=max_points, origin_point=origin_point,
                      share_boundary_points=share_boundary_points, point_distances=point_distances,
                      compute_dtype=compute_dtype)  # fmt: skip
    decoding = _Decoding(occlusion_logit, num_materials, occlusion_only, records, miss_records, decodes_in_pass(p))
    if decoding.in_pass:
        _first_hidden_layer(p, rays, decoding)
        return
    hidden, counts, t_enter, t_exit, t_offset = _first_hidden_layer(p, rays, decoding)
    _decode(p, hidden, counts, t_enter, t_exit, t_offset, rays.t_min, rays.t_max, occlusion_logit, num_materials,
            records, occlusion_only)  # fmt: skip


@torch.no_grad()
def fused_hits_cpu(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor,
    encoder: SparseHashGrid,
    network: MLP,
    *,
    box_lo: Tensor,
    box_extent: Tensor,
    t_min: Tensor,
    t_max: Tensor,
    hits,
    occlusion_logit: float,
    num_materials: int,
    max_points: int,
    origin_point: bool = True,
    share_boundary_points: bool = True,
    point_distances: bool = True,
    compute_dtype: torch.dtype = torch.float32,
) -> None:
    """`LSNIFModel._intersect_chunk`'s answers written into every row of ``hits`` (the chunk's
    records, CPU; their contents on entry do not matter: `Hits.uninitialized` serves) for the
    chunk's rays (``origins``, ``directions``, ``t_min``, ``t_max``, object space), which the pass
    maps into the model's box (``box_lo``, ``box_extent``) itself: the fused pass, the later layers,
    the output layer and the decoding (`_decode_kernel`). The CPU counterpart of `lsnif_fused.fused_hits`."""
    records = (hits.hit.numpy(), hits.t.numpy(), hits.normal.numpy(), hits.geometric_normal.numpy(), hits.albedo.numpy(),
               hits.material_id.numpy())  # fmt: skip
    miss_records = (hits.uv.numpy(), hits.primitive_id.numpy(), hits.instance_id.numpy())
    _hits_pass(origins, directions, occupancy, encoder, network, box_lo=box_lo, box_extent=box_extent, t_min=t_min, t_max=t_max,
               occlusion_logit=occlusion_logit, num_materials=num_materials, records=records, miss_records=miss_records,
               occlusion_only=False, max_points=max_points, origin_point=origin_point, share_boundary_points=share_boundary_points,
               point_distances=point_distances, compute_dtype=compute_dtype)  # fmt: skip


@torch.no_grad()
def fused_occluded_cpu(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor,
    encoder: SparseHashGrid,
    network: MLP,
    *,
    box_lo: Tensor,
    box_extent: Tensor,
    t_min: Tensor,
    t_max: Tensor,
    hit: Tensor,
    occlusion_logit: float,
    max_points: int,
    origin_point: bool = True,
    share_boundary_points: bool = True,
    point_distances: bool = True,
    compute_dtype: torch.dtype = torch.float32,
) -> None:
    """`fused_hits_cpu`'s ``hit`` decisions alone, written into every row of ``hit`` ([chunk] bool;
    its contents on entry do not matter): the output layer computes only its first 16 columns
    (occlusion and distance are among them) and nothing else is decoded."""
    _hits_pass(origins, directions, occupancy, encoder, network, box_lo=box_lo, box_extent=box_extent, t_min=t_min, t_max=t_max,
               occlusion_logit=occlusion_logit, num_materials=0, records=(hit.numpy(), *_NO_RECORDS[1:]),
               miss_records=_NO_MISS_RECORDS, occlusion_only=True, max_points=max_points, origin_point=origin_point,
               share_boundary_points=share_boundary_points, point_distances=point_distances, compute_dtype=compute_dtype)  # fmt: skip

"""LSNIF inference on CUDA with one fused Triton kernel per ray chunk.

The kernel walks each ray through the voxels (`dda_next_point`, float64 as in `featurize_rays`)
and encodes each boundary point in the sparse hash grid as soon as it is found (`encode_point`):
points never go to global memory. Where it stops is a choice (``stage``):

- ``"input"``: it writes the network input row (bf16, the unfused path's layout) and
  the MLP runs as torch GEMMs (`MLP.forward`). No accumulator in the kernel: fewest registers.
- ``"first_layer"``: the network input is the concatenation of per-point blocks, so
  ``x @ W1^T`` is the sum over point slots of ``x_h @ W1[:, block h]^T``: one small tensor-core
  product per slot, accumulated in registers; the kernel writes the first hidden layer.
- ``"whole"``: also the other hidden layers (tensor cores, compute dtype) and the fp32 output
  layer in the kernel: 24 bytes in per ray, its outputs out.

- ``"input_per_ray"``: what ``input`` writes, from `_fused_input_per_ray_kernel`: one ray per
  lane, each point encoded level by level and feature by feature, no padded [rays, levels,
  features] tile. In ``_fused_lsnif_kernel`` the walk's [BLOCK] vectors share the tile's layout,
  so with 32 rays on 128 threads every ray is walked 4 times over; here a thread walks one ray.
  Same bytes as ``input`` (tested under the interpreter; the bench compares them on the GPU).
  The default (`DEFAULT_LAUNCH`), with `fused_hits` decoding.

Measured on an H100 (benchmarks/results/lsnif_kernels_h100.json, hq, 2^22 hairball(6) rays):
``input`` 23.7 ms, ``whole`` 25.7 ms, ``first_layer`` 54.8 ms (its best launches); unfused
26.2 ms. A point slot past every ray's last point in a block is skipped (its features are 0).
``input_per_ray`` with `fused_hits` (the output layer and the hit decoding in a kernel writing
`Hits`): 15.5 ms (hq, `DEFAULT_LAUNCH`'s comment; ``bench_lsnif_kernels_cuda.py --quick``).
By ptxas for sm_90 (hq): ``input`` 32 x 4 125 registers; ``input_per_ray`` 32 x 1 88, 128 x 4 ~105.

Same answers as the unfused path (`featurize_rays` -> `SparseHashGrid` -> MLP) up to the
compute precision: in-kernel layers accumulate in fp32 from bf16 inputs (unfused: bf16 GEMMs).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
import triton
import triton.language as tl
from torch import Tensor, nn

from ..neural.sparse_hash_grid import SparseHashGrid
from ..neural.sparse_hash_grid_triton import encode_point, encode_point_level_feature
from .lsnif_features_triton import dda_next_point, dda_point_coords, dda_setup, occupancy_bytes, plane_table

__all__ = ["FusedLayout", "FusedOutputs", "FusedWeights", "fused_hits", "fused_layout", "fused_network_outputs",
           "pack_first_layer", "pack_network", "run_fused_kernel"]


# What the kernel writes: the network input, the first hidden layer, or the network's outputs.
# ``input_per_ray`` writes what ``input`` writes, from `_fused_input_per_ray_kernel` (one ray per lane).
STAGES = {"input": 0, "first_layer": 1, "whole": 2, "input_per_ray": 0}


@triton.jit
def _fused_lsnif_kernel(
    o_ptr, d_ptr, occ_ptr, planes_ptr, table_ptr, res_ptr, w1_ptr, b1_ptr,
    wh_ptr, bh_ptr, wo_ptr, bo_ptr,
    out_ptr, t_enter_ptr, t_exit_ptr, count_ptr,
    n_rays, V, table_size, slope,
    MAX_POINTS: tl.constexpr, ORIGIN_POINTS: tl.constexpr, SHARE: tl.constexpr,
    POINT_DISTANCES: tl.constexpr, L: tl.constexpr, F: tl.constexpr, LP: tl.constexpr, FP: tl.constexpr,
    HIDDEN: tl.constexpr, IEEE: tl.constexpr, BLOCK: tl.constexpr,
    STAGE: tl.constexpr, MORE_HIDDEN: tl.constexpr, OUTPUTS: tl.constexpr, OP: tl.constexpr,
):  # fmt: skip
    rays = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    lane_ok = rays < n_rays
    r64 = rays.to(tl.int64)
    ox32 = tl.load(o_ptr + r64 * 3 + 0, mask=lane_ok, other=0.0).to(tl.float32)
    oy32 = tl.load(o_ptr + r64 * 3 + 1, mask=lane_ok, other=0.0).to(tl.float32)
    oz32 = tl.load(o_ptr + r64 * 3 + 2, mask=lane_ok, other=0.0).to(tl.float32)
    dx32 = tl.load(d_ptr + r64 * 3 + 0, mask=lane_ok, other=0.0).to(tl.float32)
    dy32 = tl.load(d_ptr + r64 * 3 + 1, mask=lane_ok, other=0.0).to(tl.float32)
    dz32 = tl.load(d_ptr + r64 * 3 + 2, mask=lane_ok, other=0.0).to(tl.float32)
    state, t_enter, t_exit = dda_setup(
        ox32.to(tl.float64), oy32.to(tl.float64), oz32.to(tl.float64),
        dx32.to(tl.float64), dy32.to(tl.float64), dz32.to(tl.float64), lane_ok, planes_ptr, V,
    )  # fmt: skip
    t_enter32 = t_enter.to(tl.float32)
    t_exit32 = t_exit.to(tl.float32)
    span = tl.maximum(t_exit32 - t_enter32, 1.1754943508222875e-38)  # lsnif_features.MIN_SPAN
    dd = dx32 * dx32 + dy32 * dy32 + dz32 * dz32
    k = tl.arange(0, LP * FP)
    n = tl.arange(0, HIDDEN)
    levels = tl.arange(0, LP)
    feats_i = tl.arange(0, FP)
    INPUTS: tl.constexpr = MAX_POINTS * L * F + (MAX_POINTS if POINT_DISTANCES else 0)
    # network-input columns of a point's features: point-major, then level, then feature
    in_cols = levels[None, :, None] * F + feats_i[None, None, :]
    in_mask = lane_ok[:, None, None] & (levels < L)[None, :, None] & (feats_i < F)[None, None, :]
    acc = tl.zeros([BLOCK, HIDDEN], tl.float32)
    count = tl.zeros([BLOCK], tl.int32)
    h = tl.full([], 0, tl.int32)
    any_alive = tl.max(state[22].to(tl.int32), axis=0) > 0
    while (h < MAX_POINTS) & any_alive:
        state, got, t, code, exiting, vx, vy, vz = dda_next_point(
            state, planes_ptr, occ_ptr, V, ORIGIN_POINTS, SHARE)  # fmt: skip
        px, py, pz = dda_point_coords(state, got, t, code, exiting, vx, vy, vz, planes_ptr)
        feats = encode_point(px, py, pz, code, got, table_ptr, res_ptr, table_size, L, F, LP, FP)
        local = tl.zeros([BLOCK], tl.float32)
        if POINT_DISTANCES:  # as `point_local_distances`, in float32 on the float32 point
            tp = ((px - ox32) * dx32 + (py - oy32) * dy32 + (pz - oz32) * dz32) / dd
            local = tl.where(got, tl.minimum(tl.maximum((tp - t_enter32) / span, 0.0), 1.0), 0.0)
        if STAGE == 0:  # the network input row, exactly as the unfused path lays it out
            row = out_ptr + r64[:, None, None] * INPUTS + h * (L * F)
            tl.store(row + in_cols, feats.to(out_ptr.dtype.element_ty), mask=in_mask)
            if POINT_DISTANCES:
                tl.store(out_ptr + r64 * INPUTS + MAX_POINTS * L * F + h, local.to(out_ptr.dtype.element_ty), mask=lane_ok)
        else:
            x = tl.reshape(feats, [BLOCK, LP * FP])  # column level * FP + feature
            if POINT_DISTANCES:
                x = tl.where(k[None, :] == L * FP, local[:, None], x)
            w = tl.load(w1_ptr + (h * (LP * FP) + k[:, None]) * HIDDEN + n[None, :])
            if IEEE:
                acc = tl.dot(x.to(w.dtype), w, acc, input_precision="ieee")
            else:
                acc = tl.dot(x.to(w.dtype), w, acc)
        count += got.to(tl.int32)
        h += 1
        any_alive = tl.max(state[22].to(tl.int32), axis=0) > 0
    tl.store(t_enter_ptr + rays, t_enter32, mask=lane_ok)
    tl.store(t_exit_ptr + rays, t_exit32, mask=lane_ok)
    tl.store(count_ptr + rays, count, mask=lane_ok)
    if STAGE == 0:
        # Slots no ray of the block reached are padding: zero features, zero distance.
        zeros = tl.zeros([BLOCK, LP, FP], tl.float32).to(out_ptr.dtype.element_ty)
        zero_row = tl.zeros([BLOCK], tl.float32).to(out_ptr.dtype.element_ty)
        for hz in range(MAX_POINTS):
            pad = (rays * 0 + hz) >= h  # a lane vector: Triton 3.9's interpreter takes no scalar bool in a mask
            tl.store(out_ptr + r64[:, None, None] * INPUTS + hz * (L * F) + in_cols, zeros, mask=in_mask & pad[:, None, None])
            if POINT_DISTANCES:
                tl.store(out_ptr + r64 * INPUTS + MAX_POINTS * L * F + hz, zero_row, mask=lane_ok & pad)
    else:
        y = acc + tl.load(b1_ptr + n)[None, :]
        y = tl.where(y >= 0.0, y, y * slope)
        if STAGE == 2:
            # The other hidden layers (activations rounded to the compute dtype between layers,
            # as the unfused path does), then the output layer in fp32.
            for layer in tl.static_range(MORE_HIDDEN):
                w = tl.load(wh_ptr + (layer * HIDDEN + n[:, None]) * HIDDEN + n[None, :])
                if IEEE:
                    y = tl.dot(y.to(w.dtype), w, input_precision="ieee")
                else:
                    y = tl.dot(y.to(w.dtype), w)
                y = y + tl.load(bh_ptr + layer * HIDDEN + n)[None, :]
                y = tl.where(y >= 0.0, y, y * slope)
            y = y.to(w1_ptr.dtype.element_ty).to(tl.float32)
            o = tl.arange(0, OP)
            out = tl.dot(y, tl.load(wo_ptr + n[:, None] * OP + o[None, :]), input_precision="ieee")
            out = out + tl.load(bo_ptr + o)[None, :]
            tl.store(out_ptr + r64[:, None] * OUTPUTS + o[None, :], out, mask=lane_ok[:, None] & (o < OUTPUTS)[None, :])
        else:
            tl.store(out_ptr + r64[:, None] * HIDDEN + n[None, :], y.to(out_ptr.dtype.element_ty), mask=lane_ok[:, None])


@triton.jit
def _pack_pair(first, second, dtype: tl.constexpr):
    """Two float32 vectors rounded to the 16-bit ``dtype``, as one uint32 (``first`` in the low
    half: its place in memory on a little-endian GPU)."""
    lo = first.to(dtype).to(tl.uint16, bitcast=True).to(tl.uint32)
    hi = second.to(dtype).to(tl.uint16, bitcast=True).to(tl.uint32)
    return lo | (hi << 16)


@triton.jit
def _fused_input_per_ray_kernel(
    o_ptr, d_ptr, occ_ptr, planes_ptr, table_ptr, res_ptr,
    out_ptr, t_enter_ptr, t_exit_ptr, count_ptr,
    n_rays, V, table_size,
    MAX_POINTS: tl.constexpr, ORIGIN_POINTS: tl.constexpr, SHARE: tl.constexpr,
    POINT_DISTANCES: tl.constexpr, L: tl.constexpr, F: tl.constexpr, BLOCK: tl.constexpr, PACK: tl.constexpr,
):  # fmt: skip
    """Stage ``input`` with one ray per lane: every tensor is a [BLOCK] vector (no [B, LP, FP]
    tile), so with BLOCK = 32 * num_warps each thread walks one ray, once. Each point is encoded
    level by level and feature by feature (`encode_point_level_feature`) and stored column by
    column. Same arithmetic, same output as `_fused_lsnif_kernel` with ``STAGE == 0``. ``PACK``
    (16-bit output, even L * F and row width): two features per 32-bit store, as a lane's stores
    each touch another row (half the store instructions)."""
    rays = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    lane_ok = rays < n_rays
    r64 = rays.to(tl.int64)
    ox32 = tl.load(o_ptr + r64 * 3 + 0, mask=lane_ok, other=0.0).to(tl.float32)
    oy32 = tl.load(o_ptr + r64 * 3 + 1, mask=lane_ok, other=0.0).to(tl.float32)
    oz32 = tl.load(o_ptr + r64 * 3 + 2, mask=lane_ok, other=0.0).to(tl.float32)
    dx32 = tl.load(d_ptr + r64 * 3 + 0, mask=lane_ok, other=0.0).to(tl.float32)
    dy32 = tl.load(d_ptr + r64 * 3 + 1, mask=lane_ok, other=0.0).to(tl.float32)
    dz32 = tl.load(d_ptr + r64 * 3 + 2, mask=lane_ok, other=0.0).to(tl.float32)
    state, t_enter, t_exit = dda_setup(
        ox32.to(tl.float64), oy32.to(tl.float64), oz32.to(tl.float64),
        dx32.to(tl.float64), dy32.to(tl.float64), dz32.to(tl.float64), lane_ok, planes_ptr, V,
    )  # fmt: skip
    t_enter32 = t_enter.to(tl.float32)
    t_exit32 = t_exit.to(tl.float32)
    span = tl.maximum(t_exit32 - t_enter32, 1.1754943508222875e-38)  # lsnif_features.MIN_SPAN
    dd = dx32 * dx32 + dy32 * dy32 + dz32 * dz32
    INPUTS: tl.constexpr = MAX_POINTS * L * F + (MAX_POINTS if POINT_DISTANCES else 0)
    row = out_ptr + r64 * INPUTS
    words = out_ptr.to(tl.pointer_type(tl.uint32)) + r64 * (INPUTS // 2)  # with PACK: INPUTS is even
    count = tl.zeros([BLOCK], tl.int32)
    h = tl.full([], 0, tl.int32)
    any_alive = tl.max(state[22].to(tl.int32), axis=0) > 0
    while (h < MAX_POINTS) & any_alive:
        state, got, t, code, exiting, vx, vy, vz = dda_next_point(
            state, planes_ptr, occ_ptr, V, ORIGIN_POINTS, SHARE)  # fmt: skip
        px, py, pz = dda_point_coords(state, got, t, code, exiting, vx, vy, vz, planes_ptr)
        pending = tl.zeros([BLOCK], tl.float32)
        for c in tl.static_range(L * F):
            resf = tl.load(res_ptr + c // F).to(tl.float32)
            feat = encode_point_level_feature(px, py, pz, code, got, table_ptr, resf, c // F, table_size, c % F, F)
            if not PACK:
                tl.store(row + h * (L * F) + c, feat.to(out_ptr.dtype.element_ty), mask=lane_ok)
            elif c % 2 == 0:
                pending = feat
            else:
                tl.store(words + h * (L * F // 2) + c // 2, _pack_pair(pending, feat, out_ptr.dtype.element_ty), mask=lane_ok)
        if POINT_DISTANCES:  # as `point_local_distances`, in float32 on the float32 point
            tp = ((px - ox32) * dx32 + (py - oy32) * dy32 + (pz - oz32) * dz32) / dd
            local = tl.where(got, tl.minimum(tl.maximum((tp - t_enter32) / span, 0.0), 1.0), 0.0)
            tl.store(row + MAX_POINTS * L * F + h, local.to(out_ptr.dtype.element_ty), mask=lane_ok)
        count += got.to(tl.int32)
        h += 1
        any_alive = tl.max(state[22].to(tl.int32), axis=0) > 0
    tl.store(t_enter_ptr + rays, t_enter32, mask=lane_ok)
    tl.store(t_exit_ptr + rays, t_exit32, mask=lane_ok)
    tl.store(count_ptr + rays, count, mask=lane_ok)
    # Slots no ray of the block reached are padding: zero features, zero distance.
    zero = tl.zeros([BLOCK], tl.float32).to(out_ptr.dtype.element_ty)
    for hz in range(MAX_POINTS):
        pad = lane_ok & ((rays * 0 + hz) >= h)  # a lane vector: Triton 3.9's interpreter takes no scalar bool in a mask
        if PACK:
            for c in tl.static_range(L * F // 2):
                tl.store(words + hz * (L * F // 2) + c, tl.zeros([BLOCK], tl.uint32), mask=pad)
        else:
            for c in tl.static_range(L * F):
                tl.store(row + hz * (L * F) + c, zero, mask=pad)
        if POINT_DISTANCES:
            tl.store(row + MAX_POINTS * L * F + hz, zero, mask=pad)


# Stage, rays per program and warps of the fused kernel. Measured on an H100 (hairball(6), 2^22
# rays, `bench_lsnif_kernels_cuda.py --quick`, benchmarks/results/lsnif_kernels_quick_h100.json):
# "input_per_ray" 64 x 2 with `fused_hits` answers hq `intersect` in 15.5 ms (271 M rays/s) against
# 26.8 ms for the earlier default ("input" 32 x 4, torch decoding); lq 9.9 ms (422 M rays/s; its best
# per-ray launch is 32 x 1). Per-ray rows were bit-identical to the tiled kernel's on the GPU, and
# fused_hits agreed with torch decoding on every hit (t within 2e-7 relative).
# ``write_hits``: `LSNIFModel.intersect` decodes with `fused_hits` (needs an input stage) instead of torch.
DEFAULT_LAUNCH = {"stage": "input_per_ray", "block": 64, "num_warps": 2, "write_hits": True}


@dataclass(frozen=True)
class FusedLayout:
    """Padded tile sizes of the fused kernel: per point slot a ``[LP * FP]`` input block (level l,
    feature f at column ``l * FP + f``; the point distance at ``L * FP``), hidden width ``HP``,
    output width ``OP``."""

    levels: int
    features: int
    level_slots: int  # LP
    feature_slots: int  # FP
    hidden: int
    hidden_padded: int  # HP
    outputs: int
    outputs_padded: int  # OP

    @property
    def block_width(self) -> int:
        return self.level_slots * self.feature_slots


def fused_layout(levels: int, features: int, hidden: int, outputs: int, point_distances: bool) -> FusedLayout:
    lp = triton.next_power_of_2(levels + (1 if point_distances else 0))
    fp = max(triton.next_power_of_2(features), triton.cdiv(16, lp))  # tensor-core products need K >= 16
    pow2 = lambda n: max(16, triton.next_power_of_2(n))  # noqa: E731
    return FusedLayout(levels, features, lp, fp, hidden, pow2(hidden), outputs, pow2(outputs))


@dataclass
class FusedWeights:
    """The MLP regrouped for the kernel (zero padding everywhere): first layer per point slot
    ``w1 [H, LP * FP, HP]``, other hidden layers ``wh [layers - 1, HP, HP]`` (input-major), both in
    the compute dtype; biases fp32; output layer ``wo [HP, OP]`` and ``bo [OP]`` in fp32."""

    layout: FusedLayout
    w1: Tensor
    b1: Tensor
    wh: Tensor
    bh: Tensor
    wo: Tensor
    bo: Tensor
    rest: list[tuple[Tensor, Tensor]]  # the other hidden layers as (weight, bias) for torch GEMMs
    hidden: list[tuple[Tensor, Tensor]]  # every hidden layer as (weight, bias) in the compute dtype (`fused_hits`)


def pack_first_layer(
    weight: Tensor, bias: Tensor, max_points: int, layout: FusedLayout, point_distances: bool, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """First-layer weights per point slot ``[H, LP * FP, HP]`` in ``dtype`` and the bias ``[HP]``
    in fp32. ``weight`` is ``[hidden, H * L * F (+ H)]``: the network input is the point-major
    encoded features, then the H point distances."""
    lay, h = layout, max_points
    lf = lay.levels * lay.features
    packed = torch.zeros(h, lay.level_slots, lay.feature_slots, lay.hidden_padded, dtype=torch.float32, device=weight.device)
    w = weight.detach().float().t()  # [inputs, hidden]
    packed[:, : lay.levels, : lay.features, : lay.hidden] = w[: h * lf].reshape(h, lay.levels, lay.features, lay.hidden)
    if point_distances:
        packed[:, lay.levels, 0, : lay.hidden] = w[h * lf : h * lf + h]
    return packed.reshape(h, lay.block_width, lay.hidden_padded).to(dtype).contiguous(), _padded(bias, lay.hidden_padded)


def _padded(t: Tensor, *shape: int) -> Tensor:
    out = torch.zeros(shape, dtype=torch.float32, device=t.device)
    out[tuple(slice(0, s) for s in t.shape)] = t.detach().float()
    return out


def pack_network(network: nn.Module, encoder: SparseHashGrid, max_points: int, point_distances: bool, dtype: torch.dtype) -> FusedWeights:
    """`FusedWeights` of an `MLP`-shaped ``network`` (``hidden`` Linear layers, ``output``)."""
    first, more = network.hidden[0], list(network.hidden[1:])
    lay = fused_layout(len(encoder.resolutions), encoder.features_per_level, first.out_features,
                       network.output.out_features, point_distances)  # fmt: skip
    hp = lay.hidden_padded
    w1, b1 = pack_first_layer(first.weight, first.bias, max_points, lay, point_distances, dtype)
    wh = torch.zeros(max(len(more), 1), hp, hp, dtype=torch.float32, device=w1.device)
    bh = torch.zeros(max(len(more), 1), hp, dtype=torch.float32, device=w1.device)
    for i, layer in enumerate(more):
        wh[i] = _padded(layer.weight.t(), hp, hp)
        bh[i] = _padded(layer.bias, hp)
    rest = [(layer.weight.detach().to(dtype), layer.bias.detach().to(dtype)) for layer in more]
    wo = _padded(network.output.weight.t(), hp, lay.outputs_padded)
    bo = _padded(network.output.bias, lay.outputs_padded)
    hidden = [(first.weight.detach().to(dtype), first.bias.detach().to(dtype))] + rest
    return FusedWeights(lay, w1, b1, wh.to(dtype).contiguous(), bh, wo, bo, rest, hidden)


@dataclass
class FusedOutputs:
    """Per ray of the chunk: network outputs (or first hidden layer), box interval, point count."""

    values: Tensor  # [N, outputs] fp32 (whole MLP), or [N, hidden] compute dtype (first layer only)
    t_enter: Tensor  # [N] float32 (inf on box miss)
    t_exit: Tensor  # [N] float32
    count: Tensor  # [N] int32: boundary points seen, up to H (0: certain miss, the row is meaningless)


def run_fused_kernel(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor,
    table: Tensor,
    resolutions: Tensor,
    weights: FusedWeights,
    *,
    max_points: int,
    origin_point: bool = True,
    share_boundary_points: bool = True,
    point_distances: bool = True,
    slope: float = 0.01,
    stage: str = "whole",
    block: int = 64,
    num_warps: int = 4,
) -> FusedOutputs:
    """Featurize + encode (+ the first layer, or the whole MLP: ``stage``) of unit-box rays ``[N, 3]``.

    ``occupancy`` [V, V, V], ``table`` [L, T, F] and ``resolutions`` (int32 [L]) on the rays'
    device. CUDA, or CPU tensors under ``TRITON_INTERPRET=1``.
    """
    device, lay = origins.device, weights.layout
    occ = occupancy_bytes(occupancy, device)
    o = origins.detach().to(torch.float32).contiguous()
    d = directions.detach().to(torch.float32).contiguous()
    n = o.shape[0]
    inputs = max_points * lay.levels * lay.features + (max_points if point_distances else 0)
    width, dtype = {"input": (inputs, weights.w1.dtype), "input_per_ray": (inputs, weights.w1.dtype),
                    "first_layer": (lay.hidden_padded, weights.w1.dtype), "whole": (lay.outputs, torch.float32)}[stage]  # fmt: skip
    values = torch.empty((n, width), dtype=dtype, device=device)
    if stage == "input":  # no matrix product: no K >= 16 padding, no distance slot (half the registers)
        lp, fp = triton.next_power_of_2(lay.levels), triton.next_power_of_2(lay.features)
    else:
        lp, fp = lay.level_slots, lay.feature_slots
    t_enter = torch.empty(n, dtype=torch.float32, device=device)
    t_exit = torch.empty(n, dtype=torch.float32, device=device)
    count = torch.empty(n, dtype=torch.int32, device=device)
    if n and stage == "input_per_ray":
        _fused_input_per_ray_kernel[(triton.cdiv(n, block),)](
            o, d, occ, plane_table(occ.shape[0], device), table.detach().contiguous(), resolutions,
            values, t_enter, t_exit, count, n, occ.shape[0], table.shape[1],
            MAX_POINTS=int(max_points), ORIGIN_POINTS=bool(origin_point), SHARE=bool(share_boundary_points),
            POINT_DISTANCES=bool(point_distances), L=lay.levels, F=lay.features, BLOCK=block,
            PACK=values.element_size() == 2 and (lay.levels * lay.features) % 2 == 0 and inputs % 2 == 0,
            num_warps=num_warps,
        )  # fmt: skip
    elif n:
        _fused_lsnif_kernel[(triton.cdiv(n, block),)](
            o, d, occ, plane_table(occ.shape[0], device), table.detach().contiguous(), resolutions,
            weights.w1, weights.b1, weights.wh, weights.bh, weights.wo, weights.bo,
            values, t_enter, t_exit, count,
            n, occ.shape[0], table.shape[1], float(slope),
            MAX_POINTS=int(max_points), ORIGIN_POINTS=bool(origin_point), SHARE=bool(share_boundary_points),
            POINT_DISTANCES=bool(point_distances), L=lay.levels, F=lay.features, LP=lp, FP=fp, HIDDEN=lay.hidden_padded,
            IEEE=weights.w1.dtype == torch.float32, BLOCK=block,
            STAGE=STAGES[stage], MORE_HIDDEN=len(weights.rest), OUTPUTS=lay.outputs, OP=lay.outputs_padded,
            num_warps=num_warps,
        )  # fmt: skip
    if stage == "first_layer":
        values = values[:, : lay.hidden]
    return FusedOutputs(values, t_enter, t_exit, count)


def _weights_for(network: nn.Module, encoder: SparseHashGrid, max_points: int, point_distances: bool, dtype: torch.dtype) -> FusedWeights:
    """`pack_network`, cached on the network and re-made when any parameter changes (keyed on
    storage and version counter, as the network's own bf16 weight cache)."""
    key = (dtype, max_points, point_distances, tuple((p.data_ptr(), p._version) for p in network.parameters()))
    cached = getattr(network, "_fused_weights", None)
    if cached is None or cached[0] != key:
        cached = (key, pack_network(network, encoder, max_points, point_distances, dtype))
        network._fused_weights = cached
    return cached[1]


def fused_network_outputs(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor,
    encoder: SparseHashGrid,
    network: nn.Module,
    *,
    max_points: int,
    origin_point: bool = True,
    share_boundary_points: bool = True,
    point_distances: bool = True,
    compute_dtype: torch.dtype = torch.bfloat16,
    stage: str | None = None,
    block: int | None = None,
    num_warps: int | None = None,
) -> FusedOutputs:
    """The LSNIF network's raw outputs ``[N, outputs]`` (fp32) for unit-box rays, fused.

    ``network`` is `MLP`-shaped (``hidden`` Linear layers, ``output``, ``slope``). ``stage``
    (default `DEFAULT_LAUNCH`): ``"whole"`` runs every layer inside the kernel; ``"first_layer"``
    stops after the first layer, the others run as torch GEMMs; ``"input"`` writes the network
    input (bf16) and the whole network runs as torch GEMMs (``network.forward``). Rays with
    ``count == 0`` are certain misses: their output rows are meaningless.
    """
    weights = _weights_for(network, encoder, max_points, point_distances, compute_dtype)
    stage = stage or DEFAULT_LAUNCH["stage"]
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {', '.join(STAGES)}, got {stage!r}")
    block = block or DEFAULT_LAUNCH["block"]
    num_warps = num_warps or DEFAULT_LAUNCH["num_warps"]
    fused = run_fused_kernel(
        origins, directions, occupancy, encoder.table, encoder._resolutions_on(origins.device), weights,
        max_points=max_points, origin_point=origin_point, share_boundary_points=share_boundary_points,
        point_distances=point_distances, slope=network.slope, stage=stage, block=block, num_warps=num_warps,
    )  # fmt: skip
    if stage in ("input", "input_per_ray"):
        fused.values = network(fused.values, compute_dtype)
    elif stage == "first_layer":
        x = fused.values
        for w, b in weights.rest:
            x = F.leaky_relu(F.linear(x, w, b), network.slope)
        fused.values = network.output(x.float())
    return fused


@triton.jit
def _column(out, cols, j):
    """Column ``j`` of a [B, OP] tile as a [B] vector (the other entries are zeros added to it)."""
    return tl.sum(tl.where(cols[None, :] == j, out, 0.0), axis=1)


@triton.jit
def _output_hits_kernel(
    x_ptr, wo_ptr, bo_ptr, count_ptr, t_enter_ptr, t_exit_ptr, t_offset_ptr, index_ptr, t_min_ptr, t_max_ptr,
    hit_ptr, t_ptr, normal_ptr, geometric_normal_ptr, albedo_ptr, material_ptr,
    n_rows, occlusion_logit,
    WIDTH: tl.constexpr, HP: tl.constexpr, OP: tl.constexpr, MATERIALS: tl.constexpr, BLOCK: tl.constexpr,
):  # fmt: skip
    """The output layer (fp32, from the compute-dtype activations ``x [N, WIDTH]`` as they are)
    and `LSNIFModel._intersect_chunk`'s decoding, written straight into the chunk's `Hits` at rows
    ``index``; rows with ``count == 0`` (certain misses) are left as `Hits.empty` made them."""
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    row_ok = rows < n_rows
    active = row_ok & (tl.load(count_ptr + rows, mask=row_ok, other=0) > 0)
    k = tl.arange(0, HP)
    cols = tl.arange(0, OP)
    x = tl.load(x_ptr + rows.to(tl.int64)[:, None] * WIDTH + k[None, :], mask=active[:, None] & (k < WIDTH)[None, :], other=0.0)
    out = tl.dot(x.to(tl.float32), tl.load(wo_ptr + k[:, None] * OP + cols[None, :]), input_precision="ieee")
    out = out + tl.load(bo_ptr + cols)[None, :]
    t_enter = tl.load(t_enter_ptr + rows, mask=active, other=0.0)
    t_exit = tl.load(t_exit_ptr + rows, mask=active, other=0.0)
    t = tl.load(t_offset_ptr + rows, mask=active, other=0.0) + t_enter + tl.sigmoid(_column(out, cols, 1)) * (t_exit - t_enter)
    ray = tl.load(index_ptr + rows, mask=active, other=0)
    hit = (_column(out, cols, 0) > occlusion_logit) & (t <= tl.load(t_max_ptr + ray, mask=active, other=0.0))
    hit = hit & (t >= tl.load(t_min_ptr + ray, mask=active, other=0.0)) & active
    nx, ny, nz = _column(out, cols, 2), _column(out, cols, 3), _column(out, cols, 4)
    # F.normalize (eps 1e-12), correctly rounded as torch's (Triton's plain sqrt and / are approximate on GPUs)
    norm = tl.maximum(tl.sqrt_rn(nx * nx + ny * ny + nz * nz), 1e-12)
    nx, ny, nz = tl.div_rn(nx, norm), tl.div_rn(ny, norm), tl.div_rn(nz, norm)
    nx, ny, nz = tl.where(hit, nx, 0.0), tl.where(hit, ny, 0.0), tl.where(hit, nz, 0.0)
    material = tl.zeros([BLOCK], tl.int64)
    if MATERIALS > 1:  # argmax, the first of equal logits
        best = _column(out, cols, 8)
        for m in tl.static_range(1, MATERIALS):
            logit = _column(out, cols, 8 + m)
            material = tl.where(logit > best, m, material)
            best = tl.maximum(best, logit)
    tl.store(hit_ptr + ray, hit.to(tl.uint8), mask=active)
    tl.store(t_ptr + ray, tl.where(hit, t, float("inf")), mask=active)
    tl.store(normal_ptr + ray * 3 + 0, nx, mask=active)
    tl.store(normal_ptr + ray * 3 + 1, ny, mask=active)
    tl.store(normal_ptr + ray * 3 + 2, nz, mask=active)
    tl.store(geometric_normal_ptr + ray * 3 + 0, nx, mask=active)
    tl.store(geometric_normal_ptr + ray * 3 + 1, ny, mask=active)
    tl.store(geometric_normal_ptr + ray * 3 + 2, nz, mask=active)
    for c in tl.static_range(3):
        tl.store(albedo_ptr + ray * 3 + c, tl.sigmoid(_column(out, cols, 5 + c)), mask=hit)
    tl.store(material_ptr + ray, tl.where(hit, material, -1), mask=active)


def fused_hits(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor,
    encoder: SparseHashGrid,
    network: nn.Module,
    *,
    index: Tensor,
    t_offset: Tensor,
    t_min: Tensor,
    t_max: Tensor,
    hits,
    occlusion_logit: float,
    num_materials: int,
    max_points: int,
    origin_point: bool = True,
    share_boundary_points: bool = True,
    point_distances: bool = True,
    compute_dtype: torch.dtype = torch.bfloat16,
    stage: str | None = None,
    block: int | None = None,
    num_warps: int | None = None,
) -> None:
    """`LSNIFModel._intersect_chunk`'s answers written into ``hits`` (a `Hits.empty` of the chunk):
    the fused kernel writes the network input (``stage`` ``input`` or ``input_per_ray``), the hidden
    layers run as torch GEMMs in ``compute_dtype``, and `_output_hits_kernel` runs the output layer
    on those activations (no fp32 copy of them) and decodes into ``hits`` at rows ``index`` (the
    chunk rays of the unit-box ``origins``; ``t_min``/``t_max`` are the chunk's). No compaction of
    the active rays: certain misses are skipped inside the kernel."""
    stage = stage or DEFAULT_LAUNCH["stage"]
    block = block or DEFAULT_LAUNCH["block"]
    num_warps = num_warps or DEFAULT_LAUNCH["num_warps"]
    if stage not in ("input", "input_per_ray"):
        raise ValueError(f"fused_hits needs stage input or input_per_ray, got {stage!r}")
    weights = _weights_for(network, encoder, max_points, point_distances, compute_dtype)
    lay = weights.layout
    fused = run_fused_kernel(
        origins, directions, occupancy, encoder.table, encoder._resolutions_on(origins.device), weights,
        max_points=max_points, origin_point=origin_point, share_boundary_points=share_boundary_points,
        point_distances=point_distances, stage=stage, block=block, num_warps=num_warps,
    )  # fmt: skip
    x = fused.values
    for w, b in weights.hidden:
        x = F.leaky_relu(F.linear(x, w, b), network.slope)
    x = x.contiguous()
    n = x.shape[0]
    if n:
        rows = 32
        _output_hits_kernel[(triton.cdiv(n, rows),)](
            x, weights.wo, weights.bo, fused.count, fused.t_enter, fused.t_exit, t_offset.to(torch.float32).contiguous(),
            index.contiguous(), t_min.to(torch.float32).contiguous(), t_max.to(torch.float32).contiguous(),
            hits.hit.view(torch.uint8), hits.t, hits.normal, hits.geometric_normal, hits.albedo, hits.material_id,
            n, float(occlusion_logit),
            WIDTH=lay.hidden, HP=lay.hidden_padded, OP=lay.outputs_padded, MATERIALS=int(num_materials), BLOCK=rows,
            num_warps=4,
        )  # fmt: skip

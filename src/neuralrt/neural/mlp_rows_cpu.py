"""An `MLP`'s layers on a block of rows inside a numba kernel (CPU): bf16 hidden layers, fp32 output layer.

The fused passes of LSNIF (`lsnif_fused_cpu`) and N-BVH (`nbvh_wavefront_cpu`) run their
networks here, `BLOCK_ROWS` rows at a time, without torch: no [M, W] gather, GEMM output or
page-faulting buffer per call. The hidden layers use the AVX-512 bf16 dot products of `bf16_dot`
(4 rows per weight pass, fp32 sums, bias, leaky ReLU, then one rounding to bf16: not torch's
summation order or its double rounding of negative activations, so answers differ from
`MLP.forward` in bf16 within bf16 rounding); the output layer is fp32 from the last hidden
layer's bf16 activations, as `MLP.forward`'s.

Where the CPU has AMX, oneDNN runs torch's bf16 GEMMs on the tiles and they win
(`HOST_HAS_AMX`; the passes keep torch's GEMMs there, docs/lsnif.md).
"""

from __future__ import annotations

import llvmlite.binding as llvm
import numba
import numpy as np
import torch

from .bf16_dot import add16, bf16_pairs, dot_rows_bf16, fma16, leaky_relu16, load16, load_bf16x16, store16, store_bf16x16
from .mlp import MLP

__all__ = ["BLOCK_ROWS", "HOST_HAS_AMX", "host_has_amx", "bias_leaky_bf16", "hidden_layers_bf16", "widen_rows_bf16",
           "output_rows", "sigmoid", "layer_pairs", "hidden_layer_pairs", "output_layer_columns"]

# Rows a block holds: the output layer's weight vectors each serve 8 rows, and its 8 accumulator
# chains hide the fused multiply-add latency (one chain of 128 dependent FMAs per row measured
# ~2x slower than LSNIF's whole decoding otherwise takes); the hidden layers take them 4 at a time.
BLOCK_ROWS = 8


def host_has_amx() -> bool:
    """Whether this CPU has AMX bf16 tiles, on which oneDNN runs torch's bf16 GEMMs."""
    try:
        return bool(llvm.get_host_cpu_features().get("amx-bf16", False))
    except RuntimeError:  # (no feature list on this platform)
        return False


HOST_HAS_AMX = host_has_amx()


@numba.njit(cache=True, inline="always")
def bias_leaky_bf16(dots, offset, bias, bias_start, width, slope, out, out_start):
    """``out[out_start + j] = bf16(leaky_relu(dots[offset + j] + bias[bias_start + j]))`` for ``width``
    (a multiple of 16) columns, 16 per instruction (``out`` flat uint16 bf16 bits; the rounding of
    `bf16_bits`). (Flat arrays and offsets, not row views: a view made in a loop costs reference
    counting there.)"""
    for c in range(0, width, 16):
        store_bf16x16(out, out_start + c, leaky_relu16(add16(load16(dots, offset + c), load16(bias, bias_start + c)), slope))


@numba.njit(cache=True, inline="always")
def hidden_layers_bf16(pairs, bias, slope, xp, xp_bf16, quad, dots):
    """The `BLOCK_ROWS` rows of ``xp`` (``[8, W / 2]`` uint32 bf16 pairs; ``xp_bf16`` the same
    memory as flat ``[8 * W]`` uint16) through the square hidden layers of ``pairs``/``bias``
    (`hidden_layer_pairs`' flat arrays), in place. ``quad`` [4] int64 and ``dots`` [4 * W] fp32: scratch."""
    half = xp.shape[1]
    width = 2 * half
    for layer in range(bias.shape[0] // width):
        for g in range(0, BLOCK_ROWS, 4):
            for i in range(4):
                quad[i] = g + i
            dot_rows_bf16(xp, quad, half, pairs, layer * half * width, width, dots)
            for i in range(4):  # these rows' inputs are read: overwrite them with the layer's outputs
                bias_leaky_bf16(dots, i * width, bias, layer * width, width, slope, xp_bf16, (g + i) * width)


@numba.njit(cache=True, inline="always")
def widen_rows_bf16(xp_bf16, rows):
    """The block's bf16 activations (flat ``[8 * W]`` uint16) widened into ``rows`` (flat fp32)."""
    for c in range(0, rows.shape[0], 16):
        store16(rows, c, load_bf16x16(xp_bf16, c))


@numba.njit(cache=True)
def output_rows(rows, wo_flat, bo, n_padded, columns, out):
    """``out[r * n_padded + :columns] = bo + rows[r * W:] @ wo`` for the `BLOCK_ROWS` rows of ``rows``
    (flat ``[8 * W]`` fp32; ``out`` flat ``[8 * n_padded]``; ``wo_flat`` the flat ``[W, n_padded]``
    weights of `output_layer_columns`; ``columns`` a multiple of 16)."""
    width = wo_flat.shape[0] // n_padded
    w1, w2, w3, w4, w5, w6, w7 = width, 2 * width, 3 * width, 4 * width, 5 * width, 6 * width, 7 * width
    for v in range(0, columns, 16):
        a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = load16(bo, v)
        for k in range(width):
            j = k * n_padded + v
            a0, a1 = fma16(a0, rows[k], wo_flat, j), fma16(a1, rows[w1 + k], wo_flat, j)
            a2, a3 = fma16(a2, rows[w2 + k], wo_flat, j), fma16(a3, rows[w3 + k], wo_flat, j)
            a4, a5 = fma16(a4, rows[w4 + k], wo_flat, j), fma16(a5, rows[w5 + k], wo_flat, j)
            a6, a7 = fma16(a6, rows[w6 + k], wo_flat, j), fma16(a7, rows[w7 + k], wo_flat, j)
        store16(out, v, a0), store16(out, n_padded + v, a1), store16(out, 2 * n_padded + v, a2)
        store16(out, 3 * n_padded + v, a3), store16(out, 4 * n_padded + v, a4), store16(out, 5 * n_padded + v, a5)
        store16(out, 6 * n_padded + v, a6), store16(out, 7 * n_padded + v, a7)


@numba.njit(cache=True, inline="always")
def sigmoid(x):
    """torch.sigmoid's formula in fp32, for decoding raw outputs (torch's vectorised exp differs from libm's by <= 3 ulp)."""
    return np.float32(1.0) / (np.float32(1.0) + np.exp(-x))


def layer_pairs(weight: torch.Tensor, bias: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """One bf16 layer (``weight [W, I]``, ``bias [W]``, as `MLP._cast_weights` gives them) as flat
    ``[ceil(I / 2) * W]`` uint32 pairs (`bf16_pairs` of ``weight^T``, input-major) and its bias
    ``[W]`` fp32 holding the bf16 values."""
    return bf16_pairs(weight.float().T.contiguous().numpy()).reshape(-1), bias.float().numpy().copy()


def hidden_layer_pairs(network: MLP, first: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The hidden layers from ``first`` on (square, ``W -> W``) as `layer_pairs`, concatenated layer by
    layer (flat ``[layers * W / 2 * W]`` uint32 and ``[layers * W]`` fp32; the bf16 copies torch's
    layers use)."""
    parts = [layer_pairs(w, b) for w, b in network._cast_weights(torch.bfloat16)[first:]]
    if not parts:
        return np.zeros(0, np.uint32), np.zeros(0, np.float32)
    return np.concatenate([p for p, _ in parts]), np.concatenate([b for _, b in parts])


def output_layer_columns(network: MLP) -> tuple[np.ndarray, np.ndarray]:
    """The output layer as ``wo [W, P]`` fp32, input-major, and the bias ``[P]``, both padded with
    zero columns to P = a multiple of 16 (one `f32x16` per 16 outputs)."""
    weight = network.output.weight.detach().float()  # [O, W]
    outputs, width = weight.shape
    padded = -(-outputs // 16) * 16
    wo = np.zeros((width, padded), np.float32)
    wo[:, :outputs] = weight.T.numpy()
    bo = np.zeros(padded, np.float32)
    bo[:outputs] = network.output.bias.detach().float().numpy()
    return wo, bo

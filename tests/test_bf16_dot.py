"""bf16 dot products in numba (`neural.bf16_dot`): vdpbf16ps, its portable emulation, the 4-row kernel."""

from __future__ import annotations

import numba
import numpy as np
import torch

from neuralrt.neural.bf16_dot import (
    HAS_AVX512_BF16, add16, bf16_bits, bf16_pairs, bf16_value, dot_bf16_pairs, dot_bf16_pairs_emulated, dot_rows_bf16,
    fma16, fma_f32, leaky_relu16, load16, load_bf16x16, store16, store_bf16x16, zeros16,
)  # fmt: skip


@numba.njit
def _dot(x_pairs, w_pairs, emulated):
    acc = zeros16()
    for p in range(x_pairs.shape[0]):
        if emulated:
            acc = dot_bf16_pairs_emulated(acc, x_pairs[p], w_pairs, p * 16)
        else:
            acc = dot_bf16_pairs(acc, x_pairs[p], w_pairs, p * 16)
    out = np.empty(16, np.float32)
    store16(out, 0, acc)
    return out


@numba.njit
def _bits(values):
    out = np.empty(values.shape[0], np.uint32)
    for i in range(values.shape[0]):
        out[i] = bf16_bits(values[i])
    return out


def _bf16(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(a).to(torch.bfloat16).double()


def test_bf16_bits_round_as_torch():
    values = (np.random.default_rng(0).standard_normal(4096) * 10.0 ** np.arange(-4, 4).repeat(512)).astype(np.float32)
    ties = np.array([1.00390625, 1.01171875, -1.00390625, 0.0, -0.0], np.float32)  # exactly halfway: to even
    values = np.concatenate([values, ties])
    expected = torch.from_numpy(values).to(torch.bfloat16).view(torch.int16).numpy().view(np.uint16)
    assert np.array_equal(_bits(values), expected.astype(np.uint32))


def test_pairs_layout_low_half_is_the_even_row():
    rows = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], np.float32)  # odd: a zero row is added
    pairs = bf16_pairs(rows)
    assert pairs.shape == (2, 2) and pairs.dtype == np.uint32
    assert (pairs[0, 0] & 0xFFFF) == 0x3F80 and (pairs[0, 0] >> 16) == 0x4040  # 1.0, 3.0
    assert (pairs[1, 1] & 0xFFFF) == 0x40C0 and (pairs[1, 1] >> 16) == 0  # 6.0, padding


def test_dot_and_its_emulation_equal_the_bf16_products_summed_in_fp64():
    rng = np.random.default_rng(1)
    x, w = rng.standard_normal(96).astype(np.float32), rng.standard_normal((96, 16)).astype(np.float32)
    x_pairs, w_pairs = bf16_pairs(x[:, None])[:, 0].copy(), bf16_pairs(w).reshape(-1)
    exact = (_bf16(x) @ _bf16(w)).numpy()
    emulated = _dot(x_pairs, w_pairs, True)
    native = _dot(x_pairs, w_pairs, False)  # vdpbf16ps where the CPU has it, else the emulation again
    scale = (_bf16(x)[:, None] * _bf16(w)).abs().sum(0).numpy()
    assert (np.abs(emulated - exact) <= 1e-6 * scale).all()  # fp32 accumulation of exact products
    assert (np.abs(native - exact) <= 1e-6 * scale).all()
    if HAS_AVX512_BF16:  # the instruction is reached (it differs from the emulation only in rounding)
        assert not np.array_equal(native, np.zeros(16, np.float32))


def test_dot_rows_equals_the_bf16_product_for_each_row_and_width():
    rng = np.random.default_rng(2)
    for width in (16, 64, 80, 128):  # the 64-column passes, the 16-column remainder, both
        x = rng.standard_normal((6, 45)).astype(np.float32)
        w = rng.standard_normal((45, width)).astype(np.float32)
        xp, wp = bf16_pairs(x.T).T.copy(), bf16_pairs(w).reshape(-1)
        rows = np.array([4, 0, 5, 5], np.int64)  # any rows, repeats allowed
        out = np.full(4 * width, np.nan, np.float32)
        for n_pairs in (23, 10):  # all pairs; a prefix (rays with fewer inputs)
            dot_rows_bf16(xp, rows, n_pairs, wp, 0, width, out)
            k = min(2 * n_pairs, 45)
            exact = (_bf16(x[rows, :k]) @ _bf16(w[:k])).numpy()
            scale = (_bf16(x[rows, :k]).abs() @ _bf16(w[:k]).abs()).numpy()
            assert (np.abs(out.reshape(4, width) - exact) <= 1e-6 * scale + 1e-30).all()
            # the same layer stored after another one in a flat array (``w_start``): the same sums
            stacked = np.concatenate([rng.integers(0, 2**32, 7 * width, dtype=np.uint32), wp])
            after = np.full(4 * width, np.nan, np.float32)
            dot_rows_bf16(xp, rows, n_pairs, stacked, 7 * width, width, after)
            assert np.array_equal(after, out)


@numba.njit
def _fmas(a, b, c, bits):
    scalar = np.empty(a.shape[0], np.float32)
    for i in range(a.shape[0]):
        scalar[i] = fma_f32(a[i], b[i], c[i])
    vector = np.empty(a.shape[0], np.float32)  # lane j: c[j] + a[0] * b[j], 16 at a time
    for s in range(0, a.shape[0], 16):
        v = fma16(load16(c, s), a[0], b, s)
        store16(vector, s, v)
    values = np.empty(bits.shape[0], np.float32)
    for i in range(bits.shape[0]):
        values[i] = bf16_value(bits[i])
    return scalar, vector, values


def test_fma_and_bf16_value_helpers():
    """fma_f32 / fma16 round once (exactly the fp64 product-sum rounded, when that is exact);
    bf16_value is torch's bf16 -> fp32."""
    rng = np.random.default_rng(4)
    a, b = (rng.integers(-2**11, 2**11, 64) / 2**6).astype(np.float32), (rng.integers(-2**11, 2**11, 64) / 2**7).astype(np.float32)
    c = rng.standard_normal(64).astype(np.float32)
    bits = rng.integers(0, 2**16, 4096).astype(np.uint16)
    bits = bits[(bits & 0x7F80) != 0x7F80]  # finite values
    scalar, vector, values = _fmas(a, b, c, bits)
    exact = (a.astype(np.float64) * b + c).astype(np.float32)  # products exact, one rounding of a 53-bit sum
    assert np.array_equal(scalar, exact)
    assert np.array_equal(vector, (np.float64(a[0]) * b.astype(np.float64) + c).astype(np.float32))
    assert np.array_equal(values, torch.from_numpy(bits.view(np.int16)).view(torch.bfloat16).float().numpy())


@numba.njit
def _epilogue(x, bias, slope):
    """Vector: bias, leaky ReLU, rounding to bf16, widening back; scalar: the same per element."""
    vector_bits = np.empty(x.shape[0], np.uint16)
    widened = np.empty(x.shape[0], np.float32)
    scalar_bits = np.empty(x.shape[0], np.uint16)
    for c in range(0, x.shape[0], 16):
        store_bf16x16(vector_bits, c, leaky_relu16(add16(load16(x, c), load16(bias, c)), slope))
        store16(widened, c, load_bf16x16(vector_bits, c))
    for i in range(x.shape[0]):
        y = x[i] + bias[i]
        y = y if y >= 0 else y * slope
        scalar_bits[i] = np.uint16(bf16_bits(y))
    return vector_bits, widened, scalar_bits


def test_vector_epilogue_equals_the_scalar_one_and_torch():
    """add16 + leaky_relu16 + store_bf16x16 give the scalar kernels' bits (torch's leaky ReLU and
    bf16 rounding, ties to even included); load_bf16x16 widens them exactly."""
    rng = np.random.default_rng(5)
    x = (rng.standard_normal(4096) * 10.0 ** rng.integers(-6, 6, 4096)).astype(np.float32)
    x[:6] = [1.00390625, 1.01171875, -1.00390625, 0.0, -0.0, -3e-39]  # ties, signed zeros, a denormal
    bias = np.zeros(4096, np.float32)
    bias[6:] = rng.standard_normal(4090).astype(np.float32)
    slope = np.float32(0.01)
    vector_bits, widened, scalar_bits = _epilogue(x, bias, slope)
    assert np.array_equal(vector_bits, scalar_bits)
    expected = torch.nn.functional.leaky_relu(torch.from_numpy(x) + torch.from_numpy(bias), float(slope)).to(torch.bfloat16)
    assert np.array_equal(vector_bits, expected.view(torch.int16).numpy().view(np.uint16))
    assert np.array_equal(widened, expected.float().numpy())

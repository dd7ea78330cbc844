"""The vector types' compress stores (`neuralrt.simd`, `neuralrt.simd16`) against numpy: each
writes the lanes of its mask in lane order at ``start`` and nothing else, also where the array
ends right after the last lane written (a register compress, then a store masked to a prefix)."""

import numba
import numpy as np
import pytest

from neuralrt.simd import compress_store_f32, compress_store_f64, compress_store_i64, floor_i64, load_f64, popcount8, splat_f64
from neuralrt.simd16 import compress16_f32, compress16_i32, compress_store_i32, load16, load16_i32, popcount16, splat_f32


@numba.njit(cache=True)
def _compress8(values, flags, out_f64, out_i64, out_f32, out_i32):
    e = 0
    for g in range(len(values) // 8):
        v = load_f64(values, 8 * g)
        m = load_f64(flags, 8 * g) > splat_f64(0.5)
        compress_store_f64(out_f64, e, v, m)
        compress_store_i64(out_i64, e, floor_i64(v), m)
        compress_store_f32(out_f32, e, v, m)
        compress_store_i32(out_i32, e, floor_i64(v), m)
        e += popcount8(m)
    return e


@numba.njit(cache=True)
def _compress16(values, integers, flags, out_f32, out_i32):
    e = 0
    for g in range(len(values) // 16):
        m = load16(flags, 16 * g) > splat_f32(0.5)
        compress16_f32(out_f32, e, load16(values, 16 * g), m)
        compress16_i32(out_i32, e, load16_i32(integers, 16 * g), m)
        e += popcount16(m)
    return e


@pytest.mark.parametrize("share", [0.0, 0.3, 0.9, 1.0])
def test_compress_stores_write_the_masked_lanes_in_order_and_nothing_else(share):
    rng = np.random.default_rng(7)
    n = 8 * 64
    values = rng.uniform(-1e3, 1e3, n)
    flags = (rng.random(n) < share).astype(np.float64)
    kept = values[flags > 0.5]
    spare = 0 if share == 1.0 else 16  # no spare room: the prefix-masked store must not touch past the end
    outs = [np.full(len(kept) + spare, -7, dtype) for dtype in (np.float64, np.int64, np.float32, np.int32)]
    assert _compress8(values, flags, *outs) == len(kept)
    expected = [kept, np.floor(kept).astype(np.int64), kept.astype(np.float32), np.floor(kept).astype(np.int32)]
    for out, want in zip(outs, expected):
        assert np.array_equal(out[: len(kept)], want)
        assert np.all(out[len(kept):] == -7)

    integers = rng.integers(-(2**31), 2**31 - 1, n, dtype=np.int32)
    out_f32, out_i32 = np.full(len(kept) + spare, -7, np.float32), np.full(len(kept) + spare, -7, np.int32)
    assert _compress16(values.astype(np.float32), integers, flags.astype(np.float32), out_f32, out_i32) == len(kept)
    assert np.array_equal(out_f32[: len(kept)], kept.astype(np.float32))
    assert np.array_equal(out_i32[: len(kept)], integers[flags > 0.5])
    assert np.all(out_f32[len(kept):] == -7) and np.all(out_i32[len(kept):] == -7)

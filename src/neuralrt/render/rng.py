"""The path tracer's random streams: one seeded stream per wavefront, in two implementations that
give the same numbers.

`TorchUniforms` draws from a torch generator on the scene's device (`sampling.make_generator`).
`NumbaUniforms` is the same stream as a CPU torch generator with that seed, bit for bit, drawn by
a numba pass: torch's CPU generator is MT19937 (seeded with the seed's low 32 bits) and its float32
uniforms are ``(next 32-bit word & (2**24 - 1)) * 2**-24``, one word per number in row-major order.
torch fills tensors one number at a time through a generic per-element loop (~5 ns a number on
this CPU); the numba pass twists and tempers whole 624-word blocks (~0.3 ns), and a bounce draws
[paths, 8] numbers (2M at 256x256x4 paths). The shading stages pick the stream with the rest of
their implementation (numba on the CPU), so images do not change with the choice.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from .sampling import make_generator

__all__ = ["TorchUniforms", "NumbaUniforms", "wavefront_seed"]

_N = 624  # MT19937 state words
_M = 397
_U32 = np.uint32


_MASK64 = (1 << 64) - 1


def _splitmix64(z: int) -> int:
    """SplitMix64's finaliser: a bijection of 64-bit words that spreads every input bit."""
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9 & _MASK64
    z = (z ^ (z >> 27)) * 0x94D049BB133111EB & _MASK64
    return z ^ (z >> 31)


def wavefront_seed(seed: int, wavefront: int) -> int:
    """The seed of a render's ``wavefront``-th stream: a hash of (``seed``, ``wavefront``) folded
    to the 32 bits the generator keeps. Every bit of ``seed`` counts (seed 2**40 is not seed 0),
    and no arithmetic relation maps one render's streams onto another's (``seed * 1_000_003 +
    wavefront`` gave seed 2021759595's first wavefront seed 0's second); two streams coincide only
    by chance, 2**-32 a pair."""
    z = _splitmix64((_splitmix64(seed & _MASK64) + 0x9E3779B97F4A7C15 * (wavefront + 1)) & _MASK64)
    return (z ^ (z >> 32)) & 0xFFFF_FFFF


class TorchUniforms:
    """float32 uniforms in [0, 1) from a torch generator seeded with ``seed`` on ``device``."""

    def __init__(self, seed: int, device="cpu"):
        self.device = torch.device(device)
        self.generator = make_generator(seed, self.device)

    def uniform(self, shape) -> Tensor:
        return torch.rand(shape, generator=self.generator, device=self.device, dtype=torch.float32)


class NumbaUniforms:
    """The stream of `TorchUniforms(seed, "cpu")`, bit for bit, as CPU tensors from numba passes."""

    def __init__(self, seed: int):
        # make_generator masks the seed to 63 bits; torch's MT19937 keeps the low 32 of those.
        self._state = _seeded_state(int(seed) & 0x7FFF_FFFF_FFFF_FFFF & 0xFFFF_FFFF)
        self._position = np.array([_N], np.int64)  # next state word; _N: twist first

    def uniform(self, shape) -> Tensor:
        out = torch.empty(shape, dtype=torch.float32)
        _fill_uniforms(self._state, self._position, out.numpy().reshape(-1))
        return out


@numba.njit(cache=True)
def _seeded_state(seed):
    """MT19937's init_genrand (as torch's at::mt19937(seed))."""
    mt = np.empty(_N, np.uint32)
    mt[0] = np.uint32(seed)
    for i in range(1, _N):
        prev = np.uint64(mt[i - 1])
        mt[i] = np.uint32((np.uint64(1812433253) * (prev ^ (prev >> np.uint64(30))) + np.uint64(i)) & np.uint64(0xFFFFFFFF))
    return mt


@numba.njit(cache=True, inline="always")
def _mix(upper, lower, far):
    y = (upper & _U32(0x80000000)) | (lower & _U32(0x7FFFFFFF))
    return far ^ (y >> _U32(1)) ^ (_U32(0x9908B0DF) * (y & _U32(1)))


@numba.njit(cache=True)
def _twist(mt):
    """The next 624 words in place (three loops instead of index arithmetic modulo 624)."""
    for i in range(_N - _M):
        mt[i] = _mix(mt[i], mt[i + 1], mt[i + _M])
    for i in range(_N - _M, _N - 1):
        mt[i] = _mix(mt[i], mt[i + 1], mt[i + _M - _N])
    mt[_N - 1] = _mix(mt[_N - 1], mt[0], mt[_M - 1])


@numba.njit(cache=True, nogil=True)
def _fill_uniforms(mt, position, out):
    """``out`` [n] float32 from the stream at ``position[0]``; advances it."""
    n = out.shape[0]
    p = position[0]
    k = 0
    scale = np.float32(1.0 / 16777216.0)  # 2**-24: a 24-bit integer times it is exact in float32
    while k < n:
        if p >= _N:
            _twist(mt)
            p = 0
        m = min(_N - p, n - k)
        words, dst = mt[p:p + m], out[k:k + m]  # slices: a loop the compiler vectorises
        for j in range(m):
            y = words[j]  # MT19937's tempering
            y ^= y >> _U32(11)
            y ^= (y << _U32(7)) & _U32(0x9D2C5680)
            y ^= (y << _U32(15)) & _U32(0xEFC60000)
            y ^= y >> _U32(18)
            dst[j] = np.float32(np.int32(y & _U32(0xFFFFFF))) * scale  # via int32: a native conversion
        p += m
        k += m
    position[0] = p

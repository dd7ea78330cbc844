"""N-BVH's training-ray sampler on the CPU: the CUDA kernel's algorithm (`nbvh_rays_triton`) in one
numba pass, with the same Philox streams, so that both draw the same candidates.

Program j owns slots ``[j q, (j + 1) q)`` and draws rounds of ``block`` candidates until it has
accepted q of them (packed in candidate order); candidate k of round r is Philox4x32-10 of
(training seed, counters ``call_base + 2 c`` and ``+ 1``, c = (j * max_rounds + r) * block + k), as
Triton's `tl.randint4x` computes it, turned into floats as `tl.random.uint_to_uniform_float`
does. Origins, directions, the cut's level, the dilation and the acceptance follow
`nbvh_rays_triton._candidates` and `_acceptance` operation for operation (float32; the heuristic in
float64); the first leaf is `nbvh_traversal._first_leaf`, the CPU's walk. The programs are handed
out to the threads one at a time (`task_queue`), and each writes its own slots, so the samples do
not depend on the thread count. sin and cos may round differently from CUDA's (last ulp; tested).

Why: the earlier CPU sampler drew its candidates with torch's generator and ~20 torch ops per
round (~300k candidates a step late in a bunny run, yield ~3%), half of N-BVH's CPU training time
(`neuralrt train --method nbvh` under cProfile: `_candidates` 35 of 70 s; docs/nbvh.md).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from ..task_queue import take_task, task_workers
from .nbvh_traversal import _STACK, _first_leaf, _np

__all__ = ["sample_leaf_chords_cpu", "philox4x32", "uniform_float", "LeafChords", "UNFILLED", "OVERFLOW", "call_base"]

UNFILLED, OVERFLOW = 1, 2  # flag bits (OVERFLOW: the CUDA walk's stack, sized from the tree; the CPU walk's holds 256)
BLOCK = 64  # candidates per round: the CUDA kernel's (the same counters, so the same candidates)
PROGRAMS = 2048  # at most; each owns ceil(n / programs) slots
MAX_ROUNDS = 1 << 16  # per program (the counters' layout); a draw that fills nothing stops at `CPU_MAX_ROUNDS`
CPU_MAX_ROUNDS = 1 << 12  # rounds a CPU program draws at most (a cut nothing is kept from: 33.5M candidates for 8,192 slots)

_MASK32 = np.uint64(0xFFFFFFFF)
_ROUND_A, _ROUND_B = np.uint64(0xD2511F53), np.uint64(0xCD9E8D57)
_KEY_A, _KEY_B = np.uint64(0x9E3779B9), np.uint64(0xBB67AE85)
_SCALE = np.float32(4.6566127342e-10)
_TWO_PI = np.float32(2 * math.pi)


class LeafChords:
    """One call's samples: chord start [n, 3] (unit cube), unit direction [n, 3], length [n], leaf [n]
    int64, Morton code [n] int32; rounds [programs] and flag [1] int32; ``block`` candidates a round."""

    def __init__(self, start, direction, length, node, code, rounds, flag, block):
        self.start, self.direction, self.length, self.node, self.code = start, direction, length, node, code
        self.rounds, self.flag, self.block = rounds, flag, block


def call_base(call: int) -> int:
    """The Philox counter where draw ``call`` starts: a call uses fewer than 2^40 counters."""
    if not 0 <= call < 1 << 23:
        raise ValueError(f"draw number {call} out of range")
    return call << 40


@numba.njit(cache=True, inline="always")
def philox4x32(seed, counter):
    """Triton's ``tl.randint4x(seed, counter)``: Philox4x32-10 of the counter (low word, high word,
    0, 0) under the key (seed's low word, high word); four uint32 values (as uint64)."""
    c0, c1 = np.uint64(counter) & _MASK32, np.uint64(counter) >> np.uint64(32)
    c2 = c3 = np.uint64(0)
    k0, k1 = np.uint64(seed) & _MASK32, (np.uint64(seed) >> np.uint64(32)) & _MASK32
    for _ in range(10):
        pb, pa = _ROUND_B * c2, _ROUND_A * c0
        c0, c1, c2, c3 = (pb >> np.uint64(32)) ^ c1 ^ k0, pb & _MASK32, (pa >> np.uint64(32)) ^ c3 ^ k1, pa & _MASK32
        k0, k1 = (k0 + _KEY_A) & _MASK32, (k1 + _KEY_B) & _MASK32
    return c0, c1, c2, c3


@numba.njit(cache=True, inline="always")
def uniform_float(x):
    """Triton's ``uint_to_uniform_float`` of a uint32: in [0, 1), float32."""
    nonneg = x if x < np.uint64(0x80000000) else _MASK32 - x  # the int32 x, or -x - 1 where negative
    return np.float32(np.int64(nonneg)) * _SCALE


@numba.njit(cache=True, inline="always")
def _candidate(seed, counter, cx, cy, cz, ex, ey, ez, registered, dil_base, dil_jitter):
    """`nbvh_rays_triton._candidates` of one counter: origin, unit direction, level, dilation and the
    acceptance uniform."""
    a0, a1, a2, a3 = philox4x32(seed, counter)
    b0, b1, b2, b3 = philox4x32(seed, counter + 1)
    half = np.float32(0.5)
    ox = cx + (uniform_float(a0) - half) * ex
    oy = cy + (uniform_float(a1) - half) * ey
    oz = cz + (uniform_float(a2) - half) * ez
    dz = np.float32(1.0) - np.float32(2.0) * uniform_float(a3)
    r = np.float32(math.sqrt(max(np.float32(1.0) - dz * dz, np.float32(0.0))))
    phi = _TWO_PI * uniform_float(b0)
    dx, dy = r * np.float32(math.cos(phi)), r * np.float32(math.sin(phi))
    count = 0
    for lvl in range(registered.shape[0]):
        count += registered[lvl] != 0
    choices = count + (registered[0] == 0)  # the live cut too while LoD 0 is missing
    pick = min(np.int32(uniform_float(b1) * np.float32(choices)), choices - 1)
    level, seen = -1, 0
    for lvl in range(registered.shape[0]):
        on = registered[lvl] != 0
        if on and seen == pick:
            level = lvl
        seen += on
    dil = dil_base + dil_jitter * uniform_float(b2)
    return ox, oy, oz, dx, dy, dz, level, dil, uniform_float(b3)


@numba.njit(cache=True, inline="always")
def _acceptance(node, loss_sum, samples, alive, h_max, min_acceptance):
    """`nbvh_rays_triton._acceptance` of one leaf (float64 heuristic), float32."""
    s = samples[node]
    if s <= 0 or h_max <= 0:
        return np.float32(1.0)
    den = math.sqrt(s * alive[node])
    h = loss_sum[node] / den if den > 0 else 0.0
    return np.float32(min(max(h / h_max, min_acceptance), 1.0))


@numba.njit(cache=True, inline="always")
def _spread10(v):
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    return (v | (v << 2)) & 0x09249249


@numba.njit(cache=True, inline="always")
def _morton(x, y, z):
    """`nbvh_rays.morton_codes` of one point (10 bits per axis, x lowest)."""
    zero, one, scale = np.float32(0.0), np.float32(1.0), np.float32(1023.0)
    qx = np.int32(min(max(x, zero), one) * scale)
    qy = np.int32(min(max(y, zero), one) * scale)
    qz = np.int32(min(max(z, zero), one) * scale)
    return np.int32(_spread10(qx) | (_spread10(qy) << 1) | (_spread10(qz) << 2))


@numba.njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _sample_kernel(center, extent, registered, dil_base, dil_jitter, lo, hi, children, lod, live, loss_sum, samples, alive, h_max,
                   min_acceptance, n, quota, seed, base, block, max_rounds, round_limit, programs, n_workers, start_out, dir_out,
                   length_out, node_out, code_out, rounds_out, unfilled_out):  # fmt: skip
    cx, cy, cz = center[0], center[1], center[2]
    ex, ey, ez = extent[0], extent[1], extent[2]
    one = np.float32(1.0)
    next_program = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):
        origins = np.empty((block, 3), np.float32)  # a round's candidates, as `_first_leaf` reads them
        inv = np.empty((block, 3), np.float32)
        dirs = np.empty((block, 3), np.float32)
        t_max = np.full(block, np.inf, np.float32)
        level = np.empty(block, np.int8)
        dilation = np.empty(block, np.float32)
        u_keep = np.empty(block, np.float32)
        node, t0, t1 = np.empty(block, np.int64), np.empty(block, np.float32), np.empty(block, np.float32)
        stack, stack_t0, stack_t1 = np.empty(_STACK, np.int64), np.empty(_STACK, np.float32), np.empty(_STACK, np.float32)
        while True:
            pid = take_task(next_program)
            if pid >= programs:
                break
            first = pid * quota
            want = min(quota, n - first)
            filled, r = 0, 0
            while filled < want and r < round_limit:
                for k in range(block):
                    counter = base + 2 * ((pid * max_rounds + r) * block + k)
                    ox, oy, oz, dx, dy, dz, lvl, dil, u = _candidate(seed, counter, cx, cy, cz, ex, ey, ez, registered, dil_base,
                                                                     dil_jitter)  # fmt: skip
                    origins[k, 0], origins[k, 1], origins[k, 2] = ox, oy, oz
                    dirs[k, 0], dirs[k, 1], dirs[k, 2] = dx, dy, dz
                    inv[k, 0], inv[k, 1], inv[k, 2] = one / dx, one / dy, one / dz
                    level[k], dilation[k], u_keep[k] = lvl, dil, u
                    _first_leaf(k, origins, inv, t_max, lo, hi, children, lod, live, level, dilation, node, t0, t1, stack, stack_t0,
                                stack_t1)  # fmt: skip
                for k in range(block):  # the accepted candidates, in candidate order
                    leaf = node[k]
                    if leaf < 0 or not u_keep[k] < _acceptance(leaf, loss_sum, samples, alive, h_max, min_acceptance):
                        continue
                    if filled < want:
                        slot = first + filled
                        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
                        sx, sy, sz = origins[k, 0] + t0[k] * dx, origins[k, 1] + t0[k] * dy, origins[k, 2] + t0[k] * dz
                        length = t1[k] - t0[k]
                        start_out[slot, 0], start_out[slot, 1], start_out[slot, 2] = sx, sy, sz
                        dir_out[slot, 0], dir_out[slot, 1], dir_out[slot, 2] = dx, dy, dz
                        length_out[slot], node_out[slot] = length, leaf
                        half = np.float32(0.5) * length
                        code_out[slot] = _morton(sx + half * dx, sy + half * dy, sz + half * dz)
                    filled += 1
                r += 1
            rounds_out[pid] = r
            unfilled_out[pid] = filled < want


def sample_leaf_chords_cpu(model, n: int, seed: int, call: int, block: int = BLOCK, max_rounds: int = CPU_MAX_ROUNDS) -> LeafChords:
    """``n`` accepted leaf chords of ``model``'s (CPU tensors) current cut and statistics (module
    docstring); `nbvh_rays_triton.sample_leaf_chords_triton`'s outputs for the same ``block``.
    ``call`` numbers the draws of a run; a program stops after ``max_rounds`` rounds (flag
    UNFILLED, its slots left at node 0)."""
    tc = model.config.training
    programs = max(1, min(PROGRAMS, -(-n // block)))
    quota = -(-max(n, 1) // programs)
    start, direction = torch.empty(n, 3), torch.empty(n, 3)
    length = torch.empty(n)
    node = torch.zeros(n, dtype=torch.int64)  # unfilled slots keep the root (in bounds for the step's statistics)
    code = torch.empty(n, dtype=torch.int32)
    rounds = torch.zeros(programs, dtype=torch.int32)
    flag = torch.zeros(1, dtype=torch.int32)
    unfilled = np.zeros(programs, np.bool_)
    if n == 0:
        return LeafChords(start, direction, length, node, code, rounds, flag, block)
    center = _np(model.unit_center, torch.float32)
    extent = (_np(model.unit_extent, torch.float32) * np.float32(tc.origin_box_scale)).astype(np.float32)
    _sample_kernel(center, extent, _np(model.registered, torch.int8), np.float32(tc.dilation), np.float32(tc.dilation_jitter),
                   _np(model.node_lo, torch.float32), _np(model.node_hi, torch.float32), _np(model.node_children, torch.int32),
                   _np(model.node_lod, torch.int8), _np(model.live, torch.bool), _np(model.loss_sum, torch.float64),
                   _np(model.samples, torch.float64), _np(model.alive_steps, torch.float64), float(model.h_max),
                   np.float32(tc.min_acceptance), n, quota, int(seed), call_base(call), block, MAX_ROUNDS, int(max_rounds), programs,
                   task_workers(programs), start.numpy(), direction.numpy(), length.numpy(), node.numpy(), code.numpy(),
                   rounds.numpy(), unfilled)  # fmt: skip
    flag[0] = UNFILLED if unfilled.any() else 0
    return LeafChords(start, direction, length, node, code, rounds, flag, block)

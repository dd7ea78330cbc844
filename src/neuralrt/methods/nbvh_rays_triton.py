"""N-BVH's training-ray sampler on CUDA: one Triton kernel, fixed-size output, no host sync.

The algorithm, and the Philox streams, of the CPU sampler (`nbvh_rays_cpu`, one numba pass):
origins uniform in the object's box scaled ``origin_box_scale`` about its centre, directions
uniform on the sphere, a cut chosen uniformly per ray among the registered LoDs (ascending, then
the live cut (-1) while LoD 0 is not registered), the box dilation ``dilation + U(0,
dilation_jitter)``, the FIRST leaf of that cut the ray crosses (`first_leaf_walk`, the walk of
`first_leaves_triton`), kept with p = max(h / h_max, min_acceptance) (1 for a leaf never sampled, or
while h_max = 0), h = loss_sum / sqrt(samples * alive_steps) read from the model's device buffers.

Every slot gets a fresh accepted sample (no stale slot, no host loop): program j owns slots
``[j q, (j + 1) q)`` and draws rounds of BLOCK candidates until it has accepted q of them; the
accepted lanes of a round are packed in candidate order by a prefix sum. The first q accepted of
an i.i.d. stream are i.i.d. from the accepted distribution, so nothing is biased by the packing.
Random numbers are Philox (`tl.randint4x`) of (training seed, call, program, round, lane): a
call is deterministic, and no torch generator is advanced. The stack of the walk holds the base
tree's depth + 2 entries, more than a first-leaf walk can push (depth + 1), so it never overflows.

Outputs stay on the device: chord starts (unit cube), unit directions, chord lengths, leaves, the
Morton codes of the chord midpoints (the CPU sampler's spatial order), rounds per program (the
yield), and a flag (bit 1: a program stopped at ``max_rounds`` with slots left, their node 0;
bit 2: a stack overflow) that the caller checks later without waiting.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import triton
import triton.language as tl
from torch import Tensor

from .nbvh_rays_cpu import MAX_ROUNDS, OVERFLOW, UNFILLED, LeafChords
from .nbvh_rays_cpu import call_base as _call_base
from .nbvh_traversal_triton import first_leaf_walk

__all__ = ["sample_leaf_chords_triton", "draw_candidates_triton", "tree_depth", "LeafChords", "UNFILLED", "OVERFLOW"]

_BLOCK = 64
_PROGRAMS = 2048  # at most; each owns ceil(n / programs) slots
_WARPS = _BLOCK // 32  # one candidate per thread
_TWO_PI = tl.constexpr(2 * math.pi)
_INF = tl.constexpr(float("inf"))


@triton.jit
def _candidates(seed, counter, cx, cy, cz, ex, ey, ez, reg_ptr, dil_base, dil_jitter, LEVELS: tl.constexpr):
    """Candidate rays for the Philox counters [B] (int64): origin, unit direction, level, dilation,
    and the uniform number that decides acceptance. ``reg_ptr``: the model's LEVELS registered flags."""
    a0, a1, a2, a3 = tl.randint4x(seed, counter)
    b0, b1, b2, b3 = tl.randint4x(seed, counter + 1)
    ox = cx + (tl.random.uint_to_uniform_float(a0) - 0.5) * ex
    oy = cy + (tl.random.uint_to_uniform_float(a1) - 0.5) * ey
    oz = cz + (tl.random.uint_to_uniform_float(a2) - 0.5) * ez
    # Uniform on the sphere: z uniform in [-1, 1], the azimuth uniform (Archimedes).
    dz = 1.0 - 2.0 * tl.random.uint_to_uniform_float(a3)
    r = tl.sqrt(tl.maximum(1.0 - dz * dz, 0.0))
    phi = _TWO_PI * tl.random.uint_to_uniform_float(b0)
    dx = r * tl.cos(phi)
    dy = r * tl.sin(phi)
    # The level: uniform among the registered LoDs (ascending), then -1 (the live cut) while LoD 0 is missing.
    count = tl.load(reg_ptr).to(tl.int32) * 0
    for lvl in tl.static_range(LEVELS):
        count += tl.load(reg_ptr + lvl).to(tl.int32)
    live_too = 1 - tl.load(reg_ptr).to(tl.int32)
    choices = count + live_too
    pick = tl.minimum((tl.random.uint_to_uniform_float(b1) * choices.to(tl.float32)).to(tl.int32), choices - 1)
    level = tl.zeros_like(pick) - 1
    seen = tl.zeros_like(pick)
    for lvl in tl.static_range(LEVELS):
        on = tl.load(reg_ptr + lvl).to(tl.int32)
        level = tl.where((on != 0) & (seen == pick), lvl, level)
        seen += on
    dil = dil_base + dil_jitter * tl.random.uint_to_uniform_float(b2)
    u_keep = tl.random.uint_to_uniform_float(b3)
    return ox, oy, oz, dx, dy, dz, level, dil, u_keep


@triton.jit
def _acceptance(node, found, loss_sum_ptr, samples_ptr, alive_ptr, h_max, min_acceptance):
    """p [B] float32 of the leaves: `NBVHModel.acceptance` (float64 heuristic, as the CPU)."""
    loss = tl.load(loss_sum_ptr + node, mask=found, other=0.0)
    samples = tl.load(samples_ptr + node, mask=found, other=0.0)
    alive = tl.load(alive_ptr + node, mask=found, other=0.0)
    den = tl.sqrt(samples * alive)
    h = tl.where(den > 0, loss / tl.where(den > 0, den, 1.0), 0.0)
    ratio = tl.minimum(tl.maximum(h / tl.where(h_max > 0, h_max, 1.0), min_acceptance), 1.0)
    p = tl.where(samples > 0, tl.where(h_max > 0, ratio, 1.0), 1.0)
    return p.to(tl.float32)


@triton.jit
def _store_xyz(ptr, i, x, y, z, mask):
    """Rows ``i`` [B] of a [n, 3] float32 array set to (x, y, z)."""
    tl.store(ptr + i * 3, x, mask=mask)
    tl.store(ptr + i * 3 + 1, y, mask=mask)
    tl.store(ptr + i * 3 + 2, z, mask=mask)


@triton.jit
def _spread10(v):
    """The low 10 bits of v [B] (int32) moved to bits 0, 3, 6, ... (Morton interleave)."""
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    v = (v | (v << 2)) & 0x09249249
    return v


@triton.jit
def _morton(x, y, z):
    """30-bit Morton codes of unit-cube points (clamped; 10 bits per axis, x lowest), as `morton_codes`."""
    qx = (tl.minimum(tl.maximum(x, 0.0), 1.0) * 1023.0).to(tl.int32)
    qy = (tl.minimum(tl.maximum(y, 0.0), 1.0) * 1023.0).to(tl.int32)
    qz = (tl.minimum(tl.maximum(z, 0.0), 1.0) * 1023.0).to(tl.int32)
    return _spread10(qx) | (_spread10(qy) << 1) | (_spread10(qz) << 2)


@triton.jit(do_not_specialize=["n", "quota", "seed", "call_base", "max_rounds"])  # one compiled kernel whatever their values
def _sample_kernel(center_ptr, extent_ptr, reg_ptr, box_scale, dil_base, dil_jitter,
                   lo_ptr, hi_ptr, children_ptr, lod_ptr, live_ptr,
                   loss_sum_ptr, samples_ptr, alive_ptr, h_max_ptr, min_acceptance,
                   start_out, dir_out, length_out, node_out, code_out, rounds_out, flag_ptr, stack_ptr, stack_f_ptr,
                   n, quota, seed, call_base, max_rounds,
                   STACK: tl.constexpr, BLOCK: tl.constexpr, LEVELS: tl.constexpr, LAYOUT_ROUNDS: tl.constexpr):  # fmt: skip
    pid = tl.program_id(0)
    lanes = tl.arange(0, BLOCK)
    first = pid * quota
    want = tl.minimum(quota, n - first)
    stack_node = stack_ptr + pid.to(tl.int64) * (3 * STACK * BLOCK) + lanes
    stack_t0 = stack_f_ptr + pid.to(tl.int64) * (3 * STACK * BLOCK) + STACK * BLOCK + lanes
    stack_t1 = stack_t0 + STACK * BLOCK
    cx, cy, cz = tl.load(center_ptr), tl.load(center_ptr + 1), tl.load(center_ptr + 2)
    ex, ey, ez = tl.load(extent_ptr) * box_scale, tl.load(extent_ptr + 1) * box_scale, tl.load(extent_ptr + 2) * box_scale
    h_max = tl.load(h_max_ptr)
    tmax = tl.zeros([BLOCK], tl.float32) + _INF
    ok = lanes < BLOCK
    overflowed = tl.zeros([BLOCK], tl.int32)
    filled = pid * 0
    r = pid * 0
    while (filled < want) & (r < max_rounds):
        # Two Philox counters per candidate: (program, round, lane) below 2^40, above them the call; laid
        # out by the fixed LAYOUT_ROUNDS (the CPU sampler's), not by where this draw stops (max_rounds).
        cand = (pid.to(tl.int64) * LAYOUT_ROUNDS + r) * BLOCK + lanes
        counter = call_base + 2 * cand
        ox, oy, oz, dx, dy, dz, lvl, dil, u_keep = _candidates(seed, counter, cx, cy, cz, ex, ey, ez, reg_ptr, dil_base,
                                                               dil_jitter, LEVELS)  # fmt: skip
        ix, iy, iz = tl.math.div_rn(1.0, dx), tl.math.div_rn(1.0, dy), tl.math.div_rn(1.0, dz)  # IEEE, as torch's 1 / d
        node, t0, t1, over = first_leaf_walk(ox, oy, oz, ix, iy, iz, tmax, lvl, dil, ok, lo_ptr, hi_ptr, children_ptr, lod_ptr,
                                             live_ptr, stack_node, stack_t0, stack_t1, STACK)  # fmt: skip
        overflowed = overflowed | over
        found = node >= 0
        p = _acceptance(node, found, loss_sum_ptr, samples_ptr, alive_ptr, h_max, min_acceptance)
        keep = found & (u_keep < p)
        pos = filled + tl.cumsum(keep.to(tl.int32), 0) - 1  # accepted lanes packed in candidate order
        write = keep & (pos < want)
        slot = (first + pos).to(tl.int64)
        sx, sy, sz = ox + t0 * dx, oy + t0 * dy, oz + t0 * dz
        length = t1 - t0
        _store_xyz(start_out, slot, sx, sy, sz, write)
        _store_xyz(dir_out, slot, dx, dy, dz, write)
        tl.store(length_out + slot, length, mask=write)
        tl.store(node_out + slot, node.to(tl.int64), mask=write)
        half = 0.5 * length
        tl.store(code_out + slot, _morton(sx + half * dx, sy + half * dy, sz + half * dz), mask=write)
        filled += tl.sum(keep.to(tl.int32), axis=0)
        r += 1
    tl.store(rounds_out + pid, r)
    flag = tl.where(filled < want, 1, 0) | tl.where(tl.max(overflowed, axis=0) > 0, 2, 0)
    tl.atomic_or(flag_ptr, flag)


@triton.jit
def _candidates_kernel(center_ptr, extent_ptr, reg_ptr, box_scale, dil_base, dil_jitter, origin_out, dir_out, level_out, dil_out,
                       u_out, n, seed, call_base, BLOCK: tl.constexpr, LEVELS: tl.constexpr):  # fmt: skip
    i = (tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)).to(tl.int64)
    ok = i < n
    cx, cy, cz = tl.load(center_ptr), tl.load(center_ptr + 1), tl.load(center_ptr + 2)
    ex, ey, ez = tl.load(extent_ptr) * box_scale, tl.load(extent_ptr + 1) * box_scale, tl.load(extent_ptr + 2) * box_scale
    ox, oy, oz, dx, dy, dz, lvl, dil, u = _candidates(seed, call_base + 2 * i, cx, cy, cz, ex, ey, ez, reg_ptr,
                                                      dil_base, dil_jitter, LEVELS)  # fmt: skip
    _store_xyz(origin_out, i, ox, oy, oz, ok)
    _store_xyz(dir_out, i, dx, dy, dz, ok)
    tl.store(level_out + i, lvl.to(tl.int8), mask=ok)
    tl.store(dil_out + i, dil, mask=ok)
    tl.store(u_out + i, u, mask=ok)


def tree_depth(children: Tensor) -> int:
    """Levels below the root of the tree ``children [M, 2]`` (-1: none; read once, on the host)."""
    kids = children.detach().cpu().numpy()
    frontier, depth = np.zeros(1, np.int64), 0
    while True:
        nxt = kids[frontier].reshape(-1)
        nxt = nxt[nxt >= 0]
        if len(nxt) == 0:
            return depth
        frontier, depth = nxt, depth + 1


def _level_flags(model) -> Tensor:
    return model.registered.view(torch.int8)


def sample_leaf_chords_triton(model, n: int, seed: int, call: int, stack_depth: int, max_rounds: int = MAX_ROUNDS) -> LeafChords:
    """``n`` accepted leaf chords of ``model``'s current cut and statistics (see the module docstring).
    ``call`` numbers the draws of a run (a different stream each); ``stack_depth``: `tree_depth` of the model's tree."""
    dev = model.node_lo.device
    tc = model.config.training
    programs = max(1, min(_PROGRAMS, triton.cdiv(n, _BLOCK)))
    quota = triton.cdiv(max(n, 1), programs)
    stack = stack_depth + 2
    start = torch.empty(n, 3, device=dev)
    direction = torch.empty(n, 3, device=dev)
    length = torch.empty(n, device=dev)
    # Slots a program could not fill (flag UNFILLED) keep node 0, the root, so that the step's
    # statistics stay in bounds until the caller sees the flag.
    node = torch.zeros(n, dtype=torch.int64, device=dev)
    code = torch.empty(n, dtype=torch.int32, device=dev)
    rounds = torch.zeros(programs, dtype=torch.int32, device=dev)
    flag = torch.zeros(1, dtype=torch.int32, device=dev)
    if n == 0:
        return LeafChords(start, direction, length, node, code, rounds, flag, _BLOCK)
    scratch = torch.empty(programs * 3 * stack * _BLOCK, dtype=torch.int32, device=dev)
    _sample_kernel[(programs,)](
        model.unit_center.float().contiguous(), model.unit_extent.float().contiguous(), _level_flags(model),
        float(tc.origin_box_scale), float(tc.dilation), float(tc.dilation_jitter),
        model.node_lo, model.node_hi, model.node_children, model.node_lod, model.live.view(torch.int8),
        model.loss_sum, model.samples, model.alive_steps, model.h_max, float(tc.min_acceptance),
        start, direction, length, node, code, rounds, flag, scratch, scratch.view(torch.float32),
        n, quota, int(seed), _call_base(call), min(int(max_rounds), MAX_ROUNDS), STACK=stack, BLOCK=_BLOCK,
        LEVELS=model.registered.numel(), LAYOUT_ROUNDS=MAX_ROUNDS, num_warps=_WARPS,
    )  # fmt: skip
    return LeafChords(start, direction, length, node, code, rounds, flag, _BLOCK)


def draw_candidates_triton(model, n: int, seed: int, call: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The candidate rays alone, before the walk and the acceptance (for tests and diagnostics):
    origins [n, 3] (unit cube), unit directions [n, 3], levels [n] int8, dilations [n], acceptance uniforms [n]."""
    dev = model.node_lo.device
    tc = model.config.training
    origin, direction = torch.empty(n, 3, device=dev), torch.empty(n, 3, device=dev)
    level, dil, u = torch.empty(n, dtype=torch.int8, device=dev), torch.empty(n, device=dev), torch.empty(n, device=dev)
    block = 1024 if dev.type == "cpu" else 128  # the interpreter: fewer, larger programs
    if n:
        _candidates_kernel[(triton.cdiv(n, block),)](
            model.unit_center.float().contiguous(), model.unit_extent.float().contiguous(), _level_flags(model),
            float(tc.origin_box_scale), float(tc.dilation), float(tc.dilation_jitter), origin, direction, level, dil, u,
            n, int(seed), _call_base(call), BLOCK=block, LEVELS=model.registered.numel(),
            num_warps=max(1, block // 32) if dev.type != "cpu" else 1,
        )  # fmt: skip
    return origin, direction, level, dil, u

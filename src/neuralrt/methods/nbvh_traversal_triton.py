"""N-BVH cut traversal on CUDA: the numba stack walks of `nbvh_traversal` as Triton kernels.

Same contract as `list_leaves` / `first_leaves` on the CPU: the same float32 slab test (``1 / d``
is computed by torch, IEEE division, as numpy does for numba), the same leaf and acceptance rules,
each ray's leaves sorted by (t0, node) (a per-ray insertion sort, as numba), the same first leaf
(nearer child first, boxes entered after the best leaf so far skipped, the same tie rule). Only
compares, no arithmetic beyond the slab test, so compiled kernels give the numba kernels' lists
bit for bit, not only under the interpreter.

Lanes are rays (BLOCK per program); each lane walks its own stack, kept in a scratch buffer laid
out slot-major per program (lanes at the same depth touch adjacent words). The grid is persistent
(at most ``_PROGRAMS`` programs loop over the blocks), so the scratch is ``_PROGRAMS x STACK x
BLOCK`` words whatever the number of rays. The stack holds 64 entries; a lane that would overflow
sets a flag and the call is repeated with numba's 256 (and numba's rule: drop the push), so the
answers equal numba's for every tree. A stack of D + 1 entries suffices for a tree of depth D.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch import Tensor

from .nbvh_traversal import CutArrays, LeafList

__all__ = ["list_leaves_triton", "first_leaves_triton", "first_leaf_walk"]

_ENTER_MIN = tl.constexpr(1e-4)  # as nbvh_traversal (Triton reads globals only as constexpr)
_EXIT_MIN = tl.constexpr(1e-3)
_INF = tl.constexpr(float("inf"))
_SHORT_STACK, _NUMBA_STACK = 64, 256
_PROGRAMS = 2048  # persistent grid: enough blocks in flight for any current GPU
_BLOCK = 64
_WARPS = _BLOCK // 32  # one ray per thread (more warps would hold each lane twice)


@triton.jit
def _slab(ox, oy, oz, ix, iy, iz, lo_ptr, hi_ptr, node, dil, mask):
    """(t_near, t_far) of the dilated box of ``node`` [B] (float32, as numba's `_slab`: its
    ``min(a, b)`` is ``a`` unless ``b < a``, ``max`` likewise)."""
    n3 = node.to(tl.int64) * 3
    tn = tl.zeros_like(ox) - _INF
    tf = tl.zeros_like(ox) + _INF
    for axis in tl.static_range(3):
        if axis == 0:
            o, inv = ox, ix
        elif axis == 1:
            o, inv = oy, iy
        else:
            o, inv = oz, iz
        ta = ((tl.load(lo_ptr + n3 + axis, mask=mask, other=0.0) - dil) - o) * inv
        tb = ((tl.load(hi_ptr + n3 + axis, mask=mask, other=0.0) + dil) - o) * inv
        ta = tl.where(ta != ta, -_INF, ta)  # 0 * inf: the origin lies on the slab plane of a parallel ray
        tb = tl.where(tb != tb, _INF, tb)
        near = tl.where(tb < ta, tb, ta)
        far = tl.where(tb > ta, tb, ta)
        tn = tl.where(near > tn, near, tn)
        tf = tl.where(far < tf, far, tf)
    return tn, tf


@triton.jit
def _children_and_leaf(node, lvl, children_ptr, lod_ptr, live_ptr, mask):
    """Children [B] x 2 and whether ``node`` ends the walk: no children, or a leaf of the ray's cut."""
    c0 = tl.load(children_ptr + node.to(tl.int64) * 2, mask=mask, other=-1)
    c1 = tl.load(children_ptr + node.to(tl.int64) * 2 + 1, mask=mask, other=-1)
    live = tl.load(live_ptr + node, mask=mask, other=0) != 0
    lod = tl.load(lod_ptr + node, mask=mask, other=127).to(tl.int32)
    leaf = (c0 < 0) | tl.where(lvl < 0, live, lod <= lvl)
    return c0, c1, leaf


@triton.jit
def _load_ray(i, ok, o_ptr, inv_ptr, tmax_ptr, level_ptr, dil_ptr):
    i3 = i * 3
    ox = tl.load(o_ptr + i3, mask=ok, other=0.0)
    oy = tl.load(o_ptr + i3 + 1, mask=ok, other=0.0)
    oz = tl.load(o_ptr + i3 + 2, mask=ok, other=0.0)
    ix = tl.load(inv_ptr + i3, mask=ok, other=1.0)
    iy = tl.load(inv_ptr + i3 + 1, mask=ok, other=1.0)
    iz = tl.load(inv_ptr + i3 + 2, mask=ok, other=1.0)
    tmax = tl.load(tmax_ptr + i, mask=ok, other=0.0)
    lvl = tl.load(level_ptr + i, mask=ok, other=0).to(tl.int32)
    dil = tl.load(dil_ptr + i, mask=ok, other=0.0)
    return ox, oy, oz, ix, iy, iz, tmax, lvl, dil


@triton.jit
def _list_kernel(o_ptr, inv_ptr, tmax_ptr, level_ptr, dil_ptr, lo_ptr, hi_ptr, children_ptr, lod_ptr, live_ptr,
                 count_ptr, start_ptr, node_out, t0_out, t1_out, stack_ptr, overflow_ptr, n, rounds,
                 WRITE: tl.constexpr, STACK: tl.constexpr, BLOCK: tl.constexpr):  # fmt: skip
    """Count (WRITE false) or list and sort (WRITE true) each ray's leaves: numba's `_walk`."""
    pid = tl.program_id(0)
    n_programs = tl.num_programs(0)
    lanes = tl.arange(0, BLOCK)
    stack = stack_ptr + pid.to(tl.int64) * (STACK * BLOCK) + lanes  # slot s of a lane at stack + s * BLOCK
    overflowed = tl.zeros([BLOCK], tl.int32)
    k = pid * 0
    while k < rounds:  # (a while loop: the interpreter cannot take a runtime bound in range())
        i = (pid + k * n_programs).to(tl.int64) * BLOCK + lanes
        k += 1
        ok = i < n
        ox, oy, oz, ix, iy, iz, tmax, lvl, dil = _load_ray(i, ok, o_ptr, inv_ptr, tmax_ptr, level_ptr, dil_ptr)
        base = tl.zeros([BLOCK], tl.int64)
        if WRITE:
            base = tl.load(start_ptr + i, mask=ok, other=0)
        tl.store(stack, tl.zeros([BLOCK], tl.int32), mask=ok)
        sp = ok.to(tl.int32)
        count = tl.zeros([BLOCK], tl.int64)
        while tl.max(sp, axis=0) > 0:
            act = sp > 0
            sp = tl.where(act, sp - 1, sp)
            node = tl.load(stack + sp * BLOCK, mask=act, other=0)
            tn, tf = _slab(ox, oy, oz, ix, iy, iz, lo_ptr, hi_ptr, node, dil, act)
            crossed = act & (tn <= tf) & (tn < tmax)
            c0, c1, leaf = _children_and_leaf(node, lvl, children_ptr, lod_ptr, live_ptr, crossed)
            take = crossed & leaf & tl.where(tn >= 0.0, tn > _ENTER_MIN, tf > _EXIT_MIN)
            if WRITE:
                tl.store(node_out + base + count, node.to(tl.int64), mask=take)
                tl.store(t0_out + base + count, tn, mask=take)
                tl.store(t1_out + base + count, tf, mask=take)
            count += take.to(tl.int64)
            down = crossed & (~leaf) & (tf > _ENTER_MIN)
            room = sp + 2 <= STACK
            overflowed = overflowed | (down & ~room).to(tl.int32)
            down = down & room
            tl.store(stack + sp * BLOCK, c1, mask=down)
            tl.store(stack + (sp + 1) * BLOCK, c0, mask=down)
            sp = tl.where(down, sp + 2, sp)
        if WRITE:
            _sort_rows(node_out, t0_out, t1_out, base, count, ok)
        else:
            tl.store(count_ptr + i, count, mask=ok)
    tl.atomic_max(overflow_ptr, tl.max(overflowed, axis=0))


@triton.jit
def _sort_rows(node_out, t0_out, t1_out, base, count, ok):
    """Insertion sort of each lane's rows ``base : base + count`` by (t0, node), as numba's."""
    a = 1
    while tl.max(tl.where(ok, count - a, 0), axis=0) > 0:
        todo = ok & (a < count)
        pa = base + a
        kn = tl.load(node_out + pa, mask=todo, other=0)
        k0 = tl.load(t0_out + pa, mask=todo, other=0.0)
        k1 = tl.load(t1_out + pa, mask=todo, other=0.0)
        b = tl.zeros_like(base) + (a - 1)
        moving = todo
        while tl.max(moving.to(tl.int32), axis=0) > 0:
            pb = base + b
            bn = tl.load(node_out + pb, mask=moving, other=0)
            b0 = tl.load(t0_out + pb, mask=moving, other=0.0)
            shift = moving & ((b0 > k0) | ((b0 == k0) & (bn > kn)))
            b1 = tl.load(t1_out + pb, mask=shift, other=0.0)
            tl.store(node_out + pb + 1, bn, mask=shift)
            tl.store(t0_out + pb + 1, b0, mask=shift)
            tl.store(t1_out + pb + 1, b1, mask=shift)
            b = tl.where(shift, b - 1, b)
            moving = shift & (b >= 0)
        tl.store(node_out + base + b + 1, kn, mask=todo)
        tl.store(t0_out + base + b + 1, k0, mask=todo)
        tl.store(t1_out + base + b + 1, k1, mask=todo)
        a += 1


@triton.jit
def _enterable(tn, tf, tmax, leaf):
    """A crossed box that can hold a listed leaf: a valid leaf, or an interior node left ahead of the origin."""
    ok_leaf = tl.where(tn >= 0.0, tn > _ENTER_MIN, tf > _EXIT_MIN)
    return (tn <= tf) & (tn < tmax) & tl.where(leaf, ok_leaf, tf > _ENTER_MIN)


@triton.jit
def first_leaf_walk(ox, oy, oz, ix, iy, iz, tmax, lvl, dil, ok, lo_ptr, hi_ptr, children_ptr, lod_ptr, live_ptr,
                    stack_node, stack_t0, stack_t1, STACK: tl.constexpr):  # fmt: skip
    """(node (-1: none), t0, t1, overflowed) of the leaf with the smallest (t0, node) of each lane's
    ray [B]: numba's `_first_kernel`. ``stack_*``: each lane's slot 0 of its node, t0, t1 stacks
    (slot s at ``+ s * B``); a push past STACK is dropped and flagged."""
    BLOCK: tl.constexpr = ox.shape[0]
    overflowed = tl.zeros([BLOCK], tl.int32)
    best_node = tl.zeros([BLOCK], tl.int32) - 1
    best_t0 = tl.zeros([BLOCK], tl.float32) + _INF
    best_t1 = tl.zeros([BLOCK], tl.float32) + _INF
    root = tl.zeros([BLOCK], tl.int32)
    tn, tf = _slab(ox, oy, oz, ix, iy, iz, lo_ptr, hi_ptr, root, dil, ok)
    _, _, leaf = _children_and_leaf(root, lvl, children_ptr, lod_ptr, live_ptr, ok)
    push = ok & _enterable(tn, tf, tmax, leaf)
    tl.store(stack_node, root, mask=push)
    tl.store(stack_t0, tn, mask=push)
    tl.store(stack_t1, tf, mask=push)
    sp = push.to(tl.int32)
    while tl.max(sp, axis=0) > 0:
        act = sp > 0
        sp = tl.where(act, sp - 1, sp)
        node = tl.load(stack_node + sp * BLOCK, mask=act, other=0)
        tn = tl.load(stack_t0 + sp * BLOCK, mask=act, other=0.0)
        tf = tl.load(stack_t1 + sp * BLOCK, mask=act, other=0.0)
        act = act & ~(tn > best_t0)
        a, b, leaf = _children_and_leaf(node, lvl, children_ptr, lod_ptr, live_ptr, act)
        better = act & leaf & ((tn < best_t0) | (node < best_node))  # tn == best_t0 here unless smaller
        best_node = tl.where(better, node, best_node)
        best_t0 = tl.where(better, tn, best_t0)
        best_t1 = tl.where(better, tf, best_t1)
        inner = act & ~leaf
        ta0, ta1 = _slab(ox, oy, oz, ix, iy, iz, lo_ptr, hi_ptr, a, dil, inner)
        tb0, tb1 = _slab(ox, oy, oz, ix, iy, iz, lo_ptr, hi_ptr, b, dil, inner)
        _, _, leaf_a = _children_and_leaf(a, lvl, children_ptr, lod_ptr, live_ptr, inner)
        _, _, leaf_b = _children_and_leaf(b, lvl, children_ptr, lod_ptr, live_ptr, inner)
        use_a = inner & _enterable(ta0, ta1, tmax, leaf_a) & (ta0 <= best_t0)
        use_b = inner & _enterable(tb0, tb1, tmax, leaf_b) & (tb0 <= best_t0)
        room = sp + 2 <= STACK
        overflowed = overflowed | (inner & ~room).to(tl.int32)
        use_a = use_a & room
        use_b = use_b & room
        swap = use_a & use_b & (tb0 < ta0)  # far child below, near child on top
        lower = use_a | use_b
        upper = use_a & use_b
        tl.store(stack_node + sp * BLOCK, tl.where(swap | ~use_b, a, b), mask=lower)
        tl.store(stack_t0 + sp * BLOCK, tl.where(swap | ~use_b, ta0, tb0), mask=lower)
        tl.store(stack_t1 + sp * BLOCK, tl.where(swap | ~use_b, ta1, tb1), mask=lower)
        tl.store(stack_node + (sp + 1) * BLOCK, tl.where(swap, b, a), mask=upper)
        tl.store(stack_t0 + (sp + 1) * BLOCK, tl.where(swap, tb0, ta0), mask=upper)
        tl.store(stack_t1 + (sp + 1) * BLOCK, tl.where(swap, tb1, ta1), mask=upper)
        sp += lower.to(tl.int32) + upper.to(tl.int32)
    return best_node, best_t0, best_t1, overflowed


@triton.jit
def _first_kernel(o_ptr, inv_ptr, tmax_ptr, level_ptr, dil_ptr, lo_ptr, hi_ptr, children_ptr, lod_ptr, live_ptr,
                  node_out, t0_out, t1_out, stack_ptr, stack_f_ptr, overflow_ptr, n, rounds,
                  STACK: tl.constexpr, BLOCK: tl.constexpr):  # fmt: skip
    """Per ray, the leaf with the smallest (t0, node): numba's `_first_kernel`, lane by lane."""
    pid = tl.program_id(0)
    n_programs = tl.num_programs(0)
    lanes = tl.arange(0, BLOCK)
    # node, t0, t1 stacks of a program side by side (stack_f_ptr: the same words read as float32)
    stack_node = stack_ptr + pid.to(tl.int64) * (3 * STACK * BLOCK) + lanes
    stack_t0 = stack_f_ptr + pid.to(tl.int64) * (3 * STACK * BLOCK) + STACK * BLOCK + lanes
    stack_t1 = stack_t0 + STACK * BLOCK
    overflowed = tl.zeros([BLOCK], tl.int32)
    k = pid * 0
    while k < rounds:  # (a while loop: the interpreter cannot take a runtime bound in range())
        i = (pid + k * n_programs).to(tl.int64) * BLOCK + lanes
        k += 1
        ok = i < n
        ox, oy, oz, ix, iy, iz, tmax, lvl, dil = _load_ray(i, ok, o_ptr, inv_ptr, tmax_ptr, level_ptr, dil_ptr)
        best_node, best_t0, best_t1, over = first_leaf_walk(ox, oy, oz, ix, iy, iz, tmax, lvl, dil, ok, lo_ptr, hi_ptr,
                                                            children_ptr, lod_ptr, live_ptr, stack_node, stack_t0, stack_t1,
                                                            STACK)  # fmt: skip
        overflowed = overflowed | over
        tl.store(node_out + i, best_node.to(tl.int64), mask=ok)
        tl.store(t0_out + i, best_t0, mask=ok)
        tl.store(t1_out + i, best_t1, mask=ok)
    tl.atomic_max(overflow_ptr, tl.max(overflowed, axis=0))


def _rays_and_cut(origins, directions, t_max, cut: CutArrays, level, dilation) -> tuple:
    f32 = torch.float32
    inv = 1.0 / directions.to(f32)  # IEEE division (Triton's fp32 '/' may be approximate)
    return (origins.to(f32).contiguous(), inv.contiguous(), t_max.to(f32).contiguous(), level.to(torch.int8).contiguous(),
            dilation.to(f32).contiguous(), cut.lo.to(f32).contiguous(), cut.hi.to(f32).contiguous(),
            cut.children.to(torch.int32).contiguous(), cut.lod.to(torch.int8).contiguous(),
            cut.live.to(torch.int8).contiguous())  # fmt: skip


def _grid(n: int) -> tuple[int]:
    return (max(1, min(triton.cdiv(n, _BLOCK), _PROGRAMS)),)


def _rounds(n: int) -> int:
    """Blocks each program of the persistent grid walks."""
    return triton.cdiv(triton.cdiv(n, _BLOCK), _grid(n)[0])


def _with_stack(launch, n: int, words_per_slot: int, device) -> int:
    """Run ``launch(stack, overflow, STACK)`` with the short stack, again with numba's if a lane overflowed."""
    for size in (_SHORT_STACK, _NUMBA_STACK):
        programs = _grid(n)[0]
        stack = torch.empty(programs * words_per_slot * size * _BLOCK, dtype=torch.int32, device=device)
        overflow = torch.zeros(1, dtype=torch.int32, device=device)
        launch(stack, overflow, size)
        if not int(overflow.item()):
            break
    return size


def list_leaves_triton(origins: Tensor, directions: Tensor, t_max: Tensor, cut: CutArrays, level: Tensor, dilation: Tensor) -> LeafList:
    """`list_leaves` on the rays' device with Triton kernels (count, prefix sum, list + sort)."""
    n, dev = len(origins), origins.device
    args = _rays_and_cut(origins, directions, t_max, cut, level, dilation)
    counts = torch.zeros(n, dtype=torch.int64, device=dev)
    start = torch.zeros(n + 1, dtype=torch.int64, device=dev)
    empty_i, empty_f = torch.empty(0, dtype=torch.int64, device=dev), torch.empty(0, dtype=torch.float32, device=dev)
    if n == 0:
        return LeafList(start, empty_i, empty_f, empty_f.clone())

    def count(stack, overflow, size):
        _list_kernel[_grid(n)](*args, counts, start, empty_i, empty_f, empty_f, stack, overflow, n, _rounds(n),
                               WRITE=False, STACK=size, BLOCK=_BLOCK, num_warps=_WARPS)  # fmt: skip

    size = _with_stack(count, n, 1, dev)
    torch.cumsum(counts, 0, out=start[1:])
    e = int(start[-1])
    node = torch.empty(e, dtype=torch.int64, device=dev)
    t0, t1 = torch.empty(e, dtype=torch.float32, device=dev), torch.empty(e, dtype=torch.float32, device=dev)
    if e:
        stack = torch.empty(_grid(n)[0] * size * _BLOCK, dtype=torch.int32, device=dev)
        overflow = torch.zeros(1, dtype=torch.int32, device=dev)
        _list_kernel[_grid(n)](*args, counts, start, node, t0, t1, stack, overflow, n, _rounds(n),
                               WRITE=True, STACK=size, BLOCK=_BLOCK, num_warps=_WARPS)  # fmt: skip
    return LeafList(start, node, t0, t1)


def first_leaves_triton(origins: Tensor, directions: Tensor, t_max: Tensor, cut: CutArrays, level: Tensor,
                        dilation: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """`first_leaves` on the rays' device with a Triton kernel: (node [N] (-1: none), t0 [N], t1 [N])."""
    n, dev = len(origins), origins.device
    node = torch.full((n,), -1, dtype=torch.int64, device=dev)
    t0 = torch.full((n,), float("inf"), device=dev)
    t1 = torch.full((n,), float("inf"), device=dev)
    if n == 0:
        return node, t0, t1
    args = _rays_and_cut(origins, directions, t_max, cut, level, dilation)

    def first(stack, overflow, size):
        _first_kernel[_grid(n)](*args, node, t0, t1, stack, stack.view(torch.float32), overflow, n, _rounds(n),
                                STACK=size, BLOCK=_BLOCK, num_warps=_WARPS)  # fmt: skip

    _with_stack(first, n, 3, dev)
    return node, t0, t1

"""Which leaves of an N-BVH cut a ray crosses, front to back: `list_leaves`.

Everything is in the model's unit cube with unit-length directions, so the paper's absolute
thresholds apply: a leaf counts if its (dilated) box is entered ahead of the origin (t0 > 1e-4),
or contains the origin and is left beyond t1 > 1e-3 (METHODS-SPEC A4), and t0 < t_max.

A node is a leaf of the cut a ray asks for when it has no children, or when its stored LoD is at
most the ray's level (level L >= 0: the registered cut of LoD L; level -1: the live cut of
training, flagged by ``live``).

One contract, implementations chosen once by the tensors' device: a numba kernel on the CPU (tasks
of rays from `task_queue`, a stack per worker; one walk that counts, fills and sorts each
task's rays into a segment of its own, a second only where they do not fit), the same walks as
Triton kernels on CUDA (`nbvh_traversal_triton`: one ray per lane), breadth-first frontier
expansion in torch elsewhere. All sort each ray's leaves by (t0, node index) and compute the slab
test with the same float32 operations, so they give the same lists.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from ..simd import HAS_AVX512
from ..task_queue import take_task, task_count, task_workers
from .nbvh_traversal_simd import SLOTS, walk_lanes

__all__ = ["LeafList", "CutArrays", "list_leaves", "list_leaves_torch", "first_leaves", "first_leaves_torch", "NO_LOD"]

NO_LOD = 127  # stored LoD of a node that is a leaf of no registered cut
_ENTER_MIN = 1e-4  # a leaf ahead of the origin must be entered beyond this
_EXIT_MIN = 1e-3  # a leaf around the origin must be left beyond this
_STACK = 256


@dataclass
class CutArrays:
    """The tree the traversal walks (unit cube; node 0 is the root; children are adjacent)."""

    lo: Tensor  # [M, 3] float32
    hi: Tensor  # [M, 3] float32
    children: Tensor  # [M, 2] int32, -1 for none
    lod: Tensor  # [M] int8: finest registered LoD where the node is a leaf, NO_LOD if none
    live: Tensor  # [M] bool: leaf of the live cut (training)


@dataclass
class LeafList:
    """Per ray, the leaves it crosses sorted by (t0, node): rows ``start[i] : start[i + 1]``."""

    start: Tensor  # [N + 1] int64
    node: Tensor  # [E] int64
    t0: Tensor  # [E] float32 entry (negative: the origin is inside)
    t1: Tensor  # [E] float32 exit

    @property
    def counts(self) -> Tensor:
        return self.start[1:] - self.start[:-1]


# ---------------------------------------------------------------------------------------------
# numba (CPU)


@numba.njit(cache=True, inline="always")
def _slab(ox, oy, oz, ix, iy, iz, lo, hi, node, dil):
    # All in float32 (np.inf is a float64: starting from it, numba widened every min and max to
    # float64; the same values, 0.84x the list walk's time on the bunny's cut)
    inf = np.float32(np.inf)
    tn = -inf
    tf = inf
    for a in range(3):
        o = ox if a == 0 else (oy if a == 1 else oz)
        inv = ix if a == 0 else (iy if a == 1 else iz)
        ta = ((lo[node, a] - dil) - o) * inv
        tb = ((hi[node, a] + dil) - o) * inv
        if ta != ta:  # 0 * inf: the origin lies on the slab plane of a parallel ray: inside
            ta = -inf
        if tb != tb:
            tb = inf
        tn = max(tn, min(ta, tb))
        tf = min(tf, max(ta, tb))
    return tn, tf


@numba.njit(cache=True)
def _walk(i, origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, stack, out_node, out_t0, out_t1, base, limit):
    """Ray i's leaves, written from ``out_*[base]`` below index ``limit`` (0: none written): their number."""
    ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
    ix, iy, iz = inv_dirs[i, 0], inv_dirs[i, 1], inv_dirs[i, 2]
    dil = dilation[i]
    lvl = level[i]
    tmax = t_max[i]
    count = 0
    sp = 1
    stack[0] = 0
    while sp > 0:
        sp -= 1
        node = stack[sp]
        tn, tf = _slab(ox, oy, oz, ix, iy, iz, lo, hi, node, dil)
        if not (tn <= tf and tn < tmax):
            continue
        leaf = children[node, 0] < 0 or (live[node] if lvl < 0 else lod[node] <= lvl)
        if leaf:
            ok = tn > _ENTER_MIN if tn >= 0 else tf > _EXIT_MIN
            if ok:
                if base + count < limit:
                    out_node[base + count], out_t0[base + count], out_t1[base + count] = node, tn, tf
                count += 1
        elif tf > _ENTER_MIN and sp + 2 <= stack.shape[0]:
            stack[sp], stack[sp + 1] = children[node, 1], children[node, 0]
            sp += 2
    return count


# The kernels below take their rays in tasks of consecutive rays from a task queue (`task_queue`):
# numba's OpenMP layer would split a prange over rays statically, and rays differ in cost along the
# batch (a wavefront's sky and object, a training batch's two halves).
_TASK_RAYS = 256  # at least, per task
_TASKS_PER_THREAD = 32  # at most


def _tasks(n_rays: int) -> tuple[int, int]:
    """(tasks, workers) for a kernel over ``n_rays`` rays."""
    n_tasks = task_count(n_rays, _TASK_RAYS, _TASKS_PER_THREAD)
    return n_tasks, task_workers(n_tasks)


@numba.njit(parallel=True, cache=True)
def _fill_kernel(origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, start, out_node, out_t0, out_t1, n_tasks,
                 n_workers):  # fmt: skip
    n_rays = origins.shape[0]
    next_task = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):
        stack = np.empty(_STACK, np.int64)
        while True:
            task = take_task(next_task)
            if task >= n_tasks:
                break
            for i in range(task * n_rays // n_tasks, (task + 1) * n_rays // n_tasks):
                s = start[i]
                n = _walk(i, origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, stack, out_node, out_t0, out_t1,
                          s, out_node.shape[0])  # fmt: skip
                _sort_leaves(out_node, out_t0, out_t1, s, n)


@numba.njit(cache=True, inline="always")
def _sort_leaves(out_node, out_t0, out_t1, s, n):
    """Insertion sort of a ray's few leaves ``[s, s + n)`` by (t0, node)."""
    for a in range(s + 1, s + n):
        kn, k0, k1 = out_node[a], out_t0[a], out_t1[a]
        b = a - 1
        while b >= s and (out_t0[b] > k0 or (out_t0[b] == k0 and out_node[b] > kn)):
            out_node[b + 1], out_t0[b + 1], out_t1[b + 1] = out_node[b], out_t0[b], out_t1[b]
            b -= 1
        out_node[b + 1], out_t0[b + 1], out_t1[b + 1] = kn, k0, k1


@numba.njit(parallel=True, cache=True)
def _list_kernel(origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, counts, segment, out_node, out_t0, out_t1, used,
                 n_tasks, n_workers):  # fmt: skip
    """Count and fill in one walk: task t's rays write their sorted leaves one after another into
    ``out_*[segment[t] : segment[t + 1]]``; ``used[t]`` is the number written, or -1 where they did
    not fit (the counts are complete either way)."""
    n_rays = origins.shape[0]
    next_task = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):
        stack = np.empty(_STACK, np.int64)
        while True:
            task = take_task(next_task)
            if task >= n_tasks:
                break
            at, end = segment[task], segment[task + 1]
            for i in range(task * n_rays // n_tasks, (task + 1) * n_rays // n_tasks):
                n = _walk(i, origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, stack, out_node, out_t0, out_t1,
                          at, end)  # fmt: skip
                counts[i] = n
                if at + n <= end:
                    _sort_leaves(out_node, out_t0, out_t1, at, n)
                at += n
            used[task] = at - segment[task] if at <= end else -1


@numba.njit(cache=True, inline="always")
def _enterable(node, tn, tf, tmax, children, lod, live, lvl):
    """Whether a crossed box can hold a listed leaf: a valid leaf, or an interior node left ahead of the origin."""
    if not (tn <= tf and tn < tmax):
        return False
    if children[node, 0] < 0 or (live[node] if lvl < 0 else lod[node] <= lvl):
        return tn > _ENTER_MIN if tn >= 0 else tf > _EXIT_MIN
    return tf > _ENTER_MIN


@numba.njit(cache=True, inline="always")
def _first_leaf(i, origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, out_node, out_t0, out_t1, stack, stack_t0,
                stack_t1):  # fmt: skip
    """Ray i's first leaf into ``out_*[i]``: nearer child first, and a box entered after the best
    leaf so far is skipped (a child's box lies in its parent's, so nothing below it is entered
    earlier). ``stack*``: scratch."""
    ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
    ix, iy, iz = inv_dirs[i, 0], inv_dirs[i, 1], inv_dirs[i, 2]
    dil, lvl, tmax = dilation[i], level[i], t_max[i]
    best_node, best_t0, best_t1 = -1, np.float32(np.inf), np.float32(np.inf)
    sp = 0
    tn, tf = _slab(ox, oy, oz, ix, iy, iz, lo, hi, 0, dil)
    if _enterable(0, tn, tf, tmax, children, lod, live, lvl):
        stack[0], stack_t0[0], stack_t1[0] = 0, tn, tf
        sp = 1
    while sp > 0:
        sp -= 1
        node, tn, tf = stack[sp], stack_t0[sp], stack_t1[sp]
        if tn > best_t0:
            continue
        if children[node, 0] < 0 or (live[node] if lvl < 0 else lod[node] <= lvl):
            if tn < best_t0 or node < best_node:  # tn == best_t0 here unless smaller
                best_node, best_t0, best_t1 = node, tn, tf
            continue
        a, b = children[node, 0], children[node, 1]
        ta0, ta1 = _slab(ox, oy, oz, ix, iy, iz, lo, hi, a, dil)
        tb0, tb1 = _slab(ox, oy, oz, ix, iy, iz, lo, hi, b, dil)
        use_a = _enterable(a, ta0, ta1, tmax, children, lod, live, lvl) and ta0 <= best_t0
        use_b = _enterable(b, tb0, tb1, tmax, children, lod, live, lvl) and tb0 <= best_t0
        if sp + 2 > _STACK:
            continue
        if use_a and use_b and tb0 < ta0:  # far child below, near child on top
            stack[sp], stack_t0[sp], stack_t1[sp] = a, ta0, ta1
            stack[sp + 1], stack_t0[sp + 1], stack_t1[sp + 1] = b, tb0, tb1
            sp += 2
            continue
        if use_b:
            stack[sp], stack_t0[sp], stack_t1[sp] = b, tb0, tb1
            sp += 1
        if use_a:
            stack[sp], stack_t0[sp], stack_t1[sp] = a, ta0, ta1
            sp += 1
    out_node[i], out_t0[i], out_t1[i] = best_node, best_t0, best_t1


@numba.njit(parallel=True, cache=True)
def _first_kernel(origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, out_node, out_t0, out_t1, n_tasks,
                  n_workers):  # fmt: skip
    """Per ray, the leaf with the smallest (t0, node): what `list_leaves` would list first."""
    n = origins.shape[0]
    next_task = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):
        stack = np.empty(_STACK, np.int64)
        stack_t0 = np.empty(_STACK, np.float32)
        stack_t1 = np.empty(_STACK, np.float32)
        while True:
            task = take_task(next_task)
            if task >= n_tasks:
                break
            for i in range(task * n // n_tasks, (task + 1) * n // n_tasks):
                _first_leaf(i, origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, out_node, out_t0, out_t1,
                            stack, stack_t0, stack_t1)  # fmt: skip


def _np(t: Tensor, dtype) -> np.ndarray:
    return t.detach().to(dtype).contiguous().numpy()


def _kernel_args(origins, directions, t_max, cut: CutArrays, level, dilation) -> tuple:
    with np.errstate(divide="ignore"):
        inv = (1.0 / _np(directions, torch.float32)).astype(np.float32)
    return (_np(origins, torch.float32), inv, _np(t_max, torch.float32), _np(cut.lo, torch.float32), _np(cut.hi, torch.float32),
            _np(cut.children, torch.int32), _np(cut.lod, torch.int8), _np(cut.live, torch.bool), _np(level, torch.int8),
            _np(dilation, torch.float32))  # fmt: skip


def _first_leaves_numba(origins, directions, t_max, cut: CutArrays, level, dilation) -> tuple[Tensor, Tensor, Tensor]:
    n = len(origins)
    node, t0, t1 = np.full(n, -1, np.int64), np.empty(n, np.float32), np.empty(n, np.float32)
    if n:
        _first_kernel(*_kernel_args(origins, directions, t_max, cut, level, dilation), node, t0, t1, *_tasks(n))
    return torch.from_numpy(node), torch.from_numpy(t0), torch.from_numpy(t1)


# Room per ray in `_list_kernel`'s segments (a task's rays share theirs): where a task's leaves do not
# fit, the fill pass walks every ray again.
_SEGMENT_LEAVES_PER_RAY = 8


def _list_leaves_numba(origins, directions, t_max, cut: CutArrays, level, dilation) -> LeafList:
    """One walk per ray where every task's leaves fit its segment (`_list_kernel`), else a second
    (`_fill_kernel`): the same lists."""
    n = len(origins)
    args = _kernel_args(origins, directions, t_max, cut, level, dilation)
    n_tasks, n_workers = _tasks(n)
    segment = (np.arange(n_tasks + 1) * n // n_tasks) * _SEGMENT_LEAVES_PER_RAY
    buffers = np.empty(segment[-1], np.int64), np.empty(segment[-1], np.float32), np.empty(segment[-1], np.float32)
    counts, used = np.empty(n, np.int64), np.empty(n_tasks, np.int64)
    if n:
        _list_kernel(*args, counts, segment, *buffers, used, n_tasks, n_workers)
    start = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=start[1:])
    if n == 0 or (used >= 0).all():
        node, t0, t1 = (np.concatenate([b[segment[t] : segment[t] + used[t]] for t in range(n_tasks)]) if n else b[:0] for b in buffers)
    else:
        e = int(start[-1])
        node, t0, t1 = np.empty(e, np.int64), np.empty(e, np.float32), np.empty(e, np.float32)
        _fill_kernel(*args, start, node, t0, t1, n_tasks, n_workers)
    return LeafList(torch.from_numpy(start), torch.from_numpy(node), torch.from_numpy(t0), torch.from_numpy(t1))


# Where numba compiles for AVX-512 the lists come from the 16-lane walk (`nbvh_traversal_simd`):
# the same lists; False: `_list_kernel` (elsewhere LLVM would lower the lanes to scalar loops).
SIMD_LIST = HAS_AVX512


def _float32_above(threshold: float) -> np.float32:
    """The float32 F with ``x > F`` exactly where ``x > threshold`` (a float64 constant, as the
    scalar walk compares) for every float32 x: the largest float32 not above ``threshold``."""
    f = np.float32(threshold)
    return np.nextafter(f, np.float32(-np.inf)) if f > threshold else f


@numba.njit(parallel=True, cache=True)
def _lanes_kernel(ray_ids, ox, oy, oz, ix, iy, iz, t_max, dilation, level, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z, child0, child1, leaf_key,
                  enter_min, exit_min, n_slots, slot_node, slot_t0, slot_t1, counts, n_tasks, n_workers):  # fmt: skip
    """`walk_lanes` over tasks of rays (`task_queue`), a lane stack per worker."""
    n = ox.shape[0]
    next_task = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):
        stack = np.empty(16 * _STACK, np.int32)
        while True:
            task = take_task(next_task)
            if task >= n_tasks:
                break
            walk_lanes(task * n // n_tasks, (task + 1) * n // n_tasks, ray_ids, ox, oy, oz, ix, iy, iz, t_max, dilation, level, lo_x,
                       lo_y, lo_z, hi_x, hi_y, hi_z, child0, child1, leaf_key, stack, enter_min, exit_min, n_slots, slot_node, slot_t0,
                       slot_t1, counts)  # fmt: skip


@numba.njit(parallel=True, cache=True)
def _pack_kernel(counts, start, n_slots, slot_node, slot_t0, slot_t1, out_node, out_t0, out_t1, n_tasks, n_workers):
    """Ray i's leaves from its slots (`walk_lanes`) at ``out_*[start[i]:]``, sorted by (t0, node),
    where it has at most ``n_slots`` (the others: `_rewalk_kernel`)."""
    n = counts.shape[0]
    next_task = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):
        while True:
            task = take_task(next_task)
            if task >= n_tasks:
                break
            for i in range(task * n // n_tasks, (task + 1) * n // n_tasks):
                s, c = start[i], counts[i]
                if c <= n_slots:
                    for k in range(c):
                        j = i * n_slots + k
                        out_node[s + k], out_t0[s + k], out_t1[s + k] = slot_node[j], slot_t0[j], slot_t1[j]
                    _sort_leaves(out_node, out_t0, out_t1, s, c)


@numba.njit(parallel=True, cache=True)
def _rewalk_kernel(rays, origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, start, out_node, out_t0, out_t1):
    """The leaves of ``rays`` (more than their slots) walked again by `_walk`, sorted, at ``out_*[start[i]:]``."""
    for k in numba.prange(rays.shape[0]):
        stack = np.empty(_STACK, np.int64)
        i = rays[k]
        s, e = start[i], start[i + 1]
        _walk(i, origins, inv_dirs, t_max, lo, hi, children, lod, live, level, dilation, stack, out_node, out_t0, out_t1, s, e)
        _sort_leaves(out_node, out_t0, out_t1, s, e - s)


def _list_leaves_simd(origins, directions, t_max, cut: CutArrays, level, dilation, slots: int = SLOTS) -> LeafList:
    """`_list_leaves_numba`'s lists from the 16-lane walk, then a packing pass (and `_walk` again
    for the few rays with more leaves than their slots)."""
    n = len(origins)
    args = _kernel_args(origins, directions, t_max, cut, level, dilation)
    o, inv, tmax, lo, hi, children, lod, live, lvl, dil = args
    columns = [np.ascontiguousarray(a[:, k]) for a in (o, inv) for k in range(3)]
    corners = [np.ascontiguousarray(a[:, k]) for a in (lo, hi) for k in range(3)]
    child0, child1 = np.ascontiguousarray(children[:, 0]), np.ascontiguousarray(children[:, 1])
    leaf_key = lod.astype(np.int32) + 256 * live.astype(np.int32)
    counts = np.empty(n, np.int32)
    slot_arrays = np.empty(n * slots, np.int32), np.empty(n * slots, np.float32), np.empty(n * slots, np.float32)
    n_tasks, n_workers = _tasks(n)
    if n:
        _lanes_kernel(np.arange(n + 16, dtype=np.int32), *columns, tmax, dil, lvl.astype(np.int32), *corners, child0, child1, leaf_key,
                      _float32_above(_ENTER_MIN), _float32_above(_EXIT_MIN), slots, *slot_arrays, counts, n_tasks, n_workers)  # fmt: skip
    start = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=start[1:])
    e = int(start[-1])
    node, t0, t1 = np.empty(e, np.int64), np.empty(e, np.float32), np.empty(e, np.float32)
    if n:
        _pack_kernel(counts, start, slots, *slot_arrays, node, t0, t1, n_tasks, n_workers)
    more = np.flatnonzero(counts > slots)
    if len(more):
        _rewalk_kernel(more, *args, start, node, t0, t1)
    return LeafList(torch.from_numpy(start), torch.from_numpy(node), torch.from_numpy(t0), torch.from_numpy(t1))


# ---------------------------------------------------------------------------------------------
# torch (any device)


def list_leaves_torch(origins, directions, t_max, cut: CutArrays, level, dilation) -> LeafList:
    """Breadth-first frontier of (ray, node) pairs, then one sort by (ray, t0, node)."""
    dev = origins.device
    inv = 1.0 / directions.float()
    ray = torch.arange(len(origins), device=dev)
    node = torch.zeros(len(origins), dtype=torch.long, device=dev)
    children = cut.children.long()
    found = []
    while len(ray):
        dil = dilation[ray, None]
        o, iv = origins[ray], inv[ray]
        ta = torch.nan_to_num(((cut.lo[node] - dil) - o) * iv, nan=-float("inf"))
        tb = torch.nan_to_num(((cut.hi[node] + dil) - o) * iv, nan=float("inf"))
        tn = torch.minimum(ta, tb).amax(-1)
        tf = torch.maximum(ta, tb).amin(-1)
        hit = (tn <= tf) & (tn < t_max[ray])
        lvl = level[ray]
        leaf = (children[node, 0] < 0) | torch.where(lvl < 0, cut.live[node], cut.lod[node].to(lvl.dtype) <= lvl)
        ok = torch.where(tn >= 0, tn > _ENTER_MIN, tf > _EXIT_MIN)
        keep = hit & leaf & ok
        found.append((ray[keep], node[keep], tn[keep], tf[keep]))
        down = hit & ~leaf & (tf > _ENTER_MIN)
        ray = ray[down].repeat_interleave(2)
        node = children[node[down]].reshape(-1)
    r, nd, t0, t1 = (torch.cat(parts) for parts in zip(*found))
    # Lexicographic (ray, t0, node): stable sorts from the last key to the first.
    order = torch.argsort(nd, stable=True)
    order = order[torch.argsort(t0[order], stable=True)]
    order = order[torch.argsort(r[order], stable=True)]
    r, nd, t0, t1 = r[order], nd[order], t0[order], t1[order]
    start = torch.zeros(len(origins) + 1, dtype=torch.long, device=dev)
    start[1:] = torch.cumsum(torch.bincount(r, minlength=len(origins)), 0)
    return LeafList(start, nd, t0, t1)


def list_leaves(origins: Tensor, directions: Tensor, t_max: Tensor, cut: CutArrays, level: Tensor, dilation: Tensor) -> LeafList:
    """The leaves of ``cut`` each ray crosses, sorted by (t0, node), on the rays' device.

    ``origins``/``directions`` [N, 3] float32 in the unit cube (directions unit length);
    ``t_max`` [N]; ``level`` [N] int (-1: the live cut); ``dilation`` [N] leaf-box growth."""
    if origins.device.type == "cpu":
        lanes = SIMD_LIST and len(origins) * SLOTS < 2**31  # (the lanes index the slots in int32)
        return (_list_leaves_simd if lanes else _list_leaves_numba)(origins, directions, t_max, cut, level, dilation)
    if origins.device.type == "cuda":
        from .nbvh_traversal_triton import list_leaves_triton

        return list_leaves_triton(origins, directions, t_max, cut, level, dilation)
    return list_leaves_torch(origins, directions, t_max, cut, level, dilation)


def first_leaves_torch(origins, directions, t_max, cut: CutArrays, level, dilation) -> tuple[Tensor, Tensor, Tensor]:
    leaves = list_leaves_torch(origins, directions, t_max, cut, level, dilation)
    has = leaves.counts > 0
    first = leaves.start[:-1].clamp(max=max(len(leaves.node) - 1, 0))
    if len(leaves.node) == 0:
        inf = torch.full((len(origins),), float("inf"), device=origins.device)
        return torch.full((len(origins),), -1, dtype=torch.long, device=origins.device), inf, inf.clone()
    inf = torch.full_like(leaves.t0[first], float("inf"))
    return (torch.where(has, leaves.node[first], -1), torch.where(has, leaves.t0[first], inf), torch.where(has, leaves.t1[first], inf))


def first_leaves(origins: Tensor, directions: Tensor, t_max: Tensor, cut: CutArrays, level: Tensor, dilation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(node [N] (-1: none), t0 [N], t1 [N]): the first entry `list_leaves` would give each ray (training samples it)."""
    if origins.device.type == "cpu":
        return _first_leaves_numba(origins, directions, t_max, cut, level, dilation)
    if origins.device.type == "cuda":
        from .nbvh_traversal_triton import first_leaves_triton

        return first_leaves_triton(origins, directions, t_max, cut, level, dilation)
    return first_leaves_torch(origins, directions, t_max, cut, level, dilation)

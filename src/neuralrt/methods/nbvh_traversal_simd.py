"""`nbvh_traversal`'s leaf walk for sixteen rays at a time (AVX-512): one ray a lane.

The scalar walk (`nbvh_traversal._walk`) pops a node, tests its box and branches on the outcome;
about 40% of the boxes a ray is tested against are missed, in no pattern a branch predictor
learns, and each ray is one chain of dependent loads. Here each lane walks its own ray with its
own stack (persistent lanes: a lane whose ray ends takes the next one), and a step pops, tests
and pushes in every lane at once with masks instead of branches: the node's box, children and
LoD are gathered, the listed leaves and pushed children scattered.

**The same lists.** Per lane the slab test is `nbvh_traversal._slab`'s float32 operations in its
order (the same bits), the leaf rule and the stack discipline are `_walk`'s, so a ray visits the
same nodes and lists the same leaves. A ray's first leaves (up to a number of slots, `SLOTS` by
default) go to its own slots unsorted; the packing pass (`nbvh_traversal._pack_kernel`) sorts them
by (t0, node) as `_walk`'s callers do, and a ray with more leaves is walked again by `_walk`.
"""

from __future__ import annotations

import numba
import numpy as np

from ..simd16 import (
    bits16, expand16_f32, expand16_i32, gather16_f32, gather16_i32, lane_index16, popcount16, scatter16_f32, scatter16_i32, select16, splat_f32,
    splat_i32, splat_m16, vmax16, vmin16,
)  # fmt: skip

__all__ = ["SLOTS", "walk_lanes"]

# Leaves a ray keeps in its own slots (more: walked again by `_walk`). The bunny's cut, 2^16 rays:
# 2% of the rays list more than 8, 0.1% more than 16 (the list 0.72x the scalar kernel's time
# with 8 slots, 0.62x with 16)
SLOTS = 16


@numba.njit(cache=True, inline="always")
def _slab16(o, inv, lo, hi, dil, tn, tf):
    """One axis of `nbvh_traversal._slab` per lane: the updated (tn, tf)."""
    ta = ((lo - dil) - o) * inv
    tb = ((hi + dil) - o) * inv
    ta = select16(ta != ta, splat_f32(-np.inf), ta)  # 0 * inf: the origin on the slab plane of a parallel ray
    tb = select16(tb != tb, splat_f32(np.inf), tb)
    return vmax16(tn, vmin16(ta, tb)), vmin16(tf, vmax16(ta, tb))


@numba.njit(cache=True)
def walk_lanes(first, stop, ray_ids, ox_, oy_, oz_, ix_, iy_, iz_, t_max, dilation, level, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z,
               child0, child1, leaf_key, stack, enter_min, exit_min, n_slots, slot_node, slot_t0, slot_t1, counts):  # fmt: skip
    """Rays ``[first, stop)`` (``ray_ids``: ``arange`` with 16 spare entries; the rays' values as
    columns: origins, inverse directions, ``t_max``, ``dilation``, ``level`` int32): ``counts[i]``
    leaves listed for ray i, the first ``n_slots`` at ``slot_*[i * n_slots + k]`` in walk order. The cut
    as columns: box corners, children (int32, -1 for none) and ``leaf_key`` (int32: the LoD, plus
    256 where the node is a leaf of the live cut). ``stack``: int32 scratch of 16 x depth."""
    depth = stack.shape[0] // 16
    lane = lane_index16()
    stack_base = lane * splat_i32(depth)
    zero_i, one_i, two_i, slots = splat_i32(0), splat_i32(1), splat_i32(2), splat_i32(n_slots)
    live_bit, lod_bits, depth_v = splat_i32(256), splat_i32(255), splat_i32(depth)
    zero, inf = splat_f32(0.0), splat_f32(np.inf)
    enter_v, exit_v = splat_f32(enter_min), splat_f32(exit_min)
    ray = sp = count = lvl = zero_i
    ox = oy = oz = ix = iy = iz = tmax = dil = zero
    active = splat_m16(False)
    taken = first
    while True:
        if taken < stop and bits16(active) != 0xFFFF:  # idle lanes take the next rays, in order
            take = ~active
            ray = expand16_i32(ray_ids, taken, take, ray)
            take = take & (ray < splat_i32(stop))
            ox, oy, oz = expand16_f32(ox_, taken, take, ox), expand16_f32(oy_, taken, take, oy), expand16_f32(oz_, taken, take, oz)
            ix, iy, iz = expand16_f32(ix_, taken, take, ix), expand16_f32(iy_, taken, take, iy), expand16_f32(iz_, taken, take, iz)
            tmax, dil = expand16_f32(t_max, taken, take, tmax), expand16_f32(dilation, taken, take, dil)
            lvl = expand16_i32(level, taken, take, lvl)
            scatter16_i32(stack, stack_base, zero_i, take)  # the root
            sp = select16(take, one_i, sp)
            count = select16(take, zero_i, count)
            taken += popcount16(take)
            active = active | take
        if bits16(active) == 0:
            return
        sp = select16(active, sp - one_i, sp)
        node = gather16_i32(stack, stack_base + sp, active)
        tn, tf = splat_f32(-np.inf), inf
        tn, tf = _slab16(ox, ix, gather16_f32(lo_x, node, active), gather16_f32(hi_x, node, active), dil, tn, tf)
        tn, tf = _slab16(oy, iy, gather16_f32(lo_y, node, active), gather16_f32(hi_y, node, active), dil, tn, tf)
        tn, tf = _slab16(oz, iz, gather16_f32(lo_z, node, active), gather16_f32(hi_z, node, active), dil, tn, tf)
        crossed = active & (tn <= tf) & (tn < tmax)
        first_child = gather16_i32(child0, node, crossed)
        key = gather16_i32(leaf_key, node, crossed)
        leaf = (first_child < zero_i) | select16(lvl < zero_i, key >= live_bit, (key & lod_bits) <= lvl)
        listed = crossed & leaf & select16(tn >= zero, tn > enter_v, tf > exit_v)
        if bits16(listed) != 0:
            kept = listed & (count < slots)
            slot = ray * slots + count
            scatter16_i32(slot_node, slot, node, kept)
            scatter16_f32(slot_t0, slot, tn, kept)
            scatter16_f32(slot_t1, slot, tf, kept)
            count = count + select16(listed, one_i, zero_i)
        push = crossed & ~leaf & (tf > enter_v) & (sp + two_i <= depth_v)
        if bits16(push) != 0:  # the second child below the first, as `_walk`
            scatter16_i32(stack, stack_base + sp, gather16_i32(child1, node, push), push)
            scatter16_i32(stack, stack_base + sp + one_i, first_child, push)
            sp = sp + select16(push, two_i, zero_i)
        done = active & (sp == zero_i)
        if bits16(done) != 0:
            scatter16_i32(counts, ray, count, done)
            active = active & ~done

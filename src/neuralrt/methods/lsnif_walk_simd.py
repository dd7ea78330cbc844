"""`lsnif_features.walk_ray` for a group of rays, sixteen rays at a time in float32 (AVX-512).

`walk_ray` walks in float64. Here the start of each ray (slab tests, first voxel, first plane
times) is `walk_ray`'s own float64 arithmetic, 8 rays at a time (`neuralrt.simd`), and the steps
run in float32, 16 lanes per instruction (`neuralrt.simd16`): a lane walks one ray, and takes the
next queued one when its ray ends (persistent lanes).

**The same decisions as `walk_ray`.** Plane times ``(k / V - o) / d`` are computed from the plane
equation in both, so with a power-of-two V (the planes exact in float32) a float32 time is within
``3u`` (u = 2^-24) of the same exact value as the float64 one, which is within ``4 * 2^-53``. A step
decides as `walk_ray` does wherever the closest plane time is positive and more than a factor ``1 +
2^-20`` below the other two and above the current time: then the same axis is the closest in
float64, ahead of the current time, and times still increase strictly (so a shared boundary point
is recognised the same way). A lane where that does not hold (ties: rays through voxel edges or
corners, starts on a plane) drops its ray, whose points are then discarded and the ray walked
again by `walk_ray`; so are rays whose values do not fit float32's range well (``|o| > 2^30`` or
``|1/d| > 2^60``, e.g. denormal directions). So the counts, the points' voxels, face codes and
slots, and ``t_enter``/``t_exit`` are `walk_ray`'s exactly.

**Coordinates to float32 rounding.** A point on its crossed plane takes the plane's value (exact);
its other two coordinates are ``o + t * d`` clamped to the voxel, computed in float32 rather than
rounded from float64: within ``2^-21 * (2 + |o|)`` of `walk_ray`'s (tested), so the encoder's
inputs move by a few ulps. V that are not powers of two keep `walk_ray` in the fused pass.

The points are written unordered (in the order the lanes emit them: compress stores, no
scatters), each with its ray and its slot in the ray's point list, which is what the fused pass
needs (`lsnif_fused_cpu`: a point's network inputs go to its ray's row, at its slot), and with
its local distance, computed by its lane with `lsnif_features.local_distance`'s float32
operations (the same bits as that scalar code on the same point).

On the 2-core Zen 5 development machine, for 2^17 hairball(6) `lq` rays on one thread, the steps
of this walk take ~4.6 ms against ~7.6 ms for the earlier 8-lane float64 walk, the whole walk
with its start ~5.9 against ~8.9 ms (docs/lsnif.md, "Session 32"). Session 37 (the occupancy
as bits, each cell's gathered one step ahead, the voxel bounds computed rather than carried,
the start without gathers): the whole walk 5.27 against 6.37 ms, alternating in one process
(groups of 128 rays, as the fused pass walks them). Where the CPU lacks AVX-512,
LLVM lowers the same code to scalar loops (correct, slower): the fused pass then uses `walk_ray`.
"""

from __future__ import annotations

import numba
import numpy as np

from ..simd import (
    compress_store_f32, floor_i64, gather_i32, lane_index, load_f64, popcount8, select, splat_f64, splat_i64, to_f64, vmax, vmin,
)  # fmt: skip
from ..simd16 import (
    bits16, compress16_f32, compress16_i32, compress_store_i32, expand16_f32, expand16_i32, gather16_i32, load16, popcount16,
    scatter16_i32, scatter16_i64, select16, splat_f32, splat_i32, splat_m16, store16, to_f32, vmax16, vmin16,
)  # fmt: skip
from .lsnif_features import MIN_SPAN, ORIGIN_POINT, local_distance, walk_ray

__all__ = ["walk_group", "walk_scratch", "float32_walk_applies", "occupancy_bits"]

# The queue of a group's rays that enter the box, one column per ray (float32 rows, then int32):
_OX, _OY, _OZ, _DX, _DY, _DZ, _INV_X, _INV_Y, _INV_Z, _TX, _TY, _TZ, _T_CUR, _T_EXIT = range(14)
_RAY, _SX, _SY, _SZ, _IX, _IY, _IZ, _CODE, _OCC = range(9)  # _OCC: the first cell's occupancy (0 or 1)
_FLOAT_ROWS, _INT_ROWS = 14, 9
_SPARE = 16  # columns past the last ray: a refill reads up to 16 entries
# A step is decided in float32 where the closest plane time beats the others and the current time
# by this factor (float32 times are within 3u of the exact ones, float64 times within 2^-51)
_MARGIN = 1.0 + 2.0**-20
_TINY = 2.0**-100  # closest plane times below this (zero, negative, denormal) are not decided in float32
_O_LIMIT, _INV_LIMIT = 2.0**30, 2.0**60


def float32_walk_applies(res: int) -> bool:
    """Whether `walk_group` walks a ``res^3`` grid: V a power of two (planes ``k / V`` exact in float32)."""
    return res >= 1 and res & (res - 1) == 0


def occupancy_bits(occ: np.ndarray) -> np.ndarray:
    """``occ`` (``[V, V, V]`` bool) as the bits `walk_group` reads: cell ``(i * V + j) * V + k`` is bit
    ``c % 32`` of int32 word ``c // 32``. A 32^3 grid takes 4 KiB, which stays in L1 while the hash
    table's reads pass through (an int32 per cell took 128 KiB)."""
    bits = np.packbits(np.ascontiguousarray(occ, dtype=np.bool_).reshape(-1), bitorder="little")
    words = np.zeros(-(-bits.size // 4) * 4, np.uint8)
    words[: bits.size] = bits
    return words.view("<i4").copy()


@numba.njit(cache=True)
def walk_scratch(group):
    """A thread's scratch for `walk_group` on groups of up to ``group`` rays: the queue (float32
    and int32 rows, flat; `_SPARE` columns after the last ray, whose sentinel is ray -1), two
    batches of 8 rays' origins and directions (float64), the 16 lanes' terms of their local distances (float32), and
    the list of rays `walk_ray` walks again."""
    columns = group + _SPARE
    return (np.empty(_FLOAT_ROWS * columns, np.float32), np.empty(_INT_ROWS * columns, np.int32), np.empty(96),
            np.empty(32, np.float32), np.empty(group + _SPARE, np.int32))  # fmt: skip


@numba.njit(cache=True, inline="always")
def _slab8(o, d, zero, one, zero_i, one_i, inf):
    """`lsnif_features._slab` per lane: (step, 1/d, t_near, t_far, ok)."""
    flat = d == zero
    inv = select(flat, zero, one / d)
    ta = (zero - o) * inv
    tb = (one - o) * inv
    near = select(flat, zero - inf, vmin(ta, tb))
    far = select(flat, inf, vmax(ta, tb))
    step = select(flat, zero_i, select(d > zero, one_i, zero_i - one_i))
    return step, inv, near, far, ~flat | ((o >= zero) & (o <= one))


@numba.njit(cache=True, inline="always")
def _start_index8(o, d, t, s, res_f, last, zero_i, on_entry_face, ok, zero):
    """`lsnif_features._start_index` per lane (lanes not ``ok`` give some index in range)."""
    f = select(ok, (o + t * d) * res_f, zero)
    i = floor_i64(f)
    i = select((s < zero_i) & (f == to_f64(i)), i - splat_i64(1), i)
    i = vmin(vmax(i, zero_i), last)
    return select(on_entry_face, select(s > zero_i, zero_i, last), i)


@numba.njit(cache=True, inline="always")
def _plane_time8(inv_res, o, inv, i, s, zero_i, one_i, inf):
    """`lsnif_features._plane_time` per lane (its planes ``k / V``: ``k * (1 / V)``, the same value for a power-of-two V)."""
    plane = to_f64(i + select(s > zero_i, one_i, zero_i)) * inv_res
    return select(s == zero_i, inf, (plane - o) * inv)


@numba.njit(cache=True, inline="always")
def _in_range8(x, limit):
    return (x <= limit) & (x >= splat_f64(0.0) - limit)


@numba.njit(cache=True, inline="always")
def _widen8(origins, directions, first, g0, n, rays8, at):
    """Rays ``first + g0 ...`` (8, the last repeated past ``n``) widened to float64 lanes at ``rays8[at:at + 48]``."""
    m = min(8, n - g0)
    for k in range(8):
        r = first + g0 + (k if k < m else 0)
        for c in range(3):
            rays8[at + c * 8 + k] = origins[r, c]
            rays8[at + (3 + c) * 8 + k] = directions[r, c]


@numba.njit(cache=True)
def _start_group(origins, directions, first, n, res, occ_bits, queue, queue_i, rays8, redo, t_enter, t_exit):
    """The start of `walk_ray` for rays ``[first, first + n)``, 8 at a time in float64: writes their
    ``t_enter``/``t_exit``, queues (rounded to float32) those that enter the box, and lists in
    ``redo`` those that enter it with values out of float32's comfortable range; returns (queued,
    listed)."""
    zero, one, inf = splat_f64(0.0), splat_f64(1.0), splat_f64(np.inf)
    zero_i, one_i, two_i = splat_i64(0), splat_i64(1), splat_i64(2)
    res_f = splat_f64(np.float64(res))
    inv_res = splat_f64(1.0 / res)
    res_i, five, low_bits = splat_i64(res), splat_i64(5), splat_i64(31)
    last = splat_i64(res - 1)
    o_limit, inv_limit = splat_f64(_O_LIMIT), splat_f64(_INV_LIMIT)
    columns = queue.shape[0] // _FLOAT_ROWS
    n_queued = 0
    n_redo = 0
    _widen8(origins, directions, first, 0, n, rays8, 0)
    for g0 in range(0, n, 8):
        m = min(8, n - g0)
        # The rays' float32 origins and directions, widened, as lanes: written one batch ahead, in
        # two halves (a vector load of just-stored scalars waits for them to reach the cache)
        half = ((g0 >> 3) & 1) * 48
        ox, oy, oz = load_f64(rays8, half), load_f64(rays8, half + 8), load_f64(rays8, half + 16)
        dx, dy, dz = load_f64(rays8, half + 24), load_f64(rays8, half + 32), load_f64(rays8, half + 40)
        if g0 + 8 < n:
            _widen8(origins, directions, first, g0 + 8, n, rays8, 48 - half)
        lanes = lane_index() < splat_i64(m)
        total = ox + oy + oz + dx + dy + dz
        ok = lanes & ((total - total) == zero) & ~((dx == zero) & (dy == zero) & (dz == zero))  # finite, not zero
        sx, inv_x, nx, fx, okx = _slab8(ox, dx, zero, one, zero_i, one_i, inf)
        sy, inv_y, ny, fy, oky = _slab8(oy, dy, zero, one, zero_i, one_i, inf)
        sz, inv_z, nz, fz, okz = _slab8(oz, dz, zero, one, zero_i, one_i, inf)
        ok = ok & okx & oky & okz
        t_near, near_axis = nx, zero_i
        later = ny > t_near
        t_near, near_axis = select(later, ny, t_near), select(later, one_i, near_axis)
        later = nz > t_near
        t_near, near_axis = select(later, nz, t_near), select(later, two_i, near_axis)
        t_far = vmin(fx, vmin(fy, fz))
        inside = t_near < zero
        t_cur = select(inside, zero, t_near)
        ok = ok & (t_cur < t_far)
        ix = _start_index8(ox, dx, t_cur, sx, res_f, last, zero_i, ~inside & (near_axis == zero_i), ok, zero)
        iy = _start_index8(oy, dy, t_cur, sy, res_f, last, zero_i, ~inside & (near_axis == one_i), ok, zero)
        iz = _start_index8(oz, dz, t_cur, sz, res_f, last, zero_i, ~inside & (near_axis == two_i), ok, zero)
        compress_store_f32(t_enter, first + g0, select(ok, t_cur, inf), lanes)  # a prefix mask: a plain store
        compress_store_f32(t_exit, first + g0, select(ok, t_far, inf), lanes)
        fits = (_in_range8(ox, o_limit) & _in_range8(oy, o_limit) & _in_range8(oz, o_limit) & _in_range8(inv_x, inv_limit)
                & _in_range8(inv_y, inv_limit) & _in_range8(inv_z, inv_limit))  # fmt: skip
        ray = lane_index() + splat_i64(g0)
        cell = (ix * res_i + iy) * res_i + iz
        occupied = (gather_i32(occ_bits, cell >> five, ok) >> (cell & low_bits)) & one_i
        compress_store_i32(redo, n_redo, ray, ok & ~fits)
        n_redo += popcount8(ok & ~fits)
        ok = ok & fits
        for row, value in ((_OX, ox), (_OY, oy), (_OZ, oz), (_DX, dx), (_DY, dy), (_DZ, dz), (_INV_X, inv_x), (_INV_Y, inv_y),
                           (_INV_Z, inv_z), (_T_CUR, t_cur), (_T_EXIT, t_far)):  # fmt: skip
            compress_store_f32(queue, row * columns + n_queued, value, ok)
        compress_store_f32(queue, _TX * columns + n_queued, _plane_time8(inv_res, ox, inv_x, ix, sx, zero_i, one_i, inf), ok)
        compress_store_f32(queue, _TY * columns + n_queued, _plane_time8(inv_res, oy, inv_y, iy, sy, zero_i, one_i, inf), ok)
        compress_store_f32(queue, _TZ * columns + n_queued, _plane_time8(inv_res, oz, inv_z, iz, sz, zero_i, one_i, inf), ok)
        for row, value in ((_RAY, ray), (_SX, sx), (_SY, sy), (_SZ, sz), (_IX, ix), (_IY, iy), (_IZ, iz),
                           (_CODE, select(inside, splat_i64(ORIGIN_POINT), near_axis)), (_OCC, occupied)):  # fmt: skip
            compress_store_i32(queue_i, row * columns + n_queued, value, ok)
        n_queued += popcount8(ok)
    for k in range(_SPARE):
        queue_i[_RAY * columns + n_queued + k] = -1  # the refill stops here
    return n_queued, n_redo


@numba.njit(cache=True, inline="always")
def _point16(on_plane, exiting, positive, o, d, t, lo, hi):
    """`lsnif_features._coord` per lane: on the crossed plane, ``hi`` where (step > 0) == exiting, else
    ``lo``; off it, ``o + t * d`` clamped to the voxel."""
    plane = select16(positive, hi, lo) if exiting else select16(positive, lo, hi)
    return select16(on_plane, plane, vmin16(vmax16(o + t * d, lo), hi))


@numba.njit(cache=True, inline="always")
def _local_distance16(px, py, pz, ox, oy, oz, dx, dy, dz, dd, te, span, zero, one):
    """`lsnif_features.local_distance` per lane (``dd``, ``span`` its ray's terms): the same float32 operations."""
    t = ((px - ox) * dx + (py - oy) * dy + (pz - oz) * dz) / dd
    return vmin16(vmax16((t - te) / span, zero), one)


@numba.njit(cache=True, inline="always")
def _store16(point_x, point_y, point_z, point_local, point_code, point_ray, point_slot, e, mask, px, py, pz, local, code, ray, slot):
    """The points of the lanes of ``mask`` appended at ``e`` of the ``point_*`` arrays (compress
    stores); returns the new number of points."""
    compress16_f32(point_x, e, px, mask)
    compress16_f32(point_y, e, py, mask)
    compress16_f32(point_z, e, pz, mask)
    compress16_f32(point_local, e, local, mask)
    compress16_i32(point_code, e, code, mask)
    compress16_i32(point_ray, e, ray, mask)
    compress16_i32(point_slot, e, slot, mask)
    return e + popcount16(mask)


@numba.njit(cache=True)
def _walk_lanes(queue, queue_i, n_queued, occ_bits, res, max_points, origin_point, share, redo, n_redo, lane_terms,
                point_x, point_y, point_z, point_local, point_code, point_ray, point_slot, counts, truncated_rays):  # fmt: skip
    """The steps of the queued rays, 16 lanes at a time: writes their points and their local
    distances (`lsnif_features.local_distance`; returns their number and the length of ``redo``,
    where the rays dropped on an undecided step are appended), the counts of the rays walked to
    their end and a 1 in ``truncated_rays`` for those that had more points than H."""
    columns = queue.shape[0] // _FLOAT_ROWS
    inf = splat_f32(np.inf)
    zero, zero_i, one_i, two_i = splat_f32(0.0), splat_i32(0), splat_i32(1), splat_i32(2)
    one, margin, tiny, min_span = splat_f32(1.0), splat_f32(_MARGIN), splat_f32(_TINY), splat_f32(MIN_SPAN)
    origin_code = splat_i32(ORIGIN_POINT)
    res_v = splat_i32(res)
    five_i, low_bits = splat_i32(5), splat_i32(31)  # a cell's word and bit in occ_bits
    inv_res = splat_f32(np.float32(1.0 / res))  # exact: V a power of two
    full = splat_i32(max_points)
    share_v = splat_m16(share)
    skip_origin = splat_m16(not origin_point)
    ox = oy = oz = dx = dy = dz = inv_x = inv_y = inv_z = tx = ty = tz = t_cur = zero
    last_t = splat_f32(-np.inf)
    ray = sx = sy = sz = ix = iy = iz = code = count = occ_lane = zero_i
    active = splat_m16(False)
    taken = 0  # queue entries handed to lanes
    e = 0
    while True:
        if taken < n_queued and bits16(active) != 0xFFFF:  # refill idle lanes, in queue order
            take = ~active
            ray = expand16_i32(queue_i, _RAY * columns + taken, take, ray)
            take = take & (ray >= zero_i)
            ox = expand16_f32(queue, _OX * columns + taken, take, ox)
            oy = expand16_f32(queue, _OY * columns + taken, take, oy)
            oz = expand16_f32(queue, _OZ * columns + taken, take, oz)
            dx = expand16_f32(queue, _DX * columns + taken, take, dx)
            dy = expand16_f32(queue, _DY * columns + taken, take, dy)
            dz = expand16_f32(queue, _DZ * columns + taken, take, dz)
            inv_x = expand16_f32(queue, _INV_X * columns + taken, take, inv_x)
            inv_y = expand16_f32(queue, _INV_Y * columns + taken, take, inv_y)
            inv_z = expand16_f32(queue, _INV_Z * columns + taken, take, inv_z)
            tx = expand16_f32(queue, _TX * columns + taken, take, tx)
            ty = expand16_f32(queue, _TY * columns + taken, take, ty)
            tz = expand16_f32(queue, _TZ * columns + taken, take, tz)
            t_cur = expand16_f32(queue, _T_CUR * columns + taken, take, t_cur)
            sx = expand16_i32(queue_i, _SX * columns + taken, take, sx)
            sy = expand16_i32(queue_i, _SY * columns + taken, take, sy)
            sz = expand16_i32(queue_i, _SZ * columns + taken, take, sz)
            ix = expand16_i32(queue_i, _IX * columns + taken, take, ix)
            iy = expand16_i32(queue_i, _IY * columns + taken, take, iy)
            iz = expand16_i32(queue_i, _IZ * columns + taken, take, iz)
            code = expand16_i32(queue_i, _CODE * columns + taken, take, code)
            occ_lane = expand16_i32(queue_i, _OCC * columns + taken, take, occ_lane)
            # the rays' t_enter (their start time) and span for their local distances, kept in memory (registers are scarce)
            te = expand16_f32(queue, _T_CUR * columns + taken, take, load16(lane_terms, 0))
            t_exit = expand16_f32(queue, _T_EXIT * columns + taken, take, te)
            store16(lane_terms, 0, te)
            store16(lane_terms, 16, select16(take, vmax16(t_exit - te, min_span), load16(lane_terms, 16)))
            count = select16(take, zero_i, count)
            last_t = select16(take, splat_f32(-np.inf), last_t)
            taken += popcount16(take)
            active = active | take
        if bits16(active) == 0:
            return e, n_redo
        # The closest plane; strict < so ties go to the lower axis (as walk_ray)
        y_before_x = ty < tx
        is_z = select16(y_before_x, tz < ty, tz < tx)
        is_y = y_before_x & ~is_z
        is_x = ~(is_z | is_y)
        t_next = select16(is_z, tz, select16(is_y, ty, tx))
        axis = select16(is_z, two_i, select16(is_y, one_i, zero_i))
        ended = active & (t_next == inf)  # no plane ahead on any axis
        live = active & ~ended
        # Decided as in float64 (module docstring), else the ray goes to walk_ray
        beaten = t_next * margin
        decided = ((t_next >= tiny) & (t_next > t_cur * margin) & (is_x | (tx > beaten)) & (is_y | (ty > beaten))
                   & (is_z | (tz > beaten)))  # fmt: skip
        undecided = live & ~decided
        if bits16(undecided) != 0:
            compress16_i32(redo, n_redo, ray, undecided)
            n_redo += popcount16(undecided)
            live = live & ~undecided
            active = active & ~undecided
        occupied = occ_lane != zero_i
        emit = live & occupied  # (t_next > t_cur where decided)
        if bits16(emit) != 0:
            entry = emit & ~((share_v & (t_cur == last_t)) | ((code == origin_code) & skip_origin))
            full_at_entry = entry & (count == full)
            entry = entry & ~full_at_entry
            positive_x, positive_y, positive_z = sx > zero_i, sy > zero_i, sz > zero_i
            te, span, dd = load16(lane_terms, 0), load16(lane_terms, 16), dx * dx + dy * dy + dz * dz
            # The voxel's bounds k / V and (k + 1) / V, exact in float32 (V a power of two): computed, not
            # carried per lane (six fewer registers and queue rows)
            lo_x, lo_y, lo_z = to_f32(ix) * inv_res, to_f32(iy) * inv_res, to_f32(iz) * inv_res
            hi_x, hi_y, hi_z = lo_x + inv_res, lo_y + inv_res, lo_z + inv_res
            if bits16(entry) != 0:
                px = _point16(code == zero_i, False, positive_x, ox, dx, t_cur, lo_x, hi_x)
                py = _point16(code == one_i, False, positive_y, oy, dy, t_cur, lo_y, hi_y)
                pz = _point16(code == two_i, False, positive_z, oz, dz, t_cur, lo_z, hi_z)
                local = _local_distance16(px, py, pz, ox, oy, oz, dx, dy, dz, dd, te, span, zero, one)
                e = _store16(point_x, point_y, point_z, point_local, point_code, point_ray, point_slot, e, entry, px, py, pz, local, code,
                             ray, count)  # fmt: skip
                count = count + select16(entry, one_i, zero_i)
            leave = emit & ~full_at_entry
            full_at_exit = leave & (count == full)
            leave = leave & ~full_at_exit
            px = _point16(is_x, True, positive_x, ox, dx, t_next, lo_x, hi_x)
            py = _point16(is_y, True, positive_y, oy, dy, t_next, lo_y, hi_y)
            pz = _point16(is_z, True, positive_z, oz, dz, t_next, lo_z, hi_z)
            local = _local_distance16(px, py, pz, ox, oy, oz, dx, dy, dz, dd, te, span, zero, one)
            e = _store16(point_x, point_y, point_z, point_local, point_code, point_ray, point_slot, e, leave, px, py, pz, local, axis,
                         ray, count)  # fmt: skip
            count = count + select16(leave, one_i, zero_i)
            last_t = select16(leave, t_next, last_t)
            truncated = full_at_entry | full_at_exit
            if bits16(truncated) != 0:
                scatter16_i32(truncated_rays, ray, one_i, truncated)
            ended = ended | truncated
            live = live & ~truncated
        # Step the closest plane's axis; only its plane time and bounds change
        ix = ix + select16(is_x, sx, zero_i)
        iy = iy + select16(is_y, sy, zero_i)
        iz = iz + select16(is_z, sz, zero_i)
        stepped = select16(is_z, iz, select16(is_y, iy, ix))
        left = live & ((stepped < zero_i) | (stepped >= res_v))
        live = live & ~left
        # The next cell's occupancy, gathered here rather than at the next step's start: the gather's
        # latency overlaps the rest of this step and the refill
        cell = (ix * res_v + iy) * res_v + iz
        occ_lane = (gather16_i32(occ_bits, cell >> five_i, live) >> (cell & low_bits)) & one_i
        s = select16(is_z, sz, select16(is_y, sy, sx))
        o = select16(is_z, oz, select16(is_y, oy, ox))
        inv = select16(is_z, inv_z, select16(is_y, inv_y, inv_x))
        plane = to_f32(stepped + select16(s > zero_i, one_i, zero_i)) * inv_res  # the next plane, k / V exactly
        t_plane = (plane - o) * inv
        tx = select16(is_x, t_plane, tx)
        ty = select16(is_y, t_plane, ty)
        tz = select16(is_z, t_plane, tz)
        t_cur = t_next
        code = axis
        done = ended | left
        if bits16(done) != 0:
            scatter16_i64(counts, ray, count, done)
            active = active & ~done


@numba.njit(cache=True)
def _walk_again(origins, directions, first, occ, planes, max_points, origin_point, share, redo, n_redo, pts, axes, e,
                point_x, point_y, point_z, point_local, point_code, point_ray, point_slot, counts, truncated, t_enter, t_exit):  # fmt: skip
    """The rays listed in ``redo`` by `walk_ray`: their points from the lanes dropped from the list,
    `walk_ray`'s appended; returns the new number of points."""
    for k in range(n_redo):
        counts[redo[k]] = -1
    kept = 0
    for i in range(e):
        if counts[point_ray[i]] >= 0:
            point_x[kept], point_y[kept], point_z[kept], point_local[kept] = point_x[i], point_y[i], point_z[i], point_local[i]
            point_code[kept], point_ray[kept], point_slot[kept] = point_code[i], point_ray[i], point_slot[i]
            kept += 1
    for k in range(n_redo):
        g = redo[k]
        r = first + g
        count, cut, _, _ = walk_ray(np.float64(origins[r, 0]), np.float64(origins[r, 1]), np.float64(origins[r, 2]),
                                    np.float64(directions[r, 0]), np.float64(directions[r, 1]), np.float64(directions[r, 2]),
                                    occ, planes, max_points, origin_point, share, pts, axes, g)  # fmt: skip
        counts[g] = count
        truncated[g] = cut
        for h in range(count):
            px, py, pz = pts[g, h, 0], pts[g, h, 1], pts[g, h, 2]
            point_x[kept], point_y[kept], point_z[kept] = px, py, pz
            point_local[kept] = local_distance(px, py, pz, origins[r, 0], origins[r, 1], origins[r, 2], directions[r, 0],
                                               directions[r, 1], directions[r, 2], t_enter[r], t_exit[r])  # fmt: skip
            point_code[kept], point_ray[kept], point_slot[kept] = axes[g, h], g, h
            kept += 1
    return kept


@numba.njit(cache=True)
def walk_group(origins, directions, first, n, occ, occ_bits, planes, max_points, origin_point, share, queue, queue_i, rays8,
               lane_terms, redo, pts, axes, point_x, point_y, point_z, point_local, point_code, point_ray, point_slot, counts, truncated,
               t_enter, t_exit):  # fmt: skip
    """`walk_ray` for rays ``[first, first + n)`` (``n`` <= the scratch's group; `walk_scratch`) on
    the grid ``occ`` (``[V, V, V]``, V a power of two; ``occ_bits``: `occupancy_bits` of it;
    ``planes``: ``k / V``, float64): ``counts[g]`` and ``truncated[g]`` (int32, 1 where the ray had
    more points than H) for ray ``first + g``, ``t_enter``/``t_exit`` at ``first + g``; returns the
    number of points, written to ``point_*[:e]`` in no particular order: coordinates and local distance (`lsnif_features.local_distance`, float32), face code,
    ray ``g`` and slot (the point's index in its ray's list), int32. ``pts``/``axes`` (``[group, H,
    3]`` float32, ``[group, H]`` int8): scratch for `walk_ray`."""
    n_queued, n_redo = _start_group(origins, directions, first, n, occ.shape[0], occ_bits, queue, queue_i, rays8, redo, t_enter, t_exit)
    for g in range(n):
        counts[g] = 0
        truncated[g] = 0
    e, n_redo = _walk_lanes(queue, queue_i, n_queued, occ_bits, occ.shape[0], max_points, origin_point, share, redo, n_redo,
                            lane_terms, point_x, point_y, point_z, point_local, point_code, point_ray, point_slot, counts,
                            truncated)  # fmt: skip
    if n_redo > 0:
        e = _walk_again(origins, directions, first, occ, planes, max_points, origin_point, share, redo, n_redo, pts, axes, e,
                        point_x, point_y, point_z, point_local, point_code, point_ray, point_slot, counts, truncated, t_enter,
                        t_exit)  # fmt: skip
    return e

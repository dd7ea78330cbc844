"""The voxel walk of `lsnif_features.walk_ray` for a group of rays, eight rays at a time (AVX-512).

Same decisions and the same float64 arithmetic as `walk_ray`, lane by lane (`neuralrt.simd`
vectors: no fused multiply-adds, numba's min/max), so the points are bit for bit the scalar
walk's; what differs is their order. Eight lanes each walk one ray; a lane whose ray ends takes
the next queued one (persistent lanes, so a group does not wait for its longest ray 8 times over).
The starts (slab tests, first voxel, first plane times) are computed 8 rays at a time too, and
the rays that enter the box are queued densely (compress stores); a lane is refilled from the
queue with expand loads.

The points are written unordered (in the order the lanes emit them: compress stores, no
scatters), each with its ray and its slot in the ray's point list, which is what the fused
pass needs (`lsnif_fused_cpu`: a point's network inputs go to its ray's row, at its slot).

On the 2-core Zen 5 development machine, for 2^17 hairball(6) rays (`hq`, H = 18), this walk takes
~7.3 ms against ~9.8 ms for `walk_ray` (ad hoc, both threads). Where the CPU lacks AVX-512 LLVM
lowers the same code to scalar loops (correct, slower): the fused pass then uses `walk_ray`.
"""

from __future__ import annotations

import numba
import numpy as np

from ..simd import (
    bits8, compress_store_f32, compress_store_f64, compress_store_i64, expand_f64, expand_i64, floor_i64, gather_f64, gather_i32,
    lane_index, load_f64, popcount8, scatter_i64, select, splat_f64, splat_i64, splat_m8, to_f64, vmax, vmin,
)  # fmt: skip
from .lsnif_features import ORIGIN_POINT

__all__ = ["walk_group", "walk_scratch"]

# The queue of a group's rays that enter the box, one column per ray (float64 rows, then int64):
_OX, _OY, _OZ, _DX, _DY, _DZ, _INV_X, _INV_Y, _INV_Z, _TX, _TY, _TZ, _T_CUR, _LO_X, _LO_Y, _LO_Z, _HI_X, _HI_Y, _HI_Z = range(19)
_RAY, _SX, _SY, _SZ, _IX, _IY, _IZ, _CODE = range(8)
_FLOAT_ROWS, _INT_ROWS = 19, 8


@numba.njit(cache=True)
def walk_scratch(group):
    """A thread's scratch for `walk_group` on groups of up to ``group`` rays: the queue (float64
    and int64 rows; 8 spare columns, as the refill reads up to 8 entries past the last ray, whose
    sentinel is ray -1) and 8 rays' origins and directions."""
    return np.empty((_FLOAT_ROWS, group + 8)), np.empty((_INT_ROWS, group + 8), np.int64), np.empty(48)


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
def _plane_time8(planes, o, inv, i, s, zero_i, one_i, inf, ok):
    """`lsnif_features._plane_time` per lane."""
    plane = gather_f64(planes, i + select(s > zero_i, one_i, zero_i), ok & (s != zero_i), inf)
    return select(s == zero_i, inf, (plane - o) * inv)


@numba.njit(cache=True)
def _start_group(origins, directions, first, n, res, planes, queue, queue_i, rays8, t_enter, t_exit):
    """The start of `walk_ray` for rays ``[first, first + n)``, 8 at a time: writes their
    ``t_enter``/``t_exit`` and queues those that enter the box; returns how many it queued."""
    zero, one, inf = splat_f64(0.0), splat_f64(1.0), splat_f64(np.inf)
    zero_i, one_i, two_i = splat_i64(0), splat_i64(1), splat_i64(2)
    res_f = splat_f64(np.float64(res))
    last = splat_i64(res - 1)
    columns = queue.shape[1]
    qf = queue.reshape(-1)
    qi = queue_i.reshape(-1)
    n_queued = 0
    for g0 in range(0, n, 8):
        m = min(8, n - g0)
        for k in range(8):  # the rays' float32 origins and directions, widened, as lanes
            r = first + g0 + (k if k < m else 0)
            for c in range(3):
                rays8[c * 8 + k] = origins[r, c]
                rays8[(3 + c) * 8 + k] = directions[r, c]
        lanes = lane_index() < splat_i64(m)
        ox, oy, oz = load_f64(rays8, 0), load_f64(rays8, 8), load_f64(rays8, 16)
        dx, dy, dz = load_f64(rays8, 24), load_f64(rays8, 32), load_f64(rays8, 40)
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
        for row, value in ((_OX, ox), (_OY, oy), (_OZ, oz), (_DX, dx), (_DY, dy), (_DZ, dz), (_INV_X, inv_x), (_INV_Y, inv_y),
                           (_INV_Z, inv_z), (_T_CUR, t_cur)):  # fmt: skip
            compress_store_f64(qf, row * columns + n_queued, value, ok)
        compress_store_f64(qf, _TX * columns + n_queued, _plane_time8(planes, ox, inv_x, ix, sx, zero_i, one_i, inf, ok), ok)
        compress_store_f64(qf, _TY * columns + n_queued, _plane_time8(planes, oy, inv_y, iy, sy, zero_i, one_i, inf, ok), ok)
        compress_store_f64(qf, _TZ * columns + n_queued, _plane_time8(planes, oz, inv_z, iz, sz, zero_i, one_i, inf, ok), ok)
        for row, i in ((_LO_X, ix), (_LO_Y, iy), (_LO_Z, iz)):
            compress_store_f64(qf, row * columns + n_queued, gather_f64(planes, i, ok, zero), ok)
            compress_store_f64(qf, (row + 3) * columns + n_queued, gather_f64(planes, i + one_i, ok, zero), ok)
        for row, value in ((_RAY, lane_index() + splat_i64(g0)), (_SX, sx), (_SY, sy), (_SZ, sz), (_IX, ix), (_IY, iy), (_IZ, iz),
                           (_CODE, select(inside, splat_i64(ORIGIN_POINT), near_axis))):  # fmt: skip
            compress_store_i64(qi, row * columns + n_queued, value, ok)
        n_queued += popcount8(ok)
    for k in range(8):
        queue_i[_RAY, n_queued + k] = -1  # the refill stops here
    return n_queued


@numba.njit(cache=True, inline="always")
def _point8(on_plane, exiting, positive, o, d, t, lo, hi):
    """`lsnif_features._coord` per lane: on the crossed plane, ``hi`` where (step > 0) == exiting, else
    ``lo``; off it, ``o + t * d`` clamped to the voxel."""
    plane = select(positive, hi, lo) if exiting else select(positive, lo, hi)
    return select(on_plane, plane, vmin(vmax(o + t * d, lo), hi))


@numba.njit(cache=True)
def walk_group(origins, directions, first, n, occ_cells, res, planes, max_points, origin_point, share, queue, queue_i, rays8,
               point_x, point_y, point_z, point_code, point_ray, point_slot, counts, t_enter, t_exit):  # fmt: skip
    """`walk_ray` for rays ``[first, first + n)`` (``n`` <= the scratch's group; `walk_scratch`):
    ``counts[g]`` for ray ``first + g``, ``t_enter``/``t_exit`` at ``first + g``; returns the number
    of points, written to ``point_*[:e]`` in no particular order: coordinates (float32), face code,
    ray ``g`` and slot (the point's index in its ray's list). ``occ_cells``: the occupancy as int32,
    flat (``[V^3]``); ``planes``: ``k / V`` (float64, ``V + 1``)."""
    n_queued = _start_group(origins, directions, first, n, res, planes, queue, queue_i, rays8, t_enter, t_exit)
    for g in range(n):
        counts[g] = 0
    columns = queue.shape[1]
    qf = queue.reshape(-1)
    qi = queue_i.reshape(-1)
    inf = splat_f64(np.inf)
    zero, zero_i, one_i, two_i = splat_f64(0.0), splat_i64(0), splat_i64(1), splat_i64(2)
    origin_code = splat_i64(ORIGIN_POINT)
    res_v = splat_i64(res)
    res_f = splat_f64(np.float64(res))
    full = splat_i64(max_points)
    share_v = splat_m8(share)
    skip_origin = splat_m8(not origin_point)
    ox = oy = oz = dx = dy = dz = inv_x = inv_y = inv_z = tx = ty = tz = t_cur = lo_x = lo_y = lo_z = hi_x = hi_y = hi_z = zero
    last_t = splat_f64(-np.inf)
    ray = sx = sy = sz = ix = iy = iz = code = count = zero_i
    active = splat_m8(False)
    taken = 0  # queue entries handed to lanes
    e = 0
    while True:
        if taken < n_queued and bits8(active) != 0xFF:  # refill idle lanes, in queue order
            take = ~active
            ray = expand_i64(qi, _RAY * columns + taken, take, ray)
            take = take & (ray >= zero_i)
            ox = expand_f64(qf, _OX * columns + taken, take, ox)
            oy = expand_f64(qf, _OY * columns + taken, take, oy)
            oz = expand_f64(qf, _OZ * columns + taken, take, oz)
            dx = expand_f64(qf, _DX * columns + taken, take, dx)
            dy = expand_f64(qf, _DY * columns + taken, take, dy)
            dz = expand_f64(qf, _DZ * columns + taken, take, dz)
            inv_x = expand_f64(qf, _INV_X * columns + taken, take, inv_x)
            inv_y = expand_f64(qf, _INV_Y * columns + taken, take, inv_y)
            inv_z = expand_f64(qf, _INV_Z * columns + taken, take, inv_z)
            tx = expand_f64(qf, _TX * columns + taken, take, tx)
            ty = expand_f64(qf, _TY * columns + taken, take, ty)
            tz = expand_f64(qf, _TZ * columns + taken, take, tz)
            t_cur = expand_f64(qf, _T_CUR * columns + taken, take, t_cur)
            lo_x = expand_f64(qf, _LO_X * columns + taken, take, lo_x)
            lo_y = expand_f64(qf, _LO_Y * columns + taken, take, lo_y)
            lo_z = expand_f64(qf, _LO_Z * columns + taken, take, lo_z)
            hi_x = expand_f64(qf, _HI_X * columns + taken, take, hi_x)
            hi_y = expand_f64(qf, _HI_Y * columns + taken, take, hi_y)
            hi_z = expand_f64(qf, _HI_Z * columns + taken, take, hi_z)
            sx = expand_i64(qi, _SX * columns + taken, take, sx)
            sy = expand_i64(qi, _SY * columns + taken, take, sy)
            sz = expand_i64(qi, _SZ * columns + taken, take, sz)
            ix = expand_i64(qi, _IX * columns + taken, take, ix)
            iy = expand_i64(qi, _IY * columns + taken, take, iy)
            iz = expand_i64(qi, _IZ * columns + taken, take, iz)
            code = expand_i64(qi, _CODE * columns + taken, take, code)
            count = select(take, zero_i, count)
            last_t = select(take, splat_f64(-np.inf), last_t)
            taken += popcount8(take)
            active = active | take
        if bits8(active) == 0:
            return e
        # The closest plane; strict < so ties go to the lower axis (as walk_ray)
        y_before_x = ty < tx
        is_z = select(y_before_x, tz < ty, tz < tx)
        is_y = y_before_x & ~is_z
        is_x = ~(is_z | is_y)
        t_next = select(is_z, tz, select(is_y, ty, tx))
        axis = select(is_z, two_i, select(is_y, one_i, zero_i))
        ended = active & (t_next == inf)  # plane times overflowed: nothing to walk
        live = active & ~ended
        t_next = vmax(t_next, t_cur)
        occupied = gather_i32(occ_cells, (ix * res_v + iy) * res_v + iz, live) != zero_i
        emit = live & occupied & (t_next > t_cur)
        if bits8(emit) != 0:
            entry = emit & ~((share_v & (t_cur == last_t)) | ((code == origin_code) & skip_origin))
            full_at_entry = entry & (count == full)
            entry = entry & ~full_at_entry
            positive_x, positive_y, positive_z = sx > zero_i, sy > zero_i, sz > zero_i
            if bits8(entry) != 0:
                compress_store_f32(point_x, e, _point8(code == zero_i, False, positive_x, ox, dx, t_cur, lo_x, hi_x), entry)
                compress_store_f32(point_y, e, _point8(code == one_i, False, positive_y, oy, dy, t_cur, lo_y, hi_y), entry)
                compress_store_f32(point_z, e, _point8(code == two_i, False, positive_z, oz, dz, t_cur, lo_z, hi_z), entry)
                compress_store_i64(point_code, e, code, entry)
                compress_store_i64(point_ray, e, ray, entry)
                compress_store_i64(point_slot, e, count, entry)
                e += popcount8(entry)
                count = count + select(entry, one_i, zero_i)
            leave = emit & ~full_at_entry
            full_at_exit = leave & (count == full)
            leave = leave & ~full_at_exit
            compress_store_f32(point_x, e, _point8(is_x, True, positive_x, ox, dx, t_next, lo_x, hi_x), leave)
            compress_store_f32(point_y, e, _point8(is_y, True, positive_y, oy, dy, t_next, lo_y, hi_y), leave)
            compress_store_f32(point_z, e, _point8(is_z, True, positive_z, oz, dz, t_next, lo_z, hi_z), leave)
            compress_store_i64(point_code, e, axis, leave)
            compress_store_i64(point_ray, e, ray, leave)
            compress_store_i64(point_slot, e, count, leave)
            e += popcount8(leave)
            count = count + select(leave, one_i, zero_i)
            last_t = select(leave, t_next, last_t)
            truncated = full_at_entry | full_at_exit
            ended = ended | truncated
            live = live & ~truncated
        # Step the closest plane's axis; only its plane time and bounds change
        ix = ix + select(is_x, sx, zero_i)
        iy = iy + select(is_y, sy, zero_i)
        iz = iz + select(is_z, sz, zero_i)
        stepped = select(is_z, iz, select(is_y, iy, ix))
        left = live & ((stepped < zero_i) | (stepped >= res_v))
        live = live & ~left
        lo = to_f64(stepped) / res_f  # k / V, bit-equal to planes[k], instead of two gathers
        hi = to_f64(stepped + one_i) / res_f
        s = select(is_z, sz, select(is_y, sy, sx))
        o = select(is_z, oz, select(is_y, oy, ox))
        inv = select(is_z, inv_z, select(is_y, inv_y, inv_x))
        t_plane = (select(s > zero_i, hi, lo) - o) * inv
        tx, lo_x, hi_x = select(is_x, t_plane, tx), select(is_x, lo, lo_x), select(is_x, hi, hi_x)
        ty, lo_y, hi_y = select(is_y, t_plane, ty), select(is_y, lo, lo_y), select(is_y, hi, hi_y)
        tz, lo_z, hi_z = select(is_z, t_plane, tz), select(is_z, lo, lo_z), select(is_z, hi, hi_z)
        t_cur = t_next
        code = axis
        done = ended | left
        if bits8(done) != 0:
            scatter_i64(counts, ray, count, done)
            active = active & ~done

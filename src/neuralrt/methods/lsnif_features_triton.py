"""LSNIF ray featurization on CUDA: the 3D-DDA of `lsnif_features` as a Triton kernel.

Same contract and same arithmetic as the numba kernel (`featurize_rays_numba`): the walk runs in
float64 (rays are upcast in registers), plane coordinates come from the same ``k / V`` table,
``min``/``max`` follow numba's NaN rules, ties go to the lower axis. Under ``TRITON_INTERPRET=1``
(numpy, no fused multiply-add) the result is bit-identical to numba; compiled for a GPU, the
compiler may fuse ``o + t * d`` into one FMA, which moves float64 values by an ulp: points then
agree to float32 rounding and a ray exactly on a voxel plane can, rarely, walk the other column.

The walk is written as a resumable state machine (`dda_next_point`): each call advances every
lane of a block of rays to its next boundary point. `featurize_rays_triton` calls it H times
(+1 to detect truncation); the fused inference kernel (`lsnif_fused`) calls it once per point
slot and encodes each point as it appears, so points never go to global memory there.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch import Tensor

from .lsnif_features import ORIGIN_POINT, PADDING, RayFeaturePoints, _check_rays

__all__ = ["featurize_rays_triton", "dda_setup", "dda_next_point", "dda_point_coords"]

_INF = tl.constexpr(float("inf"))  # Triton reads globals only as constexpr


@triton.jit
def _min(a, b):
    """numba's ``min(a, b)``: ``a`` unless ``b < a`` (so a NaN in ``a`` wins, one in ``b`` loses)."""
    return tl.where(b < a, b, a)


@triton.jit
def _max(a, b):
    return tl.where(b > a, b, a)


@triton.jit
def _slab(o, d):
    """Per-axis (step, 1/d, t_near, t_far, ok) of the slab [0, 1]; as `lsnif_features._slab`."""
    zero = d == 0.0
    inv = 1.0 / tl.where(zero, 1.0, d)
    ta = (0.0 - o) * inv
    tb = (1.0 - o) * inv
    step = tl.where(zero, 0, tl.where(d > 0.0, 1, -1))
    near = tl.where(zero, -_INF, _min(ta, tb))
    far = tl.where(zero, _INF, _max(ta, tb))
    ok = (~zero) | ((o >= 0.0) & (o <= 1.0))
    return step, tl.where(zero, 0.0, inv), near, far, ok


@triton.jit
def _start_index(o, d, t, s, V, on_entry_face):
    """Voxel index where the walk begins, biased against the direction on a plane (as numba)."""
    f = (o + t * d) * V
    i = tl.floor(f)
    i = tl.where((s < 0) & (f == i), i - 1.0, i)
    i = tl.minimum(tl.maximum(i, 0.0), V - 1.0)  # clamp in float: no int overflow on far rays
    i = tl.where(on_entry_face, tl.where(s > 0, 0.0, V - 1.0), i)
    return i.to(tl.int32)


@triton.jit
def _plane_time(o, inv, i, s, planes_ptr, mask):
    """Ray time of the next plane crossing from voxel ``i`` stepping ``s`` (inf when s == 0)."""
    k = tl.where(s > 0, i + 1, i)
    plane = tl.load(planes_ptr + k, mask=mask & (s != 0), other=0.0)
    return tl.where(s == 0, _INF, (plane - o) * inv)


@triton.jit
def dda_setup(ox, oy, oz, dx, dy, dz, lane_ok, planes_ptr, V):
    """Clip float64 rays to the unit box and find the start voxel.

    Returns ``(state, t_enter, t_exit)``; ``state`` is the tuple `dda_next_point` advances, with
    ``alive`` false for rays that miss the box or are degenerate (count 0, t_enter = t_exit = inf).
    """
    total = ox + oy + oz + dx + dy + dz
    finite = (total == total) & (tl.abs(total) < _INF)
    nonzero = (dx != 0.0) | (dy != 0.0) | (dz != 0.0)
    sx, inv_x, nx, fx, okx = _slab(ox, dx)
    sy, inv_y, ny, fy, oky = _slab(oy, dy)
    sz, inv_z, nz, fz, okz = _slab(oz, dz)
    # Entry: the last slab entered (first axis on ties); exit: the first slab left.
    t_near = nx
    near_axis = tl.zeros_like(sx)
    near_axis = tl.where(ny > t_near, 1, near_axis)
    t_near = tl.where(ny > t_near, ny, t_near)
    near_axis = tl.where(nz > t_near, 2, near_axis)
    t_near = tl.where(nz > t_near, nz, t_near)
    t_far = _min(fx, _min(fy, fz))
    inside = t_near < 0.0
    t_cur = tl.where(inside, 0.0, t_near)
    alive = lane_ok & finite & nonzero & okx & oky & okz & (t_cur < t_far)
    t_enter = tl.where(alive, t_cur, _INF)
    t_exit = tl.where(alive, t_far, _INF)
    ix = _start_index(ox, dx, t_cur, sx, V, (~inside) & (near_axis == 0))
    iy = _start_index(oy, dy, t_cur, sy, V, (~inside) & (near_axis == 1))
    iz = _start_index(oz, dz, t_cur, sz, V, (~inside) & (near_axis == 2))
    tx = _plane_time(ox, inv_x, ix, sx, planes_ptr, alive)
    ty = _plane_time(oy, inv_y, iy, sy, planes_ptr, alive)
    tz = _plane_time(oz, inv_z, iz, sz, planes_ptr, alive)
    entry_code = tl.where(inside, 3, near_axis)  # 3 = ORIGIN_POINT
    last_t = tl.zeros_like(t_cur) - _INF
    pending = alive & False
    state = (ox, oy, oz, dx, dy, dz, sx, sy, sz, inv_x, inv_y, inv_z,
             ix, iy, iz, tx, ty, tz, t_cur, entry_code, last_t, pending, alive)  # fmt: skip
    return state, t_enter, t_exit


@triton.jit
def dda_next_point(state, planes_ptr, occ_ptr, V, ORIGIN_POINTS: tl.constexpr, SHARE: tl.constexpr):
    """Advance every live lane to its next occupied-voxel boundary point (the numba walk, resumed).

    Returns ``(state, got, t, code, exiting, vx, vy, vz)``: ``got`` lanes found a point at ray time
    ``t`` with face code ``code`` (0/1/2, or 3 for an origin), on the exit (``exiting``) or entry
    face of voxel ``(vx, vy, vz)``; lanes without one reached the end of the box (``alive`` false).
    An entry point leaves the exit of the same voxel ``pending`` for the next call.
    """
    (ox, oy, oz, dx, dy, dz, sx, sy, sz, inv_x, inv_y, inv_z,
     ix, iy, iz, tx, ty, tz, t_cur, entry_code, last_t, pending, alive) = state  # fmt: skip
    got = alive & False
    p_t = t_cur
    p_code = entry_code
    p_exit = got
    vx = ix
    vy = iy
    vz = iz
    searching = alive
    while tl.max(searching.to(tl.int32), axis=0) > 0:
        # Closest plane; strict < so ties go to the lower axis, as in numba.
        y_lt_x = ty < tx
        z_first = tl.where(y_lt_x, tz < ty, tz < tx)
        axis = tl.where(z_first, 2, tl.where(y_lt_x, 1, 0))
        t_next = tl.where(z_first, tz, tl.where(y_lt_x, ty, tx))
        overflow = searching & (t_next == _INF)  # denormal direction: nothing to walk
        alive = alive & ~overflow
        searching = searching & ~overflow
        t_next = _max(t_next, t_cur)  # rounding at the start can put a plane behind us
        occ = tl.load(occ_ptr + (ix * V + iy) * V + iz, mask=searching, other=0)
        occupied = searching & (occ != 0) & (t_next > t_cur)
        skip_entry = pending
        if SHARE:
            skip_entry = skip_entry | (t_cur == last_t)
        if not ORIGIN_POINTS:
            skip_entry = skip_entry | (entry_code == 3)
        emit_entry = occupied & ~skip_entry
        emit_exit = occupied & skip_entry
        p_t = tl.where(emit_entry, t_cur, tl.where(emit_exit, t_next, p_t))
        p_code = tl.where(emit_entry, entry_code, tl.where(emit_exit, axis, p_code))
        p_exit = tl.where(occupied, emit_exit, p_exit)
        vx = tl.where(occupied, ix, vx)
        vy = tl.where(occupied, iy, vy)
        vz = tl.where(occupied, iz, vz)
        got = got | occupied
        pending = tl.where(occupied, emit_entry, pending)
        last_t = tl.where(emit_exit, t_next, last_t)
        # Step every searching lane except those that just emitted an entry (their exit is next).
        adv = searching & ~emit_entry
        step_x = adv & (axis == 0)
        step_y = adv & (axis == 1)
        step_z = adv & (axis == 2)
        ix = tl.where(step_x, ix + sx, ix)
        iy = tl.where(step_y, iy + sy, iy)
        iz = tl.where(step_z, iz + sz, iz)
        left = (step_x & ((ix < 0) | (ix >= V))) | (step_y & ((iy < 0) | (iy >= V))) | (
            step_z & ((iz < 0) | (iz >= V)))  # fmt: skip
        alive = alive & ~left
        tx = tl.where(step_x & ~left, _plane_time(ox, inv_x, ix, sx, planes_ptr, step_x & ~left), tx)
        ty = tl.where(step_y & ~left, _plane_time(oy, inv_y, iy, sy, planes_ptr, step_y & ~left), ty)
        tz = tl.where(step_z & ~left, _plane_time(oz, inv_z, iz, sz, planes_ptr, step_z & ~left), tz)
        t_cur = tl.where(adv, t_next, t_cur)
        entry_code = tl.where(adv, axis, entry_code)
        searching = searching & ~occupied & alive
    state = (ox, oy, oz, dx, dy, dz, sx, sy, sz, inv_x, inv_y, inv_z,
             ix, iy, iz, tx, ty, tz, t_cur, entry_code, last_t, pending, alive)  # fmt: skip
    return state, got, p_t, p_code, p_exit, vx, vy, vz


@triton.jit
def _coord(on_plane, exiting, o, d, t, i, s, planes_ptr, mask):
    lo = tl.load(planes_ptr + i, mask=mask, other=0.0)
    hi = tl.load(planes_ptr + i + 1, mask=mask, other=0.0)
    plane = tl.where((s > 0) == exiting, hi, lo)
    along = o + t * d
    clamped = _min(_max(along, lo), hi)
    return tl.where(on_plane, plane, clamped).to(tl.float32)


@triton.jit
def dda_point_coords(state, got, t, code, exiting, vx, vy, vz, planes_ptr):
    """float32 unit-box coordinates of a found point: snapped onto its plane, clamped to its voxel."""
    ox, oy, oz, dx, dy, dz, sx, sy, sz = state[0], state[1], state[2], state[3], state[4], state[5], state[6], state[7], state[8]
    px = _coord(code == 0, exiting, ox, dx, t, vx, sx, planes_ptr, got)
    py = _coord(code == 1, exiting, oy, dy, t, vy, sy, planes_ptr, got)
    pz = _coord(code == 2, exiting, oz, dz, t, vz, sz, planes_ptr, got)
    return px, py, pz


@triton.jit
def _featurize_kernel(
    o_ptr, d_ptr, occ_ptr, planes_ptr, n_rays, V,
    pts_ptr, axes_ptr, count_ptr, trunc_ptr, t_enter_ptr, t_exit_ptr,
    MAX_POINTS: tl.constexpr, ORIGIN_POINTS: tl.constexpr, SHARE: tl.constexpr, BLOCK: tl.constexpr,
):  # fmt: skip
    rays = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    lane_ok = rays < n_rays
    r64 = rays.to(tl.int64)
    ox = tl.load(o_ptr + r64 * 3 + 0, mask=lane_ok, other=0.0).to(tl.float64)
    oy = tl.load(o_ptr + r64 * 3 + 1, mask=lane_ok, other=0.0).to(tl.float64)
    oz = tl.load(o_ptr + r64 * 3 + 2, mask=lane_ok, other=0.0).to(tl.float64)
    dx = tl.load(d_ptr + r64 * 3 + 0, mask=lane_ok, other=0.0).to(tl.float64)
    dy = tl.load(d_ptr + r64 * 3 + 1, mask=lane_ok, other=0.0).to(tl.float64)
    dz = tl.load(d_ptr + r64 * 3 + 2, mask=lane_ok, other=0.0).to(tl.float64)
    state, t_enter, t_exit = dda_setup(ox, oy, oz, dx, dy, dz, lane_ok, planes_ptr, V)
    count = tl.zeros([BLOCK], tl.int32)
    for h in range(MAX_POINTS):
        state, got, t, code, exiting, vx, vy, vz = dda_next_point(
            state, planes_ptr, occ_ptr, V, ORIGIN_POINTS, SHARE)  # fmt: skip
        px, py, pz = dda_point_coords(state, got, t, code, exiting, vx, vy, vz, planes_ptr)
        row = r64 * MAX_POINTS + h
        tl.store(pts_ptr + row * 3 + 0, px, mask=got)
        tl.store(pts_ptr + row * 3 + 1, py, mask=got)
        tl.store(pts_ptr + row * 3 + 2, pz, mask=got)
        tl.store(axes_ptr + row, code.to(tl.int8), mask=got)
        count += got.to(tl.int32)
    # One more point past H means the ray was truncated.
    state, more, t, code, exiting, vx, vy, vz = dda_next_point(state, planes_ptr, occ_ptr, V, ORIGIN_POINTS, SHARE)
    tl.store(count_ptr + rays, count, mask=lane_ok)
    tl.store(trunc_ptr + rays, more.to(tl.int8), mask=lane_ok)
    tl.store(t_enter_ptr + rays, t_enter.to(tl.float32), mask=lane_ok)
    tl.store(t_exit_ptr + rays, t_exit.to(tl.float32), mask=lane_ok)


def plane_table(resolution: int, device) -> Tensor:
    """``k / V`` for k = 0..V in float64 (correctly rounded, as numpy's ``arange(V + 1) / V``)."""
    return torch.arange(resolution + 1, dtype=torch.float64, device=device) / resolution


def occupancy_bytes(occupancy: Tensor, device) -> Tensor:
    """The [V, V, V] occupancy as contiguous uint8 on ``device`` (x-major, as the kernels index it)."""
    occ = torch.as_tensor(occupancy).to(device)
    if occ.ndim != 3 or len(set(occ.shape)) != 1:
        raise ValueError(f"occupancy must be a cubic [V, V, V] array, got shape {tuple(occ.shape)}")
    occ = occ.contiguous()
    return occ.view(torch.uint8) if occ.dtype == torch.bool else occ.to(torch.uint8)  # bool: no copy


def featurize_rays_triton(
    origins: Tensor,
    directions: Tensor,
    occupancy: Tensor,
    max_points: int = 18,
    *,
    origin_point: bool = True,
    share_boundary_points: bool = True,
    block: int = 128,
) -> RayFeaturePoints:
    """`featurize_rays` as a Triton kernel on the rays' device (CUDA, or CPU under TRITON_INTERPRET=1)."""
    _check_rays(origins, directions, max_points)  # (a short direction tensor would be read past its end)
    device = origins.device
    occ = occupancy_bytes(occupancy, device)
    res = occ.shape[0]
    o = origins.detach().contiguous()
    d = directions.detach().to(device).contiguous()  # (each in its own dtype: the kernel upcasts both, as numba does)
    n = o.shape[0]
    pts = torch.zeros((n, max_points, 3), dtype=torch.float32, device=device)
    axes = torch.full((n, max_points), PADDING, dtype=torch.int8, device=device)
    counts = torch.empty(n, dtype=torch.int32, device=device)
    truncated = torch.empty(n, dtype=torch.bool, device=device)
    t_enter = torch.empty(n, dtype=torch.float32, device=device)
    t_exit = torch.empty(n, dtype=torch.float32, device=device)
    if n:
        grid = (triton.cdiv(n, block),)
        _featurize_kernel[grid](
            o, d, occ, plane_table(res, device), n, res,
            pts, axes, counts, truncated.view(torch.int8), t_enter, t_exit,
            MAX_POINTS=int(max_points), ORIGIN_POINTS=bool(origin_point), SHARE=bool(share_boundary_points),
            BLOCK=block,
        )  # fmt: skip
    return RayFeaturePoints(pts, axes, counts, truncated, t_enter, t_exit)


assert ORIGIN_POINT == 3  # the kernels spell the origin code as a literal

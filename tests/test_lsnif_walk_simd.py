"""The 16-lane float32 voxel walk (`lsnif_walk_simd`) makes `walk_ray`'s decisions: the same counts,
intervals, face codes and slots, and points on the same planes, the other coordinates to float32
rounding (in another order)."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from neuralrt.methods.lsnif_features import PADDING, featurize_rays_numba, local_distance
from neuralrt.methods.lsnif_features_simd import featurize_rays_simd, rows_scratch, walk_rows
from neuralrt.methods.lsnif_walk_simd import _start_group, _walk_lanes, float32_walk_applies, occupancy_bits, walk_scratch

GROUP = 32


def _walk_all(origins, directions, occ, occ_bits, planes, max_points, origin_point, share, points, axes, counts, truncated,
              t_enter, t_exit, local=None):  # fmt: skip
    """Every ray through `walk_rows` in groups of GROUP, its points (and their local distances,
    ``local [N, H]``) in ray order (``points [N, H, 3]``)."""
    local = np.empty((0, 0), np.float32) if local is None else local
    walk_rows(origins, directions, 0, origins.shape[0], occ, occ_bits, planes, max_points, origin_point, share,
              rows_scratch(GROUP, max_points), points, axes, counts, truncated, t_enter, t_exit, local)  # fmt: skip


@numba.njit(cache=True)
def _local_distances(points, counts, origins, directions, t_enter, t_exit):
    out = np.zeros(points.shape[:2], np.float32)
    for r in range(points.shape[0]):
        for h in range(counts[r]):
            out[r, h] = local_distance(points[r, h, 0], points[r, h, 1], points[r, h, 2], origins[r, 0], origins[r, 1], origins[r, 2],
                                       directions[r, 0], directions[r, 1], directions[r, 2], t_enter[r], t_exit[r])  # fmt: skip
    return out


def _edge_rays(n: int, seed: int):
    """Rays from around and inside the box: origins on voxel planes, axis-parallel and denormal
    directions, diagonals from grid corners inside the box (ties at every step), zero and NaN rays."""
    rng = np.random.default_rng(seed)
    o = rng.uniform(-0.5, 1.5, (n, 3))
    d = rng.normal(size=(n, 3))
    o[: n // 4] = np.round(o[: n // 4] * 16) / 16
    d[n // 4 : n // 2, rng.integers(0, 3)] = 0.0
    d[n // 2 : n // 2 + 50] = [1e-310, 1.0, 0.0]
    o[n // 2 + 50 : n // 2 + 400] = rng.uniform(0, 1, (350, 3))
    o[n // 2 + 400 : n // 2 + 500] = rng.integers(1, 16, (100, 3)) / 16
    d[n // 2 + 400 : n // 2 + 500] = rng.choice([-1.0, 1.0], (100, 3))
    o[n // 2 + 500 : n // 2 + 550] = rng.uniform(0, 1, (50, 3))
    d[n // 2 + 500 : n // 2 + 550] = [1e-40, 1.0, 0.5]  # float32 denormal: 1/d is far out of float32's range
    d[-10:] = 0.0
    o[-20:-10, 0] = np.nan
    return o.astype(np.float32), d.astype(np.float32)


@pytest.mark.parametrize("res", [16, 32])
@pytest.mark.parametrize("max_points,origin_point,share", [(1, True, True), (3, False, True), (10, True, False), (18, False, False)])
def test_simd_walk_makes_walk_rays_decisions_and_points(res, max_points, origin_point, share):
    o, d = _edge_rays(6000, seed=res)
    occ = np.random.default_rng(1).random((res, res, res)) < 0.5
    ref = featurize_rays_numba(torch.from_numpy(o), torch.from_numpy(d), occ, max_points, origin_point=origin_point,
                               share_boundary_points=share)  # fmt: skip
    n = o.shape[0]
    points = np.zeros((n, max_points, 3), np.float32)
    axes = np.full((n, max_points), -1, np.int64)
    counts = np.full(n, -1, np.int64)
    truncated = np.full(n, -1, np.int32)
    t_enter, t_exit = np.full(n, 7, np.float32), np.full(n, 7, np.float32)
    planes = np.arange(res + 1) / res
    _walk_all(o, d, occ, occupancy_bits(occ), planes, max_points, origin_point, share, points, axes, counts, truncated, t_enter,
              t_exit)  # fmt: skip
    assert np.array_equal(counts, ref.count.numpy())
    assert np.array_equal(truncated, ref.truncated.numpy().astype(np.int32))
    assert (counts == max_points).sum() > 0 and (counts == 0).sum() > 0  # truncated rays and misses both occur
    assert np.array_equal(t_enter, ref.t_enter.numpy()) and np.array_equal(t_exit, ref.t_exit.numpy())
    valid = np.arange(max_points)[None, :] < counts[:, None]
    assert np.array_equal(axes[valid], ref.face_axis.numpy()[valid].astype(np.int64))
    # On its crossed plane a point is the plane itself, bit for bit; elsewhere within the stated bound
    ref_points = ref.points.numpy()
    on_plane = axes[:, :, None] == np.arange(3)
    assert np.array_equal(points[valid[:, :, None] & on_plane], ref_points[valid[:, :, None] & on_plane])
    bound = 2.0**-21 * (2 + np.abs(o))[:, None, :]
    off = valid[:, :, None] & ~on_plane
    assert (np.abs(points - ref_points) <= bound)[off].all()
    assert (points != ref_points)[off].any()  # (float32 arithmetic: some differ)
    # The lanes' local distances: `local_distance`'s float32 operations on the walk's points, bit for bit
    local = np.full((n, max_points), np.nan, np.float32)
    _walk_all(o, d, occ, occupancy_bits(occ), planes, max_points, origin_point, share, points, axes, counts, truncated, t_enter,
              t_exit, local)  # fmt: skip
    expected = _local_distances(points, counts, o, d, t_enter, t_exit)
    assert np.array_equal(local[valid].view(np.int32), expected[valid].view(np.int32))


def test_float32_walk_applies_to_power_of_two_grids():
    assert [v for v in range(1, 70) if float32_walk_applies(v)] == [1, 2, 4, 8, 16, 32, 64]


@numba.njit(cache=True)
def _walked_again(origins, directions, occ, occ_bits, planes, max_points):
    """How many rays `walk_group` hands to `walk_ray`: at the start, and from the lanes."""
    queue, queue_i, rays8, lane_terms, redo = walk_scratch(GROUP)
    px = np.empty(GROUP * max_points, np.float32)
    code = np.empty(GROUP * max_points, np.int32)
    counts = np.empty(GROUP, np.int64)
    t_enter, t_exit = np.empty(origins.shape[0], np.float32), np.empty(origins.shape[0], np.float32)
    at_start = from_lanes = 0
    for first in range(0, origins.shape[0], GROUP):
        n = min(GROUP, origins.shape[0] - first)
        queued, listed = _start_group(origins, directions, first, n, occ.shape[0], occ_bits, queue, queue_i, rays8, redo, t_enter, t_exit)
        _, total = _walk_lanes(queue, queue_i, queued, occ_bits, occ.shape[0], max_points, True, True, redo, listed,
                               lane_terms, px, px.copy(), px.copy(), px.copy(), code, code.copy(), code.copy(), counts,
                               np.empty(GROUP, np.int32))  # fmt: skip
        at_start += listed
        from_lanes += total - listed
    return at_start, from_lanes


def test_denormal_directions_and_ties_go_to_walk_ray():
    """The rays the float32 steps cannot decide as `walk_ray` does are walked by it (the test above
    checks their answers): denormal directions from the start, diagonals through voxel corners
    from the lanes; ordinary rays rarely."""
    o, d = _edge_rays(6000, seed=3)
    occ = np.ones((16, 16, 16), bool)
    at_start, from_lanes = _walked_again(o, d, occ, occupancy_bits(occ), np.arange(17) / 16, 10)
    assert at_start == 50 and from_lanes >= 100
    rng = np.random.default_rng(0)
    o, d = rng.uniform(-0.5, 1.5, (6000, 3)).astype(np.float32), rng.normal(size=(6000, 3)).astype(np.float32)
    at_start, from_lanes = _walked_again(o, d, occ, occupancy_bits(occ), np.arange(17) / 16, 10)
    assert at_start == 0 and from_lanes < 10


@pytest.mark.parametrize("res", [1, 2, 4, 32])
def test_occupancy_bits_hold_each_cell_where_the_walk_reads_it(res):
    """Cell ``c`` is bit ``c % 32`` of word ``c // 32`` (grids under 32 cells padded to a word), and
    the walk on those bits finds `walk_ray`'s points, small grids included."""
    occ = np.random.default_rng(res).random((res, res, res)) < 0.5
    occ[0, 0, 0] = True
    bits = occupancy_bits(occ)
    assert bits.dtype == np.int32 and bits.shape == (-(-(res**3) // 32),)
    cells = np.arange(res**3)
    assert np.array_equal((bits[cells >> 5].view(np.uint32) >> (cells & 31)) & 1, occ.reshape(-1).astype(np.uint32))
    o, d = _edge_rays(2000, seed=res)
    ref = featurize_rays_numba(torch.from_numpy(o), torch.from_numpy(d), occ, 4)
    n = o.shape[0]
    points, axes = np.zeros((n, 4, 3), np.float32), np.full((n, 4), -1, np.int64)
    counts, t_enter, t_exit = np.full(n, -1, np.int64), np.empty(n, np.float32), np.empty(n, np.float32)
    _walk_all(o, d, occ, bits, np.arange(res + 1) / res, 4, True, True, points, axes, counts, np.empty(n, np.int32), t_enter, t_exit)
    assert np.array_equal(counts, ref.count.numpy()) and counts.max() > 0
    valid = np.arange(4)[None, :] < counts[:, None]
    assert np.array_equal(axes[valid], ref.face_axis.numpy()[valid].astype(np.int64))


@pytest.mark.parametrize("res,max_points,origin_point,share", [(16, 1, True, True), (32, 18, False, True), (32, 10, True, False)])
def test_featurize_rays_simd_is_featurize_rays_to_float32_rounding(res, max_points, origin_point, share):
    """`featurize_rays_simd` gives `featurize_rays_numba`'s features: counts, truncation, intervals, face
    codes and padding rows bit for bit, the points to the walk's float32 bound."""
    o, d = _edge_rays(6000, seed=res + max_points)
    occ = np.random.default_rng(2).random((res, res, res)) < 0.4
    kw = dict(origin_point=origin_point, share_boundary_points=share)
    ref = featurize_rays_numba(torch.from_numpy(o), torch.from_numpy(d), occ, max_points, **kw)
    got = featurize_rays_simd(torch.from_numpy(o), torch.from_numpy(d), torch.from_numpy(occ), max_points, **kw)
    for name in ("count", "truncated", "face_axis", "t_enter", "t_exit"):
        assert torch.equal(getattr(got, name), getattr(ref, name)), name
    assert got.truncated.any() and (got.count == 0).any()
    padding = (got.face_axis == PADDING)[:, :, None].expand_as(got.points)
    assert torch.equal(got.points[padding], torch.zeros(int(padding.sum())))
    bound = 2.0**-21 * (2 + torch.from_numpy(np.abs(o)))[:, None, :]
    assert ((got.points - ref.points).abs() <= bound)[~padding].all()
    empty = featurize_rays_simd(torch.zeros(0, 3), torch.zeros(0, 3), occ, max_points)
    assert len(empty) == 0 and empty.points.shape == (0, max_points, 3)
    with pytest.raises(ValueError, match="power-of-two"):
        featurize_rays_simd(torch.from_numpy(o), torch.from_numpy(d), np.ones((12, 12, 12), bool))

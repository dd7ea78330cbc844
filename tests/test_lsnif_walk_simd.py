"""The 8-lane voxel walk (`lsnif_walk_simd`) gives `walk_ray`'s points bit for bit (in another order)."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from neuralrt.methods.lsnif_features import featurize_rays_numba
from neuralrt.methods.lsnif_walk_simd import walk_group, walk_scratch

GROUP = 32


@numba.njit(cache=True)
def _walk_all(origins, directions, occ_cells, res, planes, max_points, origin_point, share, points, axes, counts, t_enter, t_exit):
    """Every ray through `walk_group`, its points put back in ray order (``points [N, H, 3]``)."""
    queue, queue_i, rays8 = walk_scratch(GROUP)
    px = np.empty(GROUP * max_points, np.float32)
    py = np.empty(GROUP * max_points, np.float32)
    pz = np.empty(GROUP * max_points, np.float32)
    code = np.empty(GROUP * max_points, np.int64)
    ray = np.empty(GROUP * max_points, np.int64)
    slot = np.empty(GROUP * max_points, np.int64)
    group_counts = np.empty(GROUP, np.int64)
    n_rays = origins.shape[0]
    for first in range(0, n_rays, GROUP):
        n = min(GROUP, n_rays - first)
        e = walk_group(origins, directions, first, n, occ_cells, res, planes, max_points, origin_point, share, queue, queue_i, rays8,
                       px, py, pz, code, ray, slot, group_counts, t_enter, t_exit)  # fmt: skip
        for g in range(n):
            counts[first + g] = group_counts[g]
        for i in range(e):
            r, h = first + ray[i], slot[i]
            points[r, h, 0], points[r, h, 1], points[r, h, 2] = px[i], py[i], pz[i]
            axes[r, h] = code[i]


def _edge_rays(n: int, seed: int):
    """Rays from around and inside the box: origins on voxel planes, axis-parallel and denormal
    directions, zero and NaN rays."""
    rng = np.random.default_rng(seed)
    o = rng.uniform(-0.5, 1.5, (n, 3))
    d = rng.normal(size=(n, 3))
    o[: n // 4] = np.round(o[: n // 4] * 16) / 16
    d[n // 4 : n // 2, rng.integers(0, 3)] = 0.0
    d[n // 2 : n // 2 + 50] = [1e-310, 1.0, 0.0]
    o[n // 2 + 50 : n // 2 + 400] = rng.uniform(0, 1, (350, 3))
    d[-10:] = 0.0
    o[-20:-10, 0] = np.nan
    return o.astype(np.float32), d.astype(np.float32)


@pytest.mark.parametrize("res", [16, 32])
@pytest.mark.parametrize("max_points,origin_point,share", [(1, True, True), (3, False, True), (10, True, False), (18, False, False)])
def test_simd_walk_gives_walk_rays_points_bit_for_bit(res, max_points, origin_point, share):
    o, d = _edge_rays(6000, seed=res)
    occ = np.random.default_rng(1).random((res, res, res)) < 0.5
    ref = featurize_rays_numba(torch.from_numpy(o), torch.from_numpy(d), occ, max_points, origin_point=origin_point,
                               share_boundary_points=share)  # fmt: skip
    n = o.shape[0]
    points = np.zeros((n, max_points, 3), np.float32)
    axes = np.full((n, max_points), -1, np.int64)
    counts = np.full(n, -1, np.int64)
    t_enter, t_exit = np.full(n, 7, np.float32), np.full(n, 7, np.float32)
    planes = np.arange(res + 1) / res
    _walk_all(o, d, occ.astype(np.int32).reshape(-1), res, planes, max_points, origin_point, share, points, axes, counts, t_enter, t_exit)
    assert np.array_equal(counts, ref.count.numpy())
    assert (counts == max_points).sum() > 0 and (counts == 0).sum() > 0  # truncated rays and misses both occur
    valid = np.arange(max_points)[None, :] < counts[:, None]
    assert np.array_equal(points[valid].view(np.int32), ref.points.numpy()[valid].view(np.int32))  # same bits
    assert np.array_equal(axes[valid], ref.face_axis.numpy()[valid].astype(np.int64))
    assert np.array_equal(t_enter, ref.t_enter.numpy()) and np.array_equal(t_exit, ref.t_exit.numpy())

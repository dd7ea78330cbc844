"""LSNIF ray featurization: the numba DDA against the slow reference, and analytic cases."""

import numpy as np
import pytest
import torch
import trimesh

from neuralrt.geometry.voxelize import voxelize_triangles
from neuralrt.methods.lsnif_features import (
    ORIGIN_POINT,
    PADDING,
    featurize_rays,
    featurize_rays_reference,
)


def _torus_occupancy(res: int) -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.torus(0.3, 0.1)
    verts = (mesh.vertices - mesh.bounds[0]) / (mesh.bounds[1] - mesh.bounds[0]).max() * 0.9 + 0.05
    tris = verts[mesh.faces]
    return voxelize_triangles(tris, res), tris


def _random_rays(rng, n: int, occ: np.ndarray, tris: np.ndarray | None = None):
    """Outside starts on a sphere around the box, inside starts (many in occupied voxels), and
    surface starts on triangles, with random (also axis-parallel) directions."""
    res = occ.shape[0]
    k = n // 4
    outside = rng.normal(size=(k, 3))
    outside = 0.5 + 1.2 * outside / np.linalg.norm(outside, axis=1, keepdims=True)
    to_box = rng.uniform(-0.1, 1.1, (k, 3)) - outside  # most enter the box, some miss
    occupied = np.argwhere(occ)
    in_occ = (occupied[rng.integers(len(occupied), size=k)] + rng.uniform(size=(k, 3))) / res
    anywhere = rng.uniform(size=(k, 3))
    if tris is not None:
        tri = tris[rng.integers(len(tris), size=k)]
        w = rng.dirichlet(np.ones(3), size=k)
        anywhere = np.einsum("nk,nkc->nc", w, tri)
    origins = np.concatenate([outside, in_occ, anywhere])
    directions = np.concatenate([to_box, rng.normal(size=(2 * k, 3))])
    # a few axis-parallel directions exercise the zero-component paths
    directions[::17, rng.integers(3)] = 0.0
    directions[::29, :2] = 0.0
    scale = rng.uniform(0.2, 3.0, (len(directions), 1))  # not normalised
    return torch.tensor(origins, dtype=torch.float32), torch.tensor(directions * scale, dtype=torch.float32)


def _assert_same(a, b):
    np.testing.assert_array_equal(a.count.numpy(), b.count.numpy())
    np.testing.assert_array_equal(a.truncated.numpy(), b.truncated.numpy())
    np.testing.assert_array_equal(a.face_axis.numpy(), b.face_axis.numpy())
    np.testing.assert_array_equal(a.points.numpy(), b.points.numpy())
    np.testing.assert_array_equal(a.t_enter.numpy(), b.t_enter.numpy())
    np.testing.assert_array_equal(a.t_exit.numpy(), b.t_exit.numpy())


@pytest.mark.parametrize("origin_point", [True, False])
@pytest.mark.parametrize("share", [True, False])
def test_kernel_matches_reference_on_random_occupancy(origin_point, share):
    rng = np.random.default_rng(0)
    occ = rng.uniform(size=(8, 8, 8)) < 0.3
    o, d = _random_rays(rng, 800, occ)
    kw = dict(origin_point=origin_point, share_boundary_points=share)
    fast = featurize_rays(o, d, occ, 10, **kw)
    _assert_same(fast, featurize_rays_reference(o, d, occ, 10, **kw))
    # the sample covers every case: misses, inside starts, truncation
    assert (fast.count == 0).any() and fast.truncated.any() and (fast.face_axis == ORIGIN_POINT).any() == origin_point


def test_kernel_matches_reference_on_a_voxelized_mesh():
    occ, tris = _torus_occupancy(32)
    rng = np.random.default_rng(1)
    o, d = _random_rays(rng, 600, occ, tris)
    fast = featurize_rays(o, d, torch.from_numpy(occ), 18)
    _assert_same(fast, featurize_rays_reference(o, d, occ, 18))
    assert (fast.count > 0).float().mean() > 0.3


def test_points_are_on_faces_in_ray_order_and_on_the_ray():
    occ, tris = _torus_occupancy(32)
    o, d = _random_rays(np.random.default_rng(2), 4000, occ, tris)
    f = featurize_rays(o, d, occ, 18)
    valid = torch.arange(18)[None] < f.count[:, None].long()
    assert torch.equal(valid, f.face_axis != PADDING)
    assert (f.points[~valid] == 0).all()
    face = valid & (f.face_axis != ORIGIN_POINT)
    n_idx, h_idx = face.nonzero(as_tuple=True)
    on_plane = f.points[n_idx, h_idx, f.face_axis[n_idx, h_idx].long()].double() * 32
    assert torch.equal(on_plane, on_plane.round())  # snapped exactly (pitfall 3)
    # every valid point is on its ray, with non-decreasing t
    rel = f.points.double() - o[:, None].double()
    dd = d[:, None].double()
    t = (rel * dd).sum(-1) / (dd * dd).sum(-1)
    off_ray = (rel - t[..., None] * dd).norm(dim=-1)
    assert off_ray[valid].max() < 1e-5
    t = torch.where(valid, t, torch.inf)
    assert (t[:, 1:] >= t[:, :-1] - 1e-6).all()
    # without sharing, rows (0, 1), (2, 3), ... are the entry and exit of one occupied voxel
    u = featurize_rays(o, d, occ, 18, share_boundary_points=False)
    pair = (torch.arange(9)[None] * 2 + 1) < u.count[:, None].long()
    mid = 0.5 * (u.points[:, 0::2] + u.points[:, 1::2])[pair]
    vox = (mid * 32).floor().long().clamp(0, 31)
    assert pair.sum() > 1000 and torch.from_numpy(occ)[vox[:, 0], vox[:, 1], vox[:, 2]].all()
    # origin points only ever come first
    assert (f.face_axis[:, 1:] != ORIGIN_POINT).all()


def test_analytic_axis_aligned_rays():
    occ = np.zeros((4, 4, 4), bool)
    occ[1, 1, 1] = occ[2, 1, 1] = True
    o = torch.tensor([[-1.0, 0.3, 0.4], [0.3, 0.3, 0.4], [-1.0, 0.3, 0.4], [-1.0, 0.3, 0.4], [0.5, 0.3, -1]])
    d = torch.tensor([[2.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]])
    f = featurize_rays(o, d, occ, 18)
    assert f.count.tolist() == [3, 3, 0, 3, 2]
    torch.testing.assert_close(f.t_enter[:2], torch.tensor([0.5, 0.0]))
    torch.testing.assert_close(f.t_exit[:2], torch.tensor([1.0, 0.7]))
    assert torch.isinf(f.t_enter[2]) and not f.truncated.any()
    torch.testing.assert_close(f.points[0, :3, 0], torch.tensor([0.25, 0.5, 0.75]))
    assert f.face_axis[0].tolist()[:4] == [0, 0, 0, PADDING]
    torch.testing.assert_close(f.points[1, :3], torch.tensor([[0.3, 0.3, 0.4], [0.5, 0.3, 0.4], [0.75, 0.3, 0.4]]))
    assert f.face_axis[1, :3].tolist() == [ORIGIN_POINT, 0, 0]
    # a ray inside the plane x = 0.5 between two occupied voxels walks the column floor() picks
    assert (f.points[4, :2, 0] == 0.5).all() and f.face_axis[4, :2].tolist() == [2, 2]
    torch.testing.assert_close(f.points[4, :2, 2], torch.tensor([0.25, 0.5]))
    no_origin = featurize_rays(o[1:2], d[1:2], occ, 18, origin_point=False)
    assert no_origin.count.item() == 2 and no_origin.face_axis[0, 0] == 0
    unshared = featurize_rays(o[:1], d[:1], occ, 18, share_boundary_points=False)
    torch.testing.assert_close(unshared.points[0, :4, 0], torch.tensor([0.25, 0.5, 0.5, 0.75]))


def test_truncation_and_degenerate_rays():
    full = np.ones((32, 32, 32), bool)
    o = torch.tensor([[-0.1, -0.1, -0.1], [0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [np.nan, 0.5, 0.5], [2.0, 0.5, 0.5]])
    d = torch.tensor([[1.0, 1.01, 1.02], [0, 0, 0], [0, 0, 1e-3], [1.0, 0, 0], [0, 1.0, 0]])
    f = featurize_rays(o, d, full, 18)
    assert f.count.tolist() == [18, 0, 17, 0, 0]
    assert f.truncated.tolist() == [True, False, False, False, False]
    small = featurize_rays(o[:1], d[:1], np.ones((2, 2, 2), bool), 18)
    assert small.count.item() == 5 and not small.truncated.item()  # entry + 3 planes + exit... within H
    with pytest.raises(ValueError, match="cubic"):
        featurize_rays(o, d, np.ones((4, 4, 2), bool))
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        featurize_rays(o[:, :2], d[:, :2], full)
    empty = featurize_rays(torch.zeros(0, 3), torch.zeros(0, 3), full)
    assert empty.points.shape == (0, 18, 3)


def test_results_on_input_device(device):
    occ = np.ones((4, 4, 4), bool)
    o = torch.tensor([[-0.5, 0.5, 0.5]], device=device)
    d = torch.tensor([[1.0, 0.01, 0.02]], device=device)
    f = featurize_rays(o, d, torch.from_numpy(occ).to(device))
    assert f.points.device == o.device and f.count.item() == 5
    assert f[torch.tensor([True], device=device)].count.item() == f.count.item()


@pytest.mark.parametrize("point_distances", [True, False])
def test_select_network_rays_numba_matches_torch(point_distances):
    """The CPU pass keeps the same rays and rows as the torch ops, and its point distances are
    `point_local_distances` bit for bit."""
    from dataclasses import fields

    from neuralrt.methods.lsnif_features import point_local_distances, select_network_rays, select_network_rays_torch

    g = torch.Generator().manual_seed(7)
    occ = torch.rand(16, 16, 16, generator=g) < 0.15
    o = torch.rand(4000, 3, generator=g) * 2 - 0.5
    d = torch.randn(4000, 3, generator=g)
    fp = featurize_rays(o, d, occ, 12)
    keep, kept, ko, kd, dist = select_network_rays(fp, o, d, point_distances)
    ref_keep, *_ = select_network_rays_torch(fp, o, d, point_distances)
    assert torch.equal(ref_keep, torch.nonzero(fp.count > 0).squeeze(1))
    assert 500 < len(keep) < 4000 and torch.equal(keep, ref_keep)
    ref = fp[ref_keep]
    for f in fields(ref):
        assert torch.equal(getattr(kept, f.name), getattr(ref, f.name)), f.name
    assert torch.equal(ko, o[ref_keep]) and torch.equal(kd, d[ref_keep])
    if point_distances:
        expected = point_local_distances(ref, o[ref_keep], d[ref_keep])
        assert torch.equal(dist, expected) and (dist > 0).float().mean() > 0.3
    else:
        assert dist is None


@pytest.mark.parametrize("point_distances", [True, False])
def test_select_network_rows_is_select_network_rays_without_the_copies(point_distances):
    """The index-only selection (the encoder reads the points through it) gives the same rays,
    box intervals and point distances bit for bit, on the numba and the torch path."""
    from neuralrt.methods.lsnif_features import select_network_rays_torch, select_network_rows_numba, select_network_rows_torch

    g = torch.Generator().manual_seed(8)
    occ = torch.rand(16, 16, 16, generator=g) < 0.15
    o = torch.rand(4000, 3, generator=g) * 2 - 0.5
    d = torch.randn(4000, 3, generator=g)
    fp = featurize_rays(o, d, occ, 12)
    ref_keep, ref, _, _, ref_dist = select_network_rays_torch(fp, o, d, point_distances)
    assert 500 < len(ref_keep) < 4000
    for implementation in (select_network_rows_numba, select_network_rows_torch):
        keep, t_enter, t_exit, dist = implementation(fp, o, d, point_distances)
        assert torch.equal(keep, ref_keep) and torch.equal(t_enter, ref.t_enter) and torch.equal(t_exit, ref.t_exit)
        assert torch.equal(dist, ref_dist) if point_distances else dist is None


def test_unit_box_rays_numba_matches_torch():
    """The CPU pass keeps the same valid rays and maps them with torch's float32 operations bit
    for bit, in order over its parallel blocks; bad rays (NaN, zero direction, empty or NaN
    interval) are dropped."""
    from neuralrt.methods.lsnif_features import unit_box_rays, unit_box_rays_numba, unit_box_rays_torch
    from neuralrt.rays import Rays

    g = torch.Generator().manual_seed(3)
    n = 20000  # several blocks of rays
    o, d = torch.randn(n, 3, generator=g) * 2, torch.randn(n, 3, generator=g)
    t_min = torch.where(torch.rand(n, generator=g) < 0.3, torch.rand(n, generator=g), torch.zeros(n))
    t_max = torch.where(torch.rand(n, generator=g) < 0.2, torch.rand(n, generator=g), torch.full((n,), float("inf")))
    o[:50, 1] = float("nan")
    d[50:100] = 0.0
    t_min[100:150] = float("nan")
    t_min[150:200] = -float("inf")  # valid, not shifted
    o[9000:9100, 2] = float("inf")  # in another block
    rays = Rays(o, d, t_min, t_max)
    lo, ext = torch.tensor([-2.5, -3.0, -1.0]), torch.tensor([5.0, 6.5, 3.0])
    got, ref = unit_box_rays_numba(rays, lo, ext), unit_box_rays_torch(rays, lo, ext)
    assert 13000 < len(got[0]) < n - 250 and (got[3] > 0).any()
    for a, b in zip(got, ref):
        assert torch.equal(a, b)
    assert all(torch.equal(a, b) for a, b in zip(unit_box_rays(rays, lo, ext), got))  # the CPU default

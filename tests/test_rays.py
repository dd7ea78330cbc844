"""Rays, boxes and transforms: slab test against analytic cases, transforms of rays and normals."""

import math

import pytest
import torch

from neuralrt.rays import AABB, Rays, Transform, ray_box_intervals, valid_ray_mask


def test_slab_axis_aligned():
    o = torch.tensor([[-2.0, 0.5, 0.5], [0.5, 0.5, 0.5], [-2.0, 3.0, 0.5]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    t0, t1 = ray_box_intervals(o, d, torch.zeros(3), torch.ones(3))
    assert torch.allclose(t0[:2], torch.tensor([2.0, -0.5]))
    assert torch.allclose(t1[:2], torch.tensor([3.0, 0.5]))
    assert t0[2] > t1[2]  # misses


def test_slab_diagonal_ray_matches_closed_form():
    o = torch.tensor([[-1.0, -1.0, -1.0]])
    d = torch.tensor([[1.0, 1.0, 1.0]]) / math.sqrt(3)
    t0, t1 = ray_box_intervals(o, d, torch.zeros(3), torch.ones(3))
    assert t0.item() == pytest.approx(math.sqrt(3), rel=1e-6)
    assert t1.item() == pytest.approx(2 * math.sqrt(3), rel=1e-6)


def test_invalid_rays_flagged():
    o = torch.zeros(4, 3)
    d = torch.tensor([[1.0, 0, 0], [0, 0, 0], [float("nan"), 0, 0], [float("inf"), 0, 0]])
    assert valid_ray_mask(Rays(o, d)).tolist() == [True, False, False, False]


def test_rays_shape_errors():
    with pytest.raises(ValueError, match="origins"):
        Rays(torch.zeros(3), torch.zeros(3))
    with pytest.raises(ValueError, match="directions"):
        Rays(torch.zeros(2, 3), torch.zeros(3, 3))


def test_transform_roundtrip_and_t_invariance():
    g = torch.Generator().manual_seed(1)
    xf = Transform.translate([1, 2, 3]) @ Transform.rotate([1, 1, 0], 37) @ Transform.scale([2, 0.5, 3])
    p = torch.randn(100, 3, generator=g)
    assert torch.allclose(xf.inverse().apply_points(xf.apply_points(p)), p, atol=1e-5)
    # a point at parameter t along an object-space ray sits at the same t along the world ray
    rays = Rays(torch.randn(100, 3, generator=g), torch.randn(100, 3, generator=g))
    t = torch.rand(100, generator=g) * 5
    world = xf.apply_rays(rays)
    assert torch.allclose(world.point_at(t), xf.apply_points(rays.point_at(t)), atol=1e-4)


def test_normals_by_inverse_transpose():
    # plane z = x (normal ~ (-1, 0, 1)) under a non-uniform scale stays perpendicular to the surface
    xf = Transform.scale([3.0, 1.0, 0.5])
    n = torch.nn.functional.normalize(torch.tensor([[-1.0, 0.0, 1.0]]), dim=-1)
    tangent = torch.tensor([[1.0, 0.0, 1.0]])
    n_w, t_w = xf.apply_normals(n), xf.apply_vectors(tangent)
    assert abs(float((n_w * t_w).sum())) < 1e-6
    assert float(n_w.norm()) == pytest.approx(1.0)


def test_aabb_transformed_contains_corners():
    box = AABB(torch.zeros(3), torch.ones(3))
    xf = Transform.rotate([0, 0, 1], 45)
    wb = box.transformed(xf)
    assert wb.hi[0] == pytest.approx(math.sqrt(2) / 2, abs=1e-6)
    assert wb.lo[0] == pytest.approx(-math.sqrt(2) / 2, abs=1e-6)


def test_singular_transform_rejected():
    with pytest.raises(ValueError, match="singular"):
        Transform.scale([1.0, 0.0, 1.0])

"""Rays, boxes and transforms: slab test against analytic cases, transforms of rays and normals."""

import math

import pytest
import torch

from neuralrt.errors import ConfigError
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
        Rays(torch.zeros(4, 2), torch.zeros(4, 2))
    with pytest.raises(ValueError, match="directions"):
        Rays(torch.zeros(2, 3), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="batch_shape"):
        Rays(torch.zeros(6, 3), torch.zeros(6, 3), batch_shape=(4, 2))


def test_batch_shapes_flatten_row_major_and_intervals_broadcast():
    g = torch.Generator().manual_seed(0)
    o, d = torch.randn(4, 5, 3, generator=g), torch.randn(4, 5, 3, generator=g)
    t_max = torch.rand(4, 5, generator=g)
    rays = Rays(o, d, t_min=0.25, t_max=t_max)
    assert len(rays) == 20 and rays.batch_shape == (4, 5)
    assert torch.equal(rays.origins[7], o[1, 2]) and torch.equal(rays.directions[7], d[1, 2])
    assert torch.equal(rays.t_max.reshape(rays.batch_shape), t_max) and (rays.t_min == 0.25).all()
    assert Rays(torch.zeros(3), torch.ones(3)).batch_shape == ()  # one ray
    moved = Transform.translate([1, 0, 0]).apply_rays(rays)
    assert moved.batch_shape == (4, 5) and rays.to("cpu").batch_shape == (4, 5)


def test_hit_position_is_derived_from_the_rays():
    from neuralrt.rays import Hits

    rays = Rays(torch.tensor([[0.0, 0.0, 5.0], [1.0, 0.0, 5.0]]), torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.0, -1.0]]))
    hits = Hits.empty(2)
    hits.hit[0], hits.t[0] = True, 2.0
    pos = hits.position(rays)
    assert pos[0].tolist() == [0.0, 0.0, 1.0] and torch.isnan(pos[1]).all()


def test_pinhole_rays_match_the_scene_camera():
    from neuralrt.rays import pinhole_rays
    from neuralrt.render.camera import Camera

    rays = pinhole_rays(8, 4, 40.0, origin=(0, 1, 3), look_at=(0, 0, 0))
    assert len(rays) == 32 and rays.batch_shape == (4, 8)
    torch.testing.assert_close(torch.linalg.norm(rays.directions, dim=-1), torch.ones(32))
    same = Camera.look_at((0, 1, 3), (0, 0, 0), (0, 1, 0), 40.0, (8, 4)).generate_rays(torch.arange(32), torch.full((32, 2), 0.5))
    torch.testing.assert_close(rays.directions, same.directions)
    # Pixel rows go down the image, columns to the right; the image centre looks at look_at.
    grid = rays.directions.reshape(4, 8, 3)
    assert (grid[0, :, 1] > grid[-1, :, 1]).all() and (grid[:, 0, 0] < grid[:, -1, 0]).all()
    centre = torch.nn.functional.normalize(torch.tensor([0.0, -1.0, -3.0]), dim=0)
    assert float(torch.nn.functional.normalize(grid[1:3, 3:5].mean((0, 1)), dim=0) @ centre) > 0.9999
    with pytest.raises(ValueError, match="pinhole_rays"):
        pinhole_rays(0, 4, 40.0, (0, 0, 1), (0, 0, 0))


def test_type_hints_state_shapes():
    import typing

    from neuralrt.rays import Hits

    hints = typing.get_type_hints(Rays, include_extras=True)
    assert hints["origins"].__metadata__ == ("[N, 3] float32",)
    assert typing.get_type_hints(Hits, include_extras=True)["hit"].__metadata__ == ("[N] bool",)


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


def test_package_declares_its_type_hints():
    import importlib.resources
    import tomllib
    from pathlib import Path

    assert importlib.resources.files("neuralrt").joinpath("py.typed").is_file()
    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    assert "py.typed" in pyproject["tool"]["setuptools"]["package-data"]["neuralrt"]


def test_rays_refuse_what_torch_would_silently_cast():
    import numpy as np

    from neuralrt.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^ray origins: expected real numbers, got a torch.bool tensor$"):
        Rays(torch.zeros(2, 3, dtype=torch.bool), torch.ones(2, 3))  # (was read as 0/1)
    with pytest.raises(ConfigError, match=r"^ray directions: expected real numbers, got a complex128 array$"):
        Rays(np.zeros((2, 3)), np.ones((2, 3), complex))  # (the imaginary part was dropped)


def test_hits_and_rays_check_their_arguments():
    from neuralrt.errors import ConfigError, DeviceError
    from neuralrt.rays import Hits

    rays = Rays(torch.zeros(5, 3), torch.ones(5, 3))
    with pytest.raises(ConfigError, match=r"^position: 5 rays for 2 hits"):
        Hits.empty(2).position(rays)  # (broadcast silently)
    with pytest.raises(ConfigError, match=r"^n: must be at least 0, got -1$"):
        Hits.empty(-1)
    with pytest.raises(DeviceError, match=r"^device='tpu': not a torch device"):
        rays.to("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match=r"^device='cuda': "):  # (was torch's AssertionError)
            rays.to("cuda")
        with pytest.raises(DeviceError, match=r"^device='cuda': "):
            Hits.empty(2, "cuda")


def test_rays_and_hits_compare_by_identity():
    """``==`` raised (a tensor has no single truth value); fields compare with torch.equal."""
    rays = Rays(torch.zeros(2, 3), torch.ones(2, 3))
    assert rays == rays and rays != Rays(torch.zeros(2, 3), torch.ones(2, 3))


@pytest.mark.parametrize("kwargs,message", [
    ({"width": 4.5}, r"^pinhole_rays: width: must be an integer, got 4.5$"),  # (was torch's TypeError)
    ({"origin": (0, 3)}, r"^pinhole_rays: origin must be three finite numbers \(x, y, z\), got \(0, 3\)$"),
    ({"up": (0, float("nan"), 0)}, r"^pinhole_rays: up must be three finite numbers"),
    ({"fov_y_degrees": "40"}, r"0 < fov < 180, got 4x3, fov '40'$"),
    ({"device": "tpu"}, r"^device='tpu': not a torch device"),
])
def test_pinhole_rays_check_their_arguments(kwargs, message):
    from neuralrt.errors import NeuralRTError
    from neuralrt.rays import pinhole_rays

    args = {"width": 4, "height": 3, "fov_y_degrees": 40.0, "origin": (0, 0, 3), "look_at": (0, 0, 0), **kwargs}
    with pytest.raises(NeuralRTError, match=message):
        pinhole_rays(**args)


def test_a_field_set_after_construction_is_checked_and_converted_as_at_construction():
    """A path tracer shortens t_max to the last hit: a scalar or a batch-shaped value broadcasts,
    a mis-shaped one is the construction's error (a 1-value t_max made the kernels read past it)."""
    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.geometry.procedural import box

    n = 1 << 12
    rays = Rays(torch.tensor([[0.1, 0.2, 3.0]]).expand(n, 3), torch.tensor([[0.0, 0.0, -1.0]]).expand(n, 3))
    rays.t_max = torch.tensor([5.0])
    assert rays.t_max.shape == (n,) and bool(MeshBLAS(box((2, 2, 2))).intersect(rays).hit.all())
    rays.t_max = 1.5  # (a float: stored as a tensor, one value per ray)
    assert rays.t_max.shape == (n,) and not bool(MeshBLAS(box((2, 2, 2))).intersect(rays).hit.any())
    with pytest.raises(ConfigError, match=r"ray directions \(4096, 3\) do not match origins \(1, 3\)"):
        rays.origins = torch.zeros(1, 3)
    assert rays.origins.shape == (n, 3)  # (left as it was)
    grid = Rays(torch.zeros(2, 3, 3), torch.ones(2, 3, 3))
    grid.t_min = torch.full((2, 3), 0.5)  # (in the batch shape, as at construction)
    grid.origins = torch.ones(2, 3, 3)
    assert grid.t_min.shape == (6,) and grid.origins.shape == (6, 3) and grid.batch_shape == (2, 3)


def test_hit_positions_carry_no_gradient_as_the_queries_give_none():
    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.geometry.procedural import box

    origins = torch.tensor([[0.1, 0.2, 3.0]], requires_grad=True)
    rays = Rays(origins, torch.tensor([[0.0, 0.0, -1.0]]))
    position = MeshBLAS(box((2, 2, 2))).intersect(rays).position(rays)
    assert not position.requires_grad and position.tolist() == [[pytest.approx(0.1), pytest.approx(0.2), pytest.approx(1.0)]]

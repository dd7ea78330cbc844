"""The exact-BLAS contract, on every backend present (Embree; Mitsuba/LLVM on the CPU; OptiX on CUDA):
analytic intersections, intervals, bad rays, textures, empty batches."""

import numpy as np
import pytest
import torch
import trimesh
from exact_backends import backend_params

from neuralrt import Mesh, Rays
from neuralrt.geometry.mesh import MeshMaterial


@pytest.fixture(params=backend_params())
def make_blas(request):
    """``make_blas(mesh)`` -> (BLAS on the backend's device, that device)."""
    device, cls = request.param
    return lambda mesh: (cls(mesh, device=device), torch.device(device))


def on(device, *tensors):
    return [t.to(device) for t in tensors]


def quad_mesh(z=0.0, texture=None):
    """Unit square [0,1]^2 at height z, normal +z, UVs = (x, y), one material."""
    v = np.array([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    mat = MeshMaterial("quad", np.array([0.5, 0.5, 0.5], np.float32), texture)
    return Mesh(v, f, uvs=v[:, :2].copy(), materials=[mat], name="quad")


def test_plane_hits_analytic(make_blas):
    blas, dev = make_blas(quad_mesh(z=0.25))
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(1000, 2, generator=g) * 1.4 - 0.2
    o = torch.cat([xy, torch.full((1000, 1), 2.0)], 1)
    d = torch.tensor([[0.0, 0.0, -2.0]]).expand(1000, 3)  # unnormalised: t in units of |d|
    h = blas.intersect(Rays(*on(dev, o, d)))
    assert h.t.device.type == dev.type and h.normal.device.type == dev.type
    h = h.to("cpu")
    inside = ((xy >= 0) & (xy <= 1)).all(1)
    # edges are ambiguous in float32: only check points clearly inside or outside
    clear = ((xy - 0.5).abs().amax(1) - 0.5).abs() > 1e-4
    assert torch.equal(h.hit[clear], inside[clear])
    assert torch.allclose(h.t[h.hit], torch.full_like(h.t[h.hit], 0.875), atol=1e-6)
    assert torch.allclose(h.uv[h.hit], xy[h.hit], atol=1e-5)
    assert torch.allclose(h.normal[h.hit], torch.tensor([0.0, 0.0, 1.0]))
    assert (h.material_id[h.hit] == 0).all() and (h.material_id[~h.hit] == -1).all()
    assert torch.isinf(h.t[~h.hit]).all()


def test_sphere_distance_and_normal(make_blas):
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    blas, dev = make_blas(Mesh(sphere.vertices, sphere.faces, name="sphere"))
    g = torch.Generator().manual_seed(1)
    o = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=-1) * 3.0
    d = -o + 0.2 * torch.randn(2000, 3, generator=g)
    h = blas.intersect(Rays(*on(dev, o, d))).to("cpu")
    # analytic ray/unit-sphere intersection
    a = (d * d).sum(1)
    b = 2 * (o * d).sum(1)
    c = (o * o).sum(1) - 1
    disc = b * b - 4 * a * c
    t_exact = (-b - disc.clamp(min=0).sqrt()) / (2 * a)
    sure = disc > 0.05 * a  # away from grazing rays, where the tessellation decides
    assert h.hit[sure].all()
    # tessellation error of a level-6 icosphere is ~1e-4 in radius
    assert (h.t[sure] - t_exact[sure]).abs().max() < 2e-3
    p = o + h.t[:, None] * d
    assert torch.allclose(h.normal[sure], torch.nn.functional.normalize(p[sure], dim=-1), atol=5e-3)


def test_t_interval_respected_and_occlusion_consistent(make_blas):
    blas, dev = make_blas(quad_mesh())
    o = torch.tensor([[0.5, 0.5, 1.0]]).repeat(6, 1)
    d = torch.tensor([[0.0, 0.0, -1.0]]).repeat(6, 1)
    inf = float("inf")
    t_min = torch.tensor([0.0, 0.5, 1.5, 0.0, -inf, 0.999])
    t_max = torch.tensor([2.0, 2.0, 3.0, 0.9, inf, 1.001])
    rays = Rays(*on(dev, o, d, t_min, t_max))
    h = blas.intersect(rays).to("cpu")
    assert h.hit.tolist() == [True, True, False, False, True, True]
    assert h.t[h.hit].tolist() == pytest.approx([1.0] * 4, abs=1e-6)  # t_min = -inf: measured from the origin
    assert torch.equal(blas.occluded(rays).cpu(), h.hit)


def test_bad_rays_are_misses(make_blas):
    blas, dev = make_blas(quad_mesh())
    nan, inf = float("nan"), float("inf")
    o = torch.tensor([[0.5, 0.5, 1.0]] * 8)
    d = torch.tensor([[0, 0, -1.0], [0, 0, 0], [nan, 0, -1], [0, inf, -1], [0, 0, -1], [0, 0, -1], [0, 0, -1], [0, 0, -1]])
    o[4, 0] = nan
    t_min = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, nan, 0.0, 2.0])
    t_max = torch.tensor([inf, inf, inf, inf, inf, inf, nan, 1.0])
    rays = Rays(*on(dev, o, d, t_min, t_max))
    expected = [True] + [False] * 7
    h = blas.intersect(rays).to("cpu")
    assert h.hit.tolist() == expected and torch.isinf(h.t[1:]).all() and (h.primitive_id[1:] == -1).all()
    assert blas.occluded(rays).cpu().tolist() == expected


def test_texture_albedo_lookup(make_blas):
    tex = np.zeros((4, 4, 3), np.float32)
    tex[:2, :, 0] = 1.0  # top half (v near 1) red
    tex[2:, :, 2] = 1.0  # bottom half blue
    blas, dev = make_blas(quad_mesh(texture=tex))
    o = torch.tensor([[0.5, 0.8, 1.0], [0.5, 0.2, 1.0]])
    d = torch.tensor([[0, 0, -1.0]] * 2)
    h = blas.intersect(Rays(*on(dev, o, d))).to("cpu")
    assert h.albedo[0, 0] == pytest.approx(0.5) and h.albedo[0, 2] == 0  # base colour 0.5 x red
    assert h.albedo[1, 2] == pytest.approx(0.5) and h.albedo[1, 0] == 0


def test_empty_batch(make_blas):
    blas, dev = make_blas(quad_mesh())
    empty = Rays(torch.zeros(0, 3, device=dev), torch.zeros(0, 3, device=dev))
    h = blas.intersect(empty)
    assert len(h) == 0 and h.t.device.type == dev.type and blas.occluded(empty).numel() == 0


def test_memory_and_bounds_do_not_depend_on_backend(make_blas):
    from neuralrt.accel.mesh_blas import EmbreeMeshBLAS

    mesh = quad_mesh()
    blas, _ = make_blas(mesh)
    reference = EmbreeMeshBLAS(mesh)
    assert blas.memory_bytes().as_dict() == reference.memory_bytes().as_dict()
    assert torch.equal(blas.bounds.lo, reference.bounds.lo) and torch.equal(blas.bounds.hi, reference.bounds.hi)
    assert blas.secondary_offset == reference.secondary_offset

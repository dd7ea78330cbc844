"""MeshBLAS (Embree) against analytic intersections, and its handling of bad rays."""

import numpy as np
import pytest
import torch
import trimesh

from neuralrt import Mesh, MeshBLAS, Rays
from neuralrt.geometry.mesh import MeshMaterial


def quad_mesh(z=0.0, texture=None):
    """Unit square [0,1]^2 at height z, normal +z, UVs = (x, y), one material."""
    v = np.array([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    mat = MeshMaterial("quad", np.array([0.5, 0.5, 0.5], np.float32), texture)
    return Mesh(v, f, uvs=v[:, :2].copy(), materials=[mat], name="quad")


def test_plane_hits_analytic():
    blas = MeshBLAS(quad_mesh(z=0.25))
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(1000, 2, generator=g) * 1.4 - 0.2
    o = torch.cat([xy, torch.full((1000, 1), 2.0)], 1)
    d = torch.tensor([[0.0, 0.0, -2.0]]).expand(1000, 3)  # unnormalised: t in units of |d|
    h = blas.intersect(Rays(o, d))
    inside = ((xy >= 0) & (xy <= 1)).all(1)
    # edges are ambiguous in float32: only check points clearly inside or outside
    clear = ((xy - 0.5).abs().amax(1) - 0.5).abs() > 1e-4
    assert torch.equal(h.hit[clear], inside[clear])
    assert torch.allclose(h.t[h.hit], torch.full_like(h.t[h.hit], 0.875), atol=1e-6)
    assert torch.allclose(h.uv[h.hit], xy[h.hit], atol=1e-5)
    assert torch.allclose(h.normal[h.hit], torch.tensor([0.0, 0.0, 1.0]))
    assert (h.material_id[h.hit] == 0).all() and (h.material_id[~h.hit] == -1).all()
    assert torch.isinf(h.t[~h.hit]).all()


def test_sphere_distance_and_normal():
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    blas = MeshBLAS(Mesh(sphere.vertices, sphere.faces, name="sphere"))
    g = torch.Generator().manual_seed(1)
    o = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=-1) * 3.0
    d = -o + 0.2 * torch.randn(2000, 3, generator=g)
    h = blas.intersect(Rays(o, d))
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


def test_t_interval_respected_and_occlusion_consistent():
    blas = MeshBLAS(quad_mesh())
    o = torch.tensor([[0.5, 0.5, 1.0]]).repeat(4, 1)
    d = torch.tensor([[0.0, 0.0, -1.0]]).repeat(4, 1)
    t_min = torch.tensor([0.0, 0.5, 1.5, 0.0])
    t_max = torch.tensor([2.0, 2.0, 3.0, 0.9])
    rays = Rays(o, d, t_min, t_max)
    h = blas.intersect(rays)
    assert h.hit.tolist() == [True, True, False, False]
    assert h.t[:2].tolist() == pytest.approx([1.0, 1.0], abs=1e-6)
    assert torch.equal(blas.occluded(rays), h.hit)


def test_bad_rays_are_misses():
    blas = MeshBLAS(quad_mesh())
    o = torch.tensor([[0.5, 0.5, 1.0]] * 5)
    d = torch.tensor([[0, 0, -1.0], [0, 0, 0], [float("nan"), 0, -1], [0, float("inf"), -1], [0, 0, -1]])
    o[4, 0] = float("nan")
    rays = Rays(o, d)
    assert blas.intersect(rays).hit.tolist() == [True, False, False, False, False]
    assert blas.occluded(rays).tolist() == [True, False, False, False, False]


def test_texture_albedo_lookup():
    tex = np.zeros((4, 4, 3), np.float32)
    tex[:2, :, 0] = 1.0  # top half (v near 1) red
    tex[2:, :, 2] = 1.0  # bottom half blue
    blas = MeshBLAS(quad_mesh(texture=tex))
    o = torch.tensor([[0.5, 0.8, 1.0], [0.5, 0.2, 1.0]])
    d = torch.tensor([[0, 0, -1.0]] * 2)
    h = blas.intersect(Rays(o, d))
    assert h.albedo[0, 0] == pytest.approx(0.5) and h.albedo[0, 2] == 0  # base colour 0.5 x red
    assert h.albedo[1, 2] == pytest.approx(0.5) and h.albedo[1, 0] == 0


def test_empty_batch():
    blas = MeshBLAS(quad_mesh())
    h = blas.intersect(Rays(torch.zeros(0, 3), torch.zeros(0, 3)))
    assert len(h) == 0 and blas.occluded(Rays(torch.zeros(0, 3), torch.zeros(0, 3))).numel() == 0

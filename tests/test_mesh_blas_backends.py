"""MeshBLAS backends: chosen by device at construction, and in agreement with the Embree reference
(t to 1e-4 relative; hit masks equal except grazing rays, counted and bounded)."""

import importlib

import numpy as np
import pytest
import torch
import trimesh
from exact_backends import other_backends
from test_mesh_blas_kernels import _mesh, _rays

from neuralrt import Mesh, MeshBLAS, Rays
from neuralrt.accel import mesh_blas, mesh_blas_mitsuba
from neuralrt.accel.mesh_blas import EmbreeMeshBLAS
from neuralrt.accel.mesh_blas_mitsuba import MitsubaMeshBLAS, mitsuba_variant_available
from neuralrt.errors import DeviceError

_TRIANGLE = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]]))


def test_cpu_device_builds_embree():
    for blas in (MeshBLAS(_TRIANGLE), MeshBLAS(_TRIANGLE, device="cpu"), MeshBLAS(_TRIANGLE, device=torch.device("cpu"))):
        assert type(blas) is EmbreeMeshBLAS and isinstance(blas, MeshBLAS) and blas.backend == "embree"


def test_cuda_without_mitsuba_falls_back_to_embree_with_one_notice(monkeypatch, capsys):
    monkeypatch.setattr(mesh_blas_mitsuba, "mitsuba_variant_available", lambda device: False)
    monkeypatch.setattr(mesh_blas, "_fallback_noticed", False)
    assert mesh_blas._backend_for(torch.device("cuda")) is EmbreeMeshBLAS
    assert mesh_blas._backend_for(torch.device("cuda")) is EmbreeMeshBLAS
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("neuralrt: note: Mitsuba 3 is not installed")
    assert "pip install mitsuba" in err and "Embree on the host" in err


def test_cuda_with_mitsuba_chooses_it(monkeypatch, capsys):
    monkeypatch.setattr(mesh_blas_mitsuba, "mitsuba_variant_available", lambda device: True)
    assert mesh_blas._backend_for(torch.device("cuda")) is MitsubaMeshBLAS
    assert capsys.readouterr().err == ""


def test_embree_fallback_answers_on_the_rays_device():
    # What a CUDA machine without Mitsuba gets; on CPU tensors the same class, the same answers.
    blas = EmbreeMeshBLAS(_TRIANGLE, device="cpu")
    rays = Rays(torch.tensor([[0.2, 0.2, 1.0]]), torch.tensor([[0.0, 0.0, -1.0]]))
    assert blas.intersect(rays).t.tolist() == [1.0]


@pytest.mark.skipif(not mitsuba_variant_available("cpu"), reason="Mitsuba's llvm_ad_rgb variant is not available")
def test_mitsuba_rejects_rays_on_another_device(monkeypatch):
    blas = MitsubaMeshBLAS(_TRIANGLE, device="cpu")
    rays = Rays(torch.tensor([[0.2, 0.2, 1.0]]), torch.tensor([[0.0, 0.0, -1.0]]))
    monkeypatch.setattr(Rays, "device", property(lambda self: torch.device("cuda", 0)))
    with pytest.raises(DeviceError, match="rays are on cuda:0 but this exact BLAS is on cpu"):
        blas.intersect(rays)


def _agreement(reference, other, rays):
    """Rows where the two backends disagree on hit/miss or triangle, and the largest deviations elsewhere."""
    a, b = reference.intersect(rays), other.intersect(rays.to(other.device)).to("cpu")
    both = a.hit & b.hit
    same = both & (a.primitive_id == b.primitive_id)
    rel_t = ((a.t - b.t).abs() / a.t.abs().clamp(min=1e-6))[both]
    return {
        "a": a, "b": b, "same": same,
        "hit_mismatch": int((a.hit != b.hit).sum()),
        "t_off": int((rel_t > 1e-4).sum()),
        "max_rel_t_same_triangle": float(((a.t - b.t).abs() / a.t.abs().clamp(min=1e-6))[same].max()),
        "occluded_mismatch": int((reference.occluded(rays) != other.occluded(rays.to(other.device)).cpu()).sum()),
    }


@pytest.mark.parametrize("kind", ["plain", "colours", "textured"])
@pytest.mark.parametrize("backend", other_backends())
def test_backend_agrees_with_embree(backend, kind):
    device, cls = backend
    mesh = _mesh(kind)
    rays = _rays(20000, seed=7)  # every kind of invalid ray and interval included
    r = _agreement(EmbreeMeshBLAS(mesh), cls(mesh, device=device), rays)
    a, b, same = r["a"], r["b"], r["same"]
    assert 0.2 < a.hit.float().mean() < 0.8
    # Grazing rays (through an edge or along the silhouette) may go either way: few, counted.
    assert r["hit_mismatch"] <= 20 and r["occluded_mismatch"] <= 20, r
    assert r["t_off"] <= 20, r
    assert r["max_rel_t_same_triangle"] < 1e-4, r
    assert same.sum() >= a.hit.sum() - 40
    for name, tol in (("normal", 1e-4), ("geometric_normal", 1e-6), ("uv", 1e-3), ("albedo", 1e-3)):
        assert (getattr(a, name)[same] - getattr(b, name)[same]).abs().max() < tol, name
    assert torch.equal(a.material_id[same], b.material_id[same])
    miss = ~a.hit & ~b.hit
    for name in ("t", "normal", "geometric_normal", "uv", "albedo", "material_id", "primitive_id", "instance_id"):
        assert torch.equal(getattr(a, name)[miss], getattr(b, name)[miss]), name
    assert torch.equal(b.instance_id, torch.full_like(b.instance_id, -1))
    for name in ("hit", "t", "normal", "geometric_normal", "uv", "albedo", "material_id", "primitive_id", "instance_id"):
        assert getattr(b, name).dtype == getattr(a, name).dtype, name


@pytest.mark.parametrize("backend", other_backends())
def test_no_grazing_rays_means_identical_hit_masks(backend):
    device, cls = backend
    sphere = trimesh.creation.icosphere(subdivisions=4)
    mesh = Mesh(sphere.vertices, sphere.faces)
    g = torch.Generator().manual_seed(3)
    o = torch.nn.functional.normalize(torch.randn(5000, 3, generator=g), dim=1) * 3
    aim = torch.where(torch.rand(5000, 1, generator=g) < 0.5, 0.5, 2.0) * torch.nn.functional.normalize(
        torch.randn(5000, 3, generator=g), dim=1)  # well inside, or well outside, the unit sphere
    d = aim - o
    closest = (o - (o * d).sum(1, keepdim=True) / (d * d).sum(1, keepdim=True) * d).norm(dim=1)
    clear = (closest - 1).abs() > 0.05  # the tessellation lies within 0.01 of the unit sphere
    rays = Rays(o[clear], d[clear])
    r = _agreement(EmbreeMeshBLAS(mesh), cls(mesh, device=device), rays)
    assert r["hit_mismatch"] == 0 and r["occluded_mismatch"] == 0 and r["t_off"] == 0
    assert 0.3 < r["a"].hit.float().mean() < 0.7


def test_variant_listed_but_not_shipped_is_unavailable(monkeypatch):
    # A trimmed Mitsuba install lists llvm_ad_rgb in mitsuba.variants() without its module.
    real_import = importlib.import_module

    def import_module(name, *args):
        if name.startswith("mitsuba."):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return real_import(name, *args)

    monkeypatch.setattr(importlib, "import_module", import_module)
    mesh_blas_mitsuba._variant_available.cache_clear()
    try:
        assert not mitsuba_variant_available("cpu") and not mitsuba_variant_available("cuda")
    finally:
        mesh_blas_mitsuba._variant_available.cache_clear()


@pytest.mark.parametrize("backend", other_backends())
def test_t_max_at_a_hit_keeps_it_as_embree_does(backend):
    # The interval includes t_max; Mitsuba's maxt excludes it (it kept 1,828 of 2,025 such hits).
    device, cls = backend
    sphere = trimesh.creation.icosphere(subdivisions=3)
    blas = cls(Mesh(sphere.vertices, sphere.faces), device=device)
    g = torch.Generator().manual_seed(5)
    o = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g), dim=1) * 3
    d = 0.8 * torch.nn.functional.normalize(torch.randn(4000, 3, generator=g), dim=1) - o
    for t_min in (0.0, 0.2):
        rays = Rays(o, d, t_min=t_min).to(device)
        h = blas.intersect(rays)
        assert int(h.hit.sum()) > 1000
        at_hit = Rays(rays.origins, rays.directions, t_min=t_min, t_max=torch.where(h.hit, h.t, 1.0))
        kept = blas.intersect(at_hit)
        assert torch.equal(kept.hit, h.hit) and torch.equal(blas.occluded(at_hit), h.hit)
        assert (kept.t[kept.hit] <= at_hit.t_max[kept.hit]).all()

"""The BLAS contract, checked the same way for exact `MeshBLAS` and every registered neural method
(each after a short training run), on every device of the `device` fixture.

A new method gets these tests by registering itself (`neuralrt.methods.register_method`).
"""

import math

import numpy as np
import pytest
import torch
import trimesh

from neuralrt.accel.blas import BLAS
from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.geometry.mesh import Mesh
from neuralrt.methods import get_method, is_neural, load_model, method_names
from neuralrt.rays import Hits, Rays
from neuralrt.training.api import train

KINDS = ["exact", *method_names()]


@pytest.fixture(scope="module")
def torus() -> Mesh:
    """A non-convex mesh off the origin (rays from its surface hit it again)."""
    t = trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=32, minor_sections=16)
    return Mesh(np.asarray(t.vertices) + [2.0, -1.0, 0.5], np.asarray(t.faces), vertex_normals=np.asarray(t.vertex_normals),
                name="torus")


@pytest.fixture(scope="module")
def trained(torus):
    """kind -> BLAS on the CPU: the exact mesh, or a model of each method after a short run."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # see test_lsnif.one_torch_thread
    try:
        out = {"exact": MeshBLAS(torus)}
        for name in method_names():
            spec = get_method(name)
            smallest = min(spec.presets, key=lambda p: get_method(name).config(p).training.batch_size)
            config = spec.config(smallest, steps=60, batch_size=2048, seed=0)
            out[name] = train(torus, config, progress=False)
        return out
    finally:
        torch.set_num_threads(before)


@pytest.fixture(params=KINDS)
def blas(request, trained, torus, device):
    kind = request.param
    if kind == "exact":
        return MeshBLAS(torus, device=device)
    return trained[kind].to(device)


def _rays(blas, n: int, seed: int, device) -> Rays:
    """Rays from a sphere around the object towards random points of its box."""
    g = torch.Generator().manual_seed(seed)
    b = blas.bounds
    center, radius = b.center.float(), 0.75 * b.diagonal
    o = center + radius * torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    target = b.lo.float() + torch.rand(n, 3, generator=g) * b.extent.float()
    return Rays(o, target - o).to(device)


def _check_hits(h: Hits, n: int, device) -> None:
    assert len(h) == n
    for name, shape, dtype in (("hit", (n,), torch.bool), ("t", (n,), torch.float32), ("normal", (n, 3), torch.float32),
                               ("albedo", (n, 3), torch.float32), ("material_id", (n,), torch.int64)):
        value = getattr(h, name)
        assert tuple(value.shape) == shape and value.dtype == dtype, name
        assert value.device.type == torch.device(device).type, name
    miss = ~h.hit
    assert torch.isinf(h.t[miss]).all() and (h.material_id[miss] == -1).all()
    assert torch.isfinite(h.t[h.hit]).all() and (h.material_id[h.hit] >= 0).all()
    assert torch.allclose(h.normal[h.hit].norm(dim=1), torch.ones(int(h.hit.sum()), device=h.t.device), atol=1e-3)


def test_is_a_blas(blas):
    assert isinstance(blas, BLAS)
    assert is_neural(blas) == (not isinstance(blas, MeshBLAS))


def test_intersect_shapes_and_agreement_with_occluded(blas, device):
    rays = _rays(blas, 4096, 1, device)
    h = blas.intersect(rays)
    _check_hits(h, len(rays), device)
    assert 0.2 < float(h.hit.float().mean()) < 0.95  # the torus is hit, and missed through its hole
    assert torch.equal(blas.occluded(rays), h.hit)
    empty = blas.intersect(rays[torch.zeros(len(rays), dtype=torch.bool, device=rays.device)])
    assert len(empty) == 0


def test_interval_is_respected(blas, device):
    rays = _rays(blas, 4096, 2, device)
    h = blas.intersect(rays)
    assert h.hit.any()
    # Ending every ray before its hit: nothing is hit, no shadow ray is blocked.
    short = Rays(rays.origins, rays.directions, t_max=torch.where(h.hit, 0.5 * h.t, 1.0))
    assert not blas.intersect(short).hit.any() and not blas.occluded(short).any()
    # Both ends included: ending every ray at its own hit keeps the hit (neural BLASes compared strictly).
    at_hit = Rays(rays.origins, rays.directions, t_max=torch.where(h.hit, h.t, 1.0))
    assert torch.equal(blas.intersect(at_hit).hit, h.hit) and torch.equal(blas.occluded(at_hit), h.hit)
    # Starting past the first hit: any hit lies beyond t_min.
    late = Rays(rays.origins, rays.directions, t_min=torch.where(h.hit, h.t + 1e-3, 0.0))
    h2 = blas.intersect(late)
    assert (h2.t[h2.hit] > late.t_min[h2.hit]).all()
    # A negative t_min counts as 0: no BLAS answers hits behind the origin (exact ones did, neural ones
    # missed or answered ahead), so the same rays give the same answers as from t = 0.
    behind = Rays(rays.origins, rays.directions, t_min=-10.0)
    assert torch.equal(behind.t_min, torch.zeros_like(behind.t_min))
    assert torch.equal(blas.intersect(behind).hit, h.hit)
    away = Rays(rays.origins, -rays.directions, t_min=-1e3)  # the object lies behind every origin
    assert not blas.intersect(away).hit.any() and not blas.occluded(away).any()


@pytest.mark.parametrize("scale", [1e-12, 3.0, 1e12])
def test_direction_length_only_rescales_t(blas, device, scale):
    # Directions need not be unit: t counts direction lengths, and instance transforms scale them by
    # up to 1e12 either way (neuralrt.rays.MIN_SCALE / MAX_SCALE). LSNIF clipped its box interval at
    # an absolute 1e-12 in t and so misread rays 1e12 long. Scaling is not exact in float32 (3.0), so
    # a network may answer a ray at a decision edge the other way: a few in a thousand at most.
    rays = _rays(blas, 2048, 4, device)
    h = blas.intersect(rays)
    scaled = Rays(rays.origins, rays.directions * scale)
    hs = blas.intersect(scaled)
    allowed = 2 if is_neural(blas) else 0
    assert int((hs.hit != h.hit).sum()) <= allowed
    assert int((blas.occluded(scaled) != blas.occluded(rays)).sum()) <= allowed
    both = h.hit & hs.hit
    distance_error = (hs.t[both] * scale - h.t[both]).abs() * rays.directions[both].norm(dim=1)
    assert float(distance_error.max()) < (1e-3 if is_neural(blas) else 1e-5) * blas.bounds.diagonal
    normals_apart = (hs.normal[both] - h.normal[both]).abs().max(dim=1).values > 0.05
    assert int(normals_apart.sum()) <= allowed


def test_degenerate_rays_miss_without_error(blas, device):
    nan, inf = float("nan"), float("inf")
    c = blas.bounds.center.float().tolist()
    origins = torch.tensor([[nan, 0, 0], [inf, 0, 0], c, c, [c[0] + 10, c[1], c[2]], c])
    directions = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 0], [nan, 1, 0], [-inf, 0, 0], [1.0, 0, 0]])
    rays = Rays(origins, directions, t_max=torch.tensor([inf, inf, inf, inf, inf, 0.0])).to(device)
    h = blas.intersect(rays)
    _check_hits(h, 6, device)
    assert not h.hit.any() and not blas.occluded(rays).any()


def test_bounds_memory_and_offset(blas, torus):
    lo, hi = torus.bounds
    assert np.allclose(blas.bounds.lo.cpu().numpy(), lo, atol=1e-5) and np.allclose(blas.bounds.hi.cpu().numpy(), hi, atol=1e-5)
    report = blas.memory_bytes()
    assert report.total == sum(report.parts.values()) > 0 and all(v >= 0 for v in report.parts.values())
    assert 0 <= blas.secondary_offset < 0.1 * blas.bounds.diagonal and math.isfinite(blas.secondary_offset)


def test_save_load_round_trip(blas, device, tmp_path):
    if not is_neural(blas):
        pytest.skip("exact meshes have no model file")
    loaded = load_model(blas.save(tmp_path / "m.nrt"), device=device)
    assert type(loaded) is type(blas) and loaded.config == blas.config and loaded.mesh_hash == blas.mesh_hash
    assert loaded.memory_bytes() == blas.memory_bytes() and loaded.material_names == blas.material_names
    rays = _rays(blas, 2048, 3, device)
    a, b = blas.intersect(rays), loaded.intersect(rays)
    for name in ("hit", "t", "normal", "albedo", "material_id"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_rays_on_another_device_are_one_line_errors(blas, device):
    if not is_neural(blas) or device.type != "cuda":
        pytest.skip("needs a neural model on CUDA")
    from neuralrt.errors import DeviceError

    with pytest.raises(DeviceError, match="move one with"):
        blas.intersect(_rays(blas, 16, 4, "cpu"))

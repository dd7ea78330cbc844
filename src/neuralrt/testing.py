"""The BLAS contract as checks anyone can run: neuralrt's own contract tests, for a method or BLAS of yours.

Each `CONTRACT_CHECKS` entry is a check of one promise every BLAS keeps (`neuralrt.accel.blas`):
the shapes and types of `Hits`, ``occluded == intersect().hit``, the ``[t_min, t_max]`` interval
with both ends included, direction length only rescaling ``t``, degenerate rays missing, bounds
and memory reports, the same answers from several threads at once, a model file's round trip. A check raises ``AssertionError`` naming what
broke. They are written for `contract_mesh` (a torus off the origin: rays from the surface hit it
again, rays through the hole miss) and a model trained on it by `train_for_contract`::

    from neuralrt.testing import check_contract, contract_mesh, train_for_contract

    mesh = contract_mesh()
    check_contract(train_for_contract("my_method", mesh), mesh, tmp_dir="/tmp/contract")

or, in pytest, one test per check (as neuralrt's ``tests/test_blas_contract.py`` does)::

    @pytest.mark.parametrize("name", CONTRACT_CHECKS)
    def test_contract(name, tmp_path):
        CONTRACT_CHECKS[name].run_or_skip(blas, mesh, torch.device("cpu"), tmp_path)
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .accel.blas import BLAS
from .accel.mesh_blas import MeshBLAS
from .geometry.mesh import Mesh
from .methods import get_method, is_neural, load_model
from .rays import Hits, Rays

__all__ = ["CONTRACT_CHECKS", "ContractCheck", "check_contract", "contract_mesh", "train_for_contract"]


def contract_mesh() -> Mesh:
    """The mesh the checks are written for: a torus (radii 1 and 0.35) centred at (2, -1, 0.5)."""
    import trimesh

    t = trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=32, minor_sections=16)
    return Mesh(np.asarray(t.vertices) + [2.0, -1.0, 0.5], np.asarray(t.faces), vertex_normals=np.asarray(t.vertex_normals),
                name="torus")


def train_for_contract(method: str, mesh: Mesh | None = None, steps: int = 60):
    """A model of a registered ``method`` after a short run on ``mesh`` (`contract_mesh` by default),
    from its preset with the smallest batch; one torch thread, as the checks' tolerances were set with."""
    from .training.api import train

    spec = get_method(method)
    smallest = min(spec.presets, key=lambda p: spec.config(p).training.batch_size)
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # the answers of a 60-step model depend a little on the thread count's sums
    try:
        return train(mesh if mesh is not None else contract_mesh(), spec.config(smallest, steps=steps, batch_size=2048, seed=0),
                     progress=False)
    finally:
        torch.set_num_threads(before)


@dataclass(frozen=True)
class ContractCheck:
    """One promise: ``run(blas, mesh, device, tmp_dir)`` raises AssertionError if ``blas`` breaks it;
    ``applies(blas, device)`` says whether it concerns this BLAS on this device."""

    run: Callable[[BLAS, Mesh, torch.device, Path], None]
    applies: Callable[[BLAS, torch.device], bool] = lambda blas, device: True

    def run_or_skip(self, blas: BLAS, mesh: Mesh, device: torch.device, tmp_dir: Path) -> None:
        """`run`, or ``pytest.skip`` where the check does not apply (for use inside a pytest test)."""
        if not self.applies(blas, torch.device(device)):
            import pytest

            pytest.skip("does not apply to this BLAS on this device")
        self.run(blas, mesh, torch.device(device), Path(tmp_dir))


def contract_rays(blas: BLAS, n: int, seed: int, device) -> Rays:
    """Rays from a sphere around the object towards random points of its box."""
    g = torch.Generator().manual_seed(seed)
    b = blas.bounds
    center, radius = b.center.float(), 0.75 * b.diagonal
    o = center + radius * torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    target = b.lo.float() + torch.rand(n, 3, generator=g) * b.extent.float()
    return Rays(o, target - o).to(device)


def check_hits(h: Hits, n: int, device) -> None:
    """Shapes, dtypes and device of ``n`` answers; misses at inf with material -1; unit normals on hits."""
    assert len(h) == n, f"{len(h)} answers for {n} rays"
    for name, shape, dtype in (("hit", (n,), torch.bool), ("t", (n,), torch.float32), ("normal", (n, 3), torch.float32),
                               ("albedo", (n, 3), torch.float32), ("material_id", (n,), torch.int64)):
        value = getattr(h, name)
        assert tuple(value.shape) == shape and value.dtype == dtype, f"Hits.{name}: {tuple(value.shape)} {value.dtype}, not {shape} {dtype}"
        assert value.device.type == torch.device(device).type, f"Hits.{name} on {value.device}, the rays on {device}"
    miss = ~h.hit
    assert torch.isinf(h.t[miss]).all() and (h.material_id[miss] == -1).all(), "a miss needs t = inf and material_id = -1"
    assert torch.isfinite(h.t[h.hit]).all() and (h.material_id[h.hit] >= 0).all(), "a hit needs a finite t and material_id >= 0"
    assert torch.allclose(h.normal[h.hit].norm(dim=1), torch.ones(int(h.hit.sum()), device=h.t.device), atol=1e-3), \
        "hit normals must be unit"


def _is_a_blas(blas, mesh, device, tmp_dir) -> None:
    assert isinstance(blas, BLAS), f"{type(blas).__name__} lacks part of neuralrt.accel.blas.BLAS (bounds, secondary_offset, " \
        "material_names, intersect, occluded, memory_bytes)"
    assert is_neural(blas) == (not isinstance(blas, MeshBLAS)), "is_neural must tell a neural BLAS from an exact one"


def _shapes_and_occluded(blas, mesh, device, tmp_dir) -> None:
    rays = contract_rays(blas, 4096, 1, device)
    h = blas.intersect(rays)
    check_hits(h, len(rays), device)
    hit_fraction = float(h.hit.float().mean())
    assert 0.2 < hit_fraction < 0.95, f"{hit_fraction:.3f} of the rays hit: the torus is hit, and missed through its hole"
    assert torch.equal(blas.occluded(rays), h.hit), "occluded(rays) differs from intersect(rays).hit"
    empty = blas.intersect(rays[torch.zeros(len(rays), dtype=torch.bool, device=rays.device)])
    assert len(empty) == 0, "no rays must give no answers"


def _interval(blas, mesh, device, tmp_dir) -> None:
    rays = contract_rays(blas, 4096, 2, device)
    h = blas.intersect(rays)
    assert h.hit.any()
    # Ending every ray before its hit: nothing is hit, no shadow ray is blocked.
    short = Rays(rays.origins, rays.directions, t_max=torch.where(h.hit, 0.5 * h.t, 1.0))
    assert not blas.intersect(short).hit.any() and not blas.occluded(short).any(), "a hit beyond t_max"
    # Both ends included: ending every ray at its own hit keeps the hit (neural BLASes compared strictly).
    at_hit = Rays(rays.origins, rays.directions, t_max=torch.where(h.hit, h.t, 1.0))
    assert torch.equal(blas.intersect(at_hit).hit, h.hit) and torch.equal(blas.occluded(at_hit), h.hit), \
        "t_max set to a hit's own t lost the hit: t_max is included"
    # Starting past the first hit: any hit lies beyond t_min.
    late = Rays(rays.origins, rays.directions, t_min=torch.where(h.hit, h.t + 1e-3, 0.0))
    h2 = blas.intersect(late)
    assert (h2.t[h2.hit] > late.t_min[h2.hit]).all(), "a hit before t_min"
    # A negative t_min counts as 0: no BLAS answers hits behind the origin (exact ones did, neural ones
    # missed or answered ahead), so the same rays give the same answers as from t = 0.
    behind = Rays(rays.origins, rays.directions, t_min=-10.0)
    assert torch.equal(behind.t_min, torch.zeros_like(behind.t_min))
    assert torch.equal(blas.intersect(behind).hit, h.hit), "a negative t_min changed the answers"
    away = Rays(rays.origins, -rays.directions, t_min=-1e3)  # the object lies behind every origin
    assert not blas.intersect(away).hit.any() and not blas.occluded(away).any(), "a hit behind the ray's origin"


def _direction_length(blas, mesh, device, tmp_dir) -> None:
    # Directions need not be unit: t counts direction lengths, and instance transforms scale them by
    # up to 1e12 either way (neuralrt.rays.MIN_SCALE / MAX_SCALE). LSNIF clipped its box interval at
    # an absolute 1e-12 in t and so misread rays 1e12 long. Scaling is not exact in float32 (3.0), so
    # a network may answer a ray at a decision edge the other way: a few in a thousand at most.
    rays = contract_rays(blas, 2048, 4, device)
    h = blas.intersect(rays)
    allowed = 2 if is_neural(blas) else 0
    for scale in (1e-12, 3.0, 1e12):
        scaled = Rays(rays.origins, rays.directions * scale)
        hs = blas.intersect(scaled)
        flipped = int((hs.hit != h.hit).sum())
        assert flipped <= allowed, f"directions x{scale:g}: {flipped} rays changed hit/miss (at most {allowed})"
        flipped = int((blas.occluded(scaled) != blas.occluded(rays)).sum())
        assert flipped <= allowed, f"directions x{scale:g}: {flipped} shadow rays changed (at most {allowed})"
        both = h.hit & hs.hit
        distance_error = float(((hs.t[both] * scale - h.t[both]).abs() * rays.directions[both].norm(dim=1)).max())
        tolerance = (1e-3 if is_neural(blas) else 1e-5) * blas.bounds.diagonal
        assert distance_error < tolerance, f"directions x{scale:g}: hit points moved by {distance_error:.3g} (at most {tolerance:.3g})"
        normals_apart = int(((hs.normal[both] - h.normal[both]).abs().max(dim=1).values > 0.05).sum())
        assert normals_apart <= allowed, f"directions x{scale:g}: {normals_apart} normals changed"


def _degenerate_rays(blas, mesh, device, tmp_dir) -> None:
    nan, inf = float("nan"), float("inf")
    c = blas.bounds.center.float().tolist()
    origins = torch.tensor([[nan, 0, 0], [inf, 0, 0], c, c, [c[0] + 10, c[1], c[2]], c])
    directions = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 0], [nan, 1, 0], [-inf, 0, 0], [1.0, 0, 0]])
    rays = Rays(origins, directions, t_max=torch.tensor([inf, inf, inf, inf, inf, 0.0])).to(device)
    h = blas.intersect(rays)
    check_hits(h, 6, device)
    assert not h.hit.any() and not blas.occluded(rays).any(), \
        "NaN/Inf origins or directions, a zero direction or an empty interval must miss"


def _bounds_memory_offset(blas, mesh, device, tmp_dir) -> None:
    lo, hi = mesh.bounds
    assert np.allclose(blas.bounds.lo.cpu().numpy(), lo, atol=1e-5) and np.allclose(blas.bounds.hi.cpu().numpy(), hi, atol=1e-5), \
        "bounds differ from the mesh's"
    report = blas.memory_bytes()
    assert report.total == sum(report.parts.values()) > 0 and all(v >= 0 for v in report.parts.values()), \
        f"memory_bytes: total {report.total} vs parts {report.parts}"
    assert 0 <= blas.secondary_offset < 0.1 * blas.bounds.diagonal and math.isfinite(blas.secondary_offset), \
        f"secondary_offset {blas.secondary_offset} outside [0, 0.1 x the diagonal)"


def _round_trip(blas, mesh, device, tmp_dir) -> None:
    loaded = load_model(blas.save(tmp_dir / "contract.nrt"), device=device)
    assert type(loaded) is type(blas) and loaded.config == blas.config and loaded.mesh_hash == blas.mesh_hash, \
        "the loaded model differs in type, config or mesh hash"
    assert loaded.memory_bytes() == blas.memory_bytes() and loaded.material_names == blas.material_names
    rays = contract_rays(blas, 2048, 3, device)
    a, b = blas.intersect(rays), loaded.intersect(rays)
    for name in ("hit", "t", "normal", "albedo", "material_id"):
        assert torch.equal(getattr(a, name), getattr(b, name)), f"Hits.{name} changed through save and load"


def _concurrent_queries(blas, mesh, device, tmp_dir) -> None:
    # A BLAS is shared by the threads of a program that embeds it (a renderer's workers): the same
    # rays must get the same answers whoever else is asking.
    from concurrent.futures import ThreadPoolExecutor

    batches = [contract_rays(blas, n, 10 + n, device) for n in (1, 777, 2048, 4096)]
    alone = [(blas.intersect(r), blas.occluded(r)) for r in batches]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda r: (blas.intersect(r), blas.occluded(r)), batches * 2))
    for k, (hits, blocked) in enumerate(together):
        want_hits, want_blocked = alone[k % len(batches)]
        for name in ("hit", "t", "normal", "albedo", "material_id"):
            assert torch.equal(getattr(hits, name), getattr(want_hits, name)), f"Hits.{name} differs when queried from 4 threads"
        assert torch.equal(blocked, want_blocked), "occluded differs when queried from 4 threads"


def _other_device_rays(blas, mesh, device, tmp_dir) -> None:
    from .errors import DeviceError

    try:
        blas.intersect(contract_rays(blas, 16, 4, "cpu"))
    except DeviceError as exc:
        assert "move one with" in str(exc), f"the DeviceError does not say how to move: {exc}"
    else:
        raise AssertionError("rays on the CPU given to a model on CUDA: no DeviceError")


CONTRACT_CHECKS: dict[str, ContractCheck] = {
    "is_a_blas": ContractCheck(_is_a_blas),
    "hits_shapes_and_occluded": ContractCheck(_shapes_and_occluded),
    "interval_is_respected": ContractCheck(_interval),
    "direction_length_only_rescales_t": ContractCheck(_direction_length),
    "degenerate_rays_miss": ContractCheck(_degenerate_rays),
    "bounds_memory_and_offset": ContractCheck(_bounds_memory_offset),
    "concurrent_queries": ContractCheck(_concurrent_queries),
    "save_load_round_trip": ContractCheck(_round_trip, lambda blas, device: is_neural(blas)),
    "rays_on_another_device": ContractCheck(_other_device_rays, lambda blas, device: is_neural(blas) and device.type == "cuda"),
}


def check_contract(blas: BLAS, mesh: Mesh, device: str | torch.device | None = None,
                   tmp_dir: str | os.PathLike | None = None) -> list[str]:
    """Every check that applies to ``blas`` (on ``device``: the one its answers come on, the CPU by
    default) against ``mesh``; raises the first AssertionError, else returns the checks' names.
    ``tmp_dir``: where the round trip writes its model file (a temporary folder by default)."""
    device = torch.device(device if device is not None else "cpu")
    passed = []
    with tempfile.TemporaryDirectory() as scratch:
        for name, check in CONTRACT_CHECKS.items():
            if check.applies(blas, device):
                try:
                    check.run(blas, mesh, device, Path(tmp_dir if tmp_dir is not None else scratch))
                except AssertionError as exc:
                    raise AssertionError(f"contract check {name}: {exc}") from None
                passed.append(name)
    return passed

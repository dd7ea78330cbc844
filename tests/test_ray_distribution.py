"""The LSNIF training ray distribution: geometry of origins, cosine-weighted directions, state round trip."""

import numpy as np
import pytest
import torch
from scipy import stats

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.geometry.procedural import sphere
from neuralrt.training.samplers import LSNIFRaySampler, cosine_weighted_directions


def test_cosine_weighted_is_cosine_distributed():
    """For pdf cos/pi, cos^2(theta) is uniform on [0, 1]: chi-square over 20 bins, any axis."""
    rng = np.random.default_rng(3)
    axis = rng.normal(size=(200_000, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    d = cosine_weighted_directions(axis, rng)
    assert np.allclose(np.linalg.norm(d, axis=1), 1, atol=1e-9)
    cos = np.einsum("ij,ij->i", d, axis)
    assert cos.min() >= 0
    counts, _ = np.histogram(cos**2, bins=20, range=(0, 1))
    assert stats.chisquare(counts).pvalue > 1e-3
    # Azimuth is uniform too: the mean direction is the axis times E[cos] = 2/3.
    assert abs(cos.mean() - 2 / 3) < 5e-3


@pytest.fixture(scope="module")
def ball():
    return sphere(subdivisions=3, radius=1.0)


def test_outside_and_surface_rays(ball):
    exact = MeshBLAS(ball)
    s = LSNIFRaySampler(exact, exact.bounds.inflated(0.01), pool_size=4096, seed=1)
    batch = s.sample(20_000)
    o, d = batch.rays.origins.double(), batch.rays.directions.double()
    out, surf = ~batch.from_surface, batch.from_surface
    assert int(surf.sum()) == 10_000
    # Outside rays start on the sphere around the box and point inwards.
    r = torch.linalg.norm(o[out] - s.bounds.center.double(), dim=1)
    assert torch.allclose(r, torch.full_like(r, s.radius), rtol=1e-5)
    assert ((d[out] * (s.bounds.center.double() - o[out])).sum(1) > 0).all()
    # Surface rays start on the unit sphere (faceted: within the chord sag) and leave it outwards.
    rs = torch.linalg.norm(o[surf], dim=1)
    assert (rs > 0.98).all() and (rs < 1.001).all()
    # (around the facet normal, which is within a facet's angular size of the radial direction)
    assert ((d[surf] * o[surf]).sum(1) > -0.15).all() and ((d[surf] * o[surf]).sum(1)).mean() > 0.6
    # A convex object: no surface ray hits it again; outside rays that hit land on the surface.
    assert not batch.truth.hit[surf].any()
    assert batch.truth.hit[out].any()
    p = batch.rays[out].point_at(torch.where(batch.truth.hit[out], batch.truth.t[out], 0.0))[batch.truth.hit[out]]
    assert ((torch.linalg.norm(p, dim=1) - 1).abs() < 0.02).all()


def test_state_round_trip_reproduces_batches(ball):
    exact = MeshBLAS(ball)
    a = LSNIFRaySampler(exact, pool_size=2048, seed=5)
    a.sample(1000)
    meta, arrays = a.state_dict()
    first = a.sample(1000)
    b = LSNIFRaySampler(exact, pool_size=2048, seed=99)
    b.load_state_dict(meta, arrays)
    second = b.sample(1000)
    assert torch.equal(first.rays.origins, second.rays.origins)
    assert torch.equal(first.rays.directions, second.rays.directions)


def test_bad_surface_fraction(ball):
    with pytest.raises(ValueError, match="surface_fraction"):
        LSNIFRaySampler(MeshBLAS(ball), surface_fraction=1.5)

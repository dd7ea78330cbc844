"""The training ray distribution: geometry of origins, cosine-weighted directions, state round trip, device."""

import pytest
import torch
from scipy import stats

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.geometry.procedural import sphere
from neuralrt.training.ray_distribution import BoxRayDistribution, cosine_weighted_directions


def test_cosine_weighted_is_cosine_distributed():
    """For pdf cos/pi, cos^2(theta) is uniform on [0, 1]: chi-square over 20 bins, any axis."""
    g = torch.Generator().manual_seed(3)
    axis = torch.nn.functional.normalize(torch.randn(200_000, 3, generator=g, dtype=torch.float64), dim=1)
    d = cosine_weighted_directions(axis, g)
    assert torch.allclose(d.norm(dim=1), torch.ones(len(d), dtype=torch.float64), atol=1e-9)
    cos = (d * axis).sum(1)
    assert cos.min() >= 0
    counts = torch.histc(cos**2, bins=20, min=0, max=1).numpy()
    assert stats.chisquare(counts).pvalue > 1e-3
    # Azimuth is uniform too: the mean direction is the axis times E[cos] = 2/3.
    assert abs(float(cos.mean()) - 2 / 3) < 5e-3


@pytest.fixture(scope="module")
def ball():
    return sphere(subdivisions=3, radius=1.0)


def test_outside_and_surface_rays(ball, device):
    exact = MeshBLAS(ball)
    s = BoxRayDistribution(exact, exact.bounds.inflated(0.01), pool_size=4096, seed=1, device=device)
    batch = s.sample(20_000)
    assert batch.rays.device.type == device.type and batch.truth.hit.device.type == device.type
    o, d = batch.rays.origins.double().cpu(), batch.rays.directions.double().cpu()
    out, surf = ~batch.from_surface.cpu(), batch.from_surface.cpu()
    hit, t = batch.truth.hit.cpu(), batch.truth.t.cpu()
    assert int(surf.sum()) == 10_000
    # Outside rays start on the sphere around the box and point inwards.
    center = s.bounds.center.double()
    r = torch.linalg.norm(o[out] - center, dim=1)
    assert torch.allclose(r, torch.full_like(r, s.radius), rtol=1e-5)
    assert ((d[out] * (center - o[out])).sum(1) > 0).all()
    # Surface rays start on the unit sphere (faceted: within the chord sag) and leave it outwards.
    rs = torch.linalg.norm(o[surf], dim=1)
    assert (rs > 0.98).all() and (rs < 1.001).all()
    # (around the facet normal, which is within a facet's angular size of the radial direction)
    assert ((d[surf] * o[surf]).sum(1) > -0.15).all() and ((d[surf] * o[surf]).sum(1)).mean() > 0.6
    # A convex object: no surface ray hits it again; outside rays that hit land on the surface.
    assert not hit[surf].any()
    assert hit[out].any()
    p = (o + torch.where(hit, t, 0.0).double()[:, None] * d)[out & hit]
    assert ((torch.linalg.norm(p, dim=1) - 1).abs() < 0.02).all()


def test_state_round_trip_reproduces_batches(ball):
    exact = MeshBLAS(ball)
    a = BoxRayDistribution(exact, pool_size=2048, seed=5)
    a.sample(1000)
    meta, arrays = a.state_dict()
    first = a.sample(1000)
    b = BoxRayDistribution(exact, pool_size=2048, seed=99)
    b.load_state_dict(meta, arrays)
    second = b.sample(1000)
    assert torch.equal(first.rays.origins, second.rays.origins)
    assert torch.equal(first.rays.directions, second.rays.directions)


def test_own_generator_leaves_the_global_rng_alone(ball):
    torch.manual_seed(123)
    before = torch.get_rng_state()
    BoxRayDistribution(MeshBLAS(ball), pool_size=1024, seed=0).sample(512)
    assert torch.equal(torch.get_rng_state(), before)


def test_bad_surface_fraction(ball):
    with pytest.raises(ValueError, match="surface_fraction"):
        BoxRayDistribution(MeshBLAS(ball), surface_fraction=1.5)


@pytest.mark.parametrize("surface_fraction", [0.5, 0.0, 1.0])
def test_cpu_passes_match_the_torch_path(ball, surface_fraction):
    """On the CPU the rays are made and the pool refilled by numba passes from the same draws as
    the torch path: the same rays up to float rounding (sin/cos/sqrt may differ in the last ulp),
    the same pool, the same generator state, batch after batch (the pool wraps around)."""
    exact = MeshBLAS(ball)
    fast = BoxRayDistribution(exact, pool_size=3000, surface_fraction=surface_fraction, seed=4)
    ref = BoxRayDistribution(exact, pool_size=3000, surface_fraction=surface_fraction, seed=4)
    assert fast._sample == fast._sample_cpu
    ref._sample = ref._sample_torch
    for _ in range(4):
        a, b = fast.sample(2500), ref.sample(2500)
        torch.testing.assert_close(a.rays.origins, b.rays.origins, rtol=0, atol=2e-6)
        torch.testing.assert_close(a.rays.directions, b.rays.directions, rtol=0, atol=2e-6)
        assert torch.equal(a.from_surface, b.from_surface) and int(a.from_surface.sum()) == round(2500 * surface_fraction)
        assert (a.truth.hit == b.truth.hit).float().mean() > 0.999
        torch.testing.assert_close(fast.pool_points, ref.pool_points, rtol=0, atol=1e-5)
        assert torch.equal(fast.pool_normals, ref.pool_normals) and fast._pool_cursor == ref._pool_cursor
        assert torch.equal(fast.generator.get_state(), ref.generator.get_state())


def test_cpu_batches_do_not_depend_on_the_thread_count(ball):
    """The numba passes make the rays in blocks over the threads: the same bits on one thread as
    on several (a training run is reproducible on any machine size)."""
    import numba

    from neuralrt.host_threads import numba_threads

    exact = MeshBLAS(ball)
    batches = []
    for threads in (1, numba.config.NUMBA_NUM_THREADS):
        with numba_threads(threads):
            dist = BoxRayDistribution(exact, pool_size=3000, seed=8)
            batches.append([dist.sample(n) for n in (2500, 1025, 7)])
    for a, b in zip(*batches):
        assert torch.equal(a.rays.origins, b.rays.origins) and torch.equal(a.rays.directions, b.rays.directions)

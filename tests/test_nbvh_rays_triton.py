"""N-BVH's CUDA training-ray sampler (`nbvh_rays_triton`) against the CPU sampler (`nbvh_rays_cpu`,
numba) and against the distribution it must draw from. Without a GPU the kernel runs on CPU tensors
under Triton's interpreter (TRITON_INTERPRET=1, set before triton is imported), with large blocks
(the interpreter's cost is per operation). Seeded: every figure below is deterministic; the
statistical bounds are at the 1e-4 level, so a correct sampler passes them by a wide margin."""

import os

import numpy as np
import pytest
import torch

CUDA = torch.cuda.is_available()
if not CUDA:
    os.environ.setdefault("TRITON_INTERPRET", "1")
pytest.importorskip("triton")
stats = pytest.importorskip("scipy.stats")

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")
if not CUDA and os.environ.get("TRITON_INTERPRET") != "1":
    pytest.skip("no GPU and TRITON_INTERPRET is not 1", allow_module_level=True)

from neuralrt.errors import TrainingError  # noqa: E402 (after the interpreter switch)

DEVICE = torch.device("cuda" if CUDA else "cpu")
N = 8192
P_SMALL = 1e-4  # two-sample and goodness-of-fit p-values must stay above this


@pytest.fixture(scope="module")
def model():
    """The ball with a random cut (LoD 0 and 3 registered) and node statistics that give its
    leaves acceptance probabilities from 0.005 to 1 (some leaves never sampled: p = 1)."""
    from test_nbvh import CENTER, RADIUS, _random_cut

    from neuralrt.geometry.mesh import Mesh
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.nbvh import NBVHConfig, NBVHModel

    base = sphere(subdivisions=3)
    ball = Mesh(base.vertices * RADIUS + CENTER, base.faces, vertex_normals=base.vertex_normals, name="ball")
    model = NBVHModel.from_mesh(ball, NBVHConfig.preset("cpu", encoding={"levels": 3}))
    _random_cut(model, seed=1)
    g = torch.Generator().manual_seed(3)
    m = len(model.node_lo)
    model.samples.copy_(torch.where(torch.rand(m, generator=g) < 0.8, 8.0 * torch.randint(1, 50, (m,), generator=g), 0.0).double())
    model.alive_steps.fill_(20.0)
    model.loss_sum.copy_((torch.rand(m, generator=g) ** 3 * model.samples.float()).double())
    model.h_max.fill_(float(model.node_heuristic().max()) * 0.5)  # half the leaves or so at p = 1
    model._ball = ball
    return model.to(DEVICE)


@pytest.fixture(scope="module")
def kernels():
    import neuralrt.methods.nbvh_rays_triton as kernels

    saved = kernels._BLOCK, kernels._WARPS
    if not CUDA:  # few, large programs under the interpreter
        kernels._BLOCK, kernels._WARPS = 2048, 1
    yield kernels
    kernels._BLOCK, kernels._WARPS = saved


def _distribution(model, implementation, device=DEVICE):
    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.methods.nbvh_rays import NBVHRayDistribution

    return NBVHRayDistribution(model, MeshBLAS(model._ball, device=device), device, implementation=implementation)


@pytest.fixture(scope="module")
def triton_draw(model, kernels):
    sampler = _distribution(model, "triton")
    start, d, length, node = sampler._draw_triton(N)
    return sampler, start.cpu(), d.cpu(), length.cpu(), node.cpu()


def test_candidates_follow_the_papers_distribution(model, kernels):
    """Origins uniform in the 1.5x box, directions uniform on the sphere, the level uniform among
    the registered LoDs (plus the live cut while LoD 0 is missing), the dilation 1e-5 + U(0, 1e-4)."""
    n = 20000
    o, d, level, dil, u = (x.cpu() for x in kernels.draw_candidates_triton(model, n, seed=7, call=0))
    c, half = model.unit_center.cpu(), 0.75 * model.unit_extent.cpu()
    for axis in range(3):
        x = ((o[:, axis] - (c[axis] - half[axis])) / (2 * half[axis])).numpy()
        assert stats.kstest(x, "uniform").pvalue > P_SMALL
    assert torch.allclose(d.norm(dim=1), torch.ones(n), atol=1e-6)
    assert stats.kstest((d[:, 2].numpy() + 1) / 2, "uniform").pvalue > P_SMALL  # Archimedes: z uniform
    phi = (torch.atan2(d[:, 1], d[:, 0]).numpy() / (2 * np.pi)) % 1.0
    assert stats.kstest(phi, "uniform").pvalue > P_SMALL
    assert set(level.tolist()) == {0, 3}  # LoD 0 registered: no live-cut rays
    assert stats.chisquare(torch.bincount(level.long())[[0, 3]].numpy()).pvalue > P_SMALL
    assert stats.kstest(((dil - 1e-5) / 1e-4).numpy(), "uniform").pvalue > P_SMALL
    assert stats.kstest(u.numpy(), "uniform").pvalue > P_SMALL
    # Without LoD 0 the live cut is drawn too; without any LoD only the live cut.
    registered = model.registered.clone()
    try:
        model.registered.copy_(torch.tensor([False, False, True, False, False, True, False]))
        level = kernels.draw_candidates_triton(model, 6000, seed=7, call=1)[2].cpu()
        counts = [(level == v).sum().item() for v in (2, 5, -1)]
        assert sum(counts) == 6000 and stats.chisquare(counts).pvalue > P_SMALL
        model.registered.zero_()
        assert (kernels.draw_candidates_triton(model, 500, seed=7, call=2)[2] == -1).all()
    finally:
        model.registered.copy_(registered)


def _expected_leaf_shares(model, m=400_000, seed=11):
    """P(leaf) of an accepted sample, from many CPU candidates: P(first leaf) x p(leaf), normalised."""
    from neuralrt.training.ray_distribution import uniform_sphere_points

    cpu_model = model.cpu() if CUDA else model  # (in place: moved back below)
    g, tc = torch.Generator().manual_seed(seed), cpu_model.config.training
    origins = cpu_model.unit_center + (torch.rand(m, 3, generator=g) - 0.5) * (tc.origin_box_scale * cpu_model.unit_extent)
    directions = uniform_sphere_points(m, g, "cpu")
    levels = cpu_model.training_levels()
    level = levels[torch.randint(0, len(levels), (m,), generator=g)]
    dil = tc.dilation + tc.dilation_jitter * torch.rand(m, generator=g)
    node, _, _ = cpu_model.first_leaf(origins, directions, torch.full((m,), float("inf")), level, dil)
    node = node[node >= 0]
    nodes = len(cpu_model.node_lo)
    weight = torch.bincount(node, minlength=nodes).double() * cpu_model.acceptance(torch.arange(nodes)).double()
    if CUDA:
        model.to(DEVICE)
    return weight / weight.sum()


def _chi_square_pvalue(counts: torch.Tensor, shares: torch.Tensor) -> float:
    """Goodness of fit of leaf counts to expected shares, leaves expected fewer than 20 times pooled."""
    expected = shares * counts.sum()
    big = expected >= 20
    obs = torch.cat([counts[big].double(), counts[~big].double().sum()[None]]).numpy()
    exp = torch.cat([expected[big], expected[~big].sum()[None]]).numpy()
    keep = exp > 0
    return stats.chisquare(obs[keep], exp[keep] * obs[keep].sum() / exp[keep].sum()).pvalue


def test_triton_sampler_draws_the_cpu_samplers_distribution(model, triton_draw):
    """The leaves (LoD choice, first-leaf walk and acceptance p = max(h / h_max, 0.005) together)
    against P(first leaf) x p from 400k CPU candidates, for both samplers; chord lengths and
    directions against the CPU sampler's (two-sample KS)."""
    _, start, d, length, node = triton_draw
    cpu_start, cpu_d, cpu_length, cpu_node = _distribution(model.cpu() if CUDA else model, "cpu", "cpu")._draw_cpu(N)
    if CUDA:
        model.to(DEVICE)
    shares = _expected_leaf_shares(model)
    m = len(shares)
    p_leaf = model.acceptance(torch.arange(m, device=DEVICE)).cpu()
    assert p_leaf[shares > 0].min() < 0.01 and (p_leaf[shares > 0] == 1).any()  # the acceptance rule is exercised
    tri_counts, cpu_counts = torch.bincount(node, minlength=m), torch.bincount(cpu_node, minlength=m)
    assert _chi_square_pvalue(cpu_counts, shares) > P_SMALL  # the test's expectation is right
    assert _chi_square_pvalue(tri_counts, shares) > P_SMALL
    assert stats.ks_2samp(length.numpy(), cpu_length.numpy()).pvalue > P_SMALL
    for axis in range(3):
        assert stats.ks_2samp(d[:, axis].numpy(), cpu_d[:, axis].numpy()).pvalue > P_SMALL
        assert stats.ks_2samp(start[:, axis].numpy(), cpu_start[:, axis].numpy()).pvalue > P_SMALL
    # A leaf at p = 0.005 is kept 200x less often than an equally crossed leaf at p = 1: rare in both.
    low = (p_leaf < 0.01) & (shares > 0)
    assert tri_counts[low].sum() < 0.05 * N


def test_cpu_sampler_draws_the_kernels_samples(model, kernels):
    """The numba sampler (`nbvh_rays_cpu`) runs the kernel's algorithm on the same Philox streams: for
    the same block size, the same leaves, rounds and Morton codes, and the same chords up to the
    last bits of sin and cos; a limit on the rounds (not reached) changes no stream: the counters'
    layout is fixed."""
    from neuralrt.methods.nbvh_rays_cpu import CPU_MAX_ROUNDS, MAX_ROUNDS, sample_leaf_chords_cpu

    cpu_model = model.cpu() if CUDA else model
    depth = kernels.tree_depth(model.node_children)
    for seed, call, rounds in ((0, 3, (MAX_ROUNDS, CPU_MAX_ROUNDS)), (9, 0, (MAX_ROUNDS, CPU_MAX_ROUNDS)), (9, 0, (64, 32))):
        want = kernels.sample_leaf_chords_triton(model.to(DEVICE), 3000, seed, call, depth, max_rounds=rounds[0])
        got = sample_leaf_chords_cpu(cpu_model.cpu(), 3000, seed, call, block=kernels._BLOCK, max_rounds=rounds[1])
        assert torch.equal(got.node, want.node.cpu()) and torch.equal(got.rounds, want.rounds.cpu()) and int(got.flag) == int(want.flag) == 0
        assert (got.code == want.code.cpu()).float().mean() > 0.999
        for name in ("start", "direction", "length"):
            assert (getattr(got, name) - getattr(want, name).cpu()).abs().max() < 1e-5, name
    model.to(DEVICE)


def test_every_slot_holds_a_fresh_chord_of_its_leaf(model, triton_draw, kernels):
    """All N slots written with a chord of a leaf of a training cut (entered at its start, left at
    its end, within the largest dilation), in Morton order, no flag; another draw shares no row;
    the same draw number gives the same samples."""
    from neuralrt.methods.nbvh_rays import morton_codes

    sampler, start, d, length, node = triton_draw
    assert (node >= 0).all() and (length > 0).all() and torch.allclose(d.norm(dim=1), torch.ones(N), atol=1e-6)
    lod, live = model.node_lod.cpu(), model.live.cpu()
    assert ((lod[node] <= 3) | live[node]).all() and (model.node_children.cpu()[node, 0] >= 0).any()
    grow = 1e-5 + 1e-4 + 1e-6
    lo, hi = model.node_lo.cpu()[node] - grow, model.node_hi.cpu()[node] + grow
    end = start + length[:, None] * d
    assert ((start >= lo - 1e-6) & (start <= hi + 1e-6)).all() and ((end >= lo - 1e-6) & (end <= hi + 1e-6)).all()
    codes = morton_codes(start + 0.5 * length[:, None] * d)
    assert (codes[1:] >= codes[:-1]).float().mean() > 0.99  # sorted (float rounding may move a code by one cell)
    sampler._check_flags(wait=True)  # on CUDA the flags' copy lands later: read them all (a flag raises)
    assert sampler._flags == []
    depth = kernels.tree_depth(model.node_children)
    again = kernels.sample_leaf_chords_triton(model, 600, model.config.training.seed, 0, depth)
    first = kernels.sample_leaf_chords_triton(model, 600, model.config.training.seed, 0, depth)
    other = kernels.sample_leaf_chords_triton(model, 600, model.config.training.seed, 1, depth)
    assert torch.equal(again.start, first.start) and torch.equal(again.node, first.node)
    rows = {tuple(r) for r in first.start.cpu().tolist()}
    assert not rows & {tuple(r) for r in other.start.cpu().tolist()}
    assert int(first.flag) == 0 and int(first.rounds.sum()) * first.block >= 600


def test_batch_checkpoint_and_a_cut_nothing_can_be_kept_from(model, kernels):
    """`sample` hands out a TrainingBatch and tells the model the leaves; a restored state draws the
    same next batch; a cut whose leaves all have p = 0 raises the CPU sampler's error."""
    sampler = _distribution(model, "triton")
    batch = sampler.sample(300)
    assert len(batch.rays) == 300 and len(model._batch[0]) == 300 and batch.truth.hit.any()
    meta, arrays = sampler.state_dict()
    resumed = _distribution(model, "triton")
    resumed.load_state_dict(meta, arrays)
    assert meta["draws"] == 1 and torch.equal(resumed._draw_triton(300)[0], sampler._draw_triton(300)[0])
    assert 0 < sampler.last_yield() <= 1
    saved = model.loss_sum.clone(), model.samples.clone(), model.h_max.clone(), model.config
    try:
        model.loss_sum.zero_()
        model.samples.fill_(8.0)
        model.h_max.fill_(1.0)
        model.config = model.config.model_copy(update={"training": model.config.training.model_copy(update={"min_acceptance": 0.0})})
        depth = kernels.tree_depth(model.node_children)
        chords = kernels.sample_leaf_chords_triton(model, 100, 1, 0, depth, max_rounds=2)
        assert int(chords.flag) & kernels.UNFILLED and (chords.node == 0).all()
        with pytest.raises(TrainingError, match="no sampled ray"):
            sampler._watch(chords.flag)
            sampler._check_flags(wait=True)
    finally:
        model.loss_sum.copy_(saved[0])
        model.samples.copy_(saved[1])
        model.h_max.copy_(saved[2])
        model.config = saved[3]

"""NIF stage-2 inputs: the fused numba pass (CPU) against the torch ops, on the same pairs."""

import torch

from neuralrt.methods.nif import NIFNetworks, NIFPairs
from neuralrt.methods.nif_config import NIFConfig, NIFGridConfig, NIFTrainingConfig
from neuralrt.methods.nif_features import NumbaNIFFeatures, TorchNIFFeatures, nif_features_for
from neuralrt.rays import AABB


def _pairs(n=20000, seed=0):
    g = torch.Generator().manual_seed(seed)
    obj = torch.randint(0, 3, (n,), generator=g)
    o = torch.rand(n, 3, generator=g) * 5 - 2.5
    d = torch.randn(n, 3, generator=g) * 4
    d[:50, 0] = 0.0  # axis-parallel rays, some on a slab plane
    o[:25, 0] = -1.0
    d[50:60] = torch.tensor([0.0, 1.0, 0.0])  # straight up: the pole
    t_min = torch.where(torch.arange(n) % 7 == 0, 0.3, 0.0)
    return NIFPairs(obj, o, d, t_min, torch.ones(n))


def _networks(**overrides):
    cfg = NIFConfig(training=NIFTrainingConfig(init_scale=1.0, seed=2), **overrides)
    boxes = [AABB(torch.full((3,), -1.0), torch.full((3,), 1.0)), AABB(torch.tensor([0.0, 0.5, 0.0]), torch.tensor([3.0, 2.0, 1.0])),
             AABB(torch.full((3,), -2.0), torch.tensor([-0.5, 0.0, -0.5]))]
    return NIFNetworks(cfg, boxes)


def test_numba_features_equal_torch_features_and_answers():
    net, pairs = _networks(), _pairs()
    a = TorchNIFFeatures()(net, pairs)
    b = NumbaNIFFeatures()(net, pairs)
    assert torch.equal(a[0], b[0]) and torch.equal(a[2], b[2])  # same pairs, same order
    assert a[0].numel() > 1000 and a[2].numel() > 500
    assert torch.allclose(a[1], b[1], atol=1e-3)  # coordinates in float64 (numba math) vs float32 (torch), tables of O(1) values and torch.allclose(a[3], b[3], atol=1e-4)
    # Answers: equal except where a logit sits within rounding of the threshold.
    ans_a = net.occluded_from_features(len(pairs), *a)
    ans_b = net.occluded_from_features(len(pairs), *b)
    assert int((ans_a != ans_b).sum()) <= 2 and 0 < int(ans_a.sum()) < len(pairs)


def test_numba_features_follow_each_grids_resolution():
    outer = NIFConfig().outer.model_copy(update={"direction_grid": NIFGridConfig(resolution=64, features=2)})
    net, pairs = _networks(outer=outer), _pairs(4000, seed=1)
    a, b = TorchNIFFeatures()(net, pairs), NumbaNIFFeatures()(net, pairs)
    assert a[1].shape[1] == 5 and torch.allclose(a[1], b[1], atol=1e-3)  # coordinates in float64 (numba math) vs float32 (torch), tables of O(1) values


def test_implementation_is_chosen_by_device():
    assert isinstance(nif_features_for("cpu"), NumbaNIFFeatures)
    assert isinstance(nif_features_for("cuda"), TorchNIFFeatures)


def test_a_pair_at_the_box_boundary_meets_it_in_both_implementations():
    # t_max at the box entry, t_min at its exit: both ends are in the interval. The numba slab test
    # ran in float64 and the torch one in float32, strictly: 1,999 of 4,000 pairs against 0.
    from neuralrt.rays import ray_box_intervals

    box = AABB(torch.zeros(3), torch.ones(3))
    net = NIFNetworks(NIFConfig(), [box])
    g = torch.Generator().manual_seed(0)
    n = 4000
    o = torch.rand(n, 3, generator=g) * 3 - 1
    o[:, 0] = -0.1 - torch.rand(n, generator=g)  # in front of the x = 0 face
    d = torch.rand(n, 3, generator=g) - o
    t0, t1 = ray_box_intervals(o, d, box.lo, box.hi)
    obj = torch.zeros(n, dtype=torch.int64)
    for t_min, t_max in ((torch.zeros(n), t0), (t1, torch.full((n,), float("inf")))):
        pairs = NIFPairs(obj, o, d, t_min, t_max)
        a, b = TorchNIFFeatures()(net, pairs), NumbaNIFFeatures()(net, pairs)
        assert len(a[0]) == len(b[0]) == n and torch.equal(a[0], b[0])

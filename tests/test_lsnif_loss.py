"""LSNIF training loss: the numba pass (CPU: output layer + loss) against the torch ops (the reference)."""

import pytest
import torch
from torch import nn

from neuralrt.methods.lsnif_config import LossConfig
from neuralrt.methods.lsnif_loss import training_loss_numba, training_loss_torch
from neuralrt.rays import Hits


def _batch(n_rays: int, n_net: int, materials: int, width: int = 40, hit_fraction: float = 0.6, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    truth = Hits.empty(n_rays, torch.device("cpu"))
    active = torch.randperm(n_rays, generator=g)[:n_net].sort().values
    truth.hit[:] = torch.rand(n_rays, generator=g) < hit_fraction
    truth.t[:] = torch.where(truth.hit, torch.rand(n_rays, generator=g) * 3, torch.full((n_rays,), float("inf")))
    normal = torch.randn(n_rays, 3, generator=g)
    truth.normal[:] = normal / normal.norm(dim=1, keepdim=True)
    truth.albedo[:] = torch.rand(n_rays, 3, generator=g)
    truth.material_id[:] = torch.where(truth.hit, torch.randint(0, materials, (n_rays,), generator=g), -1)
    directions = torch.randn(n_rays, 3, generator=g)
    hidden = torch.relu(torch.randn(n_net, width, generator=g))
    layer = nn.Linear(width, 8 + materials)
    with torch.no_grad():
        layer.weight.copy_(torch.randn(layer.weight.shape, generator=g) * 0.5)
        layer.bias.copy_(torch.randn(layer.bias.shape, generator=g))
        layer.bias[2:5] = 0  # with the zero hidden rows below: zero normal outputs (cosine's eps clamp)
        hidden[:3] = 0
    t_enter = torch.rand(n_net, generator=g)
    t_exit = t_enter + torch.rand(n_net, generator=g) * 3
    t_exit[:2] = t_enter[:2]  # empty interval (the 1e-12 clamp)
    t_offset = torch.rand(n_net, generator=g) * 0.1
    return hidden, layer, (active, t_offset, t_enter, t_exit, directions, truth)


def _run(implementation, hidden, layer, rest, weights: LossConfig, materials: int, upstream: float = 1.0):
    hidden = hidden.detach().clone().requires_grad_(True)
    layer.zero_grad(set_to_none=True)
    result = implementation(hidden, layer, *rest, weights, materials, 0.3, torch.tensor(17))
    (result.loss * upstream).backward()
    return result, hidden.grad, layer.weight.grad.clone(), layer.bias.grad.clone()


@pytest.mark.parametrize("upstream", [1.0, 1.5])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("materials", [1, 4, 11])
@pytest.mark.parametrize("n_net", [0, 1, 700])
def test_numba_loss_matches_torch(dtype, materials, n_net, upstream):
    hidden, layer, rest = _batch(1000, n_net, materials, width=40 if materials != 4 else 128)
    hidden = hidden.to(dtype)
    weights = LossConfig(occlusion=1.0, distance=2.0, normal=0.5, albedo=3.0, material=0.25)
    ref = _run(training_loss_torch, hidden, layer, rest, weights, materials, upstream)
    new = _run(training_loss_numba, hidden, layer, rest, weights, materials, upstream)
    assert new[0].parts.keys() == ref[0].parts.keys()
    for k in ref[0].parts:
        assert new[0].parts[k] == pytest.approx(ref[0].parts[k], rel=1e-5, abs=1e-7), k
    assert float(new[0].loss.detach()) == pytest.approx(float(ref[0].loss.detach()), rel=1e-5, abs=1e-7)
    truth, active = rest[5], rest[0]
    assert (new[0].wrong_network, new[0].missed_outside, new[0].truncated) == (
        ref[0].wrong_network, int(truth.hit.sum() - truth.hit[active].sum()), 17)
    assert ref[1].dtype == new[1].dtype == dtype
    # fp32: sums in another order; bf16: the same sums rounded to bf16 may land one step apart (and
    # an upstream gradient other than 1, which training never hands in, scales the rounded values).
    tol = dict(rtol=1e-4, atol=1e-7) if dtype == torch.float32 else dict(rtol=2**-7, atol=1e-7)
    torch.testing.assert_close(new[1], ref[1], **tol)
    if dtype == torch.bfloat16 and n_net > 100 and upstream == 1.0:
        assert (new[1] == ref[1]).float().mean() > 0.99  # rounding steps agree but for rare ties
    torch.testing.assert_close(new[2], ref[2], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(new[3], ref[3], rtol=1e-4, atol=1e-6)
    if n_net > 3:  # (the first 3 hidden rows are zero)
        assert float(ref[2].abs().sum()) > 0 and float(ref[1].float().abs().sum()) > 0


@pytest.mark.parametrize("term", ["occlusion", "distance", "normal", "albedo", "material"])
def test_every_weight_is_used(term):
    """Zeroing one weight changes the numba loss and gradients exactly as it changes torch's."""
    hidden, layer, rest = _batch(600, 400, 3, seed=1)
    full = LossConfig()
    without = LossConfig(**{**full.model_dump(), term: 0.0})
    for implementation in (training_loss_torch, training_loss_numba):
        a = _run(implementation, hidden, layer, rest, full, 3)
        b = _run(implementation, hidden, layer, rest, without, 3)
        assert float(a[0].loss.detach()) - float(b[0].loss.detach()) == pytest.approx(a[0].parts[term], rel=1e-5)
        assert not torch.allclose(a[2], b[2])
    ref = _run(training_loss_torch, hidden, layer, rest, without, 3)
    new = _run(training_loss_numba, hidden, layer, rest, without, 3)
    assert float(new[0].loss.detach()) == pytest.approx(float(ref[0].loss.detach()), rel=1e-5)
    for r, n in zip(ref[1:], new[1:]):
        torch.testing.assert_close(n, r, rtol=1e-4, atol=1e-6)


def test_numba_loss_is_the_same_on_any_thread_count():
    """The rows run in fixed chunks whose partials are added in chunk order: one thread and all of
    them give the same loss and gradients, bit for bit (more rows than one chunk)."""
    import numba

    hidden, layer, rest = _batch(6000, 4500, 4, width=64, seed=2)
    hidden = hidden.to(torch.bfloat16)
    weights = LossConfig()
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = _run(training_loss_numba, hidden, layer, rest, weights, 4)
    finally:
        numba.set_num_threads(threads)
    every = _run(training_loss_numba, hidden, layer, rest, weights, 4)
    assert one[0].parts == every[0].parts and one[0].wrong_network == every[0].wrong_network
    for a, b in zip(one[1:], every[1:]):
        assert torch.equal(a, b)


@pytest.mark.parametrize("implementation", [training_loss_numba, training_loss_torch])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_padding_rows_of_hidden_are_ignored(implementation, dtype):
    """``hidden`` with rows past the network rays' (the MLP's row padding, written by the encoder):
    the same loss and gradients as without them, and a zero gradient in those rows."""
    hidden, layer, rest = _batch(1000, 700, 4, width=128, seed=3)
    hidden = hidden.to(dtype)
    padded = torch.cat([hidden, torch.full((68, 128), 7.0, dtype=dtype)])  # (nonzero: they must not count)
    weights = LossConfig()
    plain = _run(implementation, hidden, layer, rest, weights, 4)
    extra = _run(implementation, padded, layer, rest, weights, 4)
    assert plain[0].parts == extra[0].parts and float(plain[0].loss.detach()) == float(extra[0].loss.detach())
    assert extra[1].shape == padded.shape and torch.equal(extra[1][:700], plain[1]) and (extra[1][700:] == 0).all()
    assert torch.equal(extra[2], plain[2]) and torch.equal(extra[3], plain[3])

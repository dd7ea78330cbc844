"""LSNIF training loss: the numba pass (CPU) against the torch ops (the reference), values and gradients."""

import pytest
import torch

from neuralrt.methods.lsnif_config import LossConfig
from neuralrt.methods.lsnif_loss import training_loss_numba, training_loss_torch
from neuralrt.rays import Hits


def _batch(n_rays: int, n_net: int, materials: int, hit_fraction: float = 0.6, seed: int = 0):
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
    out = torch.randn(n_net, 8 + materials, generator=g) * 2
    out[:3, 2:5] = 0  # a zero normal output (cosine's eps clamp)
    t_enter = torch.rand(n_net, generator=g)
    t_exit = t_enter + torch.rand(n_net, generator=g) * 3
    t_exit[:2] = t_enter[:2]  # empty interval (the 1e-12 clamp)
    t_offset = torch.rand(n_net, generator=g) * 0.1
    return out, active, t_offset, t_enter, t_exit, directions, truth


def _run(implementation, args, weights: LossConfig, materials: int):
    out = args[0].clone().requires_grad_(True)
    result = implementation(out, *args[1:], weights, materials, 0.3, torch.tensor(17))
    (result.loss * 1.5).backward()  # a non-unit upstream gradient
    return result, out.grad


@pytest.mark.parametrize("materials", [1, 4])
@pytest.mark.parametrize("n_net", [0, 1, 700])
def test_numba_loss_matches_torch(materials, n_net):
    args = _batch(1000, n_net, materials)
    weights = LossConfig(occlusion=1.0, distance=2.0, normal=0.5, albedo=3.0, material=0.25)
    ref, ref_grad = _run(training_loss_torch, args, weights, materials)
    new, new_grad = _run(training_loss_numba, args, weights, materials)
    assert new.parts.keys() == ref.parts.keys()
    for k in ref.parts:
        assert new.parts[k] == pytest.approx(ref.parts[k], rel=1e-5, abs=1e-7), k
    assert float(new.loss.detach()) == pytest.approx(float(ref.loss.detach()), rel=1e-5, abs=1e-7)
    assert (new.wrong_network, new.missed_outside, new.truncated) == (ref.wrong_network, ref.missed_outside, ref.truncated) == (
        ref.wrong_network, int(args[6].hit.sum() - args[6].hit[args[1]].sum()), 17)
    torch.testing.assert_close(new_grad, ref_grad, rtol=1e-4, atol=1e-8)
    if n_net:
        assert float(ref_grad.abs().sum()) > 0


@pytest.mark.parametrize("term", ["occlusion", "distance", "normal", "albedo", "material"])
def test_every_weight_is_used(term):
    """Zeroing one weight changes the numba loss and gradient exactly as it changes torch's."""
    args = _batch(600, 400, 3, seed=1)
    full = LossConfig()
    without = LossConfig(**{**full.model_dump(), term: 0.0})
    for implementation in (training_loss_torch, training_loss_numba):
        a, grad_a = _run(implementation, args, full, 3)
        b, grad_b = _run(implementation, args, without, 3)
        assert float(a.loss.detach()) - float(b.loss.detach()) == pytest.approx(a.parts[term], rel=1e-5)
        assert not torch.allclose(grad_a, grad_b)
    ref_b, ref_grad_b = _run(training_loss_torch, args, without, 3)
    new_b, new_grad_b = _run(training_loss_numba, args, without, 3)
    assert float(new_b.loss.detach()) == pytest.approx(float(ref_b.loss.detach()), rel=1e-5)
    torch.testing.assert_close(new_grad_b, ref_grad_b, rtol=1e-4, atol=1e-8)

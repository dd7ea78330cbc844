"""NIF's training step: the numba CPU step (hand-written backward, numba Adam) equals autograd with
torch's optimizers, step after step, on both network kinds; the trainer picks it on the CPU."""

import pytest
import torch

from neuralrt.methods.nif import NIFNetworks
from neuralrt.methods.nif_config import NIFConfig, NIFTrainingConfig
from neuralrt.methods.nif_step import NumbaNIFStep, TorchNIFStep, nif_step_for
from neuralrt.methods.nif_training import NIFTrainer
from neuralrt.rays import AABB


def _networks():
    box = AABB(torch.full((3,), -1.0), torch.full((3,), 1.0))
    cfg = NIFConfig(training=NIFTrainingConfig(init_scale=0.3, seed=2))  # large features: every layer matters
    return NIFNetworks(cfg, [box, box])


def _columns(kind: str, n: int, g: torch.Generator) -> list[torch.Tensor]:
    obj = torch.randint(0, 2, (n,), generator=g)
    uv = torch.rand(n, 2, generator=g)
    uv[:8, 0] = torch.tensor([0.0, 1.0]).repeat(4)  # poles
    direction = torch.rand(n, 2, generator=g)
    label = (torch.rand(n, generator=g) < 0.4).float()
    if kind == "outer":
        return [obj, uv, direction, label]
    return [obj, uv, direction, torch.rand(n, generator=g) * 1.2 - 0.1, label]  # distance: clamped ends too


@pytest.mark.parametrize("kind", ["outer", "inner"])
def test_numba_step_equals_autograd_step(kind):
    g = torch.Generator().manual_seed(0)
    columns = _columns(kind, 3000, g)
    nets = [_networks() for _ in range(2)]
    assert all(torch.equal(a, b) for a, b in zip(nets[0].parameters(), nets[1].parameters()))
    steps = []
    for net, impl in zip(nets, (TorchNIFStep, NumbaNIFStep)):
        grids = [net.outer_position, net.outer_direction] if kind == "outer" else [net.inner_position, net.inner_direction, net.inner_distance]
        steps.append(impl(getattr(net, f"{kind}_mlp"), grids, lr=0.005, betas=(0.9, 0.999), eps=1e-15))
    losses = [[], []]
    for s in range(12):
        idx = torch.randperm(3000, generator=g)[:512 if s < 11 else 77]  # a short last batch too
        for k in range(2):
            losses[k].append(float(steps[k](columns, idx)))
    assert losses[0] == pytest.approx(losses[1], rel=1e-4)
    assert losses[0][-2] < losses[0][0]  # it learns
    start = _networks().state_dict()
    for (name, a), b in zip(nets[0].named_parameters(), nets[1].parameters()):
        assert torch.allclose(a, b, rtol=1e-4, atol=2e-6), name
        assert torch.equal(b, start[name]) != name.startswith(kind), name  # this kind's parameters moved, the other's did not
    for _, _, grad_sum, touched in steps[1].grid_state:  # the lazy update's scratch is clean between steps
        assert not grad_sum.any() and not touched.any()


def test_trainer_uses_the_numba_step_on_the_cpu():
    assert nif_step_for("cpu") is NumbaNIFStep and nif_step_for("cuda") is TorchNIFStep
    assert isinstance(NIFTrainer(_networks()).step_outer, NumbaNIFStep)

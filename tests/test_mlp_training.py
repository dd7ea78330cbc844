"""MLP: the bf16 hidden layers' training function against autocast (bit-equal values and gradients)."""

import pytest
import torch

from neuralrt.neural.mlp import MLP


def _forward_backward(mlp: MLP, x: torch.Tensor, mode: str, input_grad: bool):
    mlp.low_precision_training = mode
    mlp.zero_grad(set_to_none=True)
    x = x.clone().requires_grad_(input_grad)
    out = mlp(x, torch.bfloat16)
    (out.square().sum() + out[:, 0].sum()).backward()
    return out.detach(), x.grad, [p.grad.clone() for p in mlp.parameters()]


@pytest.mark.parametrize("slope", [0.01, 0.0])  # LSNIF/NIF leaky ReLU, N-BVH ReLU
@pytest.mark.parametrize("input_grad", [True, False])  # the hash grid needs the input gradient; a plain input does not
def test_function_matches_autocast_bit_for_bit(slope, input_grad):
    g = torch.Generator().manual_seed(3)
    mlp = MLP(37, 5, hidden_width=32, hidden_layers=3, slope=slope, generator=g)
    x = torch.randn(301, 37, generator=g)
    x[:7] = 0  # first-layer pre-activations exactly 0 (its bias stays 0): the mask must take autocast's branch
    with torch.no_grad():
        for layer in mlp.hidden[1:]:
            layer.bias.normal_(0, 0.1, generator=g)
    ref = _forward_backward(mlp, x, "autocast", input_grad)
    new = _forward_backward(mlp, x, "function", input_grad)
    assert torch.equal(ref[0], new[0])
    assert (ref[1] is None) == (new[1] is None) == (not input_grad)
    if input_grad:
        assert torch.equal(ref[1], new[1])
    for a, b in zip(ref[2], new[2]):
        assert a.dtype == b.dtype == torch.float32
        assert torch.equal(a, b)
    assert any(p.abs().sum() > 0 for p in new[2])

"""MLP: the bf16 hidden layers' training function against autocast (bit-equal values and gradients)."""

import numpy as np
import pytest
import torch

from neuralrt.neural import mlp as mlp_module
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


@pytest.mark.parametrize("rows", [1, 255, 301, 5391])
def test_rows_padded_for_the_gemms_change_nothing(rows, monkeypatch):
    """bf16 GEMMs on the CPU run on rows padded to a bucket (oneDNN keeps a kernel per shape): the
    answers are those of the unpadded rows, and the zero-gradient padding rows add nothing to the
    weights' gradients (a 4096-row bucket makes 301 rows 93% padding)."""
    g = torch.Generator().manual_seed(5)
    mlp = MLP(37, 5, hidden_width=64, hidden_layers=3, generator=g)
    with torch.no_grad():
        for layer in mlp.hidden:
            layer.bias.normal_(0, 0.5, generator=g)  # padding rows' activations are leaky(bias), not 0
    x = torch.randn(rows, 37, generator=g)
    results = []
    for bucket in (1, 256, 4096):
        monkeypatch.setitem(mlp_module.ROW_BUCKET, "cpu", bucket)
        assert mlp_module.padded_rows(rows, torch.device("cpu")) % bucket == 0
        with torch.no_grad():
            inference = mlp(x, torch.bfloat16)
        results.append((inference, *_forward_backward(mlp, x, "function", True)))
    reference = results[0]
    for inference, out, x_grad, grads in results[1:]:
        assert inference.shape == out.shape == (rows, 5)
        assert torch.equal(inference, reference[0]) and torch.equal(out, reference[1])  # rows are independent
        assert torch.equal(x_grad, reference[2])
        for a, b in zip(grads, reference[3]):  # sums over rows: the order may differ with their count
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_large_row_counts_pad_to_few_shapes_and_little_padding():
    """Above 16k rows the GEMM rows round to 1/32 of their power of two: at most ~3% padding, and
    at most 32 shapes per doubling of the row count (a renderer's batch sizes vary every call;
    each new shape is a new oneDNN kernel)."""
    cpu = torch.device("cpu")
    rng = np.random.default_rng(3)
    counts = rng.integers(1 << 14, 1 << 20, size=5000)
    padded = [mlp_module.padded_rows(int(n), cpu) for n in counts]
    assert all(p >= n and (p - n) <= n / 32 and p % 256 == 0 for n, p in zip(counts, padded))
    for k in range(14, 20):  # shapes per octave
        assert len({p for n, p in zip(counts, padded) if (1 << k) <= n < (1 << (k + 1))}) <= 32
    assert mlp_module.padded_rows(5_391, cpu) == 5_632  # training batches: 256-row buckets, as before

"""The fully connected network every neural intersector ends in (LSNIF, N-BVH and NIF use the same shape).

``hidden_layers`` leaky-ReLU layers of ``hidden_width`` neurons, Kaiming init, then a linear output
layer. Hidden layers may run in bf16 (see `neuralrt.neural.precision`); the output layer always
runs in fp32 so that distance outputs keep fp32 resolution.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["MLP"]


class MLP(nn.Module):
    """``in_features`` -> ``hidden_layers`` x ``hidden_width`` (leaky ReLU) -> ``out_features`` (linear).

    Parameters are fp32; ``generator`` seeds the Kaiming-uniform init (biases start at 0); the
    global torch RNG is not used. ``low_precision_training`` picks how bf16 hidden layers train:
    ``"function"`` (one autograd function, `_LowPrecisionHidden`) or ``"autocast"`` (the same
    values, bit for bit, with more work around the GEMMs; kept as its reference).
    """

    low_precision_training = "function"

    def __init__(self, in_features: int, out_features: int, hidden_width: int = 128, hidden_layers: int = 2, slope: float = 0.01,
                 generator: torch.Generator | None = None):
        super().__init__()
        widths = [in_features] + [hidden_width] * hidden_layers
        # skip_init: nn.Linear's own init would draw from the global RNG; ``generator`` sets every value below.
        # (skip_init ignores a default-device context: the meta device of a model file's check.)
        device = torch.get_default_device() if hasattr(torch, "get_default_device") else None  # (torch >= 2.3)
        self.hidden = nn.ModuleList(nn.utils.skip_init(nn.Linear, a, b, device=device) for a, b in zip(widths[:-1], widths[1:]))
        self.output = nn.utils.skip_init(nn.Linear, widths[-1], out_features, device=device)
        self.slope = slope
        for layer in self.hidden:
            nn.init.kaiming_uniform_(layer.weight, a=slope, nonlinearity="leaky_relu", generator=generator)
            nn.init.zeros_(layer.bias)
        nn.init.kaiming_uniform_(self.output.weight, a=1.0, nonlinearity="linear", generator=generator)
        nn.init.zeros_(self.output.bias)

    def forward(self, x: Tensor, compute_dtype: torch.dtype = torch.float32) -> Tensor:
        """[M, in_features] -> [M, out_features] fp32. With ``compute_dtype=torch.bfloat16`` the hidden
        layers run in bf16 (about 2x faster on CPUs with native bf16, and on GPUs)."""
        if compute_dtype != torch.float32 and not torch.is_grad_enabled():
            # Inference: reuse bf16 copies of the weights instead of casting them every call.
            rows = len(x)
            x = _pad_rows(x.to(compute_dtype), padded_rows(rows, x.device))
            for w, b in self._cast_weights(compute_dtype):
                x = F.leaky_relu(F.linear(x, w, b), self.slope)
            return self.output(x[:rows].float())
        return self.output(self.hidden_forward(x, compute_dtype).float())

    def hidden_forward(self, x: Tensor, compute_dtype: torch.dtype = torch.float32) -> Tensor:
        """The last hidden layer's activations [M, hidden_width] in ``compute_dtype`` (training: what
        `forward` hands the fp32 output layer; a loss may run that layer itself)."""
        if compute_dtype != torch.float32 and self.low_precision_training == "autocast":
            with torch.autocast(device_type=x.device.type, dtype=compute_dtype):
                for layer in self.hidden:
                    x = F.leaky_relu(layer(x), self.slope)
            return x
        if compute_dtype != torch.float32:
            weights = [p for layer in self.hidden for p in (layer.weight, layer.bias)]
            return _LowPrecisionHidden.apply(x, compute_dtype, self.slope, *weights)
        for layer in self.hidden:
            x = F.leaky_relu(layer(x), self.slope)
        return x

    def _cast_weights(self, dtype: torch.dtype) -> list[tuple[Tensor, Tensor]]:
        # Keyed on each parameter's storage and version counter: any update (optimizer step,
        # load, rounding, a move to another device) invalidates the copies.
        key = (dtype, tuple((p.data_ptr(), p._version) for p in self.hidden.parameters()))
        if getattr(self, "_cast_key", None) != key:
            self._cast = [(layer.weight.detach().to(dtype), layer.bias.detach().to(dtype)) for layer in self.hidden]
            self._cast_key = key
        return self._cast


# oneDNN (torch's CPU GEMMs) builds and caches a kernel per shape: a batch whose row count changes
# every step paid ~0.3-0.5 ms per GEMM for a new one (2 threads; 0.69 -> 1.21 ms for 5,391 x 126 x
# 128). Rows padded to a multiple of ROW_BUCKET reuse a few kernels (<= 4.7% more rows at 5,400).
# Larger row counts round to 1/32 of their power of two (<= ~3% more rows), so that a renderer's
# batches, a different size at every call, bring few shapes: on AMX a new 50,000 x 128 x 128 bf16
# shape took ~2 ms more than a known one (2 threads, Intel Xeon, session 23).
ROW_BUCKET = {"cpu": 256}


def padded_rows(rows: int, device: torch.device) -> int:
    """``rows`` rounded up to the device's GEMM row bucket (unchanged where there is none)."""
    bucket = ROW_BUCKET.get(device.type, 1)
    if bucket > 1:
        bucket = max(bucket, 1 << max(rows.bit_length() - 6, 0))
    return -(-rows // bucket) * bucket


def _pad_rows(x: Tensor, rows: int) -> Tensor:
    """``x`` with zero rows appended up to ``rows`` (``x`` itself when it has them)."""
    if len(x) == rows:
        return x
    out = x.new_empty((rows, *x.shape[1:]))
    out[: len(x)] = x
    out[len(x):] = 0
    return out


class _LowPrecisionHidden(torch.autograd.Function):
    """The hidden layers in ``dtype`` for training, as autocast computes them (same casts, GEMMs and
    sums, bit-equal), with less around them: each weight cast once for forward and backward, the
    activation applied in place, and the backward's slope mask taken from the layer outputs
    (output > 0 exactly where the pre-activation is, for slope >= 0), so no pre-activations are kept."""

    @staticmethod
    def forward(ctx, x: Tensor, dtype: torch.dtype, slope: float, *weights: Tensor) -> Tensor:
        rows = len(x)
        h = _pad_rows(x.to(dtype), padded_rows(rows, x.device))
        saved = [h]
        cast = []
        for w, b in zip(weights[::2], weights[1::2]):
            wc = w.to(dtype)
            h = F.leaky_relu_(torch.addmm(b.to(dtype), h, wc.t()), slope)
            saved.append(h)
            cast.append(wc)
        ctx.save_for_backward(*saved, *cast)
        ctx.slope, ctx.layers, ctx.x_dtype, ctx.rows = slope, len(cast), x.dtype, rows
        return h[:rows]

    @staticmethod
    def backward(ctx, grad: Tensor):
        tensors = ctx.saved_tensors
        acts, cast = tensors[: ctx.layers + 1], tensors[ctx.layers + 1:]
        # Padding rows get a zero gradient: they add nothing to the weights' and biases' gradients.
        g = _pad_rows(grad.to(acts[-1].dtype), len(acts[0]))
        grads = []
        for i in reversed(range(ctx.layers)):
            g = torch.ops.aten.leaky_relu_backward(g, acts[i + 1], ctx.slope, True)
            grads.append((g.sum(0).float(), (g.t() @ acts[i]).float()))
            g = g @ cast[i] if i > 0 or ctx.needs_input_grad[0] else None
        flat = [t for gb, gw in reversed(grads) for t in (gw, gb)]
        return (g[: ctx.rows].to(ctx.x_dtype) if g is not None else None), None, None, *flat

"""One NIF training step (a batch of labelled pairs of one network kind: outer or inner), in two
implementations with one contract, chosen once per device (`nif_step_for`).

``step = Impl(mlp, grids, lr, betas, eps)``; ``step(columns, idx)``: ``columns`` are a round's
pairs, ``(obj, coords of each grid..., label)`` (`NIFTrainer`'s buffers), ``idx`` [B] int64 the
batch. Forward the grids (bilinear) and the MLP, L2 loss between the sigmoid and the label (mean
over the batch), backward, then Adam on the MLP (``torch.optim.Adam``'s update) and lazy Adam on
the grid rows the batch touched (`nif_optim`). Returns the batch's mean loss (a 0-d tensor or a
float). Each implementation keeps its own optimizer state.

`TorchNIFStep` is autograd and torch optimizers (any device). `NumbaNIFStep` (CPU) writes the
backward out by hand: the GEMMs stay torch calls on one thread, everything else is a few numba
kernels (batch gather and grid lookup, leaky ReLU backward, the loss, Adam on each MLP tensor,
the grid gradient scattered straight into the lazy Adam rows). Profiled on statue(2)'s pairs
(docs/nif.md, "Training cost"): the autograd step spent ~70% of its time outside the GEMMs
(sparse gradient tensors, the optimizers' per-tensor ops, elementwise backward kernels) and
two-thread GEMMs of this size ran slower than one thread on the shared 2 cores. Both agree to
float32 rounding (tests/test_nif_step.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor, nn

from ..neural.dense_grid import SphericalGrid2D, corner_rows_1d, corner_rows_2d
from .nif_optim import LazyAdam, lazy_adam_weighted_numba

__all__ = ["TorchNIFStep", "NumbaNIFStep", "nif_step_for"]


class TorchNIFStep:
    """Autograd through the grids' lookups and the MLP; ``torch.optim.Adam`` for the MLP, `LazyAdam`
    for the grids (sparse gradients). Any device."""

    def __init__(self, mlp: nn.Module, grids: list[nn.Module], lr: float, betas: tuple[float, float], eps: float):
        self.mlp, self.grids = mlp, grids
        adam = dict(lr=lr, betas=tuple(betas), eps=eps)
        self.optimizers = (LazyAdam([g.table for g in grids], **adam), torch.optim.Adam(mlp.parameters(), **adam))

    def __call__(self, columns: list[Tensor], idx: Tensor) -> Tensor:
        obj, *coords, label = (c[idx] for c in columns)
        with torch.enable_grad():
            x = torch.cat([g(obj, c) for g, c in zip(self.grids, coords)], dim=-1)
            loss = (torch.sigmoid(self.mlp(x)[:, 0]) - label).square().mean()
            for o in self.optimizers:
                o.zero_grad(set_to_none=True)
            loss.backward()
        for o in self.optimizers:
            o.step()
        return loss.detach()


# -- numba kernels (CPU) ----------------------------------------------------------------------------
@numba.njit(cache=True)
def _lookup_2d(table, r, obj, uv, idx, x, col, corners, weights):
    """Batch rows ``idx`` of a `SphericalGrid2D` lookup (`corner_rows_2d`) into
    ``x[:, col:col + N]``, keeping each row's 4 corner rows and bilinear weights for the backward."""
    for i in range(idx.shape[0]):
        p = idx[i]
        (corners[i, 0], corners[i, 1], corners[i, 2], corners[i, 3],
         weights[i, 0], weights[i, 1], weights[i, 2], weights[i, 3]) = corner_rows_2d(obj[p], uv[p, 0], uv[p, 1], r)
        _gather_row(table, corners, weights, i, 4, x, col)


@numba.njit(cache=True)
def _lookup_1d(table, r, obj, s, idx, x, col, corners, weights):
    """`_lookup_2d` for a `DenseGrid1D` (`corner_rows_1d`, 2 corners)."""
    for i in range(idx.shape[0]):
        p = idx[i]
        corners[i, 0], corners[i, 1], weights[i, 0], weights[i, 1] = corner_rows_1d(obj[p], s[p], r)
        _gather_row(table, corners, weights, i, 2, x, col)


@numba.njit(cache=True)
def _gather_row(table, corners, weights, i, n_corners, x, col):
    for f in range(table.shape[1]):
        acc = np.float32(0.0)
        for c in range(n_corners):
            acc += weights[i, c] * table[corners[i, c], f]
        x[i, col + f] = acc


@numba.njit(cache=True)
def _sigmoid_l2_grad(z, label, idx, dz):
    """Sum over the batch of ``(sigmoid(z) - label)^2``; ``dz`` = d(mean loss)/dz."""
    total = 0.0
    scale = np.float32(2.0 / z.shape[0])
    one = np.float32(1.0)
    for i in range(z.shape[0]):
        s = one / (one + np.float32(math.exp(-z[i, 0])))
        e = s - label[idx[i]]
        total += e * e
        dz[i, 0] = scale * e * s * (one - s)
    return total


@numba.njit(cache=True)
def _leaky_relu_backward_(grad, out, slope):
    """``grad *= leaky'(pre)`` in place, read from the layer's output (same sign as its input for slope >= 0)."""
    s = np.float32(slope)
    for i in range(grad.shape[0]):
        for j in range(grad.shape[1]):
            if not out[i, j] > 0:
                grad[i, j] *= s


@numba.njit(cache=True)
def _adam_(p, g, m, v, lr, b1, b2, eps, bias1, bias2):
    """``torch.optim.Adam``'s single-tensor update (float32), on flat views."""
    step_size = np.float32(lr / bias1)
    bias2_sqrt = np.float32(math.sqrt(bias2))
    w1, b2f, w2, epsf = np.float32(1.0 - b1), np.float32(b2), np.float32(1.0 - b2), np.float32(eps)
    for k in range(p.shape[0]):
        gk = g[k]
        mk = m[k] + w1 * (gk - m[k])
        vk = v[k] * b2f + w2 * gk * gk
        m[k], v[k] = mk, vk
        p[k] -= step_size * (mk / (np.float32(math.sqrt(vk)) / bias2_sqrt + epsf))


class NumbaNIFStep:
    """The backward by hand: torch GEMMs on one thread, numba for the rest (CPU tensors only)."""

    def __init__(self, mlp: nn.Module, grids: list[nn.Module], lr: float, betas: tuple[float, float], eps: float):
        self.layers = [*mlp.hidden, mlp.output]
        self.slope = float(mlp.slope)
        self.grids = grids
        self.lr, (self.b1, self.b2), self.eps = float(lr), (float(betas[0]), float(betas[1])), float(eps)
        # per layer: Adam's moments of its weight and of its bias
        self.mlp_moments = [tuple((torch.zeros_like(p), torch.zeros_like(p)) for p in (layer.weight, layer.bias)) for layer in self.layers]
        # per grid: moments and the lazy update's scratch (all zero / False between steps)
        self.grid_state = [(torch.zeros_like(g.table), torch.zeros_like(g.table), torch.zeros_like(g.table),
                            torch.zeros(g.table.shape[0], dtype=torch.bool)) for g in grids]
        self.t = 0

    @torch.no_grad()
    def __call__(self, columns: list[Tensor], idx: Tensor) -> float:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # GEMMs this small: one thread measured faster on the shared cores (docs/nif.md)
        try:
            return self._step(columns, idx.contiguous())
        finally:
            torch.set_num_threads(threads)

    def _step(self, columns: list[Tensor], idx: Tensor) -> float:
        b = idx.shape[0]
        obj, *coords, label = columns
        idx_np, obj_np = idx.numpy(), obj.numpy()
        x = torch.empty(b, self.layers[0].in_features)
        col, lookups = 0, []
        for g, c in zip(self.grids, coords):
            k = 4 if isinstance(g, SphericalGrid2D) else 2
            corners, weights = np.empty((b, k), np.int64), np.empty((b, k), np.float32)
            lookup = _lookup_2d if isinstance(g, SphericalGrid2D) else _lookup_1d
            lookup(g.table.detach().numpy(), g.resolution, obj_np, c.numpy(), idx_np, x.numpy(), col, corners, weights)
            lookups.append((col, corners, weights))
            col += g.features
        # forward: keep every layer's input (the leaky ReLU's derivative is read from its output)
        acts = [x]
        for layer in self.layers[:-1]:
            h = torch.addmm(layer.bias, acts[-1], layer.weight.t())
            acts.append(torch.nn.functional.leaky_relu_(h, self.slope))
        out = self.layers[-1]
        z = torch.addmm(out.bias, acts[-1], out.weight.t())
        dz = torch.empty_like(z)
        loss = _sigmoid_l2_grad(z.numpy(), label.numpy(), idx_np, dz.numpy())
        # backward, last layer first; then Adam on each tensor as soon as its gradient exists
        self.t += 1
        bias1, bias2 = 1.0 - self.b1 ** self.t, 1.0 - self.b2 ** self.t
        grad = dz
        for k in range(len(self.layers) - 1, -1, -1):
            layer, a = self.layers[k], acts[k]
            g_w, g_b = torch.mm(grad.t(), a), grad.sum(0)
            grad_in = torch.mm(grad, layer.weight)  # before the weight moves
            if k > 0:
                _leaky_relu_backward_(grad_in.numpy(), a.numpy(), self.slope)
            for p, gp, (m, v) in zip((layer.weight, layer.bias), (g_w, g_b), self.mlp_moments[k]):
                _adam_(p.detach().view(-1).numpy(), gp.reshape(-1).numpy(), m.view(-1).numpy(), v.view(-1).numpy(),
                       self.lr, self.b1, self.b2, self.eps, bias1, bias2)
            grad = grad_in
        grad_np = grad.numpy()
        for g, (col, corners, weights), (m, v, grad_sum, touched) in zip(self.grids, lookups, self.grid_state):
            lazy_adam_weighted_numba(g.table.detach().numpy(), m.numpy(), v.numpy(), grad_sum.numpy(), touched.numpy(), corners, weights,
                                     grad_np, col, self.lr, self.b1, self.b2, self.eps, bias1, bias2)
        return loss / b


def nif_step_for(device) -> type[TorchNIFStep] | type[NumbaNIFStep]:
    """The implementation for ``device``: numba on the CPU, torch elsewhere."""
    return NumbaNIFStep if torch.device(device).type == "cpu" else TorchNIFStep


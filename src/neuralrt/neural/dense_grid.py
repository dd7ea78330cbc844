"""Dense trainable feature grids over spherical coordinates (NIF's encodings), one grid per object.

`SphericalGrid2D` holds, for each of ``objects`` objects, an ``R x R`` grid of ``N`` features over
``(u, v) = (theta / pi, (phi + pi) / 2 pi)`` (`spherical_coords`): bilinear between vertices,
periodic in azimuth ``v`` (vertex ``R`` is vertex 0, so there is no seam at phi = +-pi) and clamped
at the poles ``u = 0, 1`` (the first and last rows sit on the poles). `DenseGrid1D` is the same
along one clamped axis. All objects' grids live in one table, so one gather answers any mix of
objects (a per-query object index): NIF's "one grid gather per object" costs one call in total.

Lookups have one contract in two implementations: torch ops around one
`torch.nn.functional.embedding` gather (any device), and, for sparse grids on the CPU, numba
kernels that compute each query's corner rows and bilinear weights and gather in one pass
(`_WeightedRowGather`; its backward is two torch ops). With ``sparse=True`` the table's gradient
is sparse (the touched vertices' rows, uncoalesced), for a lazy Adam (NIF's trainer): dense
gradients and a dense Adam over a 256 x 256 x 3 table made a 2^11-pair training step 5x slower on
2 CPU cores (measured, docs/nif.md). The numba path replaces ~a dozen small torch ops forward and
backward per lookup (training steps are small: their per-op overhead dominated). Both agree to
float32 rounding, values and gradients (tests/test_nif.py). Features start
U(-init_scale, init_scale) from the given generator (NIF: 1e-4).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["spherical_coords", "SphericalGrid2D", "DenseGrid1D"]


def spherical_coords(v: Tensor) -> Tensor:
    """[M, 3] vectors -> [M, 2] ``(theta / pi, (phi + pi) / 2 pi)`` in [0, 1]: theta from +y (up), phi = atan2(z, x).

    A zero vector maps to (0.5, 0.5) (any value is as good; NIF only meets it at the box centre)."""
    length = torch.linalg.norm(v, dim=-1)
    cos_theta = torch.where(length > 0, v[:, 1] / length.clamp(min=1e-30), 0.0).clamp(-1.0, 1.0)
    theta = torch.acos(cos_theta)
    phi = torch.atan2(v[:, 2], v[:, 0])
    return torch.stack([theta / math.pi, (phi + math.pi) / (2.0 * math.pi)], dim=-1)


@numba.njit(cache=True)
def corner_rows_2d(obj, u, v, r):
    """One query's 4 table rows (top-left, top-right, bottom-left, bottom-right) and bilinear
    weights in a `SphericalGrid2D` table: periodic in ``v``, clamped at the poles (float32)."""
    one = np.float32(1.0)
    y = min(max(u * np.float32(r - 1), np.float32(0.0)), np.float32(r - 1))
    x = v * np.float32(r)
    y0 = min(math.floor(y), r - 2)
    x0 = math.floor(x)
    fy, fx = y - np.float32(y0), x - np.float32(x0)
    ix0 = int(x0) % r
    ix1 = (ix0 + 1) % r
    base = obj * (r * r) + int(y0) * r
    return (base + ix0, base + ix1, base + r + ix0, base + r + ix1,
            (one - fx) * (one - fy), fx * (one - fy), (one - fx) * fy, fx * fy)


@numba.njit(cache=True)
def corner_rows_1d(obj, s, r):
    """One query's 2 table rows and linear weights in a clamped `DenseGrid1D` table (float32)."""
    x = min(max(s * np.float32(r - 1), np.float32(0.0)), np.float32(r - 1))
    x0 = min(math.floor(x), r - 2)
    f = x - np.float32(x0)
    row = obj * r + int(x0)
    return row, row + 1, np.float32(1.0) - f, f


@numba.njit(cache=True)
def _corners_2d(obj, uv, r, corners, weights):
    """Every query's `corner_rows_2d`."""
    for i in range(obj.shape[0]):
        (corners[i, 0], corners[i, 1], corners[i, 2], corners[i, 3],
         weights[i, 0], weights[i, 1], weights[i, 2], weights[i, 3]) = corner_rows_2d(obj[i], uv[i, 0], uv[i, 1], r)


@numba.njit(cache=True)
def _corners_1d(obj, s, r, corners, weights):
    """Every query's `corner_rows_1d`."""
    for i in range(obj.shape[0]):
        corners[i, 0], corners[i, 1], weights[i, 0], weights[i, 1] = corner_rows_1d(obj[i], s[i], r)


@numba.njit(cache=True)
def _weighted_gather(table, corners, weights, out):
    for i in range(corners.shape[0]):
        for f in range(table.shape[1]):
            acc = np.float32(0.0)
            for c in range(corners.shape[1]):
                acc += weights[i, c] * table[corners[i, c], f]
            out[i, f] = acc


class _WeightedRowGather(torch.autograd.Function):
    """``out[i] = sum_c weights[i, c] * table[corners[i, c]]`` (numba, CPU); the table's gradient is sparse."""

    @staticmethod
    def forward(ctx, table: Tensor, corners: Tensor, weights: Tensor) -> Tensor:
        out = torch.empty(corners.shape[0], table.shape[1], dtype=table.dtype)
        _weighted_gather(table.detach().numpy(), corners.numpy(), weights.numpy(), out.numpy())
        ctx.save_for_backward(corners, weights)
        ctx.table_shape = table.shape
        return out

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        corners, weights = ctx.saved_tensors
        values = (weights[:, :, None] * grad_out[:, None, :]).reshape(-1, grad_out.shape[1])
        grad = torch.sparse_coo_tensor(corners.reshape(1, -1), values, ctx.table_shape, check_invariants=False)  # uncoalesced, as F.embedding's
        return grad, None, None


def _numba_lookup(table: Tensor, corners_of, obj: Tensor, coords: Tensor, r: int, k: int) -> Tensor:
    m = obj.shape[0]
    corners, weights = torch.empty(m, k, dtype=torch.int64), torch.empty(m, k, dtype=torch.float32)
    corners_of(obj.contiguous().numpy(), coords.detach().float().contiguous().numpy(), r, corners.numpy(), weights.numpy())
    return _WeightedRowGather.apply(table, corners, weights)


def _init_table(shape: tuple[int, ...], init_scale: float, generator: torch.Generator | None) -> nn.Parameter:
    table = (torch.rand(shape, generator=generator) * 2.0 - 1.0) * init_scale
    return nn.Parameter(table)


class SphericalGrid2D(nn.Module):
    """Per-object ``resolution x resolution`` grids of ``features`` values over spherical coordinates."""

    def __init__(self, objects: int, resolution: int, features: int, init_scale: float = 1e-4, generator: torch.Generator | None = None,
                 sparse: bool = False):
        super().__init__()
        if objects < 1 or resolution < 2 or features < 1:
            raise ValueError(f"need objects >= 1, resolution >= 2, features >= 1 (got {objects}, {resolution}, {features})")
        self.objects, self.resolution, self.features, self.sparse = objects, resolution, features, sparse
        # [objects * R (theta rows) * R (phi columns), N]: one table, row-major per object.
        self.table = _init_table((objects * resolution * resolution, features), init_scale, generator)

    def forward(self, obj: Tensor, uv: Tensor) -> Tensor:
        """Features [M, N] at ``uv`` [M, 2] (from `spherical_coords`) of objects ``obj`` [M] int64."""
        if self.sparse and self.table.device.type == "cpu":
            return _numba_lookup(self.table, _corners_2d, obj, uv, self.resolution, 4)
        return self.torch_forward(obj, uv)

    def torch_forward(self, obj: Tensor, uv: Tensor) -> Tensor:
        """`forward` in torch ops (any device)."""
        r = self.resolution
        y = (uv[:, 0] * (r - 1)).clamp(0.0, r - 1.0)  # theta: vertices on both poles, clamped
        x = uv[:, 1] * r  # phi: R vertices around, wrapping
        y0 = y.floor().clamp(max=r - 2)
        x0 = x.floor()
        fy, fx = (y - y0)[:, None], (x - x0)[:, None]
        y0, x0 = y0.long(), x0.long().remainder(r)
        x1 = (x0 + 1).remainder(r)
        base = obj * (r * r) + y0 * r
        corners = torch.stack([base + x0, base + x1, base + r + x0, base + r + x1], dim=1)  # [M, 4]
        v = F.embedding(corners, self.table, sparse=self.sparse)  # [M, 4, N], one gather
        top = v[:, 0] * (1.0 - fx) + v[:, 1] * fx
        bottom = v[:, 2] * (1.0 - fx) + v[:, 3] * fx
        return top * (1.0 - fy) + bottom * fy

    def memory_bytes(self, bytes_per_value: int) -> int:
        """Bytes of one object's grid (all ``features``) at ``bytes_per_value``."""
        return self.resolution * self.resolution * self.features * bytes_per_value


class DenseGrid1D(nn.Module):
    """Per-object 1D grids of ``resolution`` vertices over [0, 1] (clamped), ``features`` values each."""

    def __init__(self, objects: int, resolution: int, features: int, init_scale: float = 1e-4, generator: torch.Generator | None = None,
                 sparse: bool = False):
        super().__init__()
        if objects < 1 or resolution < 2 or features < 1:
            raise ValueError(f"need objects >= 1, resolution >= 2, features >= 1 (got {objects}, {resolution}, {features})")
        self.objects, self.resolution, self.features, self.sparse = objects, resolution, features, sparse
        self.table = _init_table((objects * resolution, features), init_scale, generator)

    def forward(self, obj: Tensor, s: Tensor) -> Tensor:
        """Features [M, N] at ``s`` [M] in [0, 1] (clamped) of objects ``obj`` [M] int64."""
        if self.sparse and self.table.device.type == "cpu":
            return _numba_lookup(self.table, _corners_1d, obj, s, self.resolution, 2)
        return self.torch_forward(obj, s)

    def torch_forward(self, obj: Tensor, s: Tensor) -> Tensor:
        """`forward` in torch ops (any device)."""
        r = self.resolution
        x = (s * (r - 1)).clamp(0.0, r - 1.0)
        x0 = x.floor().clamp(max=r - 2)
        f = (x - x0)[:, None]
        i0 = obj * r + x0.long()
        v = F.embedding(torch.stack([i0, i0 + 1], dim=1), self.table, sparse=self.sparse)  # [M, 2, N]
        return v[:, 0] * (1.0 - f) + v[:, 1] * f

    def memory_bytes(self, bytes_per_value: int) -> int:
        return self.resolution * self.features * bytes_per_value

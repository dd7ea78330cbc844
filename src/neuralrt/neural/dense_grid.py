"""Dense trainable feature grids over spherical coordinates (NIF's encodings), one grid per object.

`SphericalGrid2D` holds, for each of ``objects`` objects, an ``R x R`` grid of ``N`` features over
``(u, v) = (theta / pi, (phi + pi) / 2 pi)`` (`spherical_coords`): bilinear between vertices,
periodic in azimuth ``v`` (vertex ``R`` is vertex 0, so there is no seam at phi = +-pi) and clamped
at the poles ``u = 0, 1`` (the first and last rows sit on the poles). `DenseGrid1D` is the same
along one clamped axis. All objects' grids live in one table, so one gather answers any mix of
objects (a per-query object index): NIF's "one grid gather per object" costs one call in total.

Lookups are `torch.nn.functional.embedding` calls: any device, and with ``sparse=True`` the
table's gradient is sparse (only the touched vertices' rows), for a lazy Adam (NIF's trainer):
dense gradients and a dense Adam over a 256 x 256 x 3 table made a 2^11-pair training step 5x
slower on 2 CPU cores (measured, docs/nif.md). Features start U(-init_scale, init_scale) from the
given generator (NIF: 1e-4).
"""

from __future__ import annotations

import math

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
        r = self.resolution
        x = (s * (r - 1)).clamp(0.0, r - 1.0)
        x0 = x.floor().clamp(max=r - 2)
        f = (x - x0)[:, None]
        i0 = obj * r + x0.long()
        v = F.embedding(torch.stack([i0, i0 + 1], dim=1), self.table, sparse=self.sparse)  # [M, 2, N]
        return v[:, 0] * (1.0 - f) + v[:, 1] * f

    def memory_bytes(self, bytes_per_value: int) -> int:
        return self.resolution * self.features * bytes_per_value

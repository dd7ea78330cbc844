"""Random numbers and warps from the unit square to directions and points, batched over rays.

All functions take uniform samples as tensors (``u`` of shape [N, 2] or [N]) so that callers
control the random stream; `make_generator` gives a seeded, device-local stream.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "make_generator",
    "uniform",
    "orthonormal_basis",
    "to_local",
    "to_world",
    "cosine_hemisphere",
    "cosine_hemisphere_pdf",
    "uniform_sphere",
    "uniform_sphere_pdf",
    "uniform_triangle",
    "power_heuristic",
    "DiscreteDistribution",
    "luminance",
]


def make_generator(seed: int, device="cpu") -> torch.Generator:
    """A torch generator on ``device`` seeded with ``seed`` (the same seed gives the same stream)."""
    g = torch.Generator(device=torch.device(device))
    g.manual_seed(int(seed) & 0x7FFF_FFFF_FFFF_FFFF)
    return g


def uniform(shape, generator: torch.Generator, device="cpu") -> Tensor:
    """float32 uniforms in [0, 1) from ``generator``."""
    return torch.rand(shape, generator=generator, device=device, dtype=torch.float32)


def luminance(rgb: Tensor) -> Tensor:
    """Rec. 709 luminance of linear RGB, [..., 3] -> [...]."""
    return rgb @ torch.tensor([0.2126, 0.7152, 0.0722], dtype=rgb.dtype, device=rgb.device)


# --- frames --------------------------------------------------------------------------------------


def orthonormal_basis(n: Tensor) -> tuple[Tensor, Tensor]:
    """Tangent and bitangent for unit normals ``n`` [N, 3] (Duff et al. 2017, branchless)."""
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], -1)
    bt = torch.stack([b, sign + y * y * a, -y], -1)
    return t, bt


def to_local(v: Tensor, t: Tensor, b: Tensor, n: Tensor) -> Tensor:
    """World vectors into the frame (t, b, n): local z is the normal."""
    return torch.stack([(v * t).sum(-1), (v * b).sum(-1), (v * n).sum(-1)], -1)


def to_world(v: Tensor, t: Tensor, b: Tensor, n: Tensor) -> Tensor:
    return v[:, :1] * t + v[:, 1:2] * b + v[:, 2:3] * n


# --- warps ----------------------------------------------------------------------------------------


def _concentric_disk(u: Tensor) -> Tensor:
    """Shirley-Chiu concentric map of [0,1)^2 to the unit disk (low distortion)."""
    a = 2.0 * u - 1.0
    ax, ay = a[:, 0], a[:, 1]
    first = ax.abs() > ay.abs()
    r = torch.where(first, ax, ay)
    safe = torch.where(first, ax, ay)
    safe = torch.where(safe == 0, torch.ones_like(safe), safe)
    phi = torch.where(first, (math.pi / 4) * (ay / safe), math.pi / 2 - (math.pi / 4) * (ax / safe))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi)], -1)


def cosine_hemisphere(u: Tensor) -> Tensor:
    """Local directions with pdf cos(theta)/pi about +z, [N, 2] -> [N, 3]."""
    d = _concentric_disk(u)
    z = torch.sqrt(torch.clamp(1.0 - (d * d).sum(-1), min=0.0))
    return torch.cat([d, z[:, None]], -1)


def cosine_hemisphere_pdf(cos_theta: Tensor) -> Tensor:
    return torch.clamp(cos_theta, min=0.0) / math.pi


def uniform_sphere(u: Tensor) -> Tensor:
    """Directions uniform over the unit sphere, [N, 2] -> [N, 3]."""
    z = 1.0 - 2.0 * u[:, 0]
    r = torch.sqrt(torch.clamp(1.0 - z * z, min=0.0))
    phi = 2.0 * math.pi * u[:, 1]
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def uniform_sphere_pdf(n: int, device="cpu") -> Tensor:
    return torch.full((n,), 1.0 / (4.0 * math.pi), device=device)


def uniform_triangle(u: Tensor) -> Tensor:
    """Barycentric weights [N, 3] uniform over a triangle's area (square-root parameterisation)."""
    su = torch.sqrt(u[:, 0])
    b0 = 1.0 - su
    b1 = u[:, 1] * su
    return torch.stack([b0, b1, 1.0 - b0 - b1], -1)


def power_heuristic(pdf_a: Tensor, pdf_b: Tensor) -> Tensor:
    """Veach's power heuristic (beta = 2) weight of strategy a; 0 where both pdfs are 0."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    denom = a2 + b2
    return torch.where(denom > 0, a2 / torch.where(denom > 0, denom, 1.0), torch.zeros_like(denom))


class DiscreteDistribution:
    """Sampling indices proportional to non-negative weights [K] (inverse CDF by binary search)."""

    def __init__(self, weights: Tensor):
        w = torch.as_tensor(weights, dtype=torch.float64).clamp(min=0).reshape(-1)
        total = float(w.sum())
        if w.numel() == 0 or not math.isfinite(total) or total <= 0:
            raise ValueError("DiscreteDistribution needs finite weights with a positive sum")
        self.total = total
        self.pmf = (w / total).float()  # [K]
        cdf = torch.cumsum(w, 0) / total
        cdf[-1] = 1.0
        self.cdf = cdf  # float64 keeps the search exact for millions of entries

    def __len__(self) -> int:
        return self.pmf.numel()

    def to(self, device) -> "DiscreteDistribution":
        self.pmf, self.cdf = self.pmf.to(device), self.cdf.to(device)
        return self

    def sample(self, u: Tensor) -> Tensor:
        """Indices [N] int64 for uniforms ``u`` [N]; entries of zero weight are never chosen."""
        idx = torch.searchsorted(self.cdf, u.to(self.cdf.dtype).contiguous(), right=True)
        return idx.clamp_(max=len(self) - 1)

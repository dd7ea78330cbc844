"""Tangent-space normal maps at hits: the interpolated shading normal turned by a normal-map texel.

A texel (r, g, b) in [0, 1] encodes m = 2 (r, g, b) - 1 in the hit's tangent frame: x along the
tangent (increasing u), y along the bitangent w * cross(n, t) (increasing v: "green up", glTF's
and OpenGL's convention), z along the shading normal. The interpolated tangent is first made
orthogonal to the interpolated normal. Where the frame degenerates (zero length) or the texel
encodes no usable direction, the shading normal is kept: m pointing into the surface (z <= 0,
e.g. black texels or blue below 0.5) or much shorter than a unit vector (|m| < 0.5: a neutral
grey, which 8 bits cannot store as exactly 0.5, would otherwise tilt it by 55 degrees). One function per device family, the same float32 steps: numpy on the CPU
(`EmbreeMeshBLAS`), torch elsewhere (`mesh_blas_attributes`); tests hold them to each other.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # (torch is imported where used: mesh loading reads `usable_texel` without it)
    from torch import Tensor

__all__ = ["mapped_normals_numpy", "mapped_normals_torch", "interpolate_numpy", "usable_texel"]

_EPS = 1e-12  # squared length below which a vector counts as vanished
_MIN_TEXEL_LENGTH2 = 0.25  # an encoded unit vector's squared length is 1 up to 8-bit rounding


def interpolate_numpy(attribute: np.ndarray, corners: np.ndarray, bary_u: np.ndarray, bary_v: np.ndarray) -> np.ndarray:
    """bw * a + u * b + v * c per row (the hit kernels' order): ``corners`` [n, 3] vertex indices."""
    bu, bv = bary_u[:, None], bary_v[:, None]
    return (1.0 - bu - bv) * attribute[corners[:, 0]] + bu * attribute[corners[:, 1]] + bv * attribute[corners[:, 2]]


def usable_texel(m, length2):
    """[..., 1] bool: the decoded texel ``m`` points out of the surface and is about unit length."""
    return (m[..., 2:3] > 0) & (length2 >= _MIN_TEXEL_LENGTH2)


def mapped_normals_numpy(normal: np.ndarray, tangent: np.ndarray, texel: np.ndarray) -> np.ndarray:
    """[n, 3] float32 unit normals: ``normal`` [n, 3] unit shading normals turned by ``texel`` [n, 3]
    (the normal map's encoded values) in the frame of ``tangent`` [n, 4] (xyz, handedness w)."""
    normal, tangent, texel = (np.asarray(x, np.float32) for x in (normal, tangent, texel))
    m = texel * np.float32(2.0) - np.float32(1.0)
    t = tangent[:, :3] - normal * np.sum(normal * tangent[:, :3], axis=1, keepdims=True)
    t_len2 = np.sum(t * t, axis=1, keepdims=True)
    t = t / np.sqrt(np.maximum(t_len2, np.float32(_EPS)))
    b = np.where(tangent[:, 3:] < 0, np.float32(-1.0), np.float32(1.0)) * np.cross(normal, t)
    out = m[:, 0:1] * t + m[:, 1:2] * b + m[:, 2:3] * normal
    out_len2 = np.sum(out * out, axis=1, keepdims=True)
    usable = (t_len2 > _EPS) & (out_len2 > _EPS) & usable_texel(m, np.sum(m * m, axis=1, keepdims=True))
    return np.where(usable, out / np.sqrt(np.maximum(out_len2, np.float32(_EPS))), normal).astype(np.float32)


def mapped_normals_torch(normal: Tensor, tangent: Tensor, texel: Tensor) -> Tensor:
    """`mapped_normals_numpy` on torch tensors (any device)."""
    import torch

    m = texel * 2.0 - 1.0
    t = tangent[:, :3] - normal * (normal * tangent[:, :3]).sum(1, keepdim=True)
    t_len2 = (t * t).sum(1, keepdim=True)
    t = t / t_len2.clamp(min=_EPS).sqrt()
    b = torch.where(tangent[:, 3:] < 0, -1.0, 1.0) * torch.linalg.cross(normal, t, dim=1)
    out = m[:, 0:1] * t + m[:, 1:2] * b + m[:, 2:3] * normal
    out_len2 = (out * out).sum(1, keepdim=True)
    usable = (t_len2 > _EPS) & (out_len2 > _EPS) & usable_texel(m, (m * m).sum(1, keepdim=True))
    return torch.where(usable, out / out_len2.clamp(min=_EPS).sqrt(), normal)

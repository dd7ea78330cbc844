"""Per-vertex tangent frames of a UV-mapped mesh, for tangent-space normal maps.

Lengyel's construction (2001): each triangle's dP/du and dP/dv from its UV differences, summed at
its corners, made orthogonal to the vertex normal; the sign ``w`` says whether the UV map is
mirrored there (bitangent = w * cross(normal, tangent), the glTF convention). glTF asks for
MikkTSpace tangents when a file gives none; MikkTSpace splits vertices where frames differ and
weights corners by angle, so the two agree on smooth, unmirrored UV layouts and differ where a
vertex is shared by mirrored or sharply turning UV islands. Tangents are derived (never stored):
a `MeshBLAS` builds them once when a material has a normal map.
"""

from __future__ import annotations

import numpy as np

__all__ = ["vertex_tangents"]

_DEGENERATE_UV = 1e-20  # |du1 dv2 - du2 dv1| below it: the triangle's UVs give no direction


def vertex_tangents(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """[V, 4] float32: unit tangent (xyz, orthogonal to the vertex normal, along increasing u) and
    handedness w = +-1. Vertices whose triangles have no usable UVs get any unit vector orthogonal
    to their normal (and w = 1), so a frame always exists."""
    p = vertices.astype(np.float64)
    uv = uvs.astype(np.float64)
    n = normals.astype(np.float64)
    i0, i1, i2 = faces[:, 0], faces[:, 1], faces[:, 2]
    e1, e2 = p[i1] - p[i0], p[i2] - p[i0]
    d1, d2 = uv[i1] - uv[i0], uv[i2] - uv[i0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    usable = np.abs(det) > _DEGENERATE_UV
    r = np.where(usable, 1.0 / np.where(usable, det, 1.0), 0.0)[:, None]
    along_u = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * r
    along_v = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * r
    tangent, bitangent = _corner_sums(along_u, faces, len(p)), _corner_sums(along_v, faces, len(p))

    t = tangent - n * np.sum(n * tangent, axis=1, keepdims=True)
    length = np.linalg.norm(t, axis=1, keepdims=True)
    t = np.where(length > 1e-12, t / np.maximum(length, 1e-300), _any_orthogonal(n))
    w = np.where(np.sum(np.cross(n, t) * bitangent, axis=1) < 0.0, -1.0, 1.0)
    return np.concatenate([t, w[:, None]], axis=1).astype(np.float32)


def _corner_sums(per_face: np.ndarray, faces: np.ndarray, count: int) -> np.ndarray:
    """[V, 3]: each vertex's sum of ``per_face`` over the triangles it is a corner of."""
    corners = faces.reshape(-1)
    values = np.repeat(per_face, 3, axis=0)
    return np.stack([np.bincount(corners, weights=values[:, k], minlength=count) for k in range(3)], axis=1)


def _any_orthogonal(n: np.ndarray) -> np.ndarray:
    """A unit vector orthogonal to each row of ``n`` (x or y axis, whichever is less parallel)."""
    axis = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t = axis - n * np.sum(n * axis, axis=1, keepdims=True)
    return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-300)

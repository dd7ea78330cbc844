"""Loop subdivision for large meshes: trimesh's rules and results without its per-vertex Python
lists and int64/float64 temporaries (trimesh peaks at ~320 B per output triangle, too much at 50M)."""

import numba
import numpy as np

__all__ = ["loop_subdivided"]


@numba.njit(cache=True)
def _edge_sums(vertices, faces, edge_of_corner, n_edges):
    """Per unique edge: how many faces hold it (capped at 3) and the sum of their opposite vertices."""
    count = np.zeros(n_edges, np.int8)
    opposite = np.zeros((n_edges, 3))
    for f in range(faces.shape[0]):
        for k in range(3):
            e = edge_of_corner[3 * f + k]
            if count[e] < 3:
                count[e] += 1
            o = faces[f, (k + 2) % 3]
            for c in range(3):
                opposite[e, c] += vertices[o, c]
    return count, opposite


@numba.njit(cache=True)
def _even(vertices, edge_v, count):
    """The new positions of the old vertices (trimesh's rules: Warren's beta inside; a boundary
    vertex is 3/4 itself plus 1/8 of each neighbour that is also on a boundary)."""
    n = vertices.shape[0]
    valence = np.zeros(n, np.int64)
    nsum = np.zeros((n, 3))
    boundary = np.zeros(n, np.bool_)
    for e in range(edge_v.shape[0]):
        a, b = edge_v[e, 0], edge_v[e, 1]
        valence[a] += 1
        valence[b] += 1
        for c in range(3):
            nsum[a, c] += vertices[b, c]
            nsum[b, c] += vertices[a, c]
        if count[e] == 1:
            boundary[a] = True
            boundary[b] = True
    even = np.empty_like(vertices)
    bsum = np.zeros((n, 3))
    for e in range(edge_v.shape[0]):  # trimesh: a boundary vertex averages its boundary neighbours
        a, b = edge_v[e, 0], edge_v[e, 1]
        if boundary[a] and boundary[b]:
            for c in range(3):
                bsum[a, c] += vertices[b, c]
                bsum[b, c] += vertices[a, c]
    for v in range(n):
        k = valence[v]
        if boundary[v]:
            for c in range(3):
                even[v, c] = bsum[v, c] / 8.0 + 0.75 * vertices[v, c]
        elif k == 0:
            for c in range(3):
                even[v, c] = vertices[v, c]
        else:
            beta = (40.0 - (2.0 * np.cos(2 * np.pi / k) + 3) ** 2) / (64 * k)
            for c in range(3):
                even[v, c] = beta * nsum[v, c] + (1 - k * beta) * vertices[v, c]
    return even


def loop_subdivided(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One level of Loop subdivision: ([V + E, 3] float64 vertices, [4F, 3] int32 faces), the
    same triangles as ``trimesh.remesh.subdivide_loop`` (same corner order, same float64 positions)
    on meshes whose edges have at most two faces. The new edge vertices are numbered by sorted
    edge (trimesh numbers them otherwise)."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces)
    n = len(vertices)
    # corner k of face f starts edge (f[k], f[k+1]), as trimesh's faces_to_edges; key = lo * n + hi
    a = faces.reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)
    del a, b
    keys, edge_of_corner = np.unique(key, return_inverse=True)
    del key
    edge_of_corner = edge_of_corner.astype(np.int32)
    edge_v = np.stack([keys // n, keys % n], axis=1).astype(np.int32)
    del keys
    count, opposite = _edge_sums(vertices, faces, edge_of_corner, len(edge_v))
    if (count > 2).any():
        raise ValueError("some edges are shared by more than 2 faces")
    odd = 0.5 * (vertices[edge_v[:, 0]] + vertices[edge_v[:, 1]])
    inner = count == 2
    odd[inner] = 0.375 * vertices[edge_v[inner, 0]] + 0.375 * vertices[edge_v[inner, 1]] + opposite[inner] / 8.0
    del opposite, inner
    even = _even(vertices, edge_v, count)
    o = edge_of_corner.reshape(-1, 3) + np.int32(n)
    f = faces.astype(np.int32)
    new_faces = np.column_stack([f[:, 0], o[:, 0], o[:, 2], o[:, 0], f[:, 1], o[:, 1], o[:, 2], o[:, 1], f[:, 2], o[:, 0], o[:, 1], o[:, 2]]).reshape(-1, 3)
    return np.vstack([even, odd]), new_faces

"""Our own binned-SAH BVH over triangles, and its collapse into N-wide trees.

The tree is built for *accounting*, not for tracing (Embree traces our rays): `classical_memory`
counts the nodes of the 4-wide tree (the LSNIF paper's "BVH A") and of the 8-wide tree (the
compressed "BVH B" estimate of Ylitie et al. 2017). Building it ourselves means the node counts
are those of a real tree over the actual triangles, not a formula.

Build: top-down binary split over triangle centroids with the surface area heuristic evaluated at
``num_bins`` bin boundaries on each axis (Wald 2007), until a node holds at most
``max_leaf_size`` triangles. Collapse: each wide node starts from its binary node's two children
and repeatedly replaces the child with the largest surface area by that child's two children,
until it has ``width`` children or only leaves remain (as in Ylitie et al. and Embree's BVH4/8).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from ..errors import MeshError

__all__ = ["BVH", "build_box_bvh", "build_bvh", "collapse_bvh"]


@dataclass
class BVH:
    """An N-wide BVH as flat node arrays. Node 0 is the root; leaves reference ``prim_order``.

    - ``node_lo``, ``node_hi``: [M, 3] float32 bounds of each node.
    - ``children``: [M, width] int32 child node indices, -1 for an empty slot (all -1 in leaves).
    - ``leaf_start``, ``leaf_count``: [M] int32; a leaf holds the triangles
      ``prim_order[leaf_start : leaf_start + leaf_count]``; internal nodes have count 0.
    - ``prim_order``: [F] int32 triangle ids in leaf order (each triangle exactly once).
    """

    width: int
    max_leaf_size: int
    node_lo: np.ndarray
    node_hi: np.ndarray
    children: np.ndarray
    leaf_start: np.ndarray
    leaf_count: np.ndarray
    prim_order: np.ndarray

    @property
    def num_nodes(self) -> int:
        return int(len(self.node_lo))

    @property
    def is_leaf(self) -> np.ndarray:
        return self.leaf_count > 0

    @property
    def num_leaves(self) -> int:
        return int(self.is_leaf.sum())

    @property
    def num_internal(self) -> int:
        return self.num_nodes - self.num_leaves

    @property
    def num_triangles(self) -> int:
        return int(len(self.prim_order))

    def child_counts(self) -> np.ndarray:
        """[M] number of occupied child slots per node (0 for leaves)."""
        return (self.children >= 0).sum(1)

    def depth(self) -> int:
        """Number of nodes on the longest root-to-leaf path."""
        level, frontier = 0, np.array([0])
        while len(frontier):
            level += 1
            c = self.children[frontier].ravel()
            frontier = c[c >= 0]
        return level


# --- binary binned-SAH build --------------------------------------------------------------------


@numba.njit(cache=True)
def _area(lo0, lo1, lo2, hi0, hi1, hi2):
    dx, dy, dz = hi0 - lo0, hi1 - lo1, hi2 - lo2
    if dx < 0 or dy < 0 or dz < 0:
        return 0.0
    return 2.0 * (dx * dy + dy * dz + dz * dx)


@numba.njit(cache=True)
def _build_binary(tri_lo, tri_hi, max_leaf, num_bins):
    """Returns node_lo, node_hi, left, right, leaf_start, leaf_count, prim_order (trimmed)."""
    n = tri_lo.shape[0]
    cen = 0.5 * (tri_lo + tri_hi)
    order = np.arange(n).astype(np.int32)
    max_nodes = 2 * n
    node_lo = np.empty((max_nodes, 3), np.float32)
    node_hi = np.empty((max_nodes, 3), np.float32)
    left = np.full(max_nodes, -1, np.int32)
    right = np.full(max_nodes, -1, np.int32)
    leaf_start = np.zeros(max_nodes, np.int32)
    leaf_count = np.zeros(max_nodes, np.int32)
    # Depth-first: the stack never holds more than depth + 1 <= n + 1 entries (each split leaves
    # >= 1 triangle per side); SAH trees are ~log n deep but skewed inputs can go much deeper.
    stack_node = np.empty(n + 2, np.int64)
    stack_s = np.empty(n + 2, np.int64)
    stack_e = np.empty(n + 2, np.int64)
    bin_cnt = np.zeros((3, num_bins), np.int64)
    bin_lo = np.empty((3, num_bins, 3))
    bin_hi = np.empty((3, num_bins, 3))
    right_area = np.empty(num_bins)
    right_cnt = np.empty(num_bins, np.int64)

    n_nodes = 1
    sp = 0
    stack_node[0], stack_s[0], stack_e[0] = 0, 0, n
    sp = 1
    while sp > 0:
        sp -= 1
        node, s, e = stack_node[sp], stack_s[sp], stack_e[sp]
        # Bounds of the triangles and of their centroids.
        blo = np.full(3, np.inf)
        bhi = np.full(3, -np.inf)
        clo = np.full(3, np.inf)
        chi = np.full(3, -np.inf)
        for i in range(s, e):
            t = order[i]
            for k in range(3):
                blo[k] = min(blo[k], tri_lo[t, k])
                bhi[k] = max(bhi[k], tri_hi[t, k])
                clo[k] = min(clo[k], cen[t, k])
                chi[k] = max(chi[k], cen[t, k])
        for k in range(3):
            node_lo[node, k] = blo[k]
            node_hi[node, k] = bhi[k]
        count = e - s
        if count <= max_leaf:
            leaf_start[node] = s
            leaf_count[node] = count
            continue

        # Bin centroids on every axis with a non-zero extent.
        bin_cnt[:] = 0
        bin_lo[:] = np.inf
        bin_hi[:] = -np.inf
        for i in range(s, e):
            t = order[i]
            for a in range(3):
                ext = chi[a] - clo[a]
                if ext <= 0:
                    continue
                b = int(num_bins * (cen[t, a] - clo[a]) / ext)
                if b >= num_bins:
                    b = num_bins - 1
                bin_cnt[a, b] += 1
                for k in range(3):
                    bin_lo[a, b, k] = min(bin_lo[a, b, k], tri_lo[t, k])
                    bin_hi[a, b, k] = max(bin_hi[a, b, k], tri_hi[t, k])

        # SAH sweep: cost(split after bin b) = A_left * N_left + A_right * N_right.
        best_cost, best_axis, best_bin = np.inf, -1, -1
        for a in range(3):
            if chi[a] - clo[a] <= 0:
                continue
            lo0, lo1, lo2 = np.inf, np.inf, np.inf
            hi0, hi1, hi2 = -np.inf, -np.inf, -np.inf
            c = 0
            for b in range(num_bins - 1, 0, -1):
                c += bin_cnt[a, b]
                lo0, lo1, lo2 = min(lo0, bin_lo[a, b, 0]), min(lo1, bin_lo[a, b, 1]), min(lo2, bin_lo[a, b, 2])
                hi0, hi1, hi2 = max(hi0, bin_hi[a, b, 0]), max(hi1, bin_hi[a, b, 1]), max(hi2, bin_hi[a, b, 2])
                right_cnt[b] = c
                right_area[b] = _area(lo0, lo1, lo2, hi0, hi1, hi2)
            lo0, lo1, lo2 = np.inf, np.inf, np.inf
            hi0, hi1, hi2 = -np.inf, -np.inf, -np.inf
            c = 0
            for b in range(num_bins - 1):
                c += bin_cnt[a, b]
                lo0, lo1, lo2 = min(lo0, bin_lo[a, b, 0]), min(lo1, bin_lo[a, b, 1]), min(lo2, bin_lo[a, b, 2])
                hi0, hi1, hi2 = max(hi0, bin_hi[a, b, 0]), max(hi1, bin_hi[a, b, 1]), max(hi2, bin_hi[a, b, 2])
                if c == 0 or right_cnt[b + 1] == 0:
                    continue
                cost = _area(lo0, lo1, lo2, hi0, hi1, hi2) * c + right_area[b + 1] * right_cnt[b + 1]
                if cost < best_cost:
                    best_cost, best_axis, best_bin = cost, a, b

        mid = (s + e) // 2
        if best_axis >= 0:
            # Partition order[s:e] in place: bins <= best_bin go left.
            a = best_axis
            ext = chi[a] - clo[a]
            i, j = s, e - 1
            while i <= j:
                b = int(num_bins * (cen[order[i], a] - clo[a]) / ext)
                if b >= num_bins:
                    b = num_bins - 1
                if b <= best_bin:
                    i += 1
                else:
                    tmp = order[i]
                    order[i] = order[j]
                    order[j] = tmp
                    j -= 1
            if s < i < e:
                mid = i
        # else: all centroids coincide, so any split is as good: halve the range.

        l_node, r_node = n_nodes, n_nodes + 1
        n_nodes += 2
        left[node], right[node] = l_node, r_node
        stack_node[sp], stack_s[sp], stack_e[sp] = r_node, mid, e
        stack_node[sp + 1], stack_s[sp + 1], stack_e[sp + 1] = l_node, s, mid
        sp += 2
    return (node_lo[:n_nodes], node_hi[:n_nodes], left[:n_nodes], right[:n_nodes],
            leaf_start[:n_nodes], leaf_count[:n_nodes], order)


# --- collapse to N-wide -------------------------------------------------------------------------


@numba.njit(cache=True)
def _collapse(node_lo, node_hi, left, right, leaf_count, width):
    """Wide node -> binary node map and wide child slots (breadth-first numbering)."""
    m = node_lo.shape[0]
    area = np.empty(m)
    for b in range(m):
        area[b] = _area(node_lo[b, 0], node_lo[b, 1], node_lo[b, 2], node_hi[b, 0], node_hi[b, 1], node_hi[b, 2])
    source = np.empty(m, np.int64)  # binary node of each wide node
    children = np.full((m, width), -1, np.int32)
    source[0] = 0
    n_wide = 1
    slots = np.empty(width, np.int64)
    head = 0
    while head < n_wide:
        b = source[head]
        if leaf_count[b] == 0:
            slots[0], slots[1] = left[b], right[b]
            k = 2
            while k < width:
                # Open the internal child with the largest surface area.
                pick, pick_area = -1, -1.0
                for c in range(k):
                    if leaf_count[slots[c]] == 0 and area[slots[c]] > pick_area:
                        pick, pick_area = c, area[slots[c]]
                if pick < 0:
                    break
                opened = slots[pick]
                slots[pick] = left[opened]
                slots[k] = right[opened]
                k += 1
            for c in range(k):
                source[n_wide] = slots[c]
                children[head, c] = n_wide
                n_wide += 1
        head += 1
    return source[:n_wide], children[:n_wide]


# --- public API ---------------------------------------------------------------------------------


def _triangle_array(triangles) -> np.ndarray:
    tri = triangles.triangles() if hasattr(triangles, "triangles") else np.asarray(triangles)
    tri = np.asarray(tri, np.float32)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3) or len(tri) == 0:
        raise MeshError(f"BVH build: expected triangles of shape [F, 3, 3] with F > 0, got {tri.shape}")
    if not np.isfinite(tri).all():
        raise MeshError("BVH build: triangles contain NaN or Inf coordinates")
    return tri


def build_bvh(triangles, width: int = 2, max_leaf_size: int = 2, num_bins: int = 16) -> BVH:
    """Binned-SAH BVH over ``triangles`` (a `Mesh` or a [F, 3, 3] array), collapsed to ``width``.

    ``max_leaf_size`` defaults to 2, the LSNIF paper's BVH A ("the leaf node stores up to two
    triangles"); ``num_bins`` = 16 SAH candidate planes per axis and node. ``width`` 2 returns the
    binary tree itself; 4 and 8 give BVH A's and BVH B's layouts.
    """
    if max_leaf_size < 1 or num_bins < 2 or width < 2:
        raise ValueError(f"build_bvh: need max_leaf_size >= 1, num_bins >= 2, width >= 2 (got {max_leaf_size}, {num_bins}, {width})")
    tri = _triangle_array(triangles)
    lo, hi = tri.min(1).astype(np.float64), tri.max(1).astype(np.float64)
    node_lo, node_hi, left, right, start, count, order = _build_binary(lo, hi, int(max_leaf_size), int(num_bins))
    children = np.stack([left, right], 1)
    binary = BVH(2, int(max_leaf_size), node_lo, node_hi, children, start, count, order)
    return binary if width == 2 else collapse_bvh(binary, width)


def build_box_bvh(lo, hi, max_leaf_size: int = 1, num_bins: int = 16) -> BVH:
    """Binary binned-SAH BVH over axis-aligned boxes ``lo``/``hi`` [B, 3] (e.g. a scene's instance
    boxes) instead of triangles; ``prim_order`` holds box indices. Node bounds are exact float32
    unions of the float32 boxes."""
    lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
    if lo.ndim != 2 or lo.shape[1:] != (3,) or lo.shape != hi.shape or len(lo) == 0:
        raise ValueError(f"build_box_bvh: expected two [B, 3] arrays with B > 0, got {lo.shape} and {hi.shape}")
    node_lo, node_hi, left, right, start, count, order = _build_binary(
        lo.astype(np.float64), hi.astype(np.float64), int(max_leaf_size), int(num_bins))
    return BVH(2, int(max_leaf_size), node_lo, node_hi, np.stack([left, right], 1), start, count, order)


def collapse_bvh(binary: BVH, width: int) -> BVH:
    """Collapse a binary `BVH` into a ``width``-wide one by pulling up the largest-area children."""
    if binary.width != 2:
        raise ValueError(f"collapse_bvh: expected a binary BVH, got width {binary.width}")
    source, children = _collapse(binary.node_lo, binary.node_hi, binary.children[:, 0], binary.children[:, 1],
                                 binary.leaf_count, int(width))
    return BVH(int(width), binary.max_leaf_size, binary.node_lo[source], binary.node_hi[source], children,
               binary.leaf_start[source], binary.leaf_count[source], binary.prim_order)

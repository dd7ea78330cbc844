"""Memory of classical BVHs over a mesh, counted on trees we actually build (see docs/memory.md).

- **BVH A** (LSNIF paper, Table 1: "a 4-wide BVH ... the size of each internal node is 128 bytes and
  the leaf node stores up to two triangles"): every node of our 4-wide tree, internal and leaf,
  costs one 128-byte slot.
- **BVH B** (the paper's estimate for Ylitie et al. 2017's compressed wide BVH): 80-byte 8-wide
  internal nodes with quantised child boxes; leaves are not nodes but child slots that point into a
  triangle array in leaf order, costing a 4-byte triangle index per triangle.
- **mesh**: the vertex (float32 x 3) and index (int32 x 3) buffers. Like the paper's table, the BVH
  figures exclude these.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

from ..geometry.bvh import build_bvh, collapse_bvh
from ..geometry.mesh import Mesh

__all__ = [
    "BVH_A_NODE_BYTES",
    "BVH_B_NODE_BYTES",
    "BVH_B_TRIANGLE_INDEX_BYTES",
    "ClassicalMemory",
    "classical_memory",
]

BVH_A_NODE_BYTES = 128  # LSNIF Table 1: uncompressed 4-wide node (internal or leaf)
BVH_A_WIDTH = 4
BVH_B_NODE_BYTES = 80  # Ylitie et al. 2017: compressed 8-wide node
BVH_B_WIDTH = 8
BVH_B_TRIANGLE_INDEX_BYTES = 4  # leaf order -> mesh triangle id, one per triangle
MAX_LEAF_TRIANGLES = 2  # LSNIF Table 1: "the leaf node stores up to two triangles"


@dataclass
class ClassicalMemory:
    """Bytes of the mesh buffers and of BVH A / BVH B over it, with the node counts they come from."""

    name: str
    triangles: int
    vertices: int
    mesh_bytes: int  # 12 * vertices + 12 * triangles
    bvh_a_internal_nodes: int  # 4-wide internal nodes
    bvh_a_leaf_nodes: int  # leaves (<= 2 triangles each)
    bvh_a_bytes: int  # 128 * (internal + leaf nodes)
    bvh_b_nodes: int  # 8-wide internal nodes, at least 1 (leaves are child slots, not nodes)
    bvh_b_leaves: int  # leaf child slots (same leaves as BVH A)
    bvh_b_bytes: int  # 80 * nodes + 4 * triangles
    build_seconds: float  # binary SAH build + both collapses, wall clock

    @property
    def bvh_a_bytes_per_triangle(self) -> float:
        return self.bvh_a_bytes / self.triangles

    @property
    def bvh_b_bytes_per_triangle(self) -> float:
        return self.bvh_b_bytes / self.triangles

    def as_dict(self) -> dict:
        return {
            **asdict(self),
            "bvh_a_bytes_per_triangle": self.bvh_a_bytes_per_triangle,
            "bvh_b_bytes_per_triangle": self.bvh_b_bytes_per_triangle,
        }


def classical_memory(mesh: Mesh, num_bins: int = 16) -> ClassicalMemory:
    """Build our binned-SAH BVH over ``mesh`` (leaves <= 2 triangles), collapse it to 4- and
    8-wide, and count BVH A and BVH B bytes from the node counts (formulas in docs/memory.md).

    About 2 s per million triangles on one core (plus a one-off numba compile, cached on disk).
    """
    start = time.perf_counter()
    binary = build_bvh(mesh, width=2, max_leaf_size=MAX_LEAF_TRIANGLES, num_bins=num_bins)
    bvh_a = collapse_bvh(binary, BVH_A_WIDTH)
    bvh_b = collapse_bvh(binary, BVH_B_WIDTH)
    seconds = time.perf_counter() - start
    triangles = mesh.num_triangles
    # A compressed node always exists at the root: a one-leaf tree still needs one to point at it.
    b_nodes = max(bvh_b.num_internal, 1)
    return ClassicalMemory(
        name=mesh.name,
        triangles=triangles,
        vertices=int(len(mesh.vertices)),
        mesh_bytes=int(len(mesh.vertices) * 3 * 4 + triangles * 3 * 4),
        bvh_a_internal_nodes=bvh_a.num_internal,
        bvh_a_leaf_nodes=bvh_a.num_leaves,
        bvh_a_bytes=BVH_A_NODE_BYTES * bvh_a.num_nodes,
        bvh_b_nodes=b_nodes,
        bvh_b_leaves=bvh_b.num_leaves,
        bvh_b_bytes=BVH_B_NODE_BYTES * b_nodes + BVH_B_TRIANGLE_INDEX_BYTES * triangles,
        build_seconds=float(seconds),
    )

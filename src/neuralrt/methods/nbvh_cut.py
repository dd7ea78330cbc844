"""The N-BVH cut: base tree, split schedule, split choice, LoD registration, compaction.

The base tree is a binary SAH BVH of the object (`neuralrt.geometry.bvh`), in the model's unit
cube. A cut is a set of its nodes whose subtrees cover every triangle; it starts at the root and
grows when a live leaf is replaced by its two children (base leaves never split). Nodes are
ranked by h = loss_sum / sqrt(samples * alive_steps) (= q * sqrt(p): ranking by h equals ranking
by the paper's r = 2 log q + log p). The schedule is the authors' split scheduler
(METHODS-SPEC A3.3): at step s <= last_split with s % interval == 0, split the floor(k) leaves
with the largest h; k starts at 1 and is multiplied by ``split_scaling`` at steps 0, 2i, 4i, 8i, ...
With K LoDs, the live cut is registered as LoD L at step (K - L) * last_split / K (LoD 0, the
finest, at last_split). Each node keeps the finest LoD where it is a leaf (`NO_LOD` if none).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..geometry.bvh import build_bvh
from .nbvh_config import CutConfig
from .nbvh_traversal import NO_LOD

__all__ = ["base_tree", "split_count", "lod_to_register", "effective_last_split", "choose_splits", "kept_nodes", "compact"]


def base_tree(triangles_unit: np.ndarray, max_leaf_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lo [M, 3], hi [M, 3] float32, children [M, 2] int32) of the binary SAH BVH of unit-cube triangles."""
    bvh = build_bvh(triangles_unit.astype(np.float32), width=2, max_leaf_size=max_leaf_size)
    return bvh.node_lo.astype(np.float32), bvh.node_hi.astype(np.float32), bvh.children.astype(np.int32)


def effective_last_split(cut: CutConfig, steps: int) -> int:
    """The last split step of a run of ``steps`` steps (a shorter run ends its cut at its last step)."""
    return max(0, min(cut.last_split_step, steps - 1))


def split_count(step: int, cut: CutConfig, steps: int) -> int:
    """How many leaves the schedule splits after ``step`` (0 when it splits none)."""
    iv = cut.splitting_interval
    if step > effective_last_split(cut, steps) or step % iv:
        return 0
    k, event = 1.0, 0  # k grows after the splits of steps 0, 2 iv, 4 iv, 8 iv, ...
    while event < step:
        k *= cut.split_scaling
        event = 2 * iv if event == 0 else 2 * event
    return int(math.floor(k))


def lod_to_register(step: int, cut: CutConfig, steps: int) -> int | None:
    """The LoD whose cut is registered after ``step``'s splits, if any."""
    last = effective_last_split(cut, steps)
    for lod in range(cut.lods):
        if step == (cut.lods - lod) * last // cut.lods:
            return lod
    return None


def choose_splits(h: Tensor, live: Tensor, splittable: Tensor, count: int) -> Tensor:
    """Indices of the ``count`` (at most) live, splittable leaves with the largest h."""
    candidates = torch.nonzero(live & splittable).squeeze(1)
    count = min(count, len(candidates))
    if count <= 0:
        return candidates[:0]
    return candidates[torch.topk(h[candidates], count).indices]


def kept_nodes(children: np.ndarray, lod: np.ndarray) -> np.ndarray:
    """[M] bool: nodes that are a leaf of some registered LoD, and their ancestors."""
    keep = lod < NO_LOD
    # Children have larger indices than their parents: one pass from the back.
    for node in range(len(children) - 1, -1, -1):
        c = children[node, 0]
        if c >= 0 and (keep[c] or keep[c + 1]):
            keep[node] = True
    return keep


def compact(lo: np.ndarray, hi: np.ndarray, children: np.ndarray, lod: np.ndarray) -> tuple[np.ndarray, ...]:
    """The registered cuts as their own tree: kept nodes, renumbered in their original order
    (so siblings stay adjacent and ties in traversal order break the same way)."""
    keep = kept_nodes(children, lod)
    if not keep.any():
        keep[0] = True
    new_index = np.cumsum(keep) - 1
    kids = children[keep]
    has = (kids[:, 0] >= 0) & np.where(kids[:, 0] >= 0, keep[np.maximum(kids[:, 0], 0)], False)
    kids = np.where(has[:, None], new_index[np.maximum(kids, 0)], -1).astype(np.int32)
    return lo[keep], hi[keep], kids, lod[keep]

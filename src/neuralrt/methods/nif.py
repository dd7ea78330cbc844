"""NIF (Fujieda et al., HPG 2023): neural visibility of shadow rays against objects' boxes.

Per object, in object space, with ``c`` its box centre and ``sph`` = `spherical_coords`:

- a shadow ray starting OUTSIDE the box is an outer query: grid features at ``sph(entry - c)``
  (the point where it enters the box) and at ``sph(d)``, into the outer MLP (6 -> 64 -> 64 -> 1);
- a shadow ray starting INSIDE is an inner query: features at ``sph(o - c)``, ``sph(d)`` and at
  ``|o - c| / half diagonal`` (1D), into the inner MLP (13 -> 48 -> 48 -> 48 -> 1).

Leaky ReLU hidden layers (answering in bf16 where `neuralrt.neural.precision` picks it, training
in fp32), sigmoid output = probability that the object lets the ray through;
the ray is occluded by the object when it is below 1/2. Grids are per object (`neuralrt.neural.
dense_grid`, all objects in one table); ONE outer and ONE inner MLP serve every NIF object of a
scene (the paper's choice, Sec. 4.1). A ray that misses the object's box is visible without a query.

`NIFNetworks.occluded(pairs)` is stage 2 of the paper's two-stage execution: given every
(ray, object) pair of a batch of shadow rays (stage 1, `NIFPairs`), one grid gather per grid and
one MLP call for all outer pairs and one for all inner pairs, across objects.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..accel.blas import MemoryReport
from ..neural.dense_grid import DenseGrid1D, SphericalGrid2D, spherical_coords
from ..neural.mlp import MLP
from ..neural.precision import compute_dtype
from ..rays import AABB, ray_box_intervals
from .nif_config import NIFConfig, NIFNetworkConfig

__all__ = ["NIFPairs", "NIFQueries", "NIFNetworks", "make_queries"]


@dataclass
class NIFPairs:
    """(shadow ray, NIF object) pairs, each ray in its object's space (stage 1's output)."""

    obj: Tensor  # [P] int64 NIF object index
    origins: Tensor  # [P, 3] object space
    directions: Tensor  # [P, 3] object space, unnormalised (t is the world ray's)
    t_min: Tensor  # [P]
    t_max: Tensor  # [P]

    def __len__(self) -> int:
        return self.obj.numel()

    @staticmethod
    def cat(parts: list["NIFPairs"], device) -> "NIFPairs":
        if not parts:
            z = torch.zeros(0, device=device)
            return NIFPairs(torch.zeros(0, dtype=torch.int64, device=device), z.reshape(0, 3), z.reshape(0, 3), z, z)
        return NIFPairs(*(torch.cat([getattr(p, k) for p in parts]) for k in ("obj", "origins", "directions", "t_min", "t_max")))


@dataclass
class NIFQueries:
    """Network inputs of the pairs that meet their object's box, split into outer and inner."""

    outer_pair: Tensor  # [Po] int64 index into the pairs
    outer_obj: Tensor  # [Po] int64
    outer_position: Tensor  # [Po, 2] sph(entry - c)
    outer_direction: Tensor  # [Po, 2] sph(d)
    inner_pair: Tensor  # [Pi] int64
    inner_obj: Tensor  # [Pi]
    inner_position: Tensor  # [Pi, 2] sph(o - c)
    inner_direction: Tensor  # [Pi, 2]
    inner_distance: Tensor  # [Pi] |o - c| / half diagonal, in [0, 1]


def make_queries(pairs: NIFPairs, box_lo: Tensor, box_hi: Tensor) -> NIFQueries:
    """Classify ``pairs`` by their object's box (``box_lo``/``box_hi`` [O, 3], object space) and
    compute the spherical coordinates each network reads. Pairs whose interval misses the box get
    no query (the object cannot block them)."""
    lo, hi = box_lo[pairs.obj], box_hi[pairs.obj]
    o, d = pairs.origins, pairs.directions
    t0, t1 = ray_box_intervals(o, d, lo, hi)
    inside = ((o >= lo) & (o <= hi)).all(-1)
    meets = (t0 <= t1) & (t1 >= pairs.t_min) & (t0 <= pairs.t_max)  # [t_min, t_max], both ends included
    centre = 0.5 * (lo + hi)
    direction = spherical_coords(d)
    outer = torch.nonzero(meets & ~inside).reshape(-1)
    inner = torch.nonzero(meets & inside).reshape(-1)
    entry = o[outer] + torch.maximum(t0[outer], pairs.t_min[outer])[:, None] * d[outer]
    half_diagonal = 0.5 * torch.linalg.norm(hi[inner] - lo[inner], dim=-1).clamp(min=1e-30)
    to_origin = o[inner] - centre[inner]
    return NIFQueries(
        outer_pair=outer, outer_obj=pairs.obj[outer], outer_position=spherical_coords(entry - centre[outer]),
        outer_direction=direction[outer],
        inner_pair=inner, inner_obj=pairs.obj[inner], inner_position=spherical_coords(to_origin), inner_direction=direction[inner],
        inner_distance=(torch.linalg.norm(to_origin, dim=-1) / half_diagonal).clamp(0.0, 1.0),
    )


def _xavier_mlp(net: NIFNetworkConfig, inputs: int, slope: float, generator: torch.Generator) -> MLP:
    mlp = MLP(inputs, 1, hidden_width=net.hidden_width, hidden_layers=net.hidden_layers, slope=slope, generator=generator)
    with torch.no_grad():  # the paper's Xavier initialisation (MLP's default is Kaiming)
        for layer in [*mlp.hidden, mlp.output]:
            nn.init.xavier_uniform_(layer.weight, generator=generator)
    return mlp


class NIFNetworks(nn.Module):
    """The grids of ``len(boxes)`` NIF objects and the two shared MLPs.

    Args:
        config: `NIFConfig`.
        boxes: each object's box in its object space (already inflated by ``config.box_inflation``).
    """

    def __init__(self, config: NIFConfig, boxes: list[AABB]):
        super().__init__()
        if not boxes:
            raise ValueError("NIF needs at least one object")
        self.config = config
        g = torch.Generator().manual_seed(config.training.seed)
        n, s = len(boxes), config.training.init_scale
        out, inn = config.outer, config.inner
        # Sparse grid gradients: training updates only the vertices a batch touched (`NIFTrainer`).
        self.outer_position = SphericalGrid2D(n, out.position_grid.resolution, out.position_grid.features, s, g, sparse=True)
        self.outer_direction = SphericalGrid2D(n, out.direction_grid.resolution, out.direction_grid.features, s, g, sparse=True)
        self.inner_position = SphericalGrid2D(n, inn.position_grid.resolution, inn.position_grid.features, s, g, sparse=True)
        self.inner_direction = SphericalGrid2D(n, inn.direction_grid.resolution, inn.direction_grid.features, s, g, sparse=True)
        self.inner_distance = DenseGrid1D(n, inn.distance_grid.resolution, inn.distance_grid.features, s, g, sparse=True)
        self.outer_mlp = _xavier_mlp(out, out.input_width, config.leaky_relu_slope, g)
        self.inner_mlp = _xavier_mlp(inn, inn.input_width, config.leaky_relu_slope, g)
        self.register_buffer("box_lo", torch.stack([b.lo.float() for b in boxes]))
        self.register_buffer("box_hi", torch.stack([b.hi.float() for b in boxes]))

    @property
    def num_objects(self) -> int:
        return self.box_lo.shape[0]

    def outer_grids(self) -> list[nn.Parameter]:
        return [self.outer_position.table, self.outer_direction.table]

    def inner_grids(self) -> list[nn.Parameter]:
        return [self.inner_position.table, self.inner_direction.table, self.inner_distance.table]

    # -- the two networks' inputs (their logits: sigmoid = visibility) ------------------------------
    def outer_features(self, obj: Tensor, position: Tensor, direction: Tensor) -> Tensor:
        """[M, 6] outer MLP inputs: position grid then direction grid features."""
        return torch.cat([self.outer_position(obj, position), self.outer_direction(obj, direction)], dim=-1)

    def inner_features(self, obj: Tensor, position: Tensor, direction: Tensor, distance: Tensor) -> Tensor:
        """[M, 13] inner MLP inputs: position, direction and distance grid features."""
        return torch.cat([self.inner_position(obj, position), self.inner_direction(obj, direction), self.inner_distance(obj, distance)], dim=-1)

    def queries(self, pairs: NIFPairs) -> NIFQueries:
        return make_queries(pairs, self.box_lo, self.box_hi)

    @torch.no_grad()
    def occluded(self, pairs: NIFPairs, queries: NIFQueries | None = None) -> Tensor:
        """Stage 2: [P] bool, the pair's object blocks its ray (visibility < 1/2): one MLP call for
        every outer pair and one for every inner pair, whatever their objects."""
        q = self.queries(pairs) if queries is None else queries
        return self.occluded_from_features(len(pairs), q.outer_pair, self.outer_features(q.outer_obj, q.outer_position, q.outer_direction),
                                           q.inner_pair, self.inner_features(q.inner_obj, q.inner_position, q.inner_direction, q.inner_distance))

    @torch.no_grad()
    def occluded_from_features(self, n: int, outer_pair: Tensor, outer_x: Tensor, inner_pair: Tensor, inner_x: Tensor) -> Tensor:
        """[n] bool from the MLP inputs of the outer pairs ``outer_pair`` and inner pairs ``inner_pair``."""
        blocked = torch.zeros(n, dtype=torch.bool, device=outer_x.device)
        dtype = compute_dtype(self.config.compute_precision, outer_x.device)
        if outer_pair.numel():  # logit < 0 <=> sigmoid < 1/2
            blocked[outer_pair] = self.outer_mlp(outer_x, dtype)[:, 0] < 0
        if inner_pair.numel():
            blocked[inner_pair] = self.inner_mlp(inner_x, dtype)[:, 0] < 0
        return blocked

    # -- memory --------------------------------------------------------------------------------
    def memory_report(self) -> dict:
        """Bytes in both conventions: the paper's (4 R^2 bytes per object for each network kind's
        grids, N ignored, Sec. 5; MLPs as float32 weights without biases, the paper's 18 kB and
        21 kB) and the real run-time bytes (every grid with its N features at the precision held,
        float32; MLP weights and biases), per object and in total."""
        held = self.outer_position.table.element_size()
        r_out, r_in = self.outer_position.resolution, self.inner_position.resolution
        paper_per_object = 4 * r_out * r_out + 4 * r_in * r_in
        real_per_object = {
            "outer_grids": self.outer_position.memory_bytes(held) + self.outer_direction.memory_bytes(held),
            "inner_grids": self.inner_position.memory_bytes(held) + self.inner_direction.memory_bytes(held)
            + self.inner_distance.memory_bytes(held),
        }
        mlp = {"outer_mlp": sum(p.numel() for p in self.outer_mlp.parameters()) * held,
               "inner_mlp": sum(p.numel() for p in self.inner_mlp.parameters()) * held}
        weights = lambda mlp: sum(layer.weight.numel() for layer in [*mlp.hidden, mlp.output]) * 4  # noqa: E731
        n = self.num_objects
        return {
            "objects": n,
            "bytes_per_value": held,
            "paper_bytes_per_object": paper_per_object,
            "paper_bytes": paper_per_object * n,
            "paper_mlp_bytes": {"outer_mlp": weights(self.outer_mlp), "inner_mlp": weights(self.inner_mlp)},
            "real_bytes_per_object": real_per_object,
            "mlp_bytes": mlp,
            "real_bytes": sum(real_per_object.values()) * n + sum(mlp.values()),
        }

    def memory_bytes(self) -> MemoryReport:
        r = self.memory_report()
        return MemoryReport({"nif_grids": sum(r["real_bytes_per_object"].values()) * r["objects"], "nif_mlps": sum(r["mlp_bytes"].values())})

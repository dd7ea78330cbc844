"""The bottom-level accelerator (BLAS) interface every intersector implements.

A BLAS answers rays for one object in that object's own space. `MeshBLAS` answers exactly with
Embree; neural methods (`LSNIFBLAS`, ...) answer with a model. The scene TLAS and the integrator
only ever see this protocol.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from torch import Tensor

from ..rays import AABB, Hits, Rays


@dataclass
class MemoryReport:
    """Run-time memory of an accelerator, itemised: ``parts`` maps a name to bytes."""

    parts: dict[str, int] = field(default_factory=dict)

    @property
    def total(self) -> int:
        return int(sum(self.parts.values()))

    def __add__(self, other: "MemoryReport") -> "MemoryReport":
        merged = dict(self.parts)
        for k, v in other.parts.items():
            merged[k] = merged.get(k, 0) + v
        return MemoryReport(merged)

    def as_dict(self) -> dict:
        return {"total": self.total, **{k: int(v) for k, v in self.parts.items()}}


@runtime_checkable
class BLAS(Protocol):
    """What answers rays for one object, in object space.

    - ``bounds``: the object's AABB in object space.
    - ``intersect(rays)``: closest hit within ``[t_min, t_max]`` for each ray.
    - ``occluded(rays)``: [N] bool, whether anything is hit within ``[t_min, t_max]``.
    - ``memory_bytes()``: run-time memory, itemised.
    - ``secondary_offset``: how far (in object-space units, along the normal) a ray leaving a hit
      on this object must start to avoid hitting the same surface again.
    - ``material_names``: one name per material slot, in the order ``Hits.material_id`` indexes;
      a scene maps each name to a scene material (`neuralrt.scene.material_rules`).

    Rays and answers live on the BLAS's device; ``bounds`` are CPU tensors (an `AABB`).
    """

    bounds: AABB
    secondary_offset: float
    material_names: list[str]

    def intersect(self, rays: Rays) -> Hits:
        """The closest hit of each ray within ``[t_min, t_max]`` (`Hits`, on the rays' device)."""
        ...

    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: whether each ray hits anything within ``[t_min, t_max]`` (shadow rays)."""
        ...

    def memory_bytes(self) -> MemoryReport:
        """The run-time memory, itemised (`MemoryReport`)."""
        ...

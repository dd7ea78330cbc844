"""`StepResult`: what a model's ``training_step`` hands the shared training loop."""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor

__all__ = ["StepResult"]


@dataclass
class StepResult:
    """One training step's loss and statistics (over all rays of the batch).

    ``ray_counts`` holds method-specific per-ray counts (e.g. LSNIF's ``truncated``: rays with
    more voxel-boundary points than H); the training record keeps each as a fraction of all rays,
    ``extra[name + "_fraction"]``.
    """

    loss: Tensor  # scalar, differentiable
    parts: dict[str, float] = field(default_factory=dict)  # each loss term's value
    correct: int = 0  # rays whose hit/miss the model gets right
    count: int = 0  # rays in the batch
    network_rays: int = 0  # rays that reached the network
    ray_counts: dict[str, int] = field(default_factory=dict)

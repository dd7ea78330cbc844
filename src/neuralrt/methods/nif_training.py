"""Online training of `NIFNetworks` from labelled (shadow ray, object) pairs (the paper's Sec. 4.2).

Pairs arrive as the first samples per pixel are rendered with exact shadow rays. They are buffered
(outer and inner apart) and, once ``round_pairs`` have gathered (and at `finish`), trained on in a
round: ``passes_per_spp`` passes, each over a fresh random ``pair_fraction`` of the round's pairs
(default half: training costs about as much per pair as rendering a path sample on the CPU, and
half keeps the quality targets, docs/nif.md) in random order, in batches of ``outer_batch`` /
``inner_batch`` (the last batch of a pass may be smaller). Loss: L2 between
the sigmoid output and the label (1 = visible); Adam (lr 0.005, betas 0.9/0.999, eps 1e-15) per
network kind, so an outer step never moves inner parameters. The grids' Adam is lazy
(`nif_optim.LazyAdam`: only the vertices a batch touched move, their moments decay only when
touched): an outer step took 36 ms with dense gradients and Adam, 22 ms with
`torch.optim.SparseAdam`, 7 ms with `LazyAdam` (2 CPU cores, docs/nif.md); vertices no ray of the
view reaches have nothing to learn. Each batch is one call of the device's training step
(`nif_step`: numba with the backward by hand on the CPU, half the time of autograd there; autograd
and torch optimizers elsewhere).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch
from torch import Tensor

from .nif import NIFNetworks, NIFQueries
from .nif_optim import LazyAdam
from .nif_step import nif_step_for

__all__ = ["NIFTrainer", "NIFTrainingStats", "LazyAdam"]


@dataclass
class NIFTrainingStats:
    outer_pairs: int = 0  # labelled pairs collected
    inner_pairs: int = 0
    outer_steps: int = 0
    inner_steps: int = 0
    seconds: float = 0.0  # wall time spent training (not collecting)
    rounds: int = 0
    loss_outer: list[float] = field(default_factory=list)  # mean L2 loss of each round's last pass
    loss_inner: list[float] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


class NIFTrainer:
    def __init__(self, networks: NIFNetworks, step=None):
        """``step``: the training step implementation (`nif_step`); default the device's (numba on the CPU)."""
        self.networks = networks
        cfg = networks.config.training
        self.cfg = cfg
        step = step or nif_step_for(networks.box_lo.device)
        adam = dict(lr=cfg.learning_rate, betas=tuple(cfg.adam_betas), eps=cfg.adam_eps)
        self.step_outer = step(networks.outer_mlp, [networks.outer_position, networks.outer_direction], **adam)
        self.step_inner = step(networks.inner_mlp, [networks.inner_position, networks.inner_direction, networks.inner_distance], **adam)
        dev = networks.box_lo.device
        self.generator = torch.Generator(device=dev).manual_seed(cfg.seed + 1)
        self._outer: list[tuple[Tensor, ...]] = []
        self._inner: list[tuple[Tensor, ...]] = []
        self._buffered = 0
        self.stats = NIFTrainingStats()

    def add(self, queries: NIFQueries, visible: Tensor) -> None:
        """Buffer the queries with their exact labels (``visible`` [P] bool over the pairs ``queries`` index)."""
        q = queries
        if q.outer_pair.numel():
            self._outer.append((q.outer_obj, q.outer_position, q.outer_direction, visible[q.outer_pair].float()))
        if q.inner_pair.numel():
            self._inner.append((q.inner_obj, q.inner_position, q.inner_direction, q.inner_distance, visible[q.inner_pair].float()))
        self.stats.outer_pairs += q.outer_pair.numel()
        self.stats.inner_pairs += q.inner_pair.numel()
        self._buffered += q.outer_pair.numel() + q.inner_pair.numel()
        if self._buffered >= self.cfg.round_pairs:
            self.train_round()

    def finish(self) -> None:
        """Train on whatever is still buffered."""
        if self._buffered:
            self.train_round()

    def train_round(self) -> None:
        start = time.perf_counter()
        outer = [torch.cat(cols) for cols in zip(*self._outer)] if self._outer else None
        inner = [torch.cat(cols) for cols in zip(*self._inner)] if self._inner else None
        self._outer, self._inner, self._buffered = [], [], 0
        for p in range(self.cfg.passes_per_spp):
            last = p == self.cfg.passes_per_spp - 1
            if outer is not None:
                loss = self._pass(outer, self.cfg.outer_batch, self.step_outer, "outer_steps")
                if last:
                    self.stats.loss_outer.append(loss)
            if inner is not None:
                loss = self._pass(inner, self.cfg.inner_batch, self.step_inner, "inner_steps")
                if last:
                    self.stats.loss_inner.append(loss)
        self.stats.rounds += 1
        self.stats.seconds += time.perf_counter() - start

    def _pass(self, columns: list[Tensor], batch: int, step, counter: str) -> float:
        """One pass over a random ``pair_fraction`` of the pairs in a random order; returns the mean L2 loss over the pass."""
        n = columns[0].shape[0]
        order = torch.randperm(n, generator=self.generator, device=columns[0].device)
        n = max(1, math.ceil(n * self.cfg.pair_fraction))
        order = order[:n]
        total = 0.0
        for lo in range(0, n, batch):
            idx = order[lo:lo + batch]
            total = total + step(columns, idx) * idx.numel()  # a float (numba) or a 0-d tensor (no sync per step)
            setattr(self.stats, counter, getattr(self.stats, counter) + 1)
        return float(total) / max(n, 1)

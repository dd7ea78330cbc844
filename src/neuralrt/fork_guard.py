"""Refusing queries in a process forked after this one's OpenMP threads had run neuralrt's work.

torch and numba's parallel regions share GNU OpenMP (see ``neuralrt/__init__.py``), which cannot
run in a child forked after its threads started: the child hangs in its first parallel region,
or numba's OpenMP layer kills it ("fork() called from a process already using GNU OpenMP").
multiprocessing forks by default on Linux, so a Pool over ray batches hung with no word why. At
a fork, a parent whose numba parallel regions have run on the OpenMP layer (a model loaded, a
query) marks the child; there the entry points that would run them (a BLAS's `check_rays`,
`load_model`, `MeshBLAS`, `train`, `render`) raise one line instead, and the child's torch runs
on one thread (no pool to wake), so its own torch work still runs. numba's other threading layers
survive a fork: with them nothing is refused. A parent that ran only torch's parallel work is not
noticed (its child may hang inside torch).
"""

from __future__ import annotations

import os
import sys

from .errors import DeviceError

__all__ = ["check_not_forked"]

_unsafe_to_fork = False  # decided in the parent just before a fork
_forked_after_openmp = False  # this process is such a fork's child


def check_not_forked(where: str) -> None:
    """A one-line `DeviceError` in a child forked after OpenMP work."""
    if _forked_after_openmp:
        raise DeviceError(
            f"{where}: this process was forked (multiprocessing's default start method on Linux) from one whose OpenMP "
            "threads had already run neuralrt's work, and OpenMP cannot run in such a child (it would hang): start "
            "workers with multiprocessing.get_context('spawn') or 'forkserver' (or set NUMBA_THREADING_LAYER=workqueue)")


def _before_fork() -> None:
    global _unsafe_to_fork
    numba = sys.modules.get("numba")
    _unsafe_to_fork = False
    if numba is not None:
        try:
            _unsafe_to_fork = numba.threading_layer() == "omp"
        except ValueError:  # no parallel region has run: no layer chosen yet
            pass


def _after_fork_in_child() -> None:
    global _forked_after_openmp
    _forked_after_openmp = _forked_after_openmp or _unsafe_to_fork
    torch = sys.modules.get("torch")
    if _forked_after_openmp and torch is not None:
        torch.set_num_threads(1)  # a one-thread region wakes no pool: the child's own torch work runs, inline


if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=_before_fork, after_in_child=_after_fork_in_child)

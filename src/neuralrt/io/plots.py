"""Figures written by the commands: a training run's curve (``train --plot``, ``info --plot``).

matplotlib's object API (a `Figure` of its own, no pyplot state), so plotting is safe beside other
threads and leaves no window or global backend behind. Written atomically, like every output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import NeuralRTError
from .files import check_output_file, write_atomically

__all__ = ["PLOT_SUFFIXES", "check_plot_path", "plot_problem", "training_plot_title", "write_training_plot"]

PLOT_SUFFIXES = (".png", ".pdf", ".svg")


def check_plot_path(path) -> Path:
    """``path`` as a `Path` a figure can be written to (its suffix names the format); else one line."""
    path = Path(path)
    if path.suffix.lower() not in PLOT_SUFFIXES:
        raise NeuralRTError(f"{path}: a plot is written as {', '.join(PLOT_SUFFIXES)} (the suffix names the format)")
    check_output_file(path, "plot")
    return path


def write_training_plot(path, curve: dict, title: str) -> Path:
    """Loss (and each loss term, unweighted) on a log scale, hit accuracy and a method's states
    (N-BVH: the cut's nodes) against the training step; ``curve`` as `TrainingCurve.as_dict` stores it."""
    from matplotlib.figure import Figure

    path = check_plot_path(path)
    steps = np.asarray(curve["step"], dtype=float)
    states = sorted(curve.get("states", {}).items())
    fig = Figure(figsize=(10 + 4 * bool(states), 4), dpi=120, layout="constrained")
    fig.suptitle(title, fontsize=10)
    loss_ax, accuracy_ax, *state_ax = fig.subplots(1, 2 + bool(states))
    loss_ax.plot(steps, curve["loss"], color="black", lw=1.6, label="loss (weighted sum)")
    for term, values in sorted(curve.get("losses", {}).items()):
        loss_ax.plot(steps, values, lw=1.0, ls="--", label=term)
    loss_ax.set_yscale("log")
    loss_ax.set_ylabel("loss (mean over each point's steps)")
    loss_ax.legend(fontsize=8, frameon=False)
    accuracy_ax.plot(steps, curve["hit_accuracy"], color="tab:blue", lw=1.4)
    accuracy_ax.set_ylabel("hit / miss accuracy on the training rays")
    for name, values in states:
        state_ax[0].plot(steps, values, lw=1.4, label=name)
    if states:
        state_ax[0].set_ylabel(", ".join(name for name, _ in states))
    for ax in (loss_ax, accuracy_ax, *state_ax):
        ax.set_xlabel("step")
        ax.grid(alpha=0.3, which="both")
    fmt = path.suffix.lower().lstrip(".")
    path.parent.mkdir(parents=True, exist_ok=True)  # (as every output's folder is made)
    write_atomically(path, lambda tmp: fig.savefig(tmp, format=fmt))
    return path


def training_plot_title(method: str, mesh_name: str, record: dict) -> str:
    """``lsnif · bunny · 800 steps of 8,192 rays · 588k rays/s · hit accuracy 0.9982`` from a training record."""
    parts = [method, mesh_name or "(unnamed mesh)", f"{record.get('steps', 0):,} steps of {record.get('batch_size', 0):,} rays"]
    if record.get("rays_per_second"):
        parts.append(f"{record.get('seconds', 0.0):,.1f} s, {record['rays_per_second'] / 1e3:,.0f}k rays/s on "
                     f"{record.get('device') or '?'}")
    accuracy = record.get("hit_accuracy")
    if isinstance(accuracy, float) and np.isfinite(accuracy):
        parts.append(f"final hit accuracy {accuracy:.4f}")
    return " · ".join(parts)


def plot_problem(record) -> str | None:
    """Why ``record`` (a model's or checkpoint's training record) has no curve to draw, or None."""
    from ..training.curve import curve_problem

    curve = record.get("curve") if isinstance(record, dict) else None
    if not curve:
        return "its training record holds no curve (trained before neuralrt kept one: train it again to plot it)"
    problem = curve_problem(curve)
    return f"its training curve is malformed ({problem})" if problem else None

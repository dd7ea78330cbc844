"""Figures written by the commands: a training run's curve (``train --plot``, ``info --plot``),
eval's error distributions and image overview (``eval --images DIR``) and NIF's online training
(``render --nif``: ``OUTPUT_nif_training.png``).

matplotlib's object API (a `Figure` of its own, no pyplot state), so plotting is safe beside other
threads and leaves no window or global backend behind. Written atomically, like every output.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np

from ..errors import NeuralRTError
from ..kernel_cache import fallback_cache_dir
from .files import check_output_file, write_atomically


def _choose_matplotlib_folder() -> None:
    """Where matplotlib's config folder (``~/.config/matplotlib``: its font cache) cannot be made, a
    private one in the runtime or temporary folder, as for numba's kernels (`kernel_cache`):
    matplotlib made a temporary one per process and logged two warning lines at every first plot
    (a service account or container user with no home). A folder the user chose stays."""
    if os.environ.get("MPLCONFIGDIR") or "matplotlib" in sys.modules or not sys.platform.startswith("linux"):
        return
    try:
        config = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config") / "matplotlib"
    except RuntimeError:  # (no home to resolve: a folder no one can make, root included)
        config = Path(os.devnull) / "matplotlib"
    folder = fallback_cache_dir(config, name="matplotlib")
    if folder is not None:
        os.environ["MPLCONFIGDIR"] = folder


_choose_matplotlib_folder()  # (before matplotlib is first imported, by a function below)

__all__ = ["PLOT_SUFFIXES", "check_plot_path", "plot_problem", "training_plot_title", "write_eval_errors",
           "write_eval_overview", "write_figure", "write_nif_training_plot", "write_training_plot"]

PLOT_SUFFIXES = (".png", ".pdf", ".svg")


def check_plot_path(path) -> Path:
    """``path`` as a `Path` a figure can be written to (its suffix names the format); else one line."""
    path = Path(path)
    if path.suffix.lower() not in PLOT_SUFFIXES:
        if path.name.lower() in PLOT_SUFFIXES:  # (".png" is a name without a suffix)
            raise NeuralRTError(f"{path}: a plot needs a file name before its suffix, e.g. curve{path.name}")
        raise NeuralRTError(f"{path}: a plot's file name ends in {', '.join(PLOT_SUFFIXES)} (the suffix names the format)")
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
    fig.suptitle(_plain_text(title), fontsize=10)
    loss_ax, accuracy_ax, *state_ax = fig.subplots(1, 2 + bool(states))
    loss_ax.plot(steps, curve["loss"], color="black", lw=1.6, label="loss trained on\n(terms x their weights)")
    for term, values in sorted(curve.get("losses", {}).items()):
        loss_ax.plot(steps, values, lw=1.0, ls="--", label=f"{term}, unweighted")
    loss_ax.set_yscale("log")
    loss_ax.set_ylabel("loss (mean over each point's steps)")
    # beside the axes: on them it hid curves
    loss_ax.legend(fontsize=8, frameon=False, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    accuracy_ax.plot(steps, curve["hit_accuracy"], color="tab:blue", lw=1.4)
    accuracy_ax.set_ylabel("hit / miss accuracy on the training rays")
    for name, values in states:
        state_ax[0].plot(steps, values, lw=1.4, label=name)
    if states:
        state_ax[0].set_ylabel(", ".join(name for name, _ in states))
    for ax in (loss_ax, accuracy_ax, *state_ax):
        ax.set_xlabel("step")
        ax.grid(alpha=0.3, which="both")
    return write_figure(fig, path)


def training_plot_title(method: str | None, preset: str | None, mesh_name: str, record: dict,
                        checkpoint_step: int | None = None) -> str:
    """``lsnif hq · bunny · 800 steps of 8,192 rays · 55.7 s, 588k rays/s on cpu · final hit accuracy 0.9982``
    from a training record (the method, and its preset where the config is one: `MethodSpec.preset_of`);
    an interrupted run's checkpoint says so (``checkpoint_step``), and a resumed run where it resumed."""
    record = {key: value for key, value in record.items() if key == "device" or _is_number(value)}  # (a file's: what is no number is left out)
    steps = f"{record.get('steps', 0):,.0f} steps of {record.get('batch_size', 0):,.0f} rays"
    if checkpoint_step is not None:
        steps = f"checkpoint of an unfinished run at step {checkpoint_step:,} ({record.get('batch_size', 0):,.0f} rays a step)"
    elif record.get("resumed_from") is not None:
        steps += f" (resumed at step {record['resumed_from']:,.0f})"
    parts = [" ".join(part for part in (method, preset) if part), mesh_name or "(unnamed mesh)", steps]
    if record.get("rays_per_second"):
        where = f" on {record['device']}" if isinstance(record.get("device"), str) else ""
        seconds, first = record.get("seconds", 0.0), record.get("first_step_seconds", 0.0)
        # (rays/s leaves out each session's first step, which loads or compiles the kernels: say so where it weighs)
        loading = f" ({first:,.1f} s of it the first step, kernels loading; rays/s after it)" if first > 0.1 * seconds else ""
        parts.append(f"{seconds:,.1f} s{loading}, {record['rays_per_second'] / 1e3:,.0f}k rays/s{where}")
    accuracy = record.get("hit_accuracy")
    if isinstance(accuracy, float) and np.isfinite(accuracy):
        parts.append(f"final hit accuracy {accuracy:.4f}")
    return " · ".join(part for part in parts if part)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and bool(np.isfinite(value))


def _plain_text(text: str) -> str:
    """``text`` as matplotlib prints it literally: a ``$`` (in a mesh name) would start mathtext."""
    return text.replace("$", r"\$")


def plot_problem(record) -> str | None:
    """Why ``record`` (a model's or checkpoint's training record) has no curve to draw, or None."""
    from ..training.curve import curve_problem

    curve = record.get("curve") if isinstance(record, dict) else None
    if not curve:
        return "its training record holds no curve (trained before neuralrt kept one: train it again to plot it)"
    problem = curve_problem(curve)
    return f"its training curve is malformed ({problem})" if problem else None


def _cdf_points(values, limit: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """(sorted values, fraction at or below each), thinned to at most ``limit`` points."""
    x = np.sort(np.asarray(values, dtype=np.float64))
    y = np.arange(1, len(x) + 1) / max(len(x), 1)
    keep = np.unique(np.linspace(0, len(x) - 1, min(len(x), limit)).astype(np.int64)) if len(x) else []
    return x[keep], y[keep]


def _view_label(view: str) -> str:
    return f"orbit {view}" if view.isdigit() else f"from {view}"


def write_eval_errors(path, errors: dict, silhouette_iou: dict) -> Path:
    """eval's figure: the cumulative distributions of |t error| (over the box diagonal) and of the
    normal's angle error, for the held-out rays from outside and from the surface that both the
    model and the mesh hit (``errors``: part -> (t errors, angles)), and the silhouette IoU per view."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(14, 4), dpi=110, layout="constrained")
    t_ax, angle_ax, iou_ax = fig.subplots(1, 3)
    for part, (t_error, angle) in errors.items():
        if len(t_error):
            x, y = _cdf_points(np.maximum(np.asarray(t_error), 1e-7))  # (exact zeros at the axis' floor)
            t_ax.plot(x, y, label=f"{part}: {len(t_error):,} rays hit by both")
            x, y = _cdf_points(angle)
            angle_ax.plot(x, y, label=part)
    t_ax.set_xscale("log")
    t_ax.set_xlabel("|t error| / box diagonal")
    angle_ax.set_xscale("symlog", linthresh=1.0)
    angle_ax.set_xlabel("normal error (degrees)")
    for ax in (t_ax, angle_ax):
        ax.set_ylabel("fraction of rays hit by both")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3, which="both")
        if ax.lines:
            ax.legend(fontsize=8, frameon=False)
        else:  # (a model that answers no hit)
            ax.text(0.5, 0.5, "no held-out ray hit by both", ha="center", transform=ax.transAxes)
    views = list(silhouette_iou)
    iou_ax.bar(range(len(views)), [silhouette_iou[v] for v in views], color="tab:blue")
    iou_ax.set_xticks(range(len(views)), [_view_label(v) for v in views], rotation=45, ha="right", fontsize=8)
    low = min((v for v in silhouette_iou.values() if not math.isnan(v)), default=1.0)  # (NaN: a view neither hits)
    iou_ax.set_ylim(max(0.0, low - 0.1 * (1.0 - low) - 0.02), 1.0)
    iou_ax.set_ylabel("silhouette intersection over union")
    iou_ax.grid(alpha=0.3, axis="y")
    fig.suptitle("neural vs exact: held-out rays (left, middle) and primary-ray silhouettes (right)", fontsize=10)
    return write_figure(fig, path)


def write_eval_overview(path, shown: dict, silhouette_iou: dict) -> Path:
    """Every view's normal and depth images, exact above neural, and the silhouettes compared, in
    one figure (``shown``: view -> the five images as display values in [0, 1])."""
    from matplotlib.figure import Figure

    views = list(shown)
    rows = ("normals, exact", "normals, neural", "depth, exact", "depth, neural",
            "silhouettes: grey both,\nred exact only (a hole),\nblue neural only")
    fig = Figure(figsize=(1.9 * len(views), 1.9 * len(rows) + 0.4), dpi=110, layout="constrained")
    axes = fig.subplots(len(rows), len(views), squeeze=False)
    for c, view in enumerate(views):
        for r, image in enumerate(shown[view]):
            ax = axes[r][c]
            ax.imshow(np.clip(image, 0.0, 1.0), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                iou = silhouette_iou[view]
                ax.set_title(f"{_view_label(view)}\n{'no pixel hit' if math.isnan(iou) else f'IoU {iou:.3f}'}", fontsize=8)
            if c == 0:
                ax.set_ylabel(rows[r], fontsize=8)
    return write_figure(fig, path)


def write_nif_training_plot(path, training: dict, title: str) -> Path:
    """NIF's online training (``training``: `NIFTrainingStats.as_dict`): each network's loss on its
    last pass over each round's pairs, against the round (a round trains on `round_pairs` pairs
    collected from the exact samples)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4), dpi=120, layout="constrained")
    ax = fig.subplots()
    for key, label in (("loss_outer", "outer network (shadow rays entering the box)"),
                       ("loss_inner", "inner network (shadow rays leaving a point inside)")):
        values = training.get(key) or []
        if values:
            ax.plot(np.arange(1, len(values) + 1), values, marker="o" if len(values) < 30 else None, ms=3, label=label)
    from matplotlib.ticker import MaxNLocator

    ax.set_yscale("log")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel(f"training round ({training.get('rounds', 0)} in all, {training.get('seconds', 0.0):.2f} s)")
    ax.set_ylabel("L2 loss, last pass over the round's pairs")
    ax.grid(alpha=0.3, which="both")
    if ax.lines:
        ax.legend(fontsize=8, frameon=False)
    fig.suptitle(_plain_text(title), fontsize=10)
    return write_figure(fig, path)


def write_figure(fig, path) -> Path:
    """``fig`` saved to ``path`` atomically, in the format its suffix names, its folder made."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)  # (as every output's folder is made)
    write_atomically(path, lambda tmp: fig.savefig(tmp, format=path.suffix.lower().lstrip(".") or None))
    return path

"""A training run's curve: loss, hit accuracy and each loss term over the steps (and a method's
states, such as N-BVH's cut size, as they stood at each point's last step).

Steps are gathered into bins of ``every`` steps, each ending at a multiple of ``every``; when a run
has filled ``2 * MAX_POINTS`` bins, neighbours merge and ``every`` doubles. So a run of any length
(and a resumed run given more steps) keeps between ``MAX_POINTS`` and ``2 * MAX_POINTS`` points,
at most ~25 KB in a model file's header. A point's value is the mean over its bin's steps (the hit
accuracy: hits and misses right over rays, in the bin the steps filled; merged bins weigh by steps).

The curve lives in the `TrainingRecord` as a dict (`as_dict`); a checkpoint's also carries the bin
being filled (``"open"``), so a resumed run's curve is the uninterrupted run's.
"""

from __future__ import annotations

import math
from collections.abc import Callable

__all__ = ["TrainingCurve", "MAX_POINTS", "curve_problem"]

MAX_POINTS = 128
_SERIES = ("step", "seconds", "loss", "hit_accuracy")


def _stored(value: float) -> float:
    """Six significant digits: a curve is read by eye, and each digit is a byte in every model file."""
    return float(f"{value:.6g}") if math.isfinite(value) else value


class TrainingCurve:
    def __init__(self, every: int = 1, start: int = 0):
        self.every = every
        self.start = start  # the step the curve begins after (a run resumed from a checkpoint kept without one)
        self.points: list[dict] = []  # {"step", "seconds", "loss", "hit_accuracy", "losses": {term: mean}, "states": {name: value}}
        self._open: dict | None = None  # sums over the bin being filled
        self.states: Callable[[], dict[str, float]] | None = None  # read as a bin closes (a model's `curve_states`)

    # --- filling ------------------------------------------------------------------------------

    def add(self, step: int, seconds: float, loss: float, correct: int, count: int, losses: dict) -> None:
        """One finished step (``step`` counted from 1, ``seconds`` the run's total so far)."""
        b = self._open or {"steps": 0, "loss": 0.0, "correct": 0, "count": 0, "losses": {}}
        b["steps"] += 1
        b["loss"] += float(loss)
        b["correct"] += int(correct)
        b["count"] += int(count)
        for term, value in losses.items():
            b["losses"][term] = b["losses"].get(term, 0.0) + float(value)
        b["end"], b["seconds"] = step, seconds
        self._open = b
        if step % self.every == 0:
            self.close()

    def close(self) -> None:
        """Ends the bin being filled (at a run's end its last bin is shorter)."""
        b, self._open = self._open, None
        if not b:
            return
        n = b["steps"]
        states = {name: float(v) for name, v in self.states().items()} if self.states is not None else {}
        self.points.append({"step": b["end"], "seconds": b["seconds"], "loss": b["loss"] / n,
                            "hit_accuracy": b["correct"] / b["count"] if b["count"] else math.nan,
                            "losses": {t: v / n for t, v in b["losses"].items()}, "states": states})
        if len(self.points) >= 2 * MAX_POINTS:
            self._coarsen()

    def _coarsen(self) -> None:
        """Neighbouring bins merged into bins of twice the width (means weighed by their steps)."""
        self.every *= 2
        merged: list[dict] = []
        previous = self.start
        for p in self.points:
            width, previous = p["step"] - previous, p["step"]
            q = merged[-1] if merged else None
            if q is not None and (q["step"] - 1) // self.every == (p["step"] - 1) // self.every:
                total = q["_width"] + width
                for key in ("loss", "hit_accuracy"):
                    q[key] = (q[key] * q["_width"] + p[key] * width) / total
                for term in q["losses"].keys() | p["losses"].keys():
                    a, b = q["losses"].get(term, p["losses"].get(term)), p["losses"].get(term, q["losses"].get(term))
                    q["losses"][term] = (a * q["_width"] + b * width) / total
                q.update(step=p["step"], seconds=p["seconds"], states=dict(p["states"]), _width=total)
            else:
                merged.append({**p, "losses": dict(p["losses"]), "states": dict(p["states"]), "_width": width})
        self.points = [{k: v for k, v in q.items() if k != "_width"} for q in merged]

    # --- stored form --------------------------------------------------------------------------

    def as_dict(self, checkpoint: bool = False) -> dict:
        """Columns (``step``, ``seconds``, ``loss``, ``hit_accuracy``; ``losses``: term -> column),
        ``every`` and ``start``. A model file's are rounded (`_stored`); a ``checkpoint``'s keep every
        digit and add the bin being filled, so the resumed run merges what the uninterrupted one would."""
        kept = (lambda v: v) if checkpoint else _stored
        out = {"every": self.every, "start": self.start, "step": [p["step"] for p in self.points],
               **{k: [kept(p[k]) for p in self.points] for k in _SERIES[1:]}}
        for group in ("losses", "states"):
            names = sorted({name for p in self.points for name in p[group]})
            out[group] = {name: [kept(p[group].get(name, math.nan)) for p in self.points] for name in names}
        if checkpoint and self._open:
            out["open"] = dict(self._open, losses=dict(self._open["losses"]))
        return out

    @classmethod
    def from_dict(cls, stored: dict, start: int = 0) -> TrainingCurve:
        """The curve ``as_dict`` gave; an empty dict (a record from before curves were kept) gives
        an empty curve beginning after ``start``."""
        if not stored:
            return cls(start=start)
        curve = cls(stored["every"], stored.get("start", 0))
        columns = {k: stored[k] for k in _SERIES}
        curve.points = [{**{k: c[i] for k, c in columns.items()},
                         **{group: {name: v[i] for name, v in stored.get(group, {}).items()} for group in ("losses", "states")}}
                        for i in range(len(stored["step"]))]
        if stored.get("open"):
            curve._open = dict(stored["open"], losses=dict(stored["open"]["losses"]))
        return curve


def curve_problem(stored) -> str | None:
    """Why ``stored`` (a record's ``curve``) is not a curve `TrainingCurve.from_dict` reads, or None."""
    if not isinstance(stored, dict):
        return f"it is a {type(stored).__name__}, not a table"
    if not stored:
        return None
    every, start = stored.get("every"), stored.get("start", 0)
    if not isinstance(every, int) or isinstance(every, bool) or every < 1:
        return f"its bin width is {every!r}"
    if not isinstance(start, int) or isinstance(start, bool) or start < 0:
        return f"its start is {start!r}"
    groups = [stored.get(group, {}) for group in ("losses", "states")]
    if not all(isinstance(g, dict) for g in groups):
        return "its losses or states are not a table"
    columns = [stored.get(k) for k in _SERIES] + [c for g in groups for c in g.values()]
    if not all(isinstance(c, list) for c in columns):
        return "a column is missing or not a list"
    if len({len(c) for c in columns}) > 1:
        return "its columns differ in length"
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for c in columns for v in c):
        return "a value is not a number"
    if not all(isinstance(v, float) or -1e308 < v < 1e308 for c in columns for v in c):
        return "a value is an integer beyond floating point's range"
    steps = stored["step"]
    if any(not isinstance(s, int) for s in steps) or any(a >= b for a, b in zip([start, *steps], steps)):
        return "its steps are not increasing whole numbers"
    opened = stored.get("open")
    if opened is not None and not _well_formed_bin(opened):
        return "its open bin is malformed"
    return None


def _well_formed_bin(b) -> bool:
    """Whether ``b`` holds the sums `TrainingCurve.add` keeps (a checkpoint's open bin), each of its type."""
    def whole(v) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and v >= 0

    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    return (isinstance(b, dict) and {"steps", "loss", "correct", "count", "losses", "end", "seconds"} <= set(b)
            and all(whole(b[k]) for k in ("steps", "correct", "count", "end")) and b["steps"] >= 1
            and number(b["loss"]) and number(b["seconds"]) and isinstance(b["losses"], dict)
            and all(number(v) for v in b["losses"].values()))

"""Errors neuralrt raises for bad input. The CLI prints them as one line, never a traceback.

Warnings point at the caller's line outside neuralrt (`outside_stacklevel`), not at ours."""

import math
import os
import re
import sys

_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def outside_stacklevel() -> int:
    """The ``stacklevel`` for a ``warnings.warn`` in the function calling this one that points at the
    first frame outside the neuralrt package: the user's line, however deep in neuralrt the warning
    is raised (Python 3.12's ``skip_file_prefixes``, on 3.11 too)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    return level


class NeuralRTError(Exception):
    """Base class: a problem with the user's input, stated in one line."""


class MeshError(NeuralRTError):
    """A mesh file is missing, unreadable, empty or malformed."""


class SceneError(NeuralRTError):
    """A scene file is missing or invalid."""


class ModelFileError(NeuralRTError):
    """A model file is missing, truncated, corrupted, of another method or a newer version."""


class ImageError(NeuralRTError):
    """An image file is missing or unreadable, or two images do not match."""


class ConfigError(NeuralRTError, ValueError):
    """An argument or config value is invalid: unknown method or preset, a value out of range."""


class MeshMismatchError(NeuralRTError):
    """A model is used with a mesh it was not trained on."""


class TrainingError(NeuralRTError):
    """Training cannot go on: the loss became NaN or infinite (diverged), or no training ray could be drawn."""


class DeviceError(NeuralRTError, ValueError):
    """A device is unavailable (``cuda`` on a CPU-only torch), or rays and model sit on different devices."""


def validation_message(exc, model=None) -> str:
    """One line from a pydantic ``ValidationError``: ``training.steps: Input should be greater than or
    equal to 1 (got -3)``, errors joined by ``; ``. ``model``: the validated class, to tell union labels
    from keys (see `validation_errors`)."""
    return "; ".join(f"{key}: {msg}" if key else msg for key, msg in validation_errors(exc, model))  # (a whole-model check names its keys itself)


def validation_errors(exc, model=None) -> list[tuple[str, str]]:
    """(key path, one-line problem) per error of a pydantic ``ValidationError``, as the user wrote the keys
    (``""`` for the top level).

    pydantic puts a union member's label into the error location (``materials.0.conductor.roughness``,
    ``albedo.tuple[constrained-float, ...].0``); those parts are dropped: all of them when ``model``
    (the validated class) is given, else only labels with brackets. When one member of a union
    fits the input's shape, the others' "Input should be a valid ..." errors are dropped too.
    """
    rows = []  # (key, message, union position or None, is a type mismatch)
    for err in _length_errors(exc.errors(include_url=False), model):
        key, union_at = _user_loc(err.get("loc", ()), model)
        got = "" if isinstance(err.get("input"), dict) or "input" not in err or ", got " in err.get("msg", "") \
            else f" (got {_short_repr(err['input'])})"  # (a message of ours may name the input itself)
        rows.append((key, _bound_as_written(_one_line(err.get("msg", "invalid")), err.get("ctx")) + got, union_at, _is_type_mismatch(err)))
    fitting = {at for _, _, at, mismatch in rows if at is not None and not mismatch}
    rows = [r for r in rows if not (r[3] and r[2] in fitting)]
    return _merge_alternatives([(key, msg) for key, msg, _, _ in rows])


def _length_errors(errors: list[dict], model) -> list[dict]:
    """``errors`` with a list or tuple of the wrong length said as such, once: pydantic names a
    3-tuple given 2 values as ``position.2: Field required``, and a long one as "Tuple should have
    at most 3 items after validation, not 4"; both become ``position: takes 3 values, got 2``."""
    out, said = [], set()
    for err in errors:
        loc, value, ctx = tuple(err.get("loc", ())), err.get("input"), err.get("ctx") or {}
        if err.get("type") == "missing" and loc and isinstance(loc[-1], int) and isinstance(value, (list, tuple)):
            loc, wanted = loc[:-1], _fixed_length(model, loc[:-1])
            msg = f"takes {wanted} values, got {len(value)}" if wanted else f"takes more than {len(value)} values"
        elif err.get("type") in ("too_long", "too_short") and "actual_length" in ctx:
            wanted = _fixed_length(model, loc)
            bound = f"{wanted}" if wanted else ("at most " + str(ctx.get("max_length")) if err["type"] == "too_long"
                                                  else "at least " + str(ctx.get("min_length")))
            noun = "value" if bound.endswith(" 1") or bound == "1" else "values"
            msg = f"takes {bound} {noun}, got {ctx['actual_length']}"
        else:
            out.append(err)
            continue
        if loc not in said:
            said.add(loc)
            out.append({"type": "length", "loc": loc, "msg": msg, "input": value})
    return out


def _fixed_length(model, loc) -> int | None:
    """How many values the tuple at ``loc`` of ``model`` takes, where that is fixed (None if not, or unknown)."""
    from typing import Annotated, get_args, get_origin

    tp = model
    for part in loc:
        if tp is None:
            return None
        tp, _ = _step(tp, part)
    while tp is not None and get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    args = get_args(tp) if get_origin(tp) is tuple else ()
    return len(args) if args and Ellipsis not in args else None


def _user_loc(loc, model) -> tuple[str, tuple | None]:
    """(dotted key path without pydantic's union labels, location of the first union label or None)."""
    kept, union_at, tp = [], None, model
    for i, part in enumerate(loc):
        if tp is not None:
            tp, inserted = _step(tp, part)
        else:
            inserted = isinstance(part, str) and "[" in part
        if inserted and union_at is None:
            union_at = tuple(loc[:i])
        if not inserted:
            kept.append(str(part))
    return ".".join(kept), union_at


def _step(tp, part):
    """(the type below ``tp`` at loc part ``part`` or None if unknown, whether ``part`` is a union label)."""
    from typing import Annotated, Literal, Union, get_args, get_origin
    from types import UnionType

    from pydantic import BaseModel

    while get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    origin, args = get_origin(tp), get_args(tp)
    if origin in (Union, UnionType):
        members = [m for m in args if m is not type(None)]
        if len(members) == 1:  # Optional: pydantic adds no label
            return _step(members[0], part)
        if not isinstance(part, str):
            return None, False
        for m in members:  # the member the label names: its tag (a Literal field value), class or type name
            while get_origin(m) is Annotated:
                m = get_args(m)[0]
            if isinstance(m, type) and issubclass(m, BaseModel):
                tags = [a for f in m.model_fields.values() if get_origin(f.annotation) is Literal for a in get_args(f.annotation)]
                if part == m.__name__ or part in tags:
                    return m, True
            elif part.split("[")[0] == getattr(get_origin(m) or m, "__name__", None):
                return m, True
        return None, True
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        field = tp.model_fields.get(part) if isinstance(part, str) else None
        return (field.annotation if field is not None else None), False
    if origin in (list, set, frozenset) and isinstance(part, int):
        return args[0] if args else None, False
    if origin is tuple and isinstance(part, int):
        if len(args) == 2 and args[1] is Ellipsis:
            return args[0], False
        return (args[part] if 0 <= part < len(args) else None), False
    if origin is dict:
        return (args[1] if len(args) == 2 else None), False
    return None, False


def _is_type_mismatch(err) -> bool:
    """The input has another shape than this union member wants (a list for a string, ...)."""
    return err.get("type", "").endswith("_type") or err.get("type") == "is_instance_of"


def _merge_alternatives(rows: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """Errors of one key from a union's members as one: ``Input should be a valid tuple or a valid string``."""
    merged: dict[str, list[str]] = {}
    for key, msg in rows:
        merged.setdefault(key, []).append(msg)
    out = []
    for key, msgs in merged.items():
        prefix = "Input should be "
        if len(msgs) > 1 and all(m.startswith(prefix) for m in msgs):
            got = [m[m.index(" (got "):] for m in msgs if " (got " in m][:1]
            wants = [m.removeprefix(prefix).split(" (got ")[0] for m in msgs]
            out.append((key, prefix + " or ".join(dict.fromkeys(wants)) + "".join(got)))
        else:
            out.extend((key, m) for m in msgs)
    return out


def _one_line(msg: str) -> str:
    """A pydantic message as one line: no ``Value error, `` prefix, no "For further information" link."""
    msg = re.sub(r"\s*For further information visit https://errors\.pydantic\.dev\S*", "", str(msg))
    msg = msg.removeprefix("Value error, ").removeprefix("Assertion failed, ")
    return " ".join(msg.split())


def _bound_as_written(msg: str, ctx) -> str:
    """pydantic writes a float bound in full (1e20 as 100000000000000000000, 1e-12 as 0.000000000001): as Python would."""
    for bound in (ctx or {}).values():
        if isinstance(bound, float) and math.isfinite(bound) and (abs(bound) >= 1e6 or 0 < abs(bound) < 1e-4):
            msg = re.sub(r"(?<=to )-?[0-9.]+$", f"{bound:g}", msg)
    return msg


def _short_repr(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."

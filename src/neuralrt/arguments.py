"""Checks of count, seed and name arguments shared by the API and the lower-level entry points
(`neuralrt.api`, `render_nif`, the demo): a value of the wrong type or out of range is a one-line
`ConfigError` naming the argument, before any work."""

from __future__ import annotations

import contextlib
import contextvars
import numbers

from .errors import ConfigError

__all__ = ["SEED_LIMIT", "check_count", "check_seed", "seed_or_default", "check_name", "given", "spelled_as_flags"]

_AS_FLAGS = contextvars.ContextVar("neuralrt_arguments_as_flags", default=False)
_NO_VALUE = object()


def given(argument: str, value=_NO_VALUE, *, flag: str | None = None) -> str:
    """An argument as the user gave it, for an error message: ``--device cuda`` from the command line
    (inside `spelled_as_flags`), ``device='cuda'`` from Python. ``flag`` is the command line's
    spelling, whole, where it is not ``--`` plus the name with dashes and the value (``--no-images``
    for ``images=False``)."""
    if _AS_FLAGS.get():
        if flag is not None:
            return flag
        flag = "--" + argument.replace("_", "-")
        return flag if value is _NO_VALUE else f"{flag} {value}"
    if value is _NO_VALUE:
        return argument
    return f"{argument}={value!r}" if isinstance(value, str) else f"{argument}={value}"


@contextlib.contextmanager
def spelled_as_flags():
    """Within this block (the CLI's commands), `given` names arguments as command-line flags."""
    token = _AS_FLAGS.set(True)
    try:
        yield
    finally:
        _AS_FLAGS.reset(token)


def check_count(name: str, value, minimum: int = 1, maximum: int | None = None) -> int | None:
    """``value`` as a Python int (None stays None), or a one-line `ConfigError` unless it is an
    integer in [``minimum``, ``maximum``] (``name`` as the user wrote it). Callers keep the int: a
    numpy integer passed through ended in results (not JSON) and in torch's seeding (refused)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):  # (numpy integers are integers)
        raise ConfigError(f"{name}: must be an integer, got {value!r}")
    if value < minimum:
        raise ConfigError(f"{name}: must be at least {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise ConfigError(f"{name}: must be at most {maximum}, got {value}")
    return int(value)


SEED_LIMIT = 1 << 63  # seeds feed torch's and numba's 64-bit generators


def check_flags(**flags) -> None:
    """One-line `ConfigError` unless each value is True or False (a CLI flag cannot be anything
    else; ``"no"`` from Python would count as true)."""
    for name, flag in flags.items():
        if not isinstance(flag, bool):
            raise ConfigError(f"{given(name)}: expected True or False, got {type(flag).__name__} {flag!r}")


def check_seed(name: str, value) -> int | None:
    """``value`` as a Python int (None stays None), or a one-line `ConfigError` unless it is an
    integer in [0, 2^63)."""
    return check_count(name, value, minimum=0, maximum=SEED_LIMIT - 1)


def seed_or_default(name: str, value, default: int = 0) -> int:
    """``value`` (``default`` when None) checked as `check_seed` does, as a Python int (a numpy
    integer's fixed-width arithmetic would overflow in seed mixing)."""
    return check_seed(name, default if value is None else value)


def check_name(name: str, value) -> None:
    """One-line `ConfigError` unless ``value`` is None or a str (a method, preset or executor name)."""
    if value is not None and not isinstance(value, str):
        raise ConfigError(f"{name}: expected a name (str), got {type(value).__name__}")

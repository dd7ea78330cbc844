"""Checks of the device and path arguments that the API and the lower-level entry points share
(`neuralrt.load_model`, `neuralrt.scene.load_dict`, `MeshBLAS`, ...): bad input is a one-line
`DeviceError` / `ConfigError` before any work, never torch's or pathlib's own error from deep inside.

torch is imported inside the functions: ``neuralrt.api`` imports this module and stays quick to import.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from .arguments import given
from .errors import ConfigError, DeviceError

__all__ = ["DEVICE_TYPES", "check_device", "check_device_name", "resolve_device", "check_path", "check_memory"]

DEVICE_TYPES = ("cpu", "cuda")  # the torch device types neuralrt computes on


def check_device_name(device):
    """``device`` as a `torch.device`; a one-line `DeviceError` unless it names a CPU or CUDA device
    (whether this process has one is `check_device`'s question)."""
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise DeviceError(f"{_given_device(device)}: not a torch device (use cpu or cuda)") from None
    if dev.type not in DEVICE_TYPES:
        raise DeviceError(f"{_given_device(device)}: unsupported device type {dev.type!r} (use cpu or cuda)")
    return dev


def _given_device(device) -> str:
    """``device='cuda'`` whether it came as a string or a `torch.device` (as `given` spells it)."""
    import torch

    return given("device", str(device) if isinstance(device, torch.device) else device)


def check_device(device):
    """``device`` as tensors on it report theirs (`resolve_device`); a one-line `DeviceError` unless it
    names a torch device this process can use (``cuda`` needs a CUDA build of torch and a GPU)."""
    import torch

    dev = check_device_name(device)
    if dev.type == "cuda":
        if not torch.backends.cuda.is_built():
            raise DeviceError(f"{_given_device(device)}: this torch ({torch.__version__}) is built without CUDA; "
                              "install a CUDA build of torch to use a GPU")
        if not torch.cuda.is_available() or (dev.index or 0) >= torch.cuda.device_count():
            raise DeviceError(f"{_given_device(device)}: no CUDA device is available")
    return resolve_device(dev)


def resolve_device(device):
    """``device`` as tensors report it: ``"cuda"`` becomes ``cuda:<current index>`` (so it compares
    equal to a CUDA tensor's ``.device``); other devices as given. No checks: for devices already
    known to work (a tensor's, or one `check_device` passed)."""
    import torch

    dev = torch.device(device)
    if dev.type == "cuda" and dev.index is None:
        return torch.device("cuda", torch.cuda.current_device())
    return dev


def available_bytes(device) -> int | None:
    """Memory the process could still take on ``device`` (CPU: the kernel's MemAvailable; CUDA: free
    device memory), or None where it cannot tell."""
    import torch

    device = torch.device(device)
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def memory_shortfall(needed: int, device) -> str | None:
    """``"needs X GiB of memory, Y GiB is available on DEVICE"`` where ``needed`` bytes exceed what
    ``device`` has left, else None (also where that cannot be told)."""
    have = available_bytes(device)
    if have is not None and needed > have:
        return f"needs {needed / 2**30:.1f} GiB of memory, {have / 2**30:.1f} GiB is available on {device}"
    return None


def check_memory(what: str, needed: int, device, advice: str) -> None:
    """A one-line `ConfigError` before any work where ``what`` needs ``needed`` bytes on ``device`` and
    less is available (instead of an allocator's traceback, possibly after minutes)."""
    shortfall = memory_shortfall(needed, device)
    if shortfall:
        raise ConfigError(f"{what} {shortfall}: {advice}")


def check_path(name: str, value, optional: bool = False) -> Path | None:
    """``value`` as a `Path`; a one-line `ConfigError` unless it is a str or os.PathLike (or None when ``optional``)."""
    if value is None and optional:
        return None
    if isinstance(value, (str, os.PathLike)) and str(value) != "":
        try:
            str(value).encode("utf-8")
        except UnicodeEncodeError:  # (bytes the locale did not decode: safetensors and OpenEXR open no such path)
            shown = os.fsencode(str(value)).decode("utf-8", "backslashreplace")
            raise ConfigError(f"{shown}: this path's bytes are not text in the locale's encoding ({sys.getfilesystemencoding()}), "
                              "and model, image and scene files open by text paths only: rename it, or run in a UTF-8 "
                              "locale (PYTHONUTF8=1)") from None
        return Path(value)
    got = "an empty string" if isinstance(value, str) else type(value).__name__  # (no == on arrays)
    raise ConfigError(f"{name}: expected a path (str or os.PathLike), got {got}")

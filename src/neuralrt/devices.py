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
    except (RuntimeError, TypeError, ValueError, OverflowError):  # (an index of 10**30: "Overflow when unpacking")
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
    """Memory the process could still take on ``device``, or None where it cannot tell. CUDA: free
    device memory. CPU: the least of the kernel's MemAvailable, what a memory cgroup leaves (a
    container's or a batch job's limit, which MemAvailable does not show) and what an address-space
    limit leaves (``ulimit -v``, as SGE's h_vmem sets: in a trial, renders and trainings the
    MemAvailable check let through ended in allocator tracebacks, and FLIP in a crash)."""
    import torch

    device = torch.device(device)
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    known = [n for n in (_mem_available(), _cgroup_headroom(), _address_space_headroom()) if n is not None]
    return min(known, default=None)


def _mem_available() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_headroom(proc_cgroup: str = "/proc/self/cgroup", root: str = "/sys/fs/cgroup") -> int | None:
    """The least, over this process's memory cgroup and its ancestors (a limit set above binds too),
    of limit minus usage, inactive file cache counted as free (the kernel reclaims it); cgroup v2
    (``memory.max``) or v1 (``memory.limit_in_bytes``). None where no limit is set or readable."""
    try:
        lines = Path(proc_cgroup).read_text().splitlines()
    except OSError:
        return None
    least = None
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":  # v2's one hierarchy
            base, files = Path(root), ("memory.max", "memory.current", "inactive_file")
        elif "memory" in controllers.split(","):
            base, files = Path(root) / "memory", ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")
        else:
            continue
        folder = base / path.strip().lstrip("/")
        for level in (folder, *folder.parents):
            if not level.is_relative_to(base):
                break
            headroom = _cgroup_level_headroom(level, *files)
            if headroom is not None:
                least = headroom if least is None else min(least, headroom)
    return least


def _cgroup_level_headroom(level: Path, limit_file: str, usage_file: str, cache_key: str) -> int | None:
    try:
        limit = (level / limit_file).read_text().strip()
        if not limit.isdigit() or int(limit) >= 1 << 60:  # ("max", or v1's "no limit": 2^63 rounded to pages)
            return None
        usage = int((level / usage_file).read_text())
        stats = dict(line.split(None, 1) for line in (level / "memory.stat").read_text().splitlines() if " " in line)
        cache = int(stats.get(cache_key, 0))
    except (OSError, ValueError):
        return None
    return max(int(limit) - usage + cache, 0)


def _address_space_headroom() -> int | None:
    """What is left of an address-space limit (``ulimit -v``), or None where none is set."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft == resource.RLIM_INFINITY:
            return None
        mapped = int(Path("/proc/self/statm").read_text().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (ImportError, OSError, ValueError, IndexError):
        return None
    return max(soft - mapped, 0)


def memory_shortfall(needed: int, device) -> str | None:
    """``"needs 9.2 GiB of memory, 4.3 GiB is available on DEVICE"`` where ``needed`` bytes exceed what
    ``device`` has left, else None (also where that cannot be told)."""
    have = available_bytes(device)
    if have is not None and needed > have:
        need, left = _size(needed), _size(have)
        if need == left:  # ("8 MiB" and "8 MiB" told nothing)
            need, left = f"{needed:,} bytes", f"{have:,} bytes"
        return f"needs {need} of memory, {left} is available on {device}"
    return None


def _size(n: int) -> str:
    """Bytes to read: GiB to one decimal, below that whole MiB or KiB."""
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB" if n >= 2**20 else f"{n / 2**10:.0f} KiB"


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
        text = str(value)
        if "\x00" in text:  # (the system's calls end a name there: Python's "embedded null byte" ValueError)
            raise ConfigError(f"{name}: a path cannot hold a NUL character, got {text!r}")
        try:
            as_utf8 = text.encode("utf-8")
        except UnicodeEncodeError:  # (bytes the locale did not decode)
            as_utf8 = None
        # safetensors and OpenEXR open a path by its UTF-8 bytes: where those are not the name's bytes
        # (undecodable bytes; any non-ASCII name in another locale), they open another file, or none.
        if as_utf8 != os.fsencode(text):
            shown = os.fsencode(text).decode("utf-8", "backslashreplace")
            encoding = sys.getfilesystemencoding()
            advice = "rename it" if encoding.lower().replace("-", "") == "utf8" else \
                f"rename it, or run in a UTF-8 locale (this one's encoding: {encoding}; PYTHONUTF8=1)"
            raise ConfigError(f"{shown}: this path's bytes are not UTF-8 text, which the libraries that open model, "
                              f"image and scene files take: {advice}")
        return Path(value)
    got = "an empty string" if isinstance(value, str) else type(value).__name__  # (no == on arrays)
    raise ConfigError(f"{name}: expected a path (str or os.PathLike), got {got}")

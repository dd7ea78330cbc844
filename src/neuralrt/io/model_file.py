"""The `.nrt` model file: named arrays in safetensors plus a JSON header, written atomically.

Layout: a plain safetensors file whose ``__metadata__`` holds one key, ``"neuralrt"``, a JSON
object with at least ``format_version``, ``method``, ``arrays_sha256`` (a SHA-256 over every
array's name, dtype, shape and bytes, so flipped bits in the data are caught; safetensors itself
only checks that its header parses) and ``header_sha256`` (a SHA-256 over the rest of the object,
as sorted-key JSON, so a flipped bit in the header's numbers, e.g. the bounds or a threshold, is
caught too; inside the one key, as safetensors writes several in no fixed order). Model files of
every method share one typed header, `ModelHeader` (method, config, bounds, materials, training
record, source-mesh hash and name); nothing that can be derived (box, memory) is stored. Training checkpoints use the same container with their own
keys. Reading never executes code: safetensors parses a JSON header and raw bytes.

Format versions: 3 (current) adds ``header_sha256``; 2 has the `ModelHeader` keys and a
``method`` key inside ``config``; 1 also stored ``box`` and ``memory_bytes``, which are ignored
when a version-1 file is read. Files of versions 1 and 2 load without a header digest.

Every problem with a file raises `ModelFileError` with one line naming the file and the problem.
"""

from __future__ import annotations

import hashlib
import errno
import json
import os
from dataclasses import dataclass
from typing import Annotated
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..errors import ConfigError, ModelFileError, validation_message
from .files import write_atomically

__all__ = [
    "MODEL_SUFFIX", "check_model_path",
    "FORMAT_VERSION", "METADATA_KEY", "ModelFile", "ModelHeader", "MaterialEntry", "read_model_file", "read_header",
    "read_model", "read_model_header", "write_model", "write_model_file", "arrays_digest", "header_digest",
]

FORMAT_VERSION = 3
MODEL_SUFFIX = ".nrt"  # how `neuralrt info`, scene files and the CLI tell model files
METADATA_KEY = "neuralrt"
# Keys of the container itself, added by `write_model_file` (not part of a `ModelHeader`).
_CONTAINER_KEYS = ("format_version", "arrays_sha256", "header_sha256")
# Keys version 1 stored although they can be derived.
_DERIVED_V1_KEYS = ("box", "memory_bytes")


_Finite = Annotated[float, Field(allow_inf_nan=False)]
_FLOAT32_MAX = float(np.finfo(np.float32).max)


class MaterialEntry(BaseModel):
    """One material slot of a model: its name (mapped to a scene material) and base colour."""

    model_config = ConfigDict(extra="forbid")
    name: str
    base_color: tuple[_Finite, _Finite, _Finite] = (1.0, 1.0, 1.0)


class ModelHeader(BaseModel):
    """The header every model file has, whatever the method."""

    model_config = ConfigDict(extra="forbid")
    method: str = Field(description="registered method name, e.g. 'lsnif'")
    config: dict = Field(description="the method's full config (validated by the method's config class on load)")
    bounds: tuple[tuple[_Finite, _Finite, _Finite], tuple[_Finite, _Finite, _Finite]] = Field(
        description="tight object-space AABB (lo, hi)")
    materials: list[MaterialEntry] = Field(min_length=1, description="material slots in material-index order")
    training: dict = Field(default_factory=dict, description="the training record (steps, rays, seconds, precision, ...)")
    mesh_sha256: str | None = Field(None, description="content hash of the source mesh")
    mesh_name: str | None = None

    @model_validator(mode="after")
    def _bounds_ordered(self) -> "ModelHeader":
        lo, hi = self.bounds
        if any(abs(v) > _FLOAT32_MAX for v in (*lo, *hi)):  # a mesh's float32 vertices cannot lie there
            raise ValueError(f"bounds: {[list(lo), list(hi)]} lie beyond float32's range (3.4e38)")
        if any(a > b for a, b in zip(lo, hi)):
            raise ValueError(f"bounds: lo {list(lo)} is above hi {list(hi)} on some axis")
        return self


@dataclass
class ModelFile:
    """What a `.nrt` file holds: its JSON header and its named CPU tensors."""

    header: dict
    arrays: dict[str, Tensor]

    @property
    def method(self) -> str:
        return str(self.header["method"])


def arrays_digest(arrays: dict[str, Tensor]) -> str:
    """SHA-256 over (name, dtype, shape, bytes) of every array, in name order."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        t = arrays[name].detach().cpu().contiguous()
        h.update(f"{name}|{str(t.dtype)}|{tuple(t.shape)}|".encode())
        # View as bytes: works for every dtype, bf16 included (numpy has no bf16).
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def header_digest(header: dict) -> str:
    """SHA-256 over ``header`` without its own ``header_sha256``, as sorted-key JSON (a JSON value
    reads back to the same text, so the digest survives the file)."""
    body = {k: v for k, v in header.items() if k != "header_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def check_model_path(path: Path) -> None:
    """A one-line `ConfigError` unless ``path`` ends in ``.nrt``: `neuralrt info` and scene files tell models by it."""
    if path.suffix.lower() != MODEL_SUFFIX:
        raise ConfigError(f"{path}: a model file must end in {MODEL_SUFFIX} (`neuralrt info` and scene files tell models by it)")


def write_model_file(path: str | os.PathLike, method: str, header: dict, arrays: dict[str, Tensor]) -> Path:
    """Write ``arrays`` and ``header`` (plus format version, method, digest) atomically to ``path``.

    The file is written to a temporary sibling, flushed to disk, then renamed over ``path``: a
    crash leaves either the old file or the new one, never a half-written model.
    """
    path = Path(path)
    arrays = {k: v.detach().cpu().contiguous() for k, v in arrays.items()}
    full_header = {**header, "format_version": FORMAT_VERSION, "method": method, "arrays_sha256": arrays_digest(arrays)}
    full_header["header_sha256"] = header_digest(full_header)
    metadata = {METADATA_KEY: json.dumps(full_header, sort_keys=True)}
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda tmp: _save(arrays, tmp, metadata), fsync=True)
    return path


def _save(arrays: dict[str, Tensor], tmp: str, metadata: dict) -> None:
    from safetensors import SafetensorError
    from safetensors.torch import save_file

    try:
        save_file(arrays, tmp, metadata=metadata)
    except SafetensorError as exc:  # its I/O errors (a full disk) are not OSErrors: make them one
        raise OSError(errno.EIO, str(exc).removeprefix("Error while serializing: "), tmp) from None


def _check_data_size(path: Path, header_len: int, size: int) -> None:
    """Tell a truncated file (less data than its arrays need) from a corrupted one (more), which
    safetensors reports alike ("file not fully covered")."""
    with open(path, "rb") as f:
        f.seek(8)
        try:
            entries = json.loads(f.read(header_len))
        except (ValueError, UnicodeDecodeError, RecursionError):  # (JSONDecodeError is a ValueError)
            return  # (safetensors names the problem)
    if not isinstance(entries, dict):
        return
    offsets = [v.get("data_offsets") for k, v in entries.items() if k != "__metadata__" and isinstance(v, dict)]
    ends = [o[1] for o in offsets if isinstance(o, list) and len(o) == 2 and isinstance(o[1], int)]
    needed, present = max(ends, default=0), size - 8 - header_len
    if present < needed:
        raise ModelFileError(f"{path}: truncated model file (arrays need {needed} bytes, file has {present})")
    if present > needed:
        raise ModelFileError(f"{path}: corrupted model file ({present - needed} bytes after the arrays its header lists)")


def _open(path: Path):
    from safetensors import safe_open

    if not path.exists():
        raise ModelFileError(f"{path}: model file not found")
    if not path.is_file():
        raise ModelFileError(f"{path}: not a file")
    size = path.stat().st_size
    with open(path, "rb") as f:
        prefix = f.read(8)
    if len(prefix) < 8:
        raise ModelFileError(f"{path}: truncated model file ({size} bytes, too short for a header)")
    header_len = int(np.frombuffer(prefix, dtype="<u8")[0])
    if header_len > size - 8:
        if header_len > 100_000_000:
            raise ModelFileError(f"{path}: not a neuralrt model file (no safetensors header)")
        raise ModelFileError(f"{path}: truncated model file (header says {header_len} bytes, file has {size - 8})")
    _check_data_size(path, header_len, size)
    try:
        return safe_open(str(path), framework="pt", device="cpu")
    except Exception as exc:  # safetensors raises its own error types; report them as one line
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if "incomplete" in msg.lower() or "buffer" in msg.lower():
            raise ModelFileError(f"{path}: truncated model file ({msg})") from None
        raise ModelFileError(f"{path}: corrupted or not a neuralrt model file ({msg})") from None


def _parse_header(path: Path, handle) -> dict:
    meta = handle.metadata() or {}
    if METADATA_KEY not in meta:
        raise ModelFileError(f"{path}: not a neuralrt model file (safetensors without a '{METADATA_KEY}' header)")
    try:
        header = json.loads(meta[METADATA_KEY])
        # A lone surrogate (JSON "\ud800") is no text: printing or writing it fails later.
        json.dumps(header, ensure_ascii=False).encode("utf-8")
    except json.JSONDecodeError as exc:
        raise ModelFileError(f"{path}: corrupted header (invalid JSON: {exc.msg} at char {exc.pos})") from None
    except RecursionError:
        raise ModelFileError(f"{path}: corrupted header (JSON nested too deeply)") from None
    except UnicodeEncodeError:
        raise ModelFileError(f"{path}: corrupted header (a string that is not valid Unicode text)") from None
    except ValueError as exc:  # (an integer of thousands of digits: Python's conversion limit)
        raise ModelFileError(f"{path}: corrupted header ({str(exc).split(';')[0]})") from None
    if not isinstance(header, dict):
        raise ModelFileError(f"{path}: corrupted header (not a JSON object)")
    if _depth(header) > MAX_HEADER_DEPTH:  # (ours nest a few levels; a deep one fails later, printing it)
        raise ModelFileError(f"{path}: corrupted header (nested deeper than {MAX_HEADER_DEPTH} levels)")
    # Checked whatever the version says: a flipped digit must not pass as an older version.
    if "header_sha256" in header and header["header_sha256"] != header_digest(header):
        raise ModelFileError(f"{path}: corrupted header (checksum mismatch)")
    for key in ("format_version", "method", "arrays_sha256"):
        if key not in header:
            raise ModelFileError(f"{path}: corrupted header (missing '{key}')")
    version = header["format_version"]
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise ModelFileError(f"{path}: corrupted header (format_version {version!r})")
    if version > FORMAT_VERSION:
        raise ModelFileError(
            f"{path}: written by a newer neuralrt (format version {version}; this version reads up to "
            f"{FORMAT_VERSION}): upgrade neuralrt"
        )
    if "header_sha256" not in header and version >= 3:
        raise ModelFileError(f"{path}: corrupted header (missing 'header_sha256')")
    return header


def _check_method(path: Path, header: dict, method: str | None) -> None:
    if method is not None and header["method"] != method:
        raise ModelFileError(f"{path}: this is a '{header['method']}' model, expected '{method}'")


MAX_HEADER_DEPTH = 32  # nesting of a header's JSON: a config, a training record (ours: under 10)


def _depth(value) -> int:
    """How deeply ``value`` (parsed JSON) nests, counted without recursion."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        item, level = stack.pop()
        deepest = max(deepest, level)
        if isinstance(item, dict):
            stack.extend((v, level + 1) for v in item.values())
        elif isinstance(item, list):
            stack.extend((v, level + 1) for v in item)
    return deepest


def read_header(path: str | os.PathLike, method: str | None = None) -> dict:
    """The JSON header only (cheap: arrays are not read or verified)."""
    path = Path(path)
    header = _parse_header(path, _open(path))
    _check_method(path, header, method)
    return header


def read_model_file(path: str | os.PathLike, method: str | None = None) -> ModelFile:
    """Read and verify a model file; with ``method``, reject files of another method."""
    path = Path(path)
    handle = _open(path)
    size = path.stat().st_size  # (what the header was read from)
    header = _parse_header(path, handle)
    _check_method(path, header, method)
    arrays = _read_arrays(path, size)
    if arrays_digest(arrays) != header["arrays_sha256"]:
        raise ModelFileError(f"{path}: corrupted array data (checksum mismatch)")
    return ModelFile(header, arrays)


def _read_arrays(path: Path, size: int) -> dict[str, Tensor]:
    """Every array of the file, from its bytes read whole, not memory-mapped as safetensors' own
    reader is: a file truncated while it is read (``cp`` over it truncates first) ended the process
    with SIGBUS. A file replaced after its header was read fails the arrays' digest."""
    from safetensors.torch import load

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read the model file ({exc.strerror})") from None
    if len(data) != size:
        raise ModelFileError(f"{path}: the model file changed while it was read ({size} bytes, then {len(data)})")
    try:
        arrays = load(data)
    except Exception as exc:  # safetensors raises its own error types; report them as one line
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ModelFileError(f"{path}: corrupted array data ({msg})") from None
    return {name: arrays[name] for name in sorted(arrays)}  # (in name order, as safe_open lists them: `load`'s varies)


def _model_header(path: Path, raw: dict) -> ModelHeader:
    fields = {k: v for k, v in raw.items() if k not in _CONTAINER_KEYS}
    if raw["format_version"] == 1:
        fields = {k: v for k, v in fields.items() if k not in _DERIVED_V1_KEYS}
    try:
        return ModelHeader.model_validate(fields)
    except ValidationError as exc:
        raise ModelFileError(f"{path}: invalid model header ({validation_message(exc)[:300]})") from None


def write_model(path: str | os.PathLike, header: ModelHeader, arrays: dict[str, Tensor]) -> Path:
    """Write a model file: ``header`` plus ``arrays``, atomically (see `write_model_file`)."""
    return write_model_file(path, header.method, header.model_dump(mode="json", exclude={"method"}), arrays)


def read_model_header(path: str | os.PathLike, method: str | None = None) -> ModelHeader:
    """A model file's typed header only (cheap: arrays are not read or verified)."""
    return _model_header(Path(path), read_header(path, method=method))


def read_model(path: str | os.PathLike, method: str | None = None) -> tuple[ModelHeader, dict[str, Tensor]]:
    """Read and verify a model file: its typed header and its named CPU arrays."""
    f = read_model_file(path, method=method)
    return _model_header(Path(path), f.header), f.arrays

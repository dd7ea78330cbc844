"""The textures and material files a mesh names, as trimesh reads them beside it.

trimesh drops the ones it cannot read silently (a debug log line), so a mesh whose ``map_Kd``
image or ``mtllib`` is missing rendered white with no word why. `unread_assets` collects those log
lines for the calling thread, and its warnings as one line each (Python printed them with their
tracebacks): trimesh's other debug lines stay filtered as before.
`regular_files_resolver` is what trimesh reads them through: regular files only, since opening a
FIFO a mesh names blocked every command for ever; a name not found as written is looked for as
the file most likely meant (percent-decoded, as glTF URIs are written; with Windows backslashes;
in another letter case; several MTL files on one ``mtllib`` line); and an MTL is cleaned of what
trimesh misreads (`neuralrt.geometry.obj_files.clean_mtl_text`).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from pathlib import Path

from ..errors import outside_stacklevel

__all__ = ["unread_assets", "regular_files_resolver", "OutsideFolderError"]

_LOGGER = "trimesh.util"  # the logger trimesh's OBJ and glTF readers write to
_MATERIALS = "unable to load materials from:"
_IMAGES = ("failed to load image", "unable to load image")

_lock = threading.Lock()
_collected: dict[int, list[str]] = {}  # thread ident -> what it could not read


class _Collect(logging.Filter):
    """Installed on the logger while any thread collects; remembers the logger's levels to restore."""

    def __init__(self, logger: logging.Logger):
        super().__init__()
        self.effective_level, self.own_level = logger.getEffectiveLevel(), logger.level

    def filter(self, record: logging.LogRecord) -> bool:
        into = _collected.get(record.thread)
        exc = record.exc_info[1] if record.exc_info else None
        if into is not None and isinstance(exc, KeyboardInterrupt):
            # trimesh's OBJ reader catches BaseException around the MTL: a Ctrl-C or SIGTERM
            # (neuralrt.launch raises it as a KeyboardInterrupt) must still stop the command.
            raise exc
        if into is not None:
            what = _described(record)
            if what:
                into.append(what)
            elif record.levelno >= logging.WARNING:  # (Python's last-resort handler printed it with its traceback)
                into.append(f"trimesh: {_one_line(record)}")
                return False
        return record.levelno >= self.effective_level  # what the logger passed on before


_installed: _Collect | None = None


def _one_line(record: logging.LogRecord) -> str:
    exc = record.exc_info[1] if record.exc_info else None
    return record.getMessage() + (f" ({type(exc).__name__}: {exc})" if exc is not None else "")


def _described(record: logging.LogRecord) -> str | None:
    message = record.getMessage()
    exc = record.exc_info[1] if record.exc_info else None
    why = f" ({type(exc).__name__}: {exc})" if exc is not None else ""
    if message.startswith(_MATERIALS):
        return f"material file {message[len(_MATERIALS):].strip()} could not be read{why}; its faces render white"
    if message.startswith(_IMAGES):
        return f"a texture could not be read{why}; its material renders with its base colour"
    return None


@contextlib.contextmanager
def unread_assets():
    """Yield a list that fills with one line per texture or material file trimesh fails to read
    in this thread inside the block."""
    global _installed
    logger = logging.getLogger(_LOGGER)
    ident = threading.get_ident()
    found: list[str] = []
    with _lock:
        if _installed is None:
            _installed = _Collect(logger)
            logger.addFilter(_installed)
            logger.setLevel(logging.DEBUG)
        _collected[ident] = found
    try:
        yield found
    finally:
        with _lock:
            del _collected[ident]
            if not _collected:
                logger.removeFilter(_installed)
                logger.setLevel(_installed.own_level)
                _installed = None


class OutsideFolderError(ValueError):
    """A file a mesh names that lies outside the mesh's folder (read only beside it)."""


def regular_files_resolver(mesh_path: str):
    """trimesh's resolver for the files beside ``mesh_path``, refusing any that is not a regular
    file (a FIFO, a device, a folder) with an OSError, which trimesh logs as unread."""
    import warnings

    from trimesh.resolvers import FilePathResolver

    from .obj_files import clean_mtl_text

    class RegularFiles(FilePathResolver):
        def absolute(self, name: str):  # where `get` resolves each spelling of a name before opening it
            try:
                path = super().absolute(name)
            except ValueError:  # (trimesh's words name its own API: "pass FilePathResolver(..., allow_anywhere=True)")
                raise OutsideFolderError(f"{name.strip()[:200]!r} leads out of the folder of {Path(mesh_path).name} (a link "
                                 "elsewhere, an absolute path or '..'): the files a mesh names are read only beside "
                                 "it; copy the file there") from None
            if path.exists() and not path.is_file():
                raise OSError(f"{name.strip()} is not a regular file")
            return path

        def get(self, name: str):
            data = self._found(name)
            if name.strip().lower().endswith(".mtl"):
                data = clean_mtl_text(data, lambda material, why: warnings.warn(
                    f"{mesh_path}: the texture of material {material!r} is left out: {why}", stacklevel=outside_stacklevel()))
            return data

        def _found(self, name: str) -> bytes:
            try:
                return super().get(name)
            except FileNotFoundError:
                for other in _other_spellings(name, Path(self.parent)):
                    try:
                        return super().get(other)
                    except (FileNotFoundError, ValueError):
                        continue
                parts = name.split()
                if len(parts) > 1 and all(p.lower().endswith(".mtl") for p in parts):  # mtllib a.mtl b.mtl
                    return b"\n".join(self._found(p) for p in parts)
                raise

    return RegularFiles(mesh_path)


def _other_spellings(name: str, folder: Path) -> list[str]:
    """Names the file ``name`` most likely means where it is not found as written: percent-decoded
    (a glTF URI), with ``/`` for ``\\`` (a Windows path, whose last part `get` also tries
    alone), and each of those in the letter case the folder holds it in."""
    from urllib.parse import unquote

    name = name.strip()
    spellings = [unquote(name)] if "%" in name else []
    spellings += [s.replace("\\", "/") for s in [name, *spellings] if "\\" in s]
    for spelling in [name, *spellings]:
        for candidate in (spelling, spelling.replace("\\", "/").rsplit("/", 1)[-1]):
            cased = _in_folder_case(folder / candidate)
            if cased is not None:
                spellings.append(str(cased.relative_to(folder)))
    return spellings


def _in_folder_case(path: Path) -> Path | None:
    """``path`` with its last part spelt as the folder spells it, where only the case differs."""
    try:
        matches = [p for p in path.parent.iterdir() if p.name.lower() == path.name.lower() and p.name != path.name]
    except OSError:
        return None
    return matches[0] if len(matches) == 1 else None

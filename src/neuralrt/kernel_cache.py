"""Where numba caches neuralrt's compiled kernels, when it could cache them nowhere.

Our kernels are compiled with ``cache=True``. numba keeps their cache beside the sources
(``__pycache__``), else in the user's cache folder (``$XDG_CACHE_HOME/numba`` or
``~/.cache/numba``), else, with neither writable (a read-only install run by a service account
or a container user without a home), it refuses to compile: every command that loads a kernel
failed with numba's "cannot cache function ...: no locator available" traceback.

`choose_kernel_cache` then points ``NUMBA_CACHE_DIR`` at a private folder in the user's runtime
folder (``$XDG_RUNTIME_DIR``) or the temporary one. numba's cache index is a pickle that numba
loads, so a folder another user could have made, written to or swapped is not used: one of this
process's own is made instead, compiled again by each process as without a cache, and removed
at exit. A cache folder the user chose (``NUMBA_CACHE_DIR``, or numba's ``config.CACHE_DIR`` set
in code) is kept, unless numba cannot write it and has no folder of its own either (a read-only
shared cache: numba used it for nothing, and failed): then the private folder, with a warning.

`guard_cache_writes` makes a cache file numba cannot write for one of neuralrt's kernels (a full
disk, a quota) a warning: the kernel was compiled and runs; only the next process compiles it
again. It was the command's end (``neuralrt: error: No space left on device``, naming no file).
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import stat
import sys
import tempfile
import warnings
from pathlib import Path

__all__ = ["choose_kernel_cache", "fallback_cache_dir", "guard_cache_writes"]


def choose_kernel_cache() -> str | None:
    """Set ``NUMBA_CACHE_DIR`` where numba would find no cache folder; return what it was set to."""
    config = sys.modules.get("numba.core.config")  # (numba imported first: it read the environment already)
    chosen = os.environ.get("NUMBA_CACHE_DIR")
    configured = getattr(config, "CACHE_DIR", None) or chosen  # (set in code, or the environment's)
    if configured and (configured != chosen or _could_write(Path(configured))):
        return None  # (a folder numba can use, or one set in code: the user's choice either way)
    user_cache = Path(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")) / "numba"
    folder = fallback_cache_dir(Path(__file__).parent / "__pycache__", user_cache)
    if folder is None:
        return None  # (numba has a folder of its own; past a chosen one it cannot write, it uses that)
    if chosen:  # numba could not use it, nor any other: every kernel failed, "no locator available"
        _NOTES.append(f"NUMBA_CACHE_DIR={chosen}: numba cannot write there (it reads no cache from a folder it cannot "
                      f"write either), nor beside neuralrt or in {user_cache}: neuralrt's kernels are cached in {folder}")
    os.environ["NUMBA_CACHE_DIR"] = folder
    if config is not None:
        config.CACHE_DIR = folder
    return folder


def fallback_cache_dir(in_tree: Path, user_cache: Path | None = None, temp: Path | None = None,
                       name: str = "numba-cache") -> str | None:
    """None where numba has a cache folder (``in_tree`` or ``user_cache`` writable); else a private
    folder under ``temp`` (default: ``$XDG_RUNTIME_DIR``, else the temporary folder):
    ``neuralrt-NAME-UID`` (mode 0700; ``name``: numba-cache) when this user owns it, no one else may write it and
    no one else may rename it (``temp`` is ours or sticky), or a fresh one of this process's own."""
    if _writable(in_tree) or (user_cache is not None and _writable(user_cache)):
        return None
    try:
        temp = temp or Path(os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir())
        if not _ours_alone(temp, sticky_will_do=True):
            return None  # (another user could swap whatever we make there)
        shared = temp / f"neuralrt-{name}-{_uid()}"
        shared.mkdir(mode=0o700, exist_ok=True)
        if _ours_alone(shared) and _writable(shared):
            return str(shared)
        own = tempfile.mkdtemp(prefix=f"neuralrt-{name}-", dir=temp)
    except OSError:
        return None  # (no usable temporary folder either: numba says so itself)
    atexit.register(shutil.rmtree, own, ignore_errors=True)
    return own


def _uid() -> int:
    return os.getuid() if hasattr(os, "getuid") else 0


def _ours_alone(folder: Path, sticky_will_do: bool = False) -> bool:
    """Is ``folder`` a real folder (not a link) that no other user may write, or, with
    ``sticky_will_do``, a sticky one (``/tmp``: others may add files but not rename ours)?"""
    info = os.lstat(folder)
    if not stat.S_ISDIR(info.st_mode):
        return False
    if sticky_will_do and info.st_mode & stat.S_ISVTX:
        return True
    return info.st_uid == _uid() and not stat.S_IMODE(info.st_mode) & 0o022


def _could_write(folder: Path) -> bool:
    """Could files be made in ``folder``, or in the nearest folder above it that exists (where
    numba would make it)? Asked without making anything: ``import neuralrt`` made the user's
    chosen folder, and a file in it, each time (``--version`` too)."""
    existing = next((f for f in (folder, *folder.parents) if f.exists()), None)
    return existing is not None and existing.is_dir() and os.access(existing, os.W_OK | os.X_OK)


def _writable(folder: Path) -> bool:
    """Can a file be made in ``folder`` (made if missing)? numba's own test of a cache folder."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
        return True
    except OSError:
        return False


def guard_cache_writes() -> None:
    """Make numba's cache writes failing with an OSError a warning (once a process), now if numba's
    caching module is loaded, else when it loads (``import neuralrt`` does not import numba)."""
    module = sys.modules.get("numba.core.caching")
    if module is not None:
        _guard(module)
    elif not any(isinstance(f, _GuardOnImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _GuardOnImport())


class _GuardOnImport:
    """A `sys.meta_path` finder that only wraps the loading of ``numba.core.caching`` (found by the
    finders after it, as usual) so that `_guard` runs once it is loaded, and then takes itself out."""

    def find_spec(self, name, path=None, target=None):
        if name != "numba.core.caching":
            return None
        others = [f for f in sys.meta_path if f is not self and hasattr(f, "find_spec")]
        spec = next((found for f in others if (found := f.find_spec(name, path, target)) is not None), None)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        load = spec.loader.exec_module

        def exec_module(module):
            load(module)
            _guard(module)
            with contextlib.suppress(ValueError):  # (taken out already)
                sys.meta_path.remove(self)

        spec.loader.exec_module = exec_module
        return spec


_WARNED: list[bool] = []  # (one warning a process)


_NOTES: list[str] = []  # (what `choose_kernel_cache` changed, said when numba's caching loads: in a
#                          command, once its one-line warnings are set up)


def _guard(caching) -> None:
    if _NOTES:
        from .errors import outside_stacklevel

        warnings.warn(_NOTES.pop(), RuntimeWarning, stacklevel=outside_stacklevel())
    cache = getattr(caching, "Cache", None)
    save = getattr(cache, "save_overload", None)
    if save is None or getattr(save, "neuralrt_guarded", False):
        return

    def save_overload(self, sig, data):
        try:
            save(self, sig, data)
        except OSError as exc:
            module = getattr(getattr(self, "_py_func", None), "__module__", None) or ""
            if module.split(".")[0] != "neuralrt":  # (another package's kernels: numba's own behaviour)
                raise
            if not _WARNED:
                _WARNED.append(True)
                where = getattr(self, "_cache_path", None) or "numba's cache folder"
                warnings.warn(f"{where}: numba cannot cache compiled kernels there ({exc.strerror or exc}): they run, "
                              "and compile again in the next process", RuntimeWarning, stacklevel=2)

    save_overload.neuralrt_guarded = True
    cache.save_overload = save_overload


"""Where numba caches neuralrt's compiled kernels, when it could cache them nowhere.

Our kernels are compiled with ``cache=True``. numba keeps their cache beside the sources
(``__pycache__``), else in the user's cache folder (``$XDG_CACHE_HOME/numba`` or
``~/.cache/numba``), else, with neither writable (a read-only install run by a service account
or a container user without a home), it refuses to compile: every command that loads a kernel
failed with numba's "cannot cache function ...: no locator available" traceback.

`choose_kernel_cache` then points ``NUMBA_CACHE_DIR`` at a private folder in the temporary
directory. numba's cache index is a pickle that numba loads, so a folder another user could
have made or written to is not used: one of this process's own is made instead (compiled again
by each process, as without a cache). ``NUMBA_CACHE_DIR`` set by the user is never changed.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
from pathlib import Path

__all__ = ["choose_kernel_cache", "fallback_cache_dir"]


def choose_kernel_cache() -> str | None:
    """Set ``NUMBA_CACHE_DIR`` where numba would find no cache folder; return what it was set to."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    user_cache = Path(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")) / "numba"
    folder = fallback_cache_dir(Path(__file__).parent / "__pycache__", user_cache, Path(tempfile.gettempdir()))
    if folder is None:
        return None
    os.environ["NUMBA_CACHE_DIR"] = folder
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba imported first: it read the environment already
        config.CACHE_DIR = folder
    return folder


def fallback_cache_dir(in_tree: Path, user_cache: Path, temp: Path) -> str | None:
    """None where numba has a cache folder (``in_tree`` or ``user_cache`` writable); else a private
    folder under ``temp``: ``neuralrt-numba-cache-UID`` (mode 0700) when this user owns it and no
    one else may write it, or a fresh one of this process's own."""
    if _writable(in_tree) or _writable(user_cache):
        return None
    shared = temp / f"neuralrt-numba-cache-{os.getuid() if hasattr(os, 'getuid') else 0}"
    try:
        shared.mkdir(mode=0o700, exist_ok=True)
        info = os.lstat(shared)
        if (stat.S_ISDIR(info.st_mode) and not stat.S_IMODE(info.st_mode) & 0o022
                and (not hasattr(os, "getuid") or info.st_uid == os.getuid()) and _writable(shared)):
            return str(shared)
    except OSError:
        pass
    try:
        return tempfile.mkdtemp(prefix="neuralrt-numba-cache-", dir=temp)
    except OSError:
        return None  # (no writable temporary folder either: numba says so itself)


def _writable(folder: Path) -> bool:
    """Can a file be made in ``folder`` (made if missing)? numba's own test of a cache folder."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
        return True
    except OSError:
        return False

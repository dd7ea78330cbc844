"""`held_alone`: one process at a time works on a file (a training run on its checkpoint, a
conversion on its output scene).

Two ``neuralrt train`` (or ``convert``) commands with the same output would each overwrite the
other's checkpoint (atomically, so neither file is torn) while both train the same model on the
same cores. The second one is told instead, before its work starts. A conversion also holds its
output scene file, so that of two converts into one scene the second stops before any model.

The lock is ``flock`` on a sibling ``<file>.lock`` holding the owner's pid: the kernel releases it
when its process ends, however it ends (SIGKILL, a power cut's reboot), so a leftover file never
blocks a later run. Where ``flock`` is unavailable (a file system without locks, Windows), the run
goes on unlocked, as before this check existed.
"""

from __future__ import annotations

import contextlib
import errno
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

from ..errors import NeuralRTError

try:
    import fcntl
except ImportError:  # (Windows)
    fcntl = None

__all__ = ["held_alone", "lock_path", "wait_while_held"]

# The locks this thread holds (real paths, links followed): taking one again is a no-op. (Per thread: another
# thread's flock on its own descriptor conflicts, as another process's does.)
_HELD = threading.local()

# flock's "not supported here" errors (NFS without lockd, some FUSE file systems): run unlocked.
_NO_LOCKS = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL}


def lock_path(path: Path) -> Path:
    return path.with_name(path.name + ".lock")


@contextlib.contextmanager
def held_alone(path: str | os.PathLike, work: str = "training this model"):
    """Run the block while this process alone holds ``path``'s lock (``path``: a training run's
    checkpoint, or what ``work`` says); a one-line `NeuralRTError` naming the holder's pid and its
    ``work`` if another process holds it.
    ``path``'s folder must exist. The lock file is removed at the end. Nested blocks on one path
    in one process share the outer block's lock."""
    lock = lock_path(Path(path))
    key, held = os.path.realpath(lock), _HELD.__dict__.setdefault("paths", set())  # (one lock however spelt)
    if key in held:
        yield
        return
    fd = _acquired(lock, work) if fcntl is not None else None
    held.add(key)
    try:
        yield
    finally:
        held.discard(key)
        if fd is not None:
            with contextlib.suppress(OSError):  # (removed by hand meanwhile: nothing to clean)
                lock.unlink()  # before the unlock: a waiter that opened this file then finds it gone and retries
            os.close(fd)


def wait_while_held(path: str | os.PathLike, on_wait: Callable[[str], None]) -> bool:
    """Wait until no process holds ``path``'s lock (`held_alone`), calling ``on_wait(pid)`` first
    if one does; whether it waited. (A conversion whose model another conversion is training waits
    for it and reuses the model, where it stopped with "another process is training this model".)"""
    if fcntl is None:
        return False
    try:
        fd = os.open(lock_path(Path(path)), os.O_RDONLY)
    except OSError:  # (no lock file: no one holds it)
        return False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            return False
        except BlockingIOError:
            on_wait(_holder(fd))
            fcntl.flock(fd, fcntl.LOCK_SH)  # (released when its holder ends, however it ends)
            return True
        except OSError as exc:
            if exc.errno in _NO_LOCKS:
                return False
            raise
    finally:
        os.close(fd)


def _held_error(lock: Path, holder: str, work: str) -> NeuralRTError:
    who = ("another thread of this process" if holder == str(os.getpid())  # (two threads: the same pid)
           else f"another process{f' (pid {holder})' if holder else ''}")
    return NeuralRTError(f"{lock.with_suffix('')}: {who} is {work}; wait for it to end, or write elsewhere")


def _acquired(lock: Path, work: str) -> int | None:
    """An open, flocked descriptor of ``lock`` (the file at that name now, not one a finishing
    holder just unlinked), with this pid written in it; None where the file system has no locks."""
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise NeuralRTError(f"{lock}: cannot create the lock file ({exc.strerror or exc})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise _held_error(lock, holder, work) from None
        except OSError as exc:
            os.close(fd)
            if exc.errno in _NO_LOCKS:
                return None
            raise
        try:
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)  # the holder removed it between our open and our lock: take the new one


def _holder(fd: int) -> str:
    """The pid the holder wrote, "" if none. It writes it just after taking the lock: read at once,
    the file was empty (1 refusal in 25 said "another process" of another thread of this one)."""
    for _ in range(50):
        with contextlib.suppress(OSError, ValueError):
            return str(int(os.pread(fd, 32, 0).decode().strip()))
        time.sleep(0.002)
    return ""

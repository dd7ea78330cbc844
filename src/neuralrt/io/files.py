"""Output and input files: atomic writes that respect the user's umask, and input-file checks.

`check_output_file` / `check_output_folder` ask, before any long work, whether an output can be
written there (without creating anything). `write_atomically` is the one way neuralrt writes an
output file (images, model files, scene files, checkpoints): the data goes to a temporary
sibling, then one ``os.replace`` puts it in place, so a crash leaves the old file or the new one,
never half of one (a temporary file that a killed process left behind is removed by a later
write of the same file, once it is an hour old). A new file gets mode ``0o666`` filtered by the
umask, like any file a program opens for writing (``tempfile.mkstemp`` would make every output
``0600``); a file written again keeps its mode, as ``cp`` over it does.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import glob
import os
import re
import secrets
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path

from ..errors import NeuralRTError
from ..interrupts import interrupts_held

try:
    import fcntl
except ImportError:  # (Windows)
    fcntl = None

__all__ = ["write_atomically", "written_together", "input_file_problem", "check_output_file", "check_output_files", "check_output_folder",
           "folders_removed_if_left_empty"]


def resolved(path: str | os.PathLike) -> Path:
    """``Path(path).resolve()``, except that a loop of links is left for its first read to name (Python
    3.11 and 3.12 raised a RuntimeError there, "Symlink loop from ...", past every OSError check)."""
    try:
        return Path(path).resolve()
    except RuntimeError:
        return Path(os.path.abspath(path))


def _sibling_name(path: Path) -> Path:
    # The suffix stays last: some writers pick the format from the name.
    return path.with_name(f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}")


# A temporary sibling this old was left by a writer killed mid-write (SIGKILL, power cut): live ones
# exist for the seconds a file takes to write, so sweeping these never races a concurrent writer.
STALE_SIBLING_SECONDS = 3600


def _sweep_stale_siblings(path: Path) -> None:
    """Remove ``path``'s temporary siblings (`_sibling_name`'s pattern) older than `STALE_SIBLING_SECONDS`."""
    pattern = re.compile(re.escape(f".{path.stem}.") + "[0-9a-f]{8}" + re.escape(f".tmp{path.suffix}"))
    cutoff = time.time() - STALE_SIBLING_SECONDS
    try:
        candidates = list(path.parent.glob(glob.escape(f".{path.stem}.") + "*"))
    except OSError:
        return
    for candidate in candidates:
        with contextlib.suppress(OSError):  # gone already, or not ours to remove: never fail a write over it
            if pattern.fullmatch(candidate.name) and candidate.lstat().st_mtime < cutoff and candidate.is_file():
                candidate.unlink()


def _create_sibling(path: Path) -> Path:
    """A new empty file beside ``path`` (mode 0o666 & ~umask) with an unused hidden name; stale
    siblings an interrupted earlier write left are removed first."""
    _sweep_stale_siblings(path)
    while True:
        tmp = _sibling_name(path)
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp


def write_atomically(path: str | os.PathLike, write_to: Callable[[str], None], fsync: bool = False) -> Path:
    """Call ``write_to(tmp_path)`` (it writes the whole file there), then rename it over ``path``.

    ``path``'s folder must exist. With ``fsync`` the data is flushed to disk before the rename
    (model files and checkpoints: a power cut must not leave an empty file under the final name).
    Whatever ``write_to`` raises propagates after the temporary file is removed.
    """
    path = _link_target(Path(path))
    problem = _replace_problem(path, "file")
    if problem:  # (callers check first, before their work: this is the last guard)
        raise NeuralRTError(problem)
    tmp = _create_sibling(path)
    mode = _existing_mode(path)  # a file written again keeps its mode, as `cp` over it does
    if mode is None:
        mode = stat.S_IMODE(os.stat(tmp).st_mode)  # 0o666 & ~umask, as the kernel applied it
    staged = _STAGED.get()
    try:
        write_to(str(tmp))
        os.chmod(tmp, mode)  # some writers (safetensors) replace the file with a 0600 one of their own
        if fsync:  # (read-only: the temporary may carry a rewritten file's read-only mode already)
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        if staged is not None:  # (`written_together`: renamed with the others, at the block's end)
            staged.append((tmp, path))
            return path
        os.replace(tmp, path)
    except OSError as exc:
        if exc.filename is None or str(exc.filename) == str(tmp):  # name the file the user asked for, not our temporary
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        raise
    finally:
        if tmp.exists() and (staged is None or (tmp, path) not in staged):
            tmp.unlink()
    return path


def _replace_problem(target: Path, what: str, shown: Path | None = None) -> str | None:
    """Why writing ``what`` over the existing ``target`` (a link's target: `_link_target`) would go
    wrong, or None: anything but a regular file (a device, a FIFO: in a trial, `-o` through a link
    to /dev/null made it a regular file), or another user's file in a sticky folder such as /tmp,
    which only its owner may replace (the rename failed after the work, naming our temporary, and
    left a render's set half new). ``shown``: the name the user gave."""
    try:
        st = os.stat(target)
    except OSError:
        return None  # (nothing there yet)
    name = f"{shown}: a link to {target}," if shown is not None and shown != target else f"{target}:"
    if not stat.S_ISREG(st.st_mode) and not stat.S_ISDIR(st.st_mode):
        kind = ("a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else
                "a named pipe" if stat.S_ISFIFO(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "no file")
        return f"{name} {kind}, not a regular file: the {what} would replace it; give a file name"
    euid = os.geteuid() if hasattr(os, "geteuid") else None
    if euid not in (None, 0, st.st_uid):
        try:
            folder = os.stat(target.parent)
        except OSError:
            return None
        if folder.st_mode & stat.S_ISVTX and folder.st_uid != euid:
            return (f"{name} another user's file in a folder where only its owner may replace it (sticky, as /tmp): "
                    f"give another name for the {what}")
    return None


def _existing_mode(path: Path) -> int | None:
    """The permission bits of the regular file at ``path`` (None if there is none): a user who made
    an output private (0600) keeps it private when a run writes it again."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return stat.S_IMODE(st.st_mode) & 0o777 if stat.S_ISREG(st.st_mode) else None


_STAGED: contextvars.ContextVar[list | None] = contextvars.ContextVar("neuralrt_staged_writes", default=None)
# One set's renames at a time in this process: two threads rendering to one output interleaved
# theirs (in a trial, 6 of 60 such renders left an image with the other's AOVs; 20 of 200 bare
# ten-file sets were left mixed).
_RENAMING = threading.Lock()


@contextlib.contextmanager
def written_together():
    """Within the block, `write_atomically` leaves each file under its temporary name; when the block
    ends they are all renamed into place, or, if it fails (an interrupt too), all removed: a set of
    outputs (a render's image and AOVs, eval's figures) is written whole or not at all, never half
    new and half as an earlier run left it. A block inside another joins the outer one. Two sets
    renamed by two threads or processes are renamed one after the other, never interleaved."""
    if _STAGED.get() is not None:  # (inside another such block: its files go with that block's)
        yield
        return
    staged: list[tuple[Path, Path]] = []
    token = _STAGED.set(staged)
    try:
        yield
    except BaseException:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        raise
    finally:
        _STAGED.reset(token)
    # Another thread's or process's set renamed in between mixed the two sets: they wait for each
    # other (an interrupt while waiting stops the wait); an interrupt between two renames left half
    # the set new, and temporaries: held until the renames are done.
    path = None
    try:
        with _RENAMING, _folders_locked(path for _, path in staged), interrupts_held():
            problem = next(filter(None, (_replace_problem(path, "file") for _, path in staged)), None)
            if problem:  # (found before the first rename: none of the set is replaced)
                raise NeuralRTError(problem)
            for tmp, path in staged:
                os.replace(tmp, path)
    except BaseException as exc:
        with interrupts_held():
            for tmp, _ in staged:
                tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and path is not None:  # (it named our temporary, not the output)
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        raise


@contextlib.contextmanager
def _folders_locked(paths):
    """The block runs while this process holds ``paths``' folders locked (``flock`` on each folder,
    in one order: no deadlock), so another process's set renamed into them waits (no lock file is
    left). Where a folder cannot be locked (no ``flock``: Windows, some network file systems), as
    before: the renames are milliseconds apart."""
    fds = []
    try:
        for folder in sorted({os.path.realpath(Path(p).parent) for p in paths}) if fcntl is not None else ():
            try:
                fd = os.open(folder, os.O_RDONLY)
            except OSError:
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
            except OSError:
                os.close(fd)
                continue
            fds.append(fd)
        yield
    finally:
        for fd in fds:
            os.close(fd)


def _link_target(path: Path) -> Path:
    """Where writing ``path`` should land: a symlink's target (as ``cp`` or a shell redirection write
    through it; renaming over the link would replace the link instead), else ``path`` itself."""
    return Path(os.path.realpath(path)) if path.is_symlink() else path


def _article(noun: str) -> str:
    return "an" if noun[:1].lower() in "aeio" else "a"


def input_file_problem(path: str | os.PathLike, what: str) -> str | None:
    """None when ``path`` is a readable file, else the one-line problem naming it, e.g.
    ``"scenes: is a directory, not a scene file"`` or ``"a.obj: mesh file not found"``."""
    path = Path(path)
    if path.is_dir():
        return f"{path}: is a directory, not {_article(what)} {what}"
    if not path.exists():
        try:
            path.stat()
        except OSError as exc:
            if exc.errno == errno.ELOOP:  # (exists() says False for a loop of links too)
                return f"{path}: a loop of symbolic links, not {_article(what)} {what}"
        return f"{path}: {what} not found"
    if not path.is_file():
        return f"{path}: not a regular file (a {what} must be one)"
    return None


def _nearest_existing(folder: Path) -> Path:
    """``folder`` or its nearest ancestor that exists (the current folder for a relative path none of whose folders exist)."""
    return next((f for f in (folder, *folder.parents) if f.exists()), Path("."))


def _writable_folder_problem(folder: Path, what: str) -> str | None:
    """None when ``folder`` exists and takes new files, or can be created; else the problem."""
    ancestor = _nearest_existing(folder)
    if not ancestor.is_dir():
        where = "" if ancestor == folder else f" (on the way to {folder})"
        return f"{ancestor}: is a file, not a folder{where}"
    # Probing with a real file: os.access says yes to root everywhere (sysfs, ACLs, some network mounts).
    try:
        probe = _create_sibling(ancestor / "neuralrt-write-probe")
    except OSError as exc:  # (ENOENT where the folder exists: /proc and the like take no new files)
        reason = "it takes no new files" if exc.errno == errno.ENOENT else exc.strerror or exc
        return f"{ancestor}: cannot write the {what} there ({reason})"
    probe.unlink()
    return None


def check_output_file(path: str | os.PathLike, what: str) -> None:
    """A one-line `NeuralRTError` unless a file can be written at ``path``: not a folder, its folder
    existing (or creatable) and writable, its name short enough. Nothing is created."""
    check_output_files([path], what)


def check_output_files(paths, what: str) -> None:
    """`check_output_file` for several files (a render's image and AOVs, a model and its checkpoint),
    each folder probed once."""
    targets = []
    for path in map(Path, paths):
        if path.is_dir():
            raise NeuralRTError(f"{path}: is a folder, not {_article(what)} {what}")
        target = _link_target(path)
        if target != path and not target.parent.is_dir():  # (commands make the link's folder, not its target's)
            raise NeuralRTError(f"{path}: a link to {target}, whose folder does not exist")
        problem = _replace_problem(target, what, path)
        if problem:
            raise NeuralRTError(problem)
        targets.append(target)
    for folder in dict.fromkeys(target.parent for target in targets):
        problem = _writable_folder_problem(folder, what)
        if problem:
            raise NeuralRTError(problem)
    for target in targets:
        problem = _name_length_problem(target, what)
        if problem:
            raise NeuralRTError(problem)


def _name_length_problem(path: Path, what: str) -> str | None:
    """Too long a name for its filesystem, counting the temporary sibling `write_atomically` writes
    first (a name that fits alone would fail only at that write, after the work)."""
    try:
        limit = os.pathconf(_nearest_existing(path.parent), "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    longest = len(os.fsencode(_sibling_name(path).name))
    if longest > limit:
        return (f"{path.name[:40]}...: the {what}'s name is too long ({len(os.fsencode(path.name))} bytes; with the "
                f"temporary name it is written under first, {longest} of at most {limit})")
    return None


def check_output_folder(folder: str | os.PathLike, what: str) -> None:
    """A one-line `NeuralRTError` unless ``folder`` is (or can be made) a writable folder. Nothing is created."""
    problem = _writable_folder_problem(Path(folder), what)
    if problem:
        raise NeuralRTError(problem)


@contextlib.contextmanager
def folders_removed_if_left_empty(*folders: str | os.PathLike):
    """Run the block; if it fails (an interrupt too), remove those of ``folders`` and their ancestors
    that did not exist before it and are still empty: a failed command leaves no new empty folders."""
    new = list(dict.fromkeys(f for folder in folders for f in (Path(folder), *Path(folder).parents) if not f.exists()))
    try:
        yield
    except BaseException:
        for folder in sorted(new, key=lambda f: len(f.parts), reverse=True):  # deepest first
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        raise

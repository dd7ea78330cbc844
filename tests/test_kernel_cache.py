"""numba's kernel cache where an install is read-only and the user has no writable home: a
private folder in the runtime or temporary folder (numba refused to compile: every command failed)."""

import os
import stat
import sys
from pathlib import Path

import pytest

import neuralrt
import neuralrt.kernel_cache as kernel_cache
from neuralrt.kernel_cache import choose_kernel_cache, fallback_cache_dir

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX modes and owners")


@pytest.fixture
def unwritable(tmp_path):
    """A folder no one can make, root included: its parent is a file."""
    (tmp_path / "a-file").write_text("")
    return tmp_path / "a-file" / "numba"


@pytest.fixture
def temp(tmp_path):
    folder = tmp_path / "tmp"
    folder.mkdir(mode=0o700)
    return folder


def test_no_fallback_where_numba_has_a_cache_folder(tmp_path, unwritable, temp):
    assert fallback_cache_dir(tmp_path / "tree", unwritable, temp) is None
    assert fallback_cache_dir(unwritable, tmp_path / "home" / ".cache" / "numba", temp) is None
    assert list(temp.iterdir()) == []


def test_with_neither_a_private_folder_in_the_temporary_directory(unwritable, temp):
    folder = fallback_cache_dir(unwritable, unwritable, temp)
    assert folder == str(temp / f"neuralrt-numba-cache-{os.getuid()}")
    assert stat.S_IMODE(os.stat(folder).st_mode) == 0o700
    assert fallback_cache_dir(unwritable, unwritable, temp) == folder  # (the next process reuses it)


def test_a_folder_others_may_write_is_not_used_and_its_stand_in_goes_at_exit(unwritable, temp, monkeypatch):
    """numba loads its cache index with pickle: a folder another user could write is not trusted."""
    at_exit = []
    monkeypatch.setattr(kernel_cache.atexit, "register", lambda *call, **kw: at_exit.append((call, kw)))
    shared = temp / f"neuralrt-numba-cache-{os.getuid()}"
    shared.mkdir()
    shared.chmod(0o777)
    folder = fallback_cache_dir(unwritable, unwritable, temp)
    assert folder != str(shared) and os.path.dirname(folder) == str(temp)
    assert os.path.basename(folder).startswith("neuralrt-numba-cache-") and stat.S_IMODE(os.stat(folder).st_mode) == 0o700
    assert at_exit == [((kernel_cache.shutil.rmtree, folder), {"ignore_errors": True})]  # (one per process: removed)


def test_a_symlink_in_its_place_is_not_followed(tmp_path, unwritable, temp, monkeypatch):
    monkeypatch.setattr(kernel_cache.atexit, "register", lambda *call, **kw: None)
    (tmp_path / "elsewhere").mkdir(mode=0o700)
    (temp / f"neuralrt-numba-cache-{os.getuid()}").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    folder = fallback_cache_dir(unwritable, unwritable, temp)
    assert os.path.realpath(folder) == folder and not folder.endswith(f"-{os.getuid()}")


def test_a_temporary_folder_others_may_rename_in_is_not_used(unwritable, temp):
    temp.chmod(0o777)  # (without the sticky bit another user could swap our folder for theirs)
    assert fallback_cache_dir(unwritable, unwritable, temp) is None
    temp.chmod(0o1777)  # as /tmp
    assert fallback_cache_dir(unwritable, unwritable, temp) == str(temp / f"neuralrt-numba-cache-{os.getuid()}")


def test_the_choice_reaches_numba_and_the_users_own_setting_stays(tmp_path, monkeypatch):
    import numba.core.config

    asked = []
    monkeypatch.setattr(numba.core.config, "CACHE_DIR", "")
    monkeypatch.setattr(kernel_cache, "fallback_cache_dir", lambda *folders: asked.append(folders) or str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "their-choice"))
    assert choose_kernel_cache() is None and os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "their-choice")
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert choose_kernel_cache() == str(tmp_path)
    assert asked == [(Path(neuralrt.__file__).parent / "__pycache__", tmp_path / "xdg" / "numba")]
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path) and numba.core.config.CACHE_DIR == str(tmp_path)
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setattr(numba.core.config, "CACHE_DIR", "/set/in/code")  # (numba imported first, set by hand)
    assert choose_kernel_cache() is None and numba.core.config.CACHE_DIR == "/set/in/code"


def test_a_cache_file_numba_cannot_write_is_a_warning_and_the_kernel_runs(tmp_path):
    # A full disk under numba's cache made every command on a cold cache fail ("No space left on
    # device", naming no file). In a child: numba loads after `import neuralrt`, as in a command.
    import subprocess
    import textwrap

    kernel = "import numba\n\n@numba.njit(cache=True)\ndef f(x):\n    return x + 1\n"
    (tmp_path / "kernel_mod.py").write_text('__name__ = "neuralrt.kernel_under_test"  # (one of ours)\n' + kernel)
    (tmp_path / "their_mod.py").write_text(kernel)  # (another package's: numba's own behaviour stays)
    script = textwrap.dedent("""
        import errno, sys, warnings
        import neuralrt
        from neuralrt.kernel_cache import _GuardOnImport
        assert "numba" not in sys.modules and any(isinstance(f, _GuardOnImport) for f in sys.meta_path)
        import numba.core.caching as caching
        assert not any(isinstance(f, _GuardOnImport) for f in sys.meta_path)  # (it took itself out)

        def full(self, key, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        caching.IndexDataCacheFile.save = full
        sys.path.insert(0, sys.argv[1])
        import kernel_mod
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            print(kernel_mod.f(41))
        print(len(caught), caught[0].category.__name__, caught[0].message)
        import their_mod
        try:
            their_mod.f(1)
        except OSError as exc:
            print("theirs:", exc.strerror)
    """)
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr
    result, warned, theirs = done.stdout.splitlines()
    assert result == "42" and theirs == "theirs: No space left on device"
    assert warned.startswith(f"1 RuntimeWarning {tmp_path / 'cache'}") and warned.endswith(
        ": numba cannot cache compiled kernels there (No space left on device): they run, and compile again in the "
        "next process")


def test_a_chosen_folder_numba_cannot_write_gives_way_where_numba_has_no_other(tmp_path, unwritable, monkeypatch):
    # (a read-only shared cache in a read-only install without a home: numba used the folder for
    # nothing, found no other, and every kernel failed with "no locator available")
    import types

    import numba.core.config

    monkeypatch.setattr(numba.core.config, "CACHE_DIR", str(unwritable))
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(unwritable))
    monkeypatch.setattr(kernel_cache, "_NOTES", [])
    monkeypatch.setattr(kernel_cache, "fallback_cache_dir", lambda *folders: None)  # (numba has a folder of its own)
    assert choose_kernel_cache() is None and os.environ["NUMBA_CACHE_DIR"] == str(unwritable) and not kernel_cache._NOTES
    monkeypatch.setattr(kernel_cache, "fallback_cache_dir", lambda *folders: str(tmp_path))  # (it has none)
    assert choose_kernel_cache() == str(tmp_path)
    assert os.environ["NUMBA_CACHE_DIR"] == numba.core.config.CACHE_DIR == str(tmp_path)
    with pytest.warns(RuntimeWarning, match=f"NUMBA_CACHE_DIR={unwritable}: numba cannot write there .* neuralrt's "
                                            f"kernels are cached in {tmp_path}"):
        kernel_cache._guard(types.SimpleNamespace())  # (said when numba's caching loads)
    assert not kernel_cache._NOTES

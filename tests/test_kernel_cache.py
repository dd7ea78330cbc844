"""numba's kernel cache where an install is read-only and the user has no writable home: a
private folder in the temporary directory (numba refused to compile: every command failed)."""

import os
import stat
import sys

import pytest

import neuralrt.kernel_cache as kernel_cache
from neuralrt.kernel_cache import choose_kernel_cache, fallback_cache_dir

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX modes and owners")


@pytest.fixture
def unwritable(tmp_path):
    """A folder no one can make, root included: its parent is a file."""
    (tmp_path / "a-file").write_text("")
    return tmp_path / "a-file" / "numba"


def test_no_fallback_where_numba_has_a_cache_folder(tmp_path, unwritable):
    assert fallback_cache_dir(tmp_path / "tree", unwritable, tmp_path / "tmp") is None
    assert fallback_cache_dir(unwritable, tmp_path / "home" / ".cache" / "numba", tmp_path / "tmp") is None
    assert not (tmp_path / "tmp").exists()


def test_with_neither_a_private_folder_in_the_temporary_directory(tmp_path, unwritable):
    folder = fallback_cache_dir(unwritable, unwritable, tmp_path)
    assert folder == str(tmp_path / f"neuralrt-numba-cache-{os.getuid()}")
    assert stat.S_IMODE(os.stat(folder).st_mode) == 0o700
    assert fallback_cache_dir(unwritable, unwritable, tmp_path) == folder  # (the next process reuses it)


def test_a_folder_others_may_write_is_not_used(tmp_path, unwritable):
    """numba loads its cache index with pickle: a folder another user could write is not trusted."""
    shared = tmp_path / f"neuralrt-numba-cache-{os.getuid()}"
    shared.mkdir()
    shared.chmod(0o777)
    folder = fallback_cache_dir(unwritable, unwritable, tmp_path)
    assert folder != str(shared) and os.path.dirname(folder) == str(tmp_path)
    assert os.path.basename(folder).startswith("neuralrt-numba-cache-") and stat.S_IMODE(os.stat(folder).st_mode) == 0o700


def test_a_symlink_in_its_place_is_not_followed(tmp_path, unwritable):
    (tmp_path / "elsewhere").mkdir(mode=0o700)
    (tmp_path / f"neuralrt-numba-cache-{os.getuid()}").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    folder = fallback_cache_dir(unwritable, unwritable, tmp_path)
    assert os.path.realpath(folder) == folder and not folder.endswith(f"-{os.getuid()}")


def test_the_choice_reaches_numba_and_the_users_own_setting_stays(tmp_path, monkeypatch):
    import numba.core.config

    monkeypatch.setattr(numba.core.config, "CACHE_DIR", numba.core.config.CACHE_DIR)
    monkeypatch.setattr(kernel_cache, "fallback_cache_dir", lambda *folders: str(tmp_path))
    monkeypatch.setenv("NUMBA_CACHE_DIR", "/their/choice")
    assert choose_kernel_cache() is None and os.environ["NUMBA_CACHE_DIR"] == "/their/choice"
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert choose_kernel_cache() == str(tmp_path)
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path) and numba.core.config.CACHE_DIR == str(tmp_path)

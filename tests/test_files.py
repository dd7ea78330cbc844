"""Output files get the user's umask and appear atomically; a directory given as an input file is
named as one; every writer (images, scene files, model files) goes through the same helper."""

import os
import stat
import time

import numpy as np
import pytest
import torch

from neuralrt.errors import ImageError, MeshError, ModelFileError, SceneError
from neuralrt.geometry.mesh import load_mesh
from neuralrt.io.files import input_file_problem, write_atomically
from neuralrt.io.images import read_image, write_exr, write_hdr, write_png
from neuralrt.io.model_file import read_header, write_model_file
from neuralrt.scene.loader import load_scene, load_scene_spec
from neuralrt.scene.scene import save_scene


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    yield 0o640  # 0o666 & ~0o027
    os.umask(old)


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_every_writer_gives_outputs_the_umask_mode(tmp_path, umask_027):
    write_exr(tmp_path / "a.exr", np.ones((2, 2, 3)))
    write_png(tmp_path / "a.png", np.ones((2, 2, 3)))
    write_hdr(tmp_path / "a.hdr", np.ones((2, 2, 3)))
    spec, _, _ = load_scene_spec("builtin:instances?detail=0")
    save_scene(spec, tmp_path / "s.toml")
    write_model_file(tmp_path / "m.nrt", "test", {}, {"w": torch.zeros(3)})
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["a.exr", "a.hdr", "a.png", "m.nrt", "s.toml"]  # no temporaries left
    assert {n: _mode(tmp_path / n) for n in names} == dict.fromkeys(names, umask_027)
    assert read_header(tmp_path / "m.nrt")["method"] == "test"


def test_a_file_written_again_keeps_its_mode(tmp_path, umask_027):
    # It became 0o666 & ~umask: a private (0600) model or image was made readable by the group.
    model, image = tmp_path / "m.nrt", tmp_path / "a.png"
    write_model_file(model, "test", {}, {"w": torch.zeros(3)})
    write_png(image, np.ones((2, 2, 3)))
    os.chmod(model, 0o600)
    os.chmod(image, 0o644)
    write_model_file(model, "test", {}, {"w": torch.ones(3)})
    write_png(image, np.zeros((2, 2, 3)))
    assert (_mode(model), _mode(image)) == (0o600, 0o644)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "m.nrt"]


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")

    def half_then_fail(tmp):
        with open(tmp, "w") as f:
            f.write("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        write_atomically(target, half_then_fail)
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    write_atomically(target, lambda tmp: open(tmp, "w").write("new"))
    assert target.read_text() == "new"


def test_an_interrupt_while_a_set_is_put_in_place_lands_after_the_whole_set(tmp_path, monkeypatch):
    # It landed between two renames: half the set new, half old, and the rest left as temporaries.
    import signal

    from neuralrt.io import files

    names = ["img.exr", "img.png", "img_albedo.exr"]
    for name in names:
        (tmp_path / name).write_text("old")
    replace, renamed = os.replace, []

    def replace_then_interrupt(src, dst):
        replace(src, dst)
        renamed.append(dst)
        if len(renamed) == 1:
            signal.raise_signal(signal.SIGINT)  # (Ctrl-C, right after the first rename)

    monkeypatch.setattr(files.os, "replace", replace_then_interrupt)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with files.written_together():
                for name in names:
                    write_atomically(tmp_path / name, lambda tmp: open(tmp, "w").write("new"))
    finally:
        signal.signal(signal.SIGINT, before)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names)  # no temporaries
    assert {(tmp_path / n).read_text() for n in names} == {"new"}


def test_a_killed_writers_old_temporary_is_swept_by_the_next_write(tmp_path):
    # What a SIGKILL between creating the temporary sibling and the rename leaves behind.
    stale, fresh = tmp_path / ".model.0123abcd.tmp.nrt", tmp_path / ".model.89abcdef.tmp.nrt"
    other_file, not_ours = tmp_path / ".scene.0123abcd.tmp.toml", tmp_path / ".model.backup.nrt"
    for leftover in (stale, fresh, other_file, not_ours):
        leftover.write_bytes(b"half")
    an_hour_and_a_bit_ago = time.time() - 3700
    for old in (stale, other_file, not_ours):
        os.utime(old, (an_hour_and_a_bit_ago, an_hour_and_a_bit_ago))
    write_atomically(tmp_path / "model.nrt", lambda tmp: open(tmp, "w").write("new"))
    # Only the old temporary of the file written goes: a recent one may be a concurrent writer's,
    # another file's is swept when that file is written, and a name off the pattern is the user's.
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["model.nrt", fresh.name, other_file.name, not_ours.name])
    write_atomically(tmp_path / "scene.toml", lambda tmp: open(tmp, "w").write("s"))
    assert not other_file.exists()


def test_a_directory_as_an_input_file_is_named_as_one(tmp_path):
    folder = tmp_path / "inputs.obj"
    folder.mkdir()
    assert input_file_problem(folder, "mesh file") == f"{folder}: is a directory, not a mesh file"
    assert input_file_problem(tmp_path / "x.obj", "mesh file") == f"{tmp_path / 'x.obj'}: mesh file not found"
    with pytest.raises(MeshError, match="inputs.obj: is a directory, not a mesh file"):
        load_mesh(folder)
    with pytest.raises(ImageError, match="is a directory, not an? image file"):
        read_image(folder)
    with pytest.raises(MeshError, match="inputs.obj: is a directory, not a mesh file"):
        load_scene(folder)  # (a mesh given where a scene goes renders alone: `neuralrt.scene.studio`)
    (tmp_path / "scene.toml").mkdir()
    with pytest.raises(SceneError, match="scene.toml: is a directory, not a scene file"):
        load_scene(tmp_path / "scene.toml")
    with pytest.raises(ModelFileError, match="not a file"):
        read_header(folder)


def test_random_bytes_mesh_is_one_line_mesh_error(tmp_path):
    junk = tmp_path / "junk.obj"
    junk.write_bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(MeshError, match="junk.obj") as info:
        load_mesh(junk)
    assert "\n" not in str(info.value) and "No module" not in str(info.value)


def test_failed_render_leaves_no_empty_folders(tmp_path):
    from neuralrt import api
    from neuralrt.errors import NeuralRTError

    bad = tmp_path / "bad.toml"
    bad.write_text("[[objects]]\nmesh = 'missing.obj'\n")
    with pytest.raises(NeuralRTError, match="missing.obj"):
        api.render(bad, tmp_path / "out" / "deep" / "img.exr", progress=False)
    assert not (tmp_path / "out").exists()
    done = api.render("builtin:cornell-statue?detail=0", tmp_path / "out" / "deep" / "img.exr", spp=1,
                      resolution=(8, 8), progress=False)
    assert (tmp_path / "out" / "deep" / "img.exr").is_file() and len(done["files"]) == 10  # image + 4 AOVs, EXR and PNG each


def test_a_set_written_inside_another_appears_with_the_outer_one(tmp_path):
    # (demo: a render's image and AOVs inside the report's set; the inner block renamed them at once)
    from neuralrt.io.files import written_together

    with written_together():
        with written_together():
            write_atomically(tmp_path / "inner.txt", lambda tmp: open(tmp, "w").write("a"))
        assert not (tmp_path / "inner.txt").exists()
        write_atomically(tmp_path / "outer.txt", lambda tmp: open(tmp, "w").write("b"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inner.txt", "outer.txt"]


def test_two_threads_writing_one_set_of_outputs_leave_one_whole_set(tmp_path):
    """Two renders to one output from two threads of a process: each set of files is renamed into
    place whole (before, their renames interleaved: 20 of 200 ten-file sets were left mixed)."""
    import threading

    from neuralrt.io.files import written_together

    names = [tmp_path / f"f{k}.txt" for k in range(10)]

    def writer(tag: str) -> None:
        for i in range(3):
            with written_together():
                for path in names:
                    write_atomically(path, lambda tmp, text=f"{tag}{i}": open(tmp, "w").write(text))

    for _ in range(100):
        threads = [threading.Thread(target=writer, args=(tag,)) for tag in "AB"]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len({path.read_text() for path in names}) == 1
    assert sorted(os.listdir(tmp_path)) == sorted(path.name for path in names)  # (no temporaries)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes: POSIX")
def test_an_output_that_is_a_pipe_or_a_link_to_one_is_refused_before_the_work(tmp_path):
    # A device or pipe (or a link to one: as root, `-o` through a link to /dev/null) became a regular file.
    from neuralrt import api
    from neuralrt.errors import NeuralRTError
    from neuralrt.io.files import check_output_file

    os.mkfifo(tmp_path / "pipe.exr")
    (tmp_path / "link.exr").symlink_to(tmp_path / "pipe.exr")
    with pytest.raises(NeuralRTError, match=r"pipe.exr: a named pipe, not a regular file: the render output would replace it"):
        api.render("builtin:cornell-statue?detail=0", tmp_path / "pipe.exr", spp=1, resolution=(4, 4), progress=False)
    with pytest.raises(NeuralRTError, match=r"link.exr: a link to .*pipe.exr, a named pipe, not a regular file"):
        check_output_file(tmp_path / "link.exr", "render output")
    with pytest.raises(NeuralRTError, match="a named pipe"):  # (the writer's own guard, for callers that did not check)
        write_atomically(tmp_path / "link.exr", lambda tmp: open(tmp, "w").write("x"))
    assert stat.S_ISFIFO(os.stat(tmp_path / "pipe.exr").st_mode) and sorted(p.name for p in tmp_path.iterdir()) == ["link.exr", "pipe.exr"]


@pytest.mark.skipif(not hasattr(os, "geteuid"), reason="file owners: POSIX")
def test_another_users_file_in_a_sticky_folder_is_refused_and_no_file_of_the_set_is_replaced(tmp_path, monkeypatch):
    # In a shared sticky folder (/tmp) the rename over another user's older r_depth.exr failed after
    # the render, naming our temporary, with r.exr and two AOVs already replaced.
    from neuralrt.errors import NeuralRTError
    from neuralrt.io import files

    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    for name in ("r.exr", "r_depth.exr"):
        (shared / name).write_text("old")
    monkeypatch.setattr(files.os, "geteuid", lambda: os.stat(shared).st_uid + 1)  # (we are another user)
    with pytest.raises(NeuralRTError, match=r"r_depth.exr: another user's file in a folder where only its owner may "
                                            r"replace it \(sticky, as /tmp\): give another name for the render output"):
        files.check_output_files([shared / "r.png", shared / "r_depth.exr"], "render output")
    with pytest.raises(NeuralRTError, match="r_depth.exr: another user's file"):
        with files.written_together():  # (checked again before the first rename)
            monkeypatch.setattr(files.os, "geteuid", lambda: os.stat(shared).st_uid)
            write_atomically(shared / "r.png", lambda tmp: open(tmp, "w").write("new"))
            write_atomically(shared / "r_depth.exr", lambda tmp: open(tmp, "w").write("new"))
            monkeypatch.setattr(files.os, "geteuid", lambda: os.stat(shared).st_uid + 1)
    assert sorted(p.name for p in shared.iterdir()) == ["r.exr", "r_depth.exr"]
    assert {(shared / n).read_text() for n in ("r.exr", "r_depth.exr")} == {"old"}


@pytest.mark.skipif(not hasattr(os, "fork") or os.name != "posix", reason="flock on a folder: POSIX")
def test_another_processs_set_renamed_into_the_same_folder_waits_for_ours(tmp_path):
    # (two renders of one -o in two processes, on a slow file system, left a set of both: the
    # threads of one process waited for each other, processes did not)
    import subprocess
    import sys

    from neuralrt.io import files

    code = ("import fcntl, os, sys, time\nfd = os.open(sys.argv[1], os.O_RDONLY)\nfcntl.flock(fd, fcntl.LOCK_EX)\n"
            "print('held', flush=True)\ntime.sleep(3)\n")
    holder = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        start = time.perf_counter()
        with files.written_together():
            write_atomically(tmp_path / "a.exr", lambda tmp: open(tmp, "w").write("new"))
        waited = time.perf_counter() - start
    finally:
        holder.kill()
        holder.wait()
    assert waited > 1 and (tmp_path / "a.exr").read_text() == "new"


@pytest.mark.skipif(not hasattr(os, "fork") or os.name != "posix", reason="flock on a folder: POSIX")
def test_ctrl_c_while_waiting_for_another_processs_set_stops_the_wait(tmp_path):
    # (the wait ran with interrupts held: a holder stopped mid-rename could only be outwaited or SIGKILLed)
    import signal
    import subprocess
    import sys

    from neuralrt.io import files

    code = ("import fcntl, os, sys, time\nfd = os.open(sys.argv[1], os.O_RDONLY)\nfcntl.flock(fd, fcntl.LOCK_EX)\n"
            "print('held', flush=True)\ntime.sleep(30)\n")
    holder = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    before = signal.signal(signal.SIGALRM, lambda *_: signal.raise_signal(signal.SIGINT))
    handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert holder.stdout.readline().strip() == "held"
        start = time.perf_counter()
        signal.setitimer(signal.ITIMER_REAL, 0.5)
        with pytest.raises(KeyboardInterrupt):
            with files.written_together():
                write_atomically(tmp_path / "a.exr", lambda tmp: open(tmp, "w").write("new"))
        assert time.perf_counter() - start < 10
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, before)
        signal.signal(signal.SIGINT, handler)
        holder.kill()
        holder.wait()
    assert list(tmp_path.iterdir()) == []  # (its temporary removed, nothing renamed)

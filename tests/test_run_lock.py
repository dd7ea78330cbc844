"""One training run per checkpoint: a second process (or thread) is told, before its work, with the
holder's pid; a holder killed outright leaves no lock behind; the lock file goes when the run ends."""

import os
import signal
import subprocess
import sys
import threading

import pytest

from neuralrt.cli import main
from neuralrt.errors import NeuralRTError
from neuralrt.io.run_lock import held_alone, lock_path

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="flock: POSIX only (Windows runs unlocked)")


@pytest.fixture
def holder(tmp_path):
    """A process holding the lock of ``tmp_path/m.nrt.ckpt`` until killed (started, and holding, when yielded)."""
    checkpoint = tmp_path / "m.nrt.ckpt"
    code = ("import sys, time\nfrom neuralrt.io.run_lock import held_alone\n"
            f"with held_alone({str(checkpoint)!r}):\n    print('held', flush=True)\n    time.sleep(120)\n")
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "held"
    yield checkpoint, process
    process.kill()
    process.wait()


def test_a_second_process_is_told_who_holds_the_checkpoint(holder):
    checkpoint, process = holder
    with pytest.raises(NeuralRTError, match=rf"m\.nrt\.ckpt: another process \(pid {process.pid}\) is training this model"):
        with held_alone(checkpoint):
            pass
    assert lock_path(checkpoint).exists()  # (the holder's file is left alone)


def test_a_killed_holder_leaves_no_lock(holder):
    checkpoint, process = holder
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert lock_path(checkpoint).exists()  # its file stays, but the kernel released its lock
    with held_alone(checkpoint):
        assert lock_path(checkpoint).read_text().strip() == str(os.getpid())
    assert not lock_path(checkpoint).exists()


def test_nested_in_one_thread_shares_the_lock_and_another_thread_is_told(tmp_path):
    checkpoint = tmp_path / "m.nrt.ckpt"
    errors = []

    def other_thread():
        try:
            with held_alone(checkpoint):
                pass
        except NeuralRTError as exc:
            errors.append(str(exc))

    with held_alone(checkpoint):
        with held_alone(checkpoint):  # (api.train holds it around training.api.train, which takes it too)
            thread = threading.Thread(target=other_thread)
            thread.start()
            thread.join()
        assert lock_path(checkpoint).exists()  # the inner block did not remove the outer one's lock
    # (it said "another process (pid N)", N being this process's own)
    assert errors == [f"{checkpoint}: another thread of this process is training this model; wait for it to end, or write elsewhere"]
    assert not lock_path(checkpoint).exists()


def test_the_lock_goes_when_the_block_fails(tmp_path):
    checkpoint = tmp_path / "m.nrt.ckpt"
    with pytest.raises(KeyboardInterrupt):
        with held_alone(checkpoint):
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_train_while_another_run_trains_the_same_output_is_one_line_before_any_work(holder, capsys):
    checkpoint, process = holder
    checkpoint.write_bytes(b"the other run's")  # without the lock, this run would warn of it as left over
    output = checkpoint.with_suffix("")
    assert main(["train", "procedural:statue:0", "-o", str(output), "--preset", "lq", "--steps", "2", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"neuralrt: error: {checkpoint}: another process (pid {process.pid}) is training this model; "
                   "wait for it to end, or write elsewhere")
    assert checkpoint.read_bytes() == b"the other run's" and not output.exists()


def test_train_into_a_link_to_a_model_another_run_trains_is_told_too(holder, capsys):
    # (`-o link.nrt`, a link to m.nrt, took link.nrt.ckpt's lock: both trained, and the later write won)
    checkpoint, process = holder
    link = checkpoint.parent / "link.nrt"
    link.symlink_to(checkpoint.with_suffix("").name)
    assert main(["train", "procedural:statue:0", "-o", str(link), "--preset", "lq", "--steps", "2", "--quiet"]) == 2
    assert capsys.readouterr().err.strip() == (f"neuralrt: error: {checkpoint}: another process (pid {process.pid}) is "
                                               "training this model; wait for it to end, or write elsewhere")


def test_a_convert_into_a_scene_another_convert_holds_stops_before_any_model(tmp_path, capsys):
    """Two converts into one scene started together could both stop (only each model's checkpoint
    was held); the output scene is held first now, so the second stops before any model trains."""
    output = tmp_path / "out" / "scene.toml"
    output.parent.mkdir()
    code = ("import sys, time\nfrom neuralrt.io.run_lock import held_alone\n"
            f"with held_alone({str(output)!r}, 'converting into this scene file'):\n    print('held', flush=True)\n"
            "    time.sleep(120)\n")
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert process.stdout.readline().strip() == "held"
        assert main(["convert", "builtin:cornell-statue?detail=0", "-o", str(output), "--min-triangles", "1000",
                     "--preset", "lq", "--steps", "2", "--quiet"]) == 2
    finally:
        process.kill()
        process.wait()
    assert capsys.readouterr().err.strip() == (f"neuralrt: error: {output}: another process (pid {process.pid}) is "
                                               "converting into this scene file; wait for it to end, or write elsewhere")
    assert sorted(p.name for p in output.parent.iterdir()) == ["scene.toml.lock"]  # (the holder's; no models folder)


def test_a_convert_waits_for_a_model_another_convert_trains_and_reuses_it(tmp_path, capsys):
    """Two conversions of other scenes into one models folder: the second stopped with "another
    process is training this model"; it waits for that process now, and reuses what it wrote."""
    import json

    models, scene = tmp_path / "models", "builtin:cornell-statue?detail=0"
    common = ["--models-dir", str(models), "--min-triangles", "1000", "--preset", "lq", "--steps", "2", "--json"]
    assert main(["convert", scene, "-o", str(tmp_path / "a" / "scene.toml"), *common]) == 0
    (model,) = models.glob("*.nrt")
    model.rename(tmp_path / "aside.nrt")  # (as if the first conversion were still training it)
    checkpoint = model.with_suffix(".ckpt")
    checkpoint.write_bytes(b"its run's")  # (a Ray driver saves the model just after its worker's lock ends)
    code = ("import os, sys, time\nfrom neuralrt.io.run_lock import held_alone\n"
            f"with held_alone({str(checkpoint)!r}):\n    print('held', flush=True)\n    time.sleep(3)\n"
            f"time.sleep(0.5)\nos.rename({str(tmp_path / 'aside.nrt')!r}, {str(model)!r})\n"
            f"os.remove({str(checkpoint)!r})\n")
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert process.stdout.readline().strip() == "held"
        capsys.readouterr()
        assert main(["convert", scene, "-o", str(tmp_path / "b" / "scene.toml"), *common]) == 0
    finally:
        process.kill()
        process.wait()
    out, err = capsys.readouterr()
    assert f"waiting for pid {process.pid}, which is training {model.name}" in err and f"reusing {model.name}" in err
    result = json.loads(out)
    assert (result["trained_models"], result["reused_models"]) == (0, 1)


def test_a_local_conversion_holds_its_models_lock_until_the_model_is_saved(tmp_path):
    # (released when training ended, before the model was written: a waiting conversion woke to no model)
    from neuralrt.geometry.procedural import procedural_mesh
    from neuralrt.methods import get_method
    from neuralrt.methods.lsnif import LSNIFConfig
    from neuralrt.scene.convert_executors import LocalExecutor, TrainingJob

    config = LSNIFConfig.preset("lq").with_training(steps=2, batch_size=256)
    job = TrainingJob("m", procedural_mesh("procedural:statue:0"), config, get_method("lsnif"), tmp_path / "m.ckpt", "m")
    results = LocalExecutor(progress=False).run([job])
    next(results)  # (the model, not yet saved by its caller)
    errors = []

    def hold():
        try:
            with held_alone(tmp_path / "m.ckpt"):
                pass
        except NeuralRTError as exc:
            errors.append(str(exc))

    other = threading.Thread(target=hold)
    other.start()
    other.join()
    assert len(errors) == 1 and "another thread of this process is training this model" in errors[0]
    results.close()  # (the caller is done with it)
    assert not lock_path(tmp_path / "m.ckpt").exists()


def test_a_conversion_asks_again_as_each_local_job_starts(tmp_path, capsys, monkeypatch):
    """Two conversions started together both plan the model (no lock yet); the one whose job starts
    second found the first's lock and stopped. It is asked again as the job starts, and waits."""
    import json

    from neuralrt.scene import convert as convert_module

    models, scene = tmp_path / "models", "builtin:cornell-statue?detail=0"
    common = ["--models-dir", str(models), "--min-triangles", "1000", "--preset", "lq", "--steps", "2", "--json"]
    assert main(["convert", scene, "-o", str(tmp_path / "a" / "scene.toml"), *common]) == 0
    (model,) = models.glob("*.nrt")
    model.rename(tmp_path / "aside.nrt")
    asked = []

    def held_then_saved(path, on_wait):  # (planning: no one holds it; as the job starts: the other run has it)
        asked.append(path)
        if len(asked) == 1:
            return False
        on_wait("4242")
        (tmp_path / "aside.nrt").rename(model)  # (what the other run saved while this one waited)
        return True

    monkeypatch.setattr(convert_module, "wait_while_held", held_then_saved)
    capsys.readouterr()
    assert main(["convert", scene, "-o", str(tmp_path / "b" / "scene.toml"), *common]) == 0
    out, err = capsys.readouterr()
    assert len(asked) == 2 and "waiting for pid 4242" in err and "training lsnif" not in err
    assert (json.loads(out)["trained_models"], json.loads(out)["reused_models"]) == (0, 1)

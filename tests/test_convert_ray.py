"""The Ray executor of `neuralrt convert` (issue 12) against the local one, on one shared local Ray
instance with 2 CPUs: same model bits, finished models kept when interrupted, a killed worker
retried and resumed from its checkpoint, nothing retrained on a rerun, one-line errors.
"""

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from neuralrt.cli import main
from neuralrt.io.model_file import read_model_file
from neuralrt.scene.convert import convert_scene
from neuralrt.scene.convert_executors import TrainedModel
from neuralrt.scene.loader import load_scene
from neuralrt.scene.scene import save_scene
from neuralrt.scene.schema import CameraSpec, DiffuseMaterialSpec, EnvironmentSpec, GeneratorSpec, ObjectSpec, SceneSpec, TransformSpec

ray = pytest.importorskip("ray")

# Same threads in both executors: training is bit-reproducible for a fixed thread count.
TRAIN = dict(preset="lq", steps=40, batch=1024, seed=0, min_triangles=100, progress=False, threads_per_model=2)


@pytest.fixture(scope="module", autouse=True)
def ray_instance():
    ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level="ERROR")
    yield
    ray.shutdown()


def _scene(folder: Path, generators: list[tuple[str, dict]], copies: int = 1) -> Path:
    objects = [ObjectSpec(name=f"{name}{k}", generator=GeneratorSpec(name=name, params=params), material="white",
                          transform=TransformSpec(translate=(2.0 * i, float(k), 0)))
               for i, (name, params) in enumerate(generators) for k in range(copies)]
    spec = SceneSpec(camera=CameraSpec(position=(0, 0.5, 6), look_at=(0, 0, 0), resolution=(16, 16)),
                     materials=[DiffuseMaterialSpec(name="white", albedo=(0.7, 0.7, 0.7))], objects=objects,
                     environment=EnvironmentSpec(color=(0.2, 0.2, 0.2)))
    folder.mkdir(parents=True, exist_ok=True)
    save_scene(spec, folder / "scene.toml")
    return folder / "scene.toml"


THREE = [("sphere", {"subdivisions": 3}), ("statue", {"detail": 1}), ("hairball", {"detail": 1})]


# What describes a run rather than the model: wall time, and what a resumed run records instead of
# the uninterrupted one (an interrupted task may have finished training before it was cancelled;
# its rerun then resumes at the last step, with an empty window of running statistics).
_RUN_HISTORY = ("seconds", "rays_per_second", "first_step_seconds", "first_step_rays", "resumed_from", "final_loss", "final_losses", "hit_accuracy", "extra")


def _model_part(header: dict) -> dict:
    """A model file's header minus its run history (`_RUN_HISTORY`, the curve's seconds) and the
    header's digest (which covers the history)."""
    training = {k: v for k, v in header["training"].items() if k not in _RUN_HISTORY}
    training["curve"] = {k: v for k, v in training["curve"].items() if k != "seconds"}
    return {**{k: v for k, v in header.items() if k != "header_sha256"}, "training": training}


def _models(folder: Path) -> dict[str, dict]:
    return {p.name: read_model_file(p).header for p in sorted(folder.glob("*.nrt"))}


def _no_temporary_files(folder: Path) -> bool:
    return not [p for p in folder.rglob("*") if ".tmp" in p.name]


def test_ray_gives_the_local_models_keeps_finished_ones_when_interrupted_and_retrains_nothing(tmp_path, monkeypatch):
    scene = _scene(tmp_path, THREE, copies=2)  # 6 objects, 3 unique meshes
    local = convert_scene(scene, tmp_path / "local" / "scene.toml", **TRAIN)
    assert [m.trained_on for m in local.models] == ["local"] * 3

    # Interrupted (Ctrl-C) as the first model arrives: it stays, the scene file is not written,
    # the other tasks are cancelled and leave no half-written file.
    save = TrainedModel.save
    def save_then_interrupt(self, path):
        save(self, path)
        raise KeyboardInterrupt
    monkeypatch.setattr(TrainedModel, "save", save_then_interrupt)
    out = tmp_path / "ray" / "scene.toml"
    with pytest.raises(KeyboardInterrupt):
        convert_scene(scene, out, executor="ray", **TRAIN)
    monkeypatch.setattr(TrainedModel, "save", save)
    assert len(_models(out.parent / "models")) == 1 and not out.exists()
    assert _no_temporary_files(out.parent)

    again = convert_scene(scene, out, executor="ray", **TRAIN)
    assert sorted(m.reused for m in again.models) == [False, False, True]
    assert all(m.trained_on not in ("", "local") for m in again.models if not m.reused)  # a Ray node's address
    ray_models, local_models = _models(out.parent / "models"), _models(tmp_path / "local" / "models")
    assert list(ray_models) == list(local_models)  # same cache keys (mesh hash, config hash)
    for name in local_models:
        assert ray_models[name]["arrays_sha256"] == local_models[name]["arrays_sha256"], name
        assert _model_part(ray_models[name]) == _model_part(local_models[name]), name
    assert not list((out.parent / "models").glob("*.ckpt"))
    assert len({id(i.blas) for i in load_scene(out).accel.instances}) == 3  # 6 instances of 3 models

    stamps = {p: p.stat().st_mtime_ns for p in (out.parent / "models").glob("*.nrt")}
    rerun = convert_scene(scene, out, executor="ray", **TRAIN)
    assert all(m.reused and m.train_seconds == 0 and m.trained_on == "" for m in rerun.models)
    assert stamps == {p: p.stat().st_mtime_ns for p in (out.parent / "models").glob("*.nrt")}


def _kill_worker_after_first_checkpoint(models: Path, killed: list, timeout: float = 60.0) -> None:
    """Wait for a checkpoint in ``models``, then SIGKILL the Ray worker running that training."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        ckpts = list(models.glob("*.ckpt")) if models.is_dir() else []
        if ckpts:
            title = f"ray::neuralrt-train:{ckpts[0].stem}".encode()
            for pid in filter(str.isdigit, os.listdir("/proc")):
                try:
                    cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
                except OSError:
                    continue
                if cmdline.startswith(title):
                    os.kill(int(pid), signal.SIGKILL)
                    killed.append(int(pid))
                    return
        time.sleep(0.01)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the worker through /proc")
def test_a_killed_worker_is_retried_and_resumes_from_its_checkpoint(tmp_path, monkeypatch):
    from neuralrt.methods.lsnif_config import LSNIFConfig

    # A checkpoint every 20 of 60 steps (the config travels to the worker with the job).
    lq = LSNIFConfig.PRESETS["lq"]
    monkeypatch.setitem(LSNIFConfig.PRESETS, "lq", lambda: lq().with_training(checkpoint_every=20))
    options = {**TRAIN, "steps": 60, "batch": 512}
    scene = _scene(tmp_path, [("statue", {"detail": 1})])
    out = tmp_path / "ray" / "scene.toml"
    killed: list[int] = []
    killer = threading.Thread(target=_kill_worker_after_first_checkpoint, args=(out.parent / "models", killed))
    killer.start()
    report = convert_scene(scene, out, executor="ray", max_retries=2, **options)
    killer.join()
    assert killed, "the worker was never seen training"
    assert out.exists() and not report.models[0].reused
    header = read_model_file(report.models[0].model_path).header
    assert header["training"]["resumed_from"] in (20, 40) and header["training"]["steps"] == 60
    # Resuming is exact: the same arrays as one uninterrupted run.
    local = convert_scene(scene, tmp_path / "local" / "scene.toml", **options)
    assert read_model_file(local.models[0].model_path).header["arrays_sha256"] == header["arrays_sha256"]


def _training_worker_seen(timeout: float) -> bool:
    """Whether a Ray worker titled as a neuralrt training task runs within ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                if Path(f"/proc/{pid}/cmdline").read_bytes().startswith(b"ray::neuralrt-train:"):
                    return True
            except OSError:
                continue
        time.sleep(0.05)
    return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the worker through /proc")
def test_sigterm_stops_a_ray_convert_as_it_stops_a_local_one(tmp_path):
    """Ray's driver takes SIGTERM at its start (sys.exit; its core worker: an abort with a stack
    dump), and its waits turn the CLI's Terminated into a plain KeyboardInterrupt: the command
    keeps its own handler and ends 'terminated', exit 143, no temporary file left and no lock held."""
    scene = _scene(tmp_path, [("statue", {"detail": 1})])
    out = tmp_path / "out" / "scene.toml"
    command = [sys.executable, "-m", "neuralrt", "convert", str(scene), "-o", str(out), "--executor", "ray", "--preset", "lq",
               "--steps", "100000", "--batch", "512", "--min-triangles", "100", "--cpus-per-model", "1",
               "--threads-per-model", "1", "--quiet"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert _training_worker_seen(180), "the worker was never seen training"
        time.sleep(1.0)
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)
    finally:
        process.kill()
    assert process.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert err.strip().splitlines()[-1].startswith("neuralrt: terminated (run the same command again"), err[-2000:]
    assert _no_temporary_files(tmp_path) and not out.exists()
    # A lock file a killed worker left behind holds no lock: the rerun is not blocked by it.
    import fcntl

    for lock in tmp_path.rglob("*.lock"):
        with open(lock, "a") as f:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)  # (BlockingIOError if it were still held)


def test_every_other_registered_method_trains_on_ray(tmp_path):
    from neuralrt.methods import method_names

    scene = _scene(tmp_path, [("statue", {"detail": 1})])
    for method in set(method_names()) - {"lsnif"}:  # lsnif: the tests above
        options = {**TRAIN, "preset": None, "method": method, "steps": 20}
        ray_run = convert_scene(scene, tmp_path / method / "ray.toml", executor="ray", **options)
        local = convert_scene(scene, tmp_path / method / "local.toml", models_dir=tmp_path / "local", **options)
        a, b = (read_model_file(r.models[0].model_path).header for r in (ray_run, local))
        assert a["method"] == method and a["arrays_sha256"] == b["arrays_sha256"], method


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("neuralrt: error: "), err
    return err[0]


def test_ray_not_installed_is_one_line_before_any_work(tmp_path, monkeypatch, capsys):
    scene = _scene(tmp_path, THREE[:1])
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    out = tmp_path / "out" / "scene.toml"
    assert main(["convert", str(scene), "-o", str(out), "--executor", "ray", "--quiet"]) == 2
    assert "pip install ray (the cluster extra: pip install -e '.[cluster]'" in _one_error_line(capsys)
    assert not (tmp_path / "out").exists()


def test_unreachable_address_and_bad_options_are_one_line(tmp_path, capsys):
    scene = _scene(tmp_path, THREE[:1])
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "out" / "scene.toml"
    start = time.monotonic()
    assert main(["convert", str(scene), "-o", str(out), "--executor", "ray", "--address", f"127.0.0.1:{port}",
                 "--min-triangles", "100", "--quiet"]) == 2  # (reached once a model needs training)
    assert "ray start --head" in _one_error_line(capsys) and time.monotonic() - start < 10
    for extra, words in [(["--address", "auto"], "only with --executor ray"),
                         (["--executor", "ray", "--gpus-per-model", "1"], "needs --device cuda"),
                         (["--executor", "ray", "--cpus-per-model", "0"], "--cpus-per-model:"),
                         (["--executor", "ray", "--address", "nonsense"], "HOST:PORT"),
                         (["--executor", "ray", "--max-retries", "2147483648"], "--max-retries: Input should be less than or equal to 1000"),
                         (["--executor", "ray", "--cpus-per-model", "3"], "no Ray node has 3 CPU"),  # the 2-CPU instance
                         (["--executor", "ray", "--device", "cuda"], "no Ray node has 1 CPU and 1 GPU")]:
        assert main(["convert", str(scene), "-o", str(out), "--min-triangles", "100", *extra]) == 2
        assert words in _one_error_line(capsys), extra
    assert not (tmp_path / "out").exists()


def _serve_once(reply: bytes) -> tuple[int, threading.Thread]:
    """A port on which one connection gets ``reply`` (then closed): another kind of server, or a fake gRPC one."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)

    def answer():
        with server:
            conn, _ = server.accept()
            with conn:
                conn.recv(64)
                conn.sendall(reply)

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    return server.getsockname()[1], thread


def test_an_address_where_another_server_listens_is_one_line_at_once(tmp_path, capsys):
    from neuralrt.scene.convert_executors import _probe

    port, _ = _serve_once(b"HTTP/1.0 400 Bad Request\r\n\r\n")
    scene, out = _scene(tmp_path, THREE[:1]), tmp_path / "out" / "scene.toml"
    start = time.monotonic()
    assert main(["convert", str(scene), "-o", str(out), "--executor", "ray", "--address", f"127.0.0.1:{port}",
                 "--min-triangles", "100", "--quiet"]) == 2
    assert "something listens there, but not Ray" in _one_error_line(capsys) and time.monotonic() - start < 10
    assert not (tmp_path / "out").exists()  # made for the conversion, removed when it failed
    port, thread = _serve_once(b"\x00\x00\x18\x04\x00\x00\x00\x00\x00")  # a gRPC server's first frame: SETTINGS
    _probe(f"127.0.0.1:{port}", "--address")
    thread.join(5)


def test_ray_address_in_the_environment_is_the_cluster_without_address(tmp_path, monkeypatch, capsys):
    """As Ray reads it (`ray job submit` sets it): the run goes there, and errors name it."""
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
    scene, out = _scene(tmp_path, THREE[:1]), tmp_path / "out" / "scene.toml"
    assert main(["convert", str(scene), "-o", str(out), "--executor", "ray", "--min-triangles", "100", "--quiet"]) == 2
    line = _one_error_line(capsys)
    assert f"error: RAY_ADDRESS=127.0.0.1:{port}: no Ray cluster reachable" in line and "or unset RAY_ADDRESS" in line
    monkeypatch.setenv("RAY_ADDRESS", "nonsense")
    assert main(["convert", str(scene), "-o", str(out), "--executor", "ray", "--min-triangles", "100", "--quiet"]) == 2
    assert "RAY_ADDRESS=nonsense: expected auto, HOST:PORT" in _one_error_line(capsys)


def test_a_rerun_with_every_model_present_needs_no_cluster(tmp_path, capsys):
    scene, out = _scene(tmp_path, THREE[:1]), tmp_path / "out" / "scene.toml"
    first = convert_scene(scene, out, executor="local", **TRAIN)
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    again = convert_scene(scene, out, executor="ray", address=f"127.0.0.1:{port}", **TRAIN)
    assert [m.reused for m in again.models] == [True] and again.models[0].model_path == first.models[0].model_path

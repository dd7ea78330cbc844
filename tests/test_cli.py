"""The CLI and the Python API mirror each other: every command on tiny inputs, JSON interfaces, errors."""

import importlib
import json
import os
import subprocess
import sys

import pytest
import torch
import trimesh

from neuralrt import load_model
from neuralrt.cli import main


def _json(capsys) -> dict:
    return json.loads(capsys.readouterr().out)


def test_python_dash_m_help():
    out = subprocess.run([sys.executable, "-m", "neuralrt", "--help"], capture_output=True, text=True, check=True).stdout
    for command in ("render", "compare", "info", "train", "eval", "convert", "import", "demo"):
        assert command in out


def test_render_builtin_writes_images_and_aovs(tmp_path, capsys):
    out = tmp_path / "img.exr"
    assert main(["render", "builtin:cornell-statue?detail=0", "-o", str(out), "--spp", "1", "--res", "16x12",
                 "--quiet", "--json"]) == 0
    result = _json(capsys)
    assert result["resolution"] == [16, 12] and result["spp"] == 1
    for suffix in ("", "_albedo", "_normal", "_depth"):
        assert (tmp_path / f"img{suffix}.exr").is_file() and (tmp_path / f"img{suffix}.png").is_file()


def test_list_builtins(capsys):
    from neuralrt import api

    assert main(["render", "--list-builtins"]) == 0
    out = capsys.readouterr().out
    for name in ("cornell-statue", "hairball", "foliage", "instances"):
        assert f"builtin:{name}" in out
    assert main(["render", "--list-builtins", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == api.list_builtins()  # (the API gave (name, description) pairs)
    assert {"scene": "builtin:hairball", "description": api.list_builtins()[1]["description"]} in api.list_builtins()


def test_info_mesh_and_scene_json(tmp_path, capsys):
    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=3).export(path)
    assert main(["info", str(path), "--json"]) == 0
    info = _json(capsys)
    assert info["triangles"] == 1280
    assert info["bvh_a_bytes"] > 0 and info["bvh_b_bytes"] > 0 and info["mesh_bytes"] == 642 * 12 + 1280 * 12
    assert main(["info", "builtin:instances?detail=0", "--json"]) == 0
    scene = _json(capsys)
    assert scene["instances"] == 38 and scene["unique_blas"] == 5  # 36 copies of 3 meshes + floor + light
    assert scene["memory_by_role"]["total_bytes"] == scene["memory_bytes"] and scene["memory_by_role"]["neural_bytes"] == 0


def test_info_prints_a_far_box_with_the_digits_that_tell_its_corners_apart(tmp_path, capsys):
    # (at 6 digits a unit sphere at x = 1e7 printed "bounds: 1e+07 -1 -1, 1e+07 1 1": no width)
    scene = tmp_path / "far.toml"
    scene.write_text('[camera]\nposition = [1e7, 0, 5]\nlook_at = [1e7, 0, 0]\n\n[[objects]]\nname = "ball"\n'
                     'generator = { name = "sphere" }\ntransform = { translate = [1e7, 0, 0] }\n')
    assert main(["info", str(scene)]) == 0
    bounds = next(line for line in capsys.readouterr().out.splitlines() if line.strip().startswith("bounds:"))
    assert bounds.split(": ")[1] == "9999999 -1 -1, 10000001 1 1"
    assert main(["info", "builtin:cornell-statue"]) == 0
    assert "bounds: -1 -1 -1, 1 1 1" in capsys.readouterr().out  # (short values stay short)


def test_built_in_meshes_need_no_mesh_file(tmp_path, capsys):
    # procedural:NAME:DETAIL names a generated mesh wherever a mesh file goes (pip users have no meshes)
    from neuralrt.geometry.procedural import statue

    assert main(["info", "procedural:statue:0", "--json"]) == 0
    assert _json(capsys)["triangles"] == statue(0).num_triangles == 8392
    model = tmp_path / "statue.nrt"
    assert main(["train", "procedural:statue:0", "-o", str(model), "--preset", "lq", "--steps", "2", "--batch", "256",
                 "--quiet", "--json"]) == 0
    assert _json(capsys)["training"]["steps"] == 2
    assert main(["eval", str(model), "procedural:statue:0", "--rays", "256", "--no-images", "--json"]) == 0
    assert _json(capsys)["mesh_matches_model"] is True  # the generator is deterministic: the same hash
    assert main(["eval", str(model), "procedural:statue:1", "--rays", "256", "--no-images"]) == 2
    assert "trained on another mesh" in capsys.readouterr().err


@pytest.fixture(scope="module")
def plates(tmp_path_factory):
    """Four stacked plates: a non-convex mesh where about a quarter of the surface rays hit it again."""
    folder = tmp_path_factory.mktemp("plates")
    mesh = trimesh.util.concatenate([trimesh.creation.box(extents=(1.0, 0.06, 1.0)).apply_translation((0, 0.3 * k, 0))
                                     for k in range(4)])
    mesh.export(folder / "plates.obj")
    return folder / "plates.obj"


def test_train_info_eval_round_trip(plates, tmp_path, capsys):
    model = tmp_path / "plates.nrt"
    args = ["train", str(plates), "-o", str(model), "--preset", "lq", "--steps", "30", "--batch", "2048", "--quiet", "--json"]
    assert main(args) == 0
    trained = _json(capsys)
    assert trained["training"]["steps"] == 30 and not (tmp_path / "plates.nrt.ckpt").exists()
    assert trained["method"] == "lsnif" and trained["training"]["compute_precision"] in ("bf16", "fp32")

    assert main(["info", str(model), "--json"]) == 0
    info = _json(capsys)
    assert info["method"] == "lsnif" and info["memory_bytes"] == sum(info["memory_parts"].values())
    assert set(info["memory_parts"]) == {"voxels", "encoder", "mlp"}
    # Held as float32 (the table: twice its fp16 bytes), the occupancy as one bool a voxel (8x its bits).
    loaded = load_model(model)
    assert info["held_bytes"] == 2 * info["memory_parts"]["encoder"] + 8 * info["memory_parts"]["voxels"] + sum(
        t.numel() * 4 for t in loaded.network.parameters()) + 24  # (+ the box: 2 x 3 float32)
    assert info["config"]["method"] == "lsnif" and info["config"]["network"]["hidden_width"] == 64  # the full config
    assert info["config"]["training"]["steps"] == 30

    assert main(["eval", str(model), str(plates), "--rays", "4096", "--no-images", "--json"]) == 0
    metrics = _json(capsys)
    for part in ("outside", "surface"):
        for key in ("accuracy", "false_positive_rate", "false_negative_rate", "t_error_median", "t_error_p90",
                    "normal_error_deg_median", "normal_error_deg_p90"):
            assert key in metrics[part]
        m = metrics[part]
        # Against the always-miss model (accuracy 1 - true_hit_fraction): at most half its errors.
        # Measured after 30 steps: outside 0.948 (always-miss 0.47), surface 0.964 (always-miss 0.76).
        assert m["true_hit_fraction"] > 0.2
        assert 1 - m["accuracy"] < 0.5 * m["true_hit_fraction"], (part, m["accuracy"], m["true_hit_fraction"])


def test_two_runs_of_one_seed_train_the_same_arrays_and_info_says_so(plates, tmp_path, capsys):
    # The files differ (their training records keep wall times): `cmp` could not tell equal models.
    digests, files = [], []
    for k in range(2):
        model = tmp_path / f"m{k}.nrt"
        assert main(["train", str(plates), "-o", str(model), "--preset", "lq", "--steps", "4", "--batch", "512", "--quiet"]) == 0
        capsys.readouterr()
        assert main(["info", str(model), "--json"]) == 0
        digests.append(_json(capsys)["arrays_sha256"])
        files.append(model.read_bytes())
    assert digests[0] == digests[1] and len(digests[0]) == 64 and files[0] != files[1]


def test_eval_against_another_mesh_is_an_error_unless_allowed(plates, tmp_path, capsys):
    model = tmp_path / "plates.nrt"
    assert main(["train", str(plates), "-o", str(model), "--preset", "lq", "--steps", "2", "--batch", "256", "--quiet"]) == 0
    other = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=2).export(other)
    capsys.readouterr()
    assert main(["eval", str(model), str(other), "--rays", "256", "--no-images", "--json"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("neuralrt: error:") and "trained on another mesh" in err and "--allow-mesh-mismatch" in err
    assert "\n" not in err
    assert main(["eval", str(model), str(other), "--rays", "256", "--no-images", "--json", "--allow-mesh-mismatch"]) == 0
    assert _json(capsys)["mesh_matches_model"] is False


def test_api_takes_mesh_objects_and_loaded_models(tmp_path):
    from neuralrt import api
    from neuralrt.geometry.procedural import sphere

    mesh = sphere(subdivisions=2)
    result = api.train(mesh, tmp_path / "m.nrt", preset="lq", steps=2, batch=256, progress=False)
    from neuralrt.methods import load_model

    model = load_model(result["model"])
    for source in (result["model"], model):
        metrics = api.evaluate(source, mesh, rays=256, images=False)
        assert metrics["mesh_matches_model"] is True and metrics["outside"]["rays"] == 128


def test_list_presets(capsys):
    assert main(["train", "--list-presets"]) == 0
    out = capsys.readouterr().out
    for preset in ("hq", "lq", "gpu"):
        assert f"lsnif    {preset}" in out
    assert "gpu" in out and "default on cuda" in out
    assert main(["train", "--list-presets", "--method", "nbvh", "--json"]) == 0  # (--method: its presets only)
    rows = json.loads(capsys.readouterr().out)
    assert rows and {row["method"] for row in rows} == {"nbvh"} and "paper" in {row["preset"] for row in rows}


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["render", "/nope/scene.toml", "-o", "x.exr"], "scene file not found"),
        (["render", "builtin:nope", "-o", "x.exr"], "unknown built-in scene"),
        (["info", "/nope/mesh.obj"], "not found"),
        (["train", "/nope/mesh.obj", "-o", "m.nrt"], "not found"),
        (["info", "/nope/model.nrt"], "model.nrt"),
        # every argument is checked before any work starts, naming the field and the reason
        (["demo", "--spp", "-1", "--out", "demo"], "spp: must be at least 1, got -1"),
        (["demo", "--preset", "mq", "--out", "demo"], "unknown lsnif preset 'mq'"),
        (["eval", "m.nrt", "mesh.obj", "--rays", "-1"], "rays: must be at least 2, got -1"),
        (["train", "mesh.obj", "-o", "m.nrt", "--steps", "-3"], "steps: must be at least 1, got -3"),
        (["train", "mesh.obj", "-o", "m.nrt", "--preset", "xx"], "unknown lsnif preset 'xx' (choose from hq, lq, gpu)"),
        (["train", "mesh.obj", "-o", "m.nrt", "--method", "nope"], "invalid choice: 'nope'"),
        (["train", "mesh.obj", "-o", "m.nrt", "--device", "tpu"], "--device tpu"),
        (["render", "builtin:cornell-statue", "-o", "x.exr", "--spp", "0"], "spp: must be at least 1, got 0"),
        (["train", "-o", "m.nrt"], "train needs MESH"),
        (["train", "procedural:statue:9", "-o", "m.nrt"], "DETAIL must be an integer in 0..5 for statue, got '9'"),
        (["info", "procedural:bunny:1"], "not a procedural mesh spec: use procedural:NAME:DETAIL"),
    ],
)
def test_bad_input_is_one_line(argv, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    try:
        status = main(argv)
    except SystemExit as exc:  # argument-parser errors exit from inside parse_args
        status = exc.code
    assert status == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("neuralrt: error:") and needle in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []  # nothing written, no folder made


def test_resume_without_checkpoint(tmp_path, capsys):
    mesh = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=1).export(mesh)
    assert main(["train", str(mesh), "-o", str(tmp_path / "m.nrt"), "--resume"]) == 2
    assert "no checkpoint" in capsys.readouterr().err


def test_cuda_on_a_cpu_only_torch_is_one_line(tmp_path, capsys, monkeypatch):
    import torch

    monkeypatch.setattr(torch.backends.cuda, "is_built", lambda: False)
    mesh = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=1).export(mesh)
    for argv in (["train", str(mesh), "-o", str(tmp_path / "m.nrt"), "--device", "cuda"],
                 ["render", "builtin:cornell-statue", "-o", str(tmp_path / "x.exr"), "--device", "cuda"],
                 ["demo", "--out", str(tmp_path / "demo"), "--device", "cuda"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("neuralrt: error: --device cuda: this torch") and "without CUDA" in err and "\n" not in err


def test_interrupted_training_says_how_to_resume(tmp_path, capsys, monkeypatch):
    from neuralrt import api

    def interrupted(*args, **kwargs):
        (tmp_path / "m.nrt.ckpt").write_bytes(b"")  # this run wrote a checkpoint before the interrupt
        raise KeyboardInterrupt

    monkeypatch.setattr(api, "train", interrupted)
    assert main(["train", "mesh.obj", "-o", str(tmp_path / "m.nrt")]) == 130
    err = capsys.readouterr().err.strip()
    assert err.startswith("neuralrt: interrupted") and "--resume" in err


def test_training_interrupted_after_its_model_was_written_says_so(tmp_path, capsys, monkeypatch):
    # (Ctrl-C while --plot drew) It said "no checkpoint was written yet: run the command again".
    from neuralrt import api

    def written_then_interrupted(*args, **kwargs):
        (tmp_path / "m.nrt").write_bytes(b"model")
        raise KeyboardInterrupt

    monkeypatch.setattr(api, "train", written_then_interrupted)
    assert main(["train", "mesh.obj", "-o", str(tmp_path / "m.nrt"), "--plot", str(tmp_path / "m.png")]) == 130
    assert capsys.readouterr().err == ("neuralrt: interrupted (the model was written before the interrupt; "
                                       "`neuralrt info MODEL --plot FILE` draws its training plot)\n")


def _compare_raising_in_a_collection(exception: BaseException):
    """A stand-in for `api.compare` during which a weakref callback (garbage collection, as during
    eval's figures) raises ``exception``, where Python cannot propagate it."""
    import gc
    import weakref

    class Figure:
        pass

    def compare(*args, **kwargs):
        def callback(ref):
            raise exception

        figure = Figure()
        ref = weakref.ref(figure, callback)
        del figure
        gc.collect()
        assert ref() is None
        return {"flip": 0.0}

    return compare


def test_an_interrupt_python_swallows_still_ends_the_command_as_interrupted(capsys, monkeypatch):
    # Raised inside a weakref callback (garbage collection during eval's figures), Python printed
    # "Exception ignored in ..." with a traceback and the command went on to exit 0.
    from neuralrt import api

    monkeypatch.setattr(api, "compare", _compare_raising_in_a_collection(KeyboardInterrupt()))  # (Ctrl-C landing there)
    assert main(["compare", "a.exr", "b.exr"]) == 130
    out, err = capsys.readouterr()
    assert "flip" in out and err == "neuralrt: interrupted\n"
    monkeypatch.setattr(api, "compare", lambda *args, **kwargs: {"flip": 0.0})
    assert main(["compare", "a.exr", "b.exr"]) == 0  # (the next command starts with no interrupt noted)


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_a_signal_during_shutdown_ends_the_process_without_a_traceback(tmp_path):
    # After the result was printed, a Ctrl-C landing in an exit callback (tqdm's, numba's) printed
    # "Exception ignored in atexit callback" and its traceback, and the process exited 0.
    import signal

    script = tmp_path / "run.py"
    script.write_text("import atexit, os, signal, sys\n"
                      "from neuralrt.launch import main\n"
                      "atexit.register(lambda: os.kill(os.getpid(), signal.SIGINT))  # (runs after those main registers)\n"
                      "sys.argv = ['neuralrt', 'info', 'builtin:cornell-statue', '--json']\n"
                      "raise SystemExit(main())\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # (CI may run us ignoring it)
    assert done.returncode == -signal.SIGINT and done.stderr == ""
    assert json.loads(done.stdout)["kind"] == "scene"  # (printed whole before the signal, into a pipe)
    # Started ignoring SIGINT (a background job of a script, nohup), it still ignores it then.
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    assert done.returncode == 0 and done.stderr == "" and json.loads(done.stdout)["kind"] == "scene"


def test_an_interrupt_python_wraps_in_another_exception_is_still_an_interrupt(capsys, monkeypatch):
    # SIGTERM during matplotlib's first import landed in a class's __set_name__: Python raised a
    # RuntimeError from it, and the command ended with that traceback and exit 1.
    from neuralrt import api
    from neuralrt.cli import Terminated

    def wrapped(*args, **kwargs):
        try:
            raise Terminated()
        except Terminated as exc:
            raise RuntimeError("Error calling __set_name__ on '_deprecate_privatize_attribute' instance") from exc

    monkeypatch.setattr(api, "compare", wrapped)
    assert main(["compare", "a.exr", "b.exr"]) == 143
    assert capsys.readouterr().err == "neuralrt: terminated\n"
    monkeypatch.setattr(api, "compare", lambda *args, **kwargs: 1 / 0)  # (other errors are not turned into one)
    with pytest.raises(ZeroDivisionError):
        main(["compare", "a.exr", "b.exr"])


@pytest.mark.parametrize("value", ["0", "abc", "-2"])
def test_a_thread_count_numba_cannot_take_is_one_line(capsys, monkeypatch, value):
    # (NUMBA_NUM_THREADS=0 ended in numba's ValueError traceback; "abc" printed a traceback inside a warning)
    monkeypatch.setenv("NUMBA_NUM_THREADS", value)
    assert main(["info", "procedural:statue:0"]) == 2
    assert capsys.readouterr().err == (f"neuralrt: error: NUMBA_NUM_THREADS={value!r}: expected a whole number of "
                                       "threads, 1 or more (unset, numba uses every core)\n")


def test_a_threading_layer_numba_cannot_use_is_one_line(capsys, monkeypatch):
    # (numba's ValueError traceback at the first kernel: "unknown to Numba", "No threading layer could be loaded")
    monkeypatch.setenv("NUMBA_THREADING_LAYER", "bogus")
    assert main(["info", "procedural:statue:0"]) == 2
    assert capsys.readouterr().err == ("neuralrt: error: NUMBA_THREADING_LAYER='bogus': numba's threading layers are "
                                       "default, safe, threadsafe, forksafe, omp, tbb, workqueue\n")
    try:
        importlib.import_module("numba.np.ufunc.tbbpool")
    except ImportError:
        monkeypatch.setenv("NUMBA_THREADING_LAYER", "tbb")
        assert main(["info", "procedural:statue:0"]) == 2
        assert capsys.readouterr().err.startswith("neuralrt: error: NUMBA_THREADING_LAYER=tbb: numba cannot load TBB here")


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["train", "--help"]])
def test_help_that_cannot_be_written_is_an_error(monkeypatch, capsys, argv):
    # (argparse dropped the failed write: `neuralrt --help > /dev/full` exited 0 having written nothing)
    import errno

    class Full:
        def write(self, text):
            raise OSError(errno.ENOSPC, "No space left on device")

        def flush(self):
            pass

    monkeypatch.setattr(sys, "stdout", Full())
    assert main(argv) == 2
    assert capsys.readouterr().err == "neuralrt: error: standard output: No space left on device\n"


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("argv", [["info", "procedural:statue:0"], ["--version"]])
@pytest.mark.parametrize("buffered", [True, False])
def test_a_result_that_cannot_be_written_is_one_line_naming_standard_output(argv, buffered):
    # Buffered (the default, stdout not a terminal), the write failed at the interpreter's final
    # flush: "Exception ignored in: <stdout>" and exit 120; unbuffered, the error named no file.
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "neuralrt", *argv], stdout=full, stderr=subprocess.PIPE,
                              text=True, env=env, timeout=300)
    errors = [line for line in done.stderr.splitlines() if not line.startswith("neuralrt: warning:")]  # (the environment's)
    assert (done.returncode, errors) == (2, ["neuralrt: error: standard output: No space left on device"])


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX descriptors")
def test_a_command_started_with_standard_output_closed_runs_without_a_traceback():
    # (`neuralrt info X >&-`: Python's sys.stdout is None, and the final flush raised AttributeError)
    done = subprocess.run([sys.executable, "-m", "neuralrt", "info", "procedural:statue:0"], stderr=subprocess.PIPE,
                          text=True, timeout=300, preexec_fn=lambda: os.close(1))
    assert (done.returncode, done.stderr) == (0, "")


def test_a_very_long_error_keeps_its_ends_in_one_line(tmp_path, capsys):
    # (a 100,000-character material name from a scene file was echoed whole)
    scene = tmp_path / "s.toml"
    scene.write_text(f'[[materials]]\nname = "{"x" * 100_000}"\n[[objects]]\nmesh = "procedural:statue:0"\n'
                     'material = "white"\n')
    assert main(["info", str(scene)]) == 2
    err = capsys.readouterr().err
    assert len(err) < 3100 and err.count("\n") == 1 and "characters left out" in err
    assert err.startswith(f"neuralrt: error: {scene}: objects.0.material: unknown material 'white'")


def test_other_exceptions_python_cannot_raise_go_to_the_hook_main_found(monkeypatch, capsys):
    # (they went to Python's own hook, past pytest's, which records them)
    import sys

    from neuralrt import api

    seen = []
    monkeypatch.setattr(sys, "unraisablehook", lambda unraisable: seen.append(str(unraisable.exc_value)))
    monkeypatch.setattr(api, "compare", _compare_raising_in_a_collection(ValueError("in a callback")))
    assert main(["compare", "a.exr", "b.exr"]) == 0
    assert seen == ["in a callback"]


def test_render_with_a_model_of_another_mesh_is_an_error_unless_allowed(plates, tmp_path, capsys):
    model = tmp_path / "plates.nrt"
    assert main(["train", str(plates), "-o", str(model), "--preset", "lq", "--steps", "2", "--batch", "256", "--quiet"]) == 0
    scene = tmp_path / "scene.toml"
    scene.write_text(f"""
[camera]
position = [0, 0, 4]
look_at = [0, 0, 0]
resolution = [8, 8]

[[objects]]
name = "ball"
generator = {{ name = "sphere", params = {{ subdivisions = 1 }} }}
model = "{model}"
""")
    capsys.readouterr()
    argv = ["render", str(scene), "-o", str(tmp_path / "out" / "img.exr"), "--spp", "1", "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "objects.0" in err and "trained on another mesh" in err and "\n" not in err
    assert main([*argv, "--allow-mesh-mismatch"]) == 0


def test_metrics_of_an_empty_set_are_null_and_a_training_seed_warns(tmp_path):
    """A rate over no rays was 0.0 ("none wrong"); eval at the model's training seed called its rays held out."""
    import math

    from neuralrt import api
    from neuralrt.eval.intersection_metrics import ray_metrics
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel
    from neuralrt.rays import Hits, Rays

    rays = Rays(torch.zeros(4, 3), torch.ones(4, 3))
    m = ray_metrics(Hits.empty(4), Hits.empty(4), rays, diagonal=1.0)  # no true hit, no predicted hit
    assert m["accuracy"] == 1.0 and m["false_positive_rate"] == 0.0
    assert all(math.isnan(m[k]) for k in ("false_negative_rate", "normal_backfacing_fraction", "t_error_median"))
    mesh = sphere(1)
    LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq")).save(tmp_path / "m.nrt")
    with pytest.warns(UserWarning, match=r"seed=0 is the model's training seed: these rays may repeat its training rays"):
        api.evaluate(tmp_path / "m.nrt", mesh, rays=64, seed=0, images=False)

"""Training curves kept in model files and checkpoints, drawn by `train --plot` and `info --plot`."""

import json
import re

import pytest
from PIL import Image

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.cli import main
from neuralrt.geometry.procedural import sphere
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel
from neuralrt.training.ray_distribution import BoxRayDistribution
from neuralrt.training.trainer import train_model


def _run(steps, **kw):
    mesh = sphere(2)
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq"))
    rays = BoxRayDistribution(MeshBLAS(mesh), model.box, pool_size=1024, seed=0)
    return train_model(model, rays, steps=steps, batch_size=256, learning_rate=0.01, progress=False, **kw)


def _interrupted(steps, checkpoint, every, stop_after):
    """A run stopped (as by Ctrl-C) after step ``stop_after`` (counted from 0), checkpointing every ``every`` steps."""
    def stop(step, optimizer):
        if step == stop_after:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _run(steps, checkpoint=checkpoint, checkpoint_every=every, on_step=stop)


def _without_seconds(curve):
    return {k: v for k, v in curve.items() if k != "seconds"}


def test_the_record_keeps_every_steps_loss_and_a_resumed_run_the_same_curve(tmp_path):
    straight = _run(7)
    curve = straight.curve
    assert curve["step"] == list(range(1, 8)) and curve["every"] == 1 and "open" not in curve
    assert set(curve["losses"]) == {"occlusion", "distance", "normal", "albedo"} and curve["states"] == {}
    assert all(0.0 <= a <= 1.0 for a in curve["hit_accuracy"]) and curve["seconds"] == sorted(curve["seconds"])
    assert curve["loss"][-1] < curve["loss"][0]
    # the record's own running means (over its 50-step window: all 7 steps here) agree
    assert straight.final_loss == pytest.approx(sum(curve["loss"]) / 7, rel=1e-5)
    assert straight.hit_accuracy == pytest.approx(sum(curve["hit_accuracy"]) / 7, rel=1e-5)  # (equal batches)
    for term, values in curve["losses"].items():
        assert straight.final_losses[term] == pytest.approx(sum(values) / 7, rel=1e-5, abs=1e-9)
    # the weighted sum the optimizer minimizes: LSNIF's loss weights are all 1
    assert curve["loss"][3] == pytest.approx(sum(v[3] for v in curve["losses"].values()), rel=1e-4)

    ckpt = tmp_path / "run.nrt"
    _interrupted(7, ckpt, every=3, stop_after=5)
    resumed = _run(7, checkpoint=ckpt, checkpoint_every=3, resume=True)
    assert resumed.resumed_from == 3 and _without_seconds(resumed.curve) == _without_seconds(curve)


def test_nbvh_curves_keep_the_cut_size():
    from neuralrt.methods.nbvh_config import NBVHConfig
    from neuralrt.training.api import train

    config = NBVHConfig.preset("cpu").with_training(steps=60, batch_size=1024)
    record = train(sphere(2), config, progress=False).training_record
    nodes = record["curve"]["states"]["BVH cut nodes"]
    assert len(nodes) == 60 and nodes == sorted(nodes) and nodes[-1] > nodes[0] >= 1  # the cut only grows


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    folder = tmp_path_factory.mktemp("plots")
    model = folder / "ball.nrt"
    assert main(["train", "procedural:statue:0", "-o", str(model), "--preset", "lq", "--steps", "12", "--batch", "512",
                 "--quiet", "--plot", str(folder / "curve.png")]) == 0
    return model


def test_train_and_info_draw_the_curve(trained, tmp_path, capsys):
    assert main(["info", str(trained), "--plot", str(tmp_path / "new" / "folder" / "c.png")]) == 0  # made, as -o's
    capsys.readouterr()
    with Image.open(trained.parent / "curve.png") as image:
        assert image.format == "PNG" and image.width > 800
    for name in ("again.png", "again.svg", "again.pdf"):
        assert main(["info", str(trained), "--plot", str(tmp_path / name), "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["plot"] == str(tmp_path / name)
    assert (tmp_path / "again.svg").read_text().lstrip().startswith("<?xml")
    assert (tmp_path / "again.pdf").read_bytes().startswith(b"%PDF")
    assert main(["info", str(trained)]) == 0
    out = capsys.readouterr().out
    assert re.search(r'"curve": "12 points, loss [0-9.e+-]+ -> [0-9.e+-]+ \(--plot FILE.png draws them\)"', out)
    assert '"loss": [' not in out
    assert main(["info", str(trained), "--json"]) == 0
    assert len(json.loads(capsys.readouterr().out)["training"]["curve"]["loss"]) == 12


def test_an_interrupted_runs_checkpoint_draws_its_curve_so_far(tmp_path, monkeypatch):
    from neuralrt import api
    from neuralrt.io import plots

    titles = []
    draw = plots.write_training_plot
    monkeypatch.setattr(plots, "write_training_plot", lambda path, curve, title: titles.append(title) or draw(path, curve, title))
    ckpt = tmp_path / "run.nrt.ckpt"
    _interrupted(9, ckpt, every=4, stop_after=5)
    result = api.info(ckpt, plot=tmp_path / "so_far.png")
    assert result["kind"] == "checkpoint" and result["training"]["curve"]["step"] == [1, 2, 3, 4]
    assert result["mesh_name"] == sphere(2).name and (tmp_path / "so_far.png").stat().st_size > 0
    # (a run without the CLI's identity records no method: the title leaves it out)
    assert titles[-1].startswith(f"{sphere(2).name} · checkpoint of an unfinished run at step 4 (256 rays a step)")
    resumed = _run(9, checkpoint=ckpt, checkpoint_every=4, resume=True)
    assert plots.training_plot_title("lsnif", None, "ball", resumed.as_dict()).startswith("lsnif · ball · 9 steps of 256 rays (resumed at step 4)")


def test_info_and_train_name_the_preset_a_model_was_made_from(trained, tmp_path):
    from neuralrt import api
    from neuralrt.methods import get_method, load_model

    assert api.info(trained)["preset"] == "lq"  # (trained with --steps and --batch: still the lq preset)
    config = load_model(trained).config
    changed = type(config).validated({**config.model_dump(), "voxel": {**config.voxel.model_dump(), "resolution": 64}})
    assert get_method("lsnif").preset_of(changed) is None and get_method("lsnif").preset_of(LSNIFConfig.preset("hq")) == "hq"


@pytest.mark.parametrize("argv, needle", [
    (["train", "procedural:statue:0", "-o", "m.nrt", "--plot", "c.jpg"], "c.jpg: a plot's file name ends in .png, .pdf, .svg"),
    (["train", "procedural:statue:0", "-o", "m.nrt", "--plot", ".png"], ".png: a plot needs a file name before its suffix"),
    (["train", "procedural:statue:0", "-o", "m.nrt", "--plot", ""], "--plot: expected a path"),
    (["train", "procedural:statue:0", "-o", "m.nrt", "--plot", "/proc/c.png"],
     "/proc: cannot write the plot there (it takes no new files)"),
    (["eval", "procedural:statue:0", "procedural:statue:0"], "names a built-in mesh, not a model: eval takes a model file"),
    (["info", "procedural:statue:0", "--plot", "c.png"], "only a model (.nrt) or training checkpoint (.ckpt) has a training curve"),
])
def test_a_plot_that_cannot_be_drawn_is_one_line_before_any_work(argv, needle, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("neuralrt: error:") and needle in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []


def test_a_model_from_before_curves_says_so(trained, tmp_path, capsys):
    from neuralrt.io.model_file import read_model_file, write_model_file

    f = read_model_file(trained)
    header = {k: v for k, v in f.header.items() if k not in ("format_version", "checksum")}
    header["training"] = {k: v for k, v in header["training"].items() if k != "curve"}
    write_model_file(tmp_path / "old.nrt", f.header["method"], header, f.arrays)
    assert main(["info", str(tmp_path / "old.nrt")]) == 0
    assert main(["info", str(tmp_path / "old.nrt"), "--plot", str(tmp_path / "c.png")]) == 2
    err = capsys.readouterr().err
    assert "holds no curve (trained before neuralrt kept one" in err and not (tmp_path / "c.png").exists()
    header["training"]["curve"] = {"every": 1, "step": [1], "seconds": [], "loss": [1.0], "hit_accuracy": [0.5]}
    write_model_file(tmp_path / "bad.nrt", f.header["method"], header, f.arrays)
    assert main(["info", str(tmp_path / "bad.nrt"), "--plot", str(tmp_path / "c.png")]) == 2
    assert "training curve is malformed (its columns differ in length)" in capsys.readouterr().err


def test_a_title_from_a_files_record_draws_whatever_it_holds(tmp_path):
    """A mesh name with ``$`` (matplotlib's mathtext) and record fields of the wrong type (an edited
    file) gave tracebacks; the title keeps what is a number and prints the name as written."""
    from neuralrt.io.plots import training_plot_title, write_training_plot

    record = {"steps": "many", "batch_size": 8192, "rays_per_second": "fast", "seconds": 3.0, "resumed_from": "x",
              "device": 5, "hit_accuracy": 0.99}
    title = training_plot_title("lsnif", "hq", r"$\frac{$", record)
    assert title == r"lsnif hq · $\frac{$ · 0 steps of 8,192 rays · final hit accuracy 0.9900"
    curve = {"step": [1, 2, 3], "loss": [3.0, 2.0, 1.0], "hit_accuracy": [0.5, 0.8, 0.9]}
    path = write_training_plot(tmp_path / "c.png", curve, title)
    assert Image.open(path).size[0] > 100


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="XDG folders: Linux")
def test_a_user_without_a_writable_config_folder_plots_without_matplotlibs_warnings(tmp_path):
    # (matplotlib made a temporary folder per process and logged two warning lines at each first plot)
    import os
    import subprocess
    import sys

    (tmp_path / "a-file").write_text("")
    run = tmp_path / "run"
    run.mkdir(mode=0o700)
    env = {k: v for k, v in os.environ.items() if k != "MPLCONFIGDIR"}
    env.update(XDG_CONFIG_HOME=str(tmp_path / "a-file" / "config"), XDG_RUNTIME_DIR=str(run))  # (no one can make it)
    script = ("import os; from neuralrt.io import plots; import matplotlib.figure; "  # (as the commands: plots first)
              "plots.write_figure(matplotlib.figure.Figure(), os.path.join(os.environ['XDG_RUNTIME_DIR'], 'f.png')); "
              "print(os.environ['MPLCONFIGDIR'], matplotlib.get_configdir(), matplotlib.get_cachedir())")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    private = str(run / f"neuralrt-matplotlib-{os.getuid()}")
    assert done.stdout.split() == [private] * 3 and (run / "f.png").stat().st_size > 0

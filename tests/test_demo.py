"""`neuralrt demo` end to end on a tiny configuration: every file of the report exists and is sane."""

import json
from pathlib import Path

from PIL import Image

import pytest

from neuralrt.cli import main
from neuralrt.errors import ConfigError


def test_demo_quick_writes_the_whole_report(tmp_path, capsys, monkeypatch):
    # Shrink the quick preset further so CI stays fast; the pipeline is the same.
    import neuralrt.demo as demo

    tiny = demo.DemoSettings(steps=40, batch=2048, detail=0, min_triangles=1000, resolution=(32, 24), spp=2,
                             max_depth=2)
    monkeypatch.setattr(demo, "DEMO_QUICK", tiny)
    out = tmp_path / "report"
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert "report:" in printed and "FLIP" in printed
    # Progress lines go to stderr: stdout is the result (strict JSON with --json, quiet or not).
    assert "[1/4] converting" in captured.err and "[1/1] training" in captured.err and "[1/" not in printed

    report = json.loads((out / "report.json").read_text())
    for key in ("flip", "psnr", "flip_other_seed", "psnr_other_seed", "flip_noise_floor"):
        assert isinstance(report[key], float)
    assert 0 <= report["flip"] <= 1
    # Shared random numbers make the same-seed comparison the closer one; at another seed the hybrid
    # carries the noise of an independent render, as the floor does.
    assert report["flip"] < report["flip_other_seed"] and report["flip_noise_floor"] > 0
    mem = report["memory"]
    assert mem["neural_bytes"] > 0 and mem["bvh_a_bytes"] > 0 and mem["bvh_b_bytes"] > 0
    # exact camera rays: the statue keeps its mesh and BVH, so the hybrid scene holds more, and says so
    assert mem["camera_bytes"] > 0 and mem["hybrid_scene_bytes"] > mem["exact_scene_bytes"] > 0
    t = report["time"]
    assert t["train_s"] > 0 and t["exact_render_s"] > 0 and t["hybrid_render_s"] > 0
    assert report["neural_objects"] == 1 and report["settings"]["resolution"] == [32, 24]
    training = report["images"].pop("training")
    for name in [*report["images"].values(), *training.values()]:
        assert (out / name).is_file(), name
    assert list(training) == ["statue-d0"] and f"![training curve of statue-d0]({training['statue-d0']})" in (out / "report.md").read_text()
    from neuralrt.methods import get_method
    from neuralrt.methods.registry import config_from_dict
    from neuralrt.io.model_file import read_model_header

    made = config_from_dict(read_model_header(out / report["models"][0]["model_path"]).config)  # (relative to the report)
    assert get_method("lsnif").preset_of(made) == "hq"  # (what the training plot's title names)
    for png in ("exact.png", "hybrid.png", "flip.png"):
        assert Image.open(out / png).size == (32, 24)
    assert Image.open(out / "side_by_side.png").size[0] == 3 * 32
    assert "FLIP hybrid vs exact" in (out / "report.md").read_text()
    assert "kept for camera rays" in (out / "report.md").read_text()
    assert report["settings"]["steps"] == 40 and report["settings"]["preset"] == "hq"  # the patched settings ran


def test_demo_flags_reach_its_settings_and_json_prints_the_report(tmp_path, capsys, monkeypatch):
    import neuralrt.demo as demo

    tiny = demo.DemoSettings(steps=40, batch=2048, detail=0, min_triangles=1000, resolution=(32, 24), spp=2,
                             max_depth=2)
    monkeypatch.setattr(demo, "DEMO_QUICK", tiny)
    out = tmp_path / "report"
    assert main(["demo", "--quick", "--out", str(out), "--quiet", "--json", "--seed", "3", "--max-depth", "1",
                 "--batch", "1024", "--min-triangles", "500", "--primary", "neural"]) == 0
    captured = capsys.readouterr()
    printed = json.loads(captured.out)
    assert printed["settings"] == {**printed["settings"], "seed": 3, "max_depth": 1, "batch": 1024, "min_triangles": 500,
                                   "primary": "neural"}
    assert printed["flip"] == json.loads((out / "report.json").read_text())["flip"]
    assert "step" not in captured.err  # (--quiet: no progress bars)
    # Again in the same folder (-o, as the other commands take it): the model is reused, and said so (not "train 0 s").
    assert main(["demo", "--quick", "-o", str(out), "--quiet", "--seed", "3", "--max-depth", "1", "--batch", "1024",
                 "--min-triangles", "500", "--primary", "neural"]) == 0
    assert "models reused from the folder" in capsys.readouterr().out
    assert "none: the model was reused from the folder" in (out / "report.md").read_text()


def test_the_help_states_the_defaults_demo_runs_with():
    import neuralrt.demo as demo
    from neuralrt.cli import build_parser

    parser = build_parser()
    helps = {a.dest: a.help for a in parser._subparsers._group_actions[0].choices["demo"]._actions}
    full, quick = demo.DEMO_DEFAULT, demo.DEMO_QUICK
    assert f"default: {full.spp}; --quick: {quick.spp})" in helps["spp"]
    assert f"default: {'x'.join(map(str, full.resolution))}; --quick: {'x'.join(map(str, quick.resolution))})" in helps["res"]
    assert f"--quick: {quick.steps})" in helps["steps"] and full.steps is None
    assert f"--quick: {quick.batch})" in helps["batch"] and full.batch is None
    assert f"default: {full.max_depth}; --quick: {quick.max_depth})" in helps["max_depth"]
    assert f"default: {full.seed})" in helps["seed"]


def test_quick_is_a_shorter_run_of_the_same_model():
    import neuralrt.demo as demo

    quick, full = demo.DEMO_QUICK, demo.DEMO_DEFAULT
    assert quick.method == full.method and quick.preset == full.preset  # the same model, trained briefly
    assert quick.steps < 1000 and quick.spp < full.spp and quick.resolution[0] < full.resolution[0]


@pytest.mark.parametrize("field, value, needle", [
    ("spp", -1, "spp: must be at least 1, got -1"),
    ("max_depth", 0, "max_depth: must be at least 1"),
    ("resolution", (0, 10), "resolution: 0x10 must be at least 1x1"),
    ("resolution", (20000, 20), "resolution: 20000x20 is over the largest allowed"),
    ("spp", 2_000_000, "spp: must be at most"),
    ("max_depth", 1000, "max_depth: must be at most 256"),
    ("seed", -1, "seed: must be at least 0"),
    ("preset", "mq", "unknown lsnif preset 'mq'"),
    ("batch", 3, "training.batch_size"),
])
def test_settings_are_checked_on_construction(field, value, needle):
    import neuralrt.demo as demo

    with pytest.raises(ConfigError, match=needle.replace("(", r"\(").replace(")", r"\)")):
        demo.DemoSettings(**{field: value})


@pytest.mark.parametrize("in_the_way", ["report.md", "exact_depth.exr", "training_0.png"])
def test_a_folder_where_a_report_file_goes_stops_the_demo_before_it_trains(tmp_path, capsys, in_the_way):
    # It was found at the end: after training and rendering, naming our temporary file, with the
    # images written so far and temporaries left behind.
    out = tmp_path / "report"
    (out / in_the_way).mkdir(parents=True)
    assert main(["demo", "--quick", "--out", str(out), "--quiet"]) == 2
    assert capsys.readouterr().err == f"neuralrt: error: {out / in_the_way}: is a folder, not a demo report file\n"
    assert sorted(p.name for p in out.iterdir()) == [in_the_way]  # (no models trained, nothing written)


def test_a_folder_where_a_model_goes_stops_the_conversion_before_it_trains(tmp_path, capsys):
    # It warned the model was "corrupted", trained it, then failed writing it.
    import json

    args = ["convert", "builtin:cornell-statue?detail=0", "-o", str(tmp_path / "s.toml"), "--min-triangles", "1000", "--preset", "lq", "--steps", "5",
            "--quiet", "--json"]
    assert main(args) == 0
    model = Path(json.loads(capsys.readouterr().out)["models"][0]["model_path"])
    model.unlink()
    model.mkdir()
    assert main(args) == 2
    assert capsys.readouterr().err == f"neuralrt: error: {model}: is a folder, not a model file\n"

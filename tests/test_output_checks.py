"""Outputs that cannot be written are refused before any work, as one line, creating nothing; and
what the CLI prints stays machine-readable (strict JSON) and one line on system errors."""

import json

import numpy as np
import pytest
import trimesh

from neuralrt import api
from neuralrt.cli import main
from neuralrt.errors import ConfigError, NeuralRTError
from neuralrt.io import files
from neuralrt.io.files import check_output_file, check_output_folder


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("neuralrt: error: "), err
    return err[0]


@pytest.fixture
def a_file(tmp_path):
    path = tmp_path / "mesh.obj"
    trimesh.creation.icosphere(subdivisions=1).export(path)
    return path


def test_checks_accept_new_nested_folders_and_create_nothing(tmp_path):
    check_output_file(tmp_path / "a" / "b" / "img.exr", "render output")
    check_output_folder(tmp_path / "c" / "d", "report")
    assert list(tmp_path.iterdir()) == []  # the write probe is gone too


def test_checks_refuse_a_file_on_the_way_and_a_folder_as_file(tmp_path, a_file):
    with pytest.raises(NeuralRTError, match=r"mesh\.obj: is a file, not a folder$"):
        check_output_file(a_file / "img.exr", "render output")
    with pytest.raises(NeuralRTError, match=r"mesh\.obj: is a file, not a folder \(on the way to .*mesh\.obj/x/y\)"):
        check_output_folder(a_file / "x" / "y", "report")
    with pytest.raises(NeuralRTError, match=r"is a folder, not a model file"):
        check_output_file(tmp_path, "model file")


def test_checks_refuse_a_folder_that_takes_no_files(tmp_path, monkeypatch):
    # (as root, a read-only mode does not stop writes: the refusal is simulated at the probe)
    def refuse(path):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(files, "_create_sibling", refuse)
    with pytest.raises(NeuralRTError, match=r": cannot write the render output there \(Permission denied\)"):
        check_output_file(tmp_path / "new" / "img.exr", "render output")


def test_render_into_a_file_fails_before_rendering(tmp_path, a_file, capsys):
    assert main(["render", "builtin:nope", "-o", str(a_file / "img.exr"), "--quiet"]) == 2
    assert "mesh.obj: is a file, not a folder" in _one_error_line(capsys)  # before the scene is even looked up


def test_train_refuses_other_suffixes_and_unwritable_folders_before_training(tmp_path, a_file, capsys):
    assert main(["train", str(a_file), "-o", str(tmp_path / "out" / "m.txt"), "--steps", "1", "--quiet"]) == 2
    assert "m.txt: a model file must end in .nrt" in _one_error_line(capsys)
    assert main(["train", str(a_file), "-o", str(a_file / "m.nrt"), "--steps", "1", "--quiet"]) == 2
    assert "is a file, not a folder" in _one_error_line(capsys)
    assert not (tmp_path / "out").exists()


def test_convert_checks_both_folders_first_and_leaves_none(tmp_path, a_file, capsys):
    out = tmp_path / "conv" / "scene.toml"
    assert main(["convert", "builtin:cornell-statue?detail=0", "-o", str(out), "--models-dir", str(a_file),
                 "--steps", "1", "--quiet"]) == 2
    assert "mesh.obj: is a file, not a folder" in _one_error_line(capsys)
    assert not (tmp_path / "conv").exists()


def test_demo_refuses_a_file_and_a_bad_scene_leaves_no_folder(tmp_path, a_file, capsys):
    assert main(["demo", "--quick", "--out", str(a_file)]) == 2
    assert "mesh.obj: is a file, not a folder" in _one_error_line(capsys)
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--scene", "builtin:nope", "--out", str(out)]) == 2
    assert "nope" in _one_error_line(capsys)
    assert not out.exists()
    # Render's bounds are checked before the training (they failed after it, leaving its models).
    for flags, message in ((["--seed", "-1"], "--seed: must be at least 0"), (["--max-depth", "1000"], "--max-depth: must be at most"),
                           (["--res", "20000x20"], "--res: 20000x20 is over the largest allowed")):
        assert main(["demo", "--quick", "--out", str(out), *flags]) == 2
        assert message in _one_error_line(capsys)
        assert not out.exists()


def test_eval_images_and_no_images_contradict(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["eval", "m.nrt", "mesh.obj", "--images", str(tmp_path), "--no-images"])
    assert stop.value.code == 2
    assert "not allowed with argument" in _one_error_line(capsys)
    with pytest.raises(ConfigError, match="contradict"):
        api.evaluate("m.nrt", "mesh.obj", images=False, image_dir=tmp_path)


@pytest.mark.parametrize("depth, message", [("0", "--max-depth: must be at least 1, got 0"),
                                            ("257", "--max-depth: must be at most 256, got 257")])
def test_max_depth_bounds_are_the_scene_files(tmp_path, capsys, depth, message):
    assert main(["render", "builtin:cornell-statue?detail=0", "-o", str(tmp_path / "i.exr"), "--max-depth", depth,
                 "--quiet"]) == 2
    assert message in _one_error_line(capsys)


def test_training_batch_has_a_ceiling(a_file, tmp_path, capsys):
    assert main(["train", str(a_file), "-o", str(tmp_path / "m.nrt"), "--batch", "100000000", "--quiet"]) == 2
    assert "training.batch_size: Input should be less than or equal to 4194304" in _one_error_line(capsys)


def test_json_output_is_strict(tmp_path, capsys):
    from neuralrt.io.images import write_exr

    image = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
    write_exr(tmp_path / "a.exr", image)
    assert main(["compare", str(tmp_path / "a.exr"), str(tmp_path / "a.exr"), "--json"]) == 0
    text = capsys.readouterr().out
    assert "Infinity" not in text and "NaN" not in text
    result = json.loads(text)
    assert result["psnr"] is None and result["flip"] == 0.0  # equal images: PSNR +inf, printed as null


def test_system_errors_are_one_line(monkeypatch, capsys):
    def refuse(path, **options):
        raise PermissionError(13, "Permission denied", "/somewhere/model.nrt")

    monkeypatch.setattr(api, "info", refuse)
    assert main(["info", "x.nrt"]) == 2
    assert _one_error_line(capsys) == "neuralrt: error: /somewhere/model.nrt: Permission denied"


def test_a_link_into_a_missing_folder_is_refused_before_any_work(tmp_path, capsys):
    (tmp_path / "out.nrt").symlink_to(tmp_path / "missing" / "x.nrt")
    with pytest.raises(NeuralRTError, match=r"out.nrt: a link to .*missing/x.nrt, whose folder does not exist"):
        check_output_file(tmp_path / "out.nrt", "model file")
    assert not (tmp_path / "missing").exists()


def test_convert_refuses_a_models_folder_at_its_output_and_an_output_that_is_its_source(tmp_path):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"objects": [{"name": "ball", "generator": {"name": "sphere"}}]}))
    for models in ("out.toml", "out.toml/models"):
        with pytest.raises(NeuralRTError, match="the models folder would be at or under the converted scene's path"):
            api.convert(scene, tmp_path / "out.toml", models_dir=tmp_path / models, min_triangles=1)
    with pytest.raises(NeuralRTError, match="the converted scene would replace the scene it converts"):
        api.convert(scene, tmp_path / "scene.json", min_triangles=1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.json"]


def test_compare_refuses_a_heat_map_over_one_of_its_images(tmp_path):
    from neuralrt.io.images import write_png

    image = np.full((4, 4, 3), 0.5, np.float32)
    write_png(tmp_path / "a.png", image)
    write_png(tmp_path / "b.png", image)
    for target, which in (("a.png", "reference"), ("b.png", "test")):
        with pytest.raises(NeuralRTError, match=f"the heat map would replace the {which} image"):
            api.compare(tmp_path / "a.png", tmp_path / "b.png", heatmap=tmp_path / target)


def test_a_render_that_fails_while_writing_leaves_the_earlier_render_whole(tmp_path, monkeypatch):
    from neuralrt.io import images
    from neuralrt.render.film import output_files

    scene = {"camera": {"resolution": [6, 4]}, "objects": [{"generator": {"name": "sphere", "params": {"subdivisions": 1}}}],
             "environment": {"color": [0.5, 0.5, 0.5]}}
    out = tmp_path / "r.exr"
    api.render(scene, out, spp=1, progress=False)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert sorted(before) == sorted(p.name for p in output_files(out))
    real, calls = images.write_png, []

    def failing(path, *args, **kwargs):  # (the disk fills up at the third PNG)
        calls.append(path)
        if len(calls) == 3:
            raise OSError(28, "No space left on device", str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(images, "write_png", failing)
    with pytest.raises(OSError, match="No space left"):
        api.render(scene, out, spp=2, seed=5, progress=False)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # (no new file, no temporary)


def test_an_eval_interrupted_while_writing_its_images_leaves_no_folder(tmp_path, monkeypatch):
    from neuralrt.geometry.procedural import make_procedural
    from neuralrt.io import plots
    from neuralrt.methods.lsnif import LSNIFModel
    from neuralrt.methods.lsnif_config import LSNIFConfig

    ball = make_procedural("sphere", subdivisions=1)
    model = LSNIFModel.from_mesh(ball, LSNIFConfig.preset("lq"))

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(plots, "write_eval_overview", interrupted)
    with pytest.raises(KeyboardInterrupt):
        api.evaluate(model, ball, rays=256, image_dir=tmp_path / "figures", timing=False, progress=False,
                     allow_mesh_mismatch=True)
    assert not (tmp_path / "figures").exists()


def test_a_render_does_not_replace_a_file_its_scene_reads(tmp_path, capsys):
    """``-o sky.exr`` wrote sky.png over the scene's environment image, ``-o r.exr`` r_albedo.png
    over its texture: each is one line now, before anything is written."""
    import trimesh
    from PIL import Image

    trimesh.creation.box().export(tmp_path / "box.obj")
    Image.new("RGB", (4, 2), (90, 120, 200)).save(tmp_path / "sky.png")
    Image.new("RGB", (2, 2), (200, 40, 40)).save(tmp_path / "r_albedo.png")
    (tmp_path / "s.toml").write_text('[camera]\nresolution = [8, 8]\nposition = [0, 0, 4]\n[render]\nspp = 1\n'
                                     '[[materials]]\nname = "tex"\nalbedo = "r_albedo.png"\n'
                                     '[[objects]]\nmesh = "box.obj"\nmaterial = "tex"\n[environment]\nimage = "sky.png"\n')
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    for output, replaced in (("sky.exr", "sky.png"), ("r.exr", "r_albedo.png"), ("s.exr", None)):
        code = main(["render", str(tmp_path / "s.toml"), "-o", str(tmp_path / output), "--quiet"])
        if replaced is None:  # (a name that replaces nothing renders)
            assert code == 0
            continue
        last = capsys.readouterr().err.strip().splitlines()[-1]  # (after the box's no-UV texture warning)
        assert code == 2 and last.startswith("neuralrt: error: ") and f"{replaced}: the render would replace a file its scene" in last
    assert all((tmp_path / name).read_bytes() == data for name, data in before.items())


@pytest.mark.parametrize("in_the_way", ["overview.png", "depth_-z_neural.png"])
def test_a_folder_where_an_eval_image_goes_stops_it_before_the_work(tmp_path, in_the_way):
    # It was found after the whole evaluation, naming our temporary file and leaving it behind.
    from neuralrt.errors import NeuralRTError
    from neuralrt.eval.intersection_metrics import image_files
    from neuralrt.geometry.procedural import make_procedural
    from neuralrt.methods.lsnif import LSNIFModel
    from neuralrt.methods.lsnif_config import LSNIFConfig

    ball = make_procedural("sphere", subdivisions=1)
    model = LSNIFModel.from_mesh(ball, LSNIFConfig.preset("lq"))
    (tmp_path / "figures" / in_the_way).mkdir(parents=True)
    with pytest.raises(NeuralRTError, match=rf"^{tmp_path / 'figures' / in_the_way}: is a folder, not an eval image$"):
        api.evaluate(model, ball, rays=256, image_dir=tmp_path / "figures", timing=False, progress=False, allow_mesh_mismatch=True)
    assert [p.name for p in (tmp_path / "figures").iterdir()] == [in_the_way]
    result = api.evaluate(model, ball, rays=256, image_dir=tmp_path / "all", timing=False, progress=False, allow_mesh_mismatch=True)
    assert sorted(p.name for p in (tmp_path / "all").iterdir()) == sorted(p.name for p in image_files(tmp_path / "all"))
    assert result["images"]["figures"]["overview"] == str(tmp_path / "all" / "overview.png")

"""Python API mistakes a researcher made in a new-user trial: each is a `NeuralRTError` of one line
naming the argument (never a bare ValueError, TypeError or torch's AssertionError), or something
the API now accepts."""

import numpy as np
import pytest
import torch

from neuralrt import api
from neuralrt.cli import main
from neuralrt.errors import ConfigError, DeviceError, MeshError
from neuralrt.geometry.mesh import load_mesh
from neuralrt.geometry.procedural import make_procedural
from neuralrt.io.images import write_exr
from neuralrt.methods import LSNIFConfig, get_method
from neuralrt.methods.lsnif import LSNIFModel
from neuralrt.render.integrator import render as render_scene
from neuralrt.rays import Transform
from neuralrt.scene.loader import load_dict

BALL = {"name": "ball", "generator": {"name": "sphere", "params": {"subdivisions": 1}}}


def _model():
    return LSNIFModel.from_mesh(make_procedural("sphere", subdivisions=1), LSNIFConfig.preset("lq"))


@pytest.mark.filterwarnings("ignore:.*cannot check that the model belongs")  # (a model alone: no mesh to check)
def test_rendering_exact_a_scene_loaded_neural_is_a_config_error():
    scene = load_dict({"camera": {"resolution": [4, 4]}, "objects": [{"model": _model()}]}, primary="neural")
    with pytest.raises(ConfigError, match="loaded with primary='neural'"):
        render_scene(scene, spp=1, primary="exact", progress=False)


def test_settings_that_are_no_integrator_settings_are_named():
    scene = load_dict({"camera": {"resolution": [4, 4]}, "objects": [BALL]})
    with pytest.raises(ConfigError, match=r"settings: expected an IntegratorSettings .* got dict"):
        render_scene(scene, settings={"spp": 2}, progress=False)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_moving_a_model_to_a_device_this_process_lacks_is_a_device_error():
    model = _model()
    with pytest.raises(DeviceError, match="^device='cuda': "):
        model.to("cuda")
    for move in (lambda: model.to(torch.device("cuda", 0)), model.cuda, lambda: model.cuda(0)):  # (cuda(): torch's AssertionError)
        with pytest.raises(DeviceError, match="^device='cuda(:0)?': "):
            move()
    assert model.to("cpu") is model and model.to(dtype=torch.float32) is model and model.cpu() is model


@pytest.mark.parametrize("argument, value", [("steps", 5), ("batch_size", 4096), ("seed", 3)])
def test_a_training_key_given_twice_differently_is_an_error(argument, value):
    spec = get_method("lsnif")
    with pytest.raises(ConfigError, match=rf"training.{argument}=.* disagree: give one of them"):
        spec.config("lq", settings={"training": {argument: value + 1}}, **{argument: value})
    same = spec.config("lq", settings={"training": {argument: value}}, **{argument: value})  # (agreeing: fine)
    assert getattr(same.training, argument) == value


def test_the_cli_names_both_spellings_of_a_training_key(tmp_path, capsys):
    assert main(["train", "procedural:statue:0", "-o", str(tmp_path / "k.nrt"), "--steps", "5", "--set", "training.steps=7"]) == 2
    assert capsys.readouterr().err == ("neuralrt: error: --steps 5 and training.steps=7 in --set disagree: give one of "
                                       "them\n")


def test_a_model_file_loaded_as_a_mesh_says_what_it_is(tmp_path):
    _model().save(tmp_path / "ball.nrt")
    with pytest.raises(MeshError, match="a neuralrt model file, not a mesh: load it with neuralrt.load_model"):
        load_mesh(tmp_path / "ball.nrt")


def test_eval_with_mesh_and_model_swapped_says_which_comes_first(tmp_path):
    _model().save(tmp_path / "ball.nrt")
    make_procedural("sphere", subdivisions=1)
    (tmp_path / "ball.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(ConfigError, match=r"the model comes first: eval MODEL MESH \(ball.nrt is the model file\)"):
        api.evaluate(tmp_path / "ball.off", tmp_path / "ball.nrt")


def test_images_of_different_sizes_are_named_width_by_height(tmp_path):
    write_exr(tmp_path / "a.exr", np.zeros((64, 96, 3), np.float32))
    write_exr(tmp_path / "b.exr", np.zeros((16, 16, 3), np.float32))
    with pytest.raises(Exception, match=r"reference 96x64 vs test 16x16 \(width x height\)"):
        api.compare(tmp_path / "a.exr", tmp_path / "b.exr")


def test_a_scene_dict_takes_the_apis_transform():
    placed = Transform.translate([1.0, 2.0, 3.0])
    scene = load_dict({"camera": {"resolution": [4, 4]}, "objects": [{**BALL, "transform": placed}]})
    assert torch.equal(scene.accel.instances[0].transform.matrix, placed.matrix)


def test_a_warning_points_at_the_callers_line_not_at_neuralrt():
    with pytest.warns(UserWarning, match="cannot check that the model belongs") as caught:
        load_dict({"camera": {"resolution": [4, 4]}, "objects": [{"model": _model()}]})
    assert caught[0].filename == __file__


def test_a_model_rendered_alone_leaves_the_warning_filters_and_other_threads_alone(tmp_path):
    """Its "cannot check" note is left unsaid in its own thread only: `warnings.catch_warnings` there
    changed every thread's filters, and leaving it made Python repeat warnings already shown."""
    import threading
    import warnings

    from neuralrt.methods.base import check_mesh_match, mesh_mismatch_unsaid
    from neuralrt.scene.loader import load_scene

    path = tmp_path / "ball.nrt"
    _model().save(path)
    load_scene(str(path), resolution=(4, 4))  # (first imports may set filters of their own)

    def probe():
        warnings.warn("probe", UserWarning)

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("default")  # once per place, as Python shows warnings
        probe()
        load_scene(str(path), resolution=(4, 4))
        probe()  # (shown again when the filters had changed meanwhile)
        assert [str(w.message) for w in seen] == ["probe"]

        warnings.simplefilter("always")
        inside, said = threading.Event(), threading.Event()
        other = threading.Thread(target=lambda: (inside.wait(60), check_mesh_match(_model(), None), said.set()))
        other.start()
        with mesh_mismatch_unsaid():
            inside.set()
            said.wait(60)
            check_mesh_match(_model(), None)  # (unsaid: this thread's block)
        other.join()
    assert [str(w.message) for w in seen[1:]] == ["cannot check that the model belongs to this object (no mesh is given)"]


def test_a_shape_without_detail_says_how_to_make_it():
    with pytest.raises(MeshError, match=r"sphere has no detail level: in Python, neuralrt.geometry.procedural.sphere\("
                                        r"subdivisions=4, radius=1.0\); in a scene file, generator = \{ name = \"sphere\" \}"):
        load_mesh("procedural:sphere:3")


def test_info_takes_a_mesh_object_as_train_and_evaluate_do():
    ball = make_procedural("sphere", subdivisions=1)
    facts = api.info(ball)
    assert facts["kind"] == "mesh" and facts["triangles"] == ball.num_triangles and facts["name"] == "sphere"
    assert facts["bvh_a_bytes"] > 0
    with pytest.raises(Exception, match="a mesh has no training curve"):
        api.info(ball, plot="curve.png")


def test_a_model_file_of_no_extent_is_refused_when_loaded(tmp_path):
    from neuralrt.errors import ModelFileError
    from neuralrt.methods import load_model

    model = _model()
    model.bounds = type(model.bounds)(torch.zeros(3), torch.zeros(3))  # (as an edited file's header says)
    model.save(tmp_path / "flat.nrt")
    with pytest.raises(ModelFileError, match=r"flat.nrt: invalid LSNIF model \(its bounds .* are no box a model is trained in"):
        load_model(tmp_path / "flat.nrt")


def test_names_from_files_are_printed_with_control_characters_escaped(capsys):
    from neuralrt.cli import _print_result

    _print_result({"mesh_name": "evil\n\x1b[31mneuralrt: error: fake"}, as_json=False)
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and "\x1b" not in out and "evil\\n\\x1b[31mneuralrt: error: fake" in out
    # Errors and warnings too: a name from a file cannot forge a second line or colour the terminal.
    from neuralrt.cli import main

    assert main(["info", "/nope/evil\n\x1b[31mneuralrt: error: fake.obj"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "\x1b" not in err and err.startswith("neuralrt: error: ")


@pytest.mark.parametrize("losses", [["x", 1.0], [None, 1.0], [10**400, 1.0]])
def test_a_training_curve_of_no_numbers_is_summed_up_in_words(losses):
    from neuralrt.cli import _curve_summary
    from neuralrt.training.curve import curve_problem

    assert _curve_summary({"loss": losses}) == "2 points, not numbers (an edited file: --plot says what is wrong)"
    assert curve_problem({"every": 1, "start": 0, "step": [1, 2], "loss": losses, "hit_accuracy": [0.5, 0.5],
                          "seconds": [0.1, 0.2], "losses": {}, "states": {}}) is not None


def test_a_section_of_another_method_names_that_method_and_dotted_settings_name_the_nesting(tmp_path, capsys):
    assert main(["train", "procedural:statue:0", "-o", str(tmp_path / "k.nrt"), "--method", "lsnif", "--set", "cut.lods=3"]) == 2
    assert capsys.readouterr().err.strip() == ("neuralrt: error: lsnif config: cut: not a section of lsnif's config (it is "
                                               "of nbvh's: --method nbvh)")
    with pytest.raises(ConfigError, match=r"^settings: 'cut.lods': sections nest as dicts here, \{'cut': \{'lods': \.\.\.\}\}"):
        get_method("nbvh").config("cpu", settings={"cut.lods": 3})
    assert get_method("nbvh").config("cpu", settings={"cut": {"lods": 3}}).cut.lods == 3


def test_an_inference_setting_of_another_method_names_it():
    """``eval --set inference.lod=2`` on an LSNIF model: lod is N-BVH's (pydantic said "Extra inputs")."""
    with pytest.raises(ConfigError, match=r"^inference.lod: not a setting of lsnif models; it is one of nbvh's "
                                          r"\(lsnif's: occlusion_threshold, secondary_offset, compute_precision"):
        _model().with_inference(lod=2)

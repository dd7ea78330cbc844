"""The method registry and what every method shares: lookup, presets per device, config dispatch,
`is_neural`, the mesh check."""

import re
import warnings

import pytest

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.errors import ConfigError, MeshMismatchError
from neuralrt.geometry.procedural import sphere
from neuralrt.methods import (
    MeshMismatchWarning,
    MethodSpec,
    check_mesh_match,
    config_from_dict,
    get_method,
    is_neural,
    method_names,
    register_method,
)
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel


def test_lookup_and_presets():
    assert "lsnif" in method_names()
    spec = get_method("lsnif")
    assert spec.model_class is LSNIFModel and spec.config_class is LSNIFConfig
    assert spec.default_preset("cpu") == "hq" and spec.default_preset("cuda") == "gpu"
    gpu = spec.config(device="cuda")
    assert (gpu.training.steps, gpu.training.batch_size) == (2000, 1 << 18)  # the paper's scale
    assert spec.config("lq", steps=7).training.steps == 7
    with pytest.raises(ConfigError, match="unknown method 'nbvhh' \\(registered: lsnif"):
        get_method("nbvhh")
    with pytest.raises(ConfigError, match="training.batch_size: Input should be greater than or equal to 16 \\(got 3\\)"):
        spec.config("hq", batch_size=3)


def test_registration_rejects_conflicts():
    spec = get_method("lsnif")
    assert register_method(spec) is spec  # the same spec again is harmless
    with pytest.raises(ValueError, match="already registered"):
        register_method(MethodSpec("lsnif", LSNIFConfig, "elsewhere:Model", "other"))
    with pytest.raises(ValueError, match="must default to 'other'"):
        register_method(MethodSpec("other", LSNIFConfig, "elsewhere:Model", "other"))


def test_config_dispatch_and_preset_merge():
    data = LSNIFConfig.preset("lq").model_dump(mode="json")
    assert config_from_dict(data) == LSNIFConfig.preset("lq")
    del data["method"]  # configs written before the method key existed are LSNIF's
    assert isinstance(config_from_dict(data), LSNIFConfig)
    merged = LSNIFConfig.preset("lq", training={"steps": 5})
    assert merged.training.steps == 5 and merged.training.batch_size == 1 << 13 and merged.network.hidden_width == 64


def test_is_neural_and_the_mesh_check():
    mesh, other = sphere(2), sphere(3)
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq"))
    assert is_neural(model) and not is_neural(MeshBLAS(mesh))
    check_mesh_match(model, mesh.content_hash())  # same mesh: silent
    with pytest.raises(MeshMismatchError, match="scene.toml: objects.0: the model was trained on another mesh"):
        check_mesh_match(model, other.content_hash(), label="scene.toml: objects.0")
    with pytest.warns(MeshMismatchWarning, match="trained on another mesh .*used anyway, as allow_mesh_mismatch=True asks"):
        check_mesh_match(model, other.content_hash(), allow_mismatch=True)  # (allowed, and said)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_mesh_match(model, None)
    assert [w.category for w in caught] == [MeshMismatchWarning] and "no mesh is given" in str(caught[0].message)


@pytest.mark.parametrize("method", ["lsnif", "nbvh"])
def test_a_config_prints_one_field_per_line_where_its_repr_is_too_long(method):
    """print(config) and notebooks showed one ~900-character line: now each line fits in 100
    columns and holds the same fields, values and order as the repr (which stays one line)."""
    spec = get_method(method)
    config = spec.config(spec.default_preset("cpu"))
    shown = []
    config._repr_pretty_(type("Printer", (), {"text": lambda self, text: shown.append(text)})(), False)
    lines = shown[0].splitlines()
    assert shown[0] == str(config) and len(lines) > 10 and max(map(len, lines)) <= 100
    def bare(text):  # (no white space, no comma before a closing bracket)
        return re.sub(r",\)", ")", "".join(text.split()))

    assert bare(str(config)) == bare(repr(config))
    assert "\n" not in repr(config) and lines[1] == f"    method='{method}',"
    assert str(config.voxel if method == "lsnif" else config.query) == repr(config.voxel if method == "lsnif" else config.query)

"""Bad input below `neuralrt.api`: `Rays`, `MeshBLAS`, `load_model` / `NeuralBLAS.load`, `load_dict` /
`load_scene`. Each is a one-line `NeuralRTError` subclass naming the argument, raised before any work,
never torch's or pathlib's own error from deep inside."""

import re

import numpy as np
import pytest
import torch

import neuralrt
from neuralrt import api, devices
from neuralrt import rays as rays_module
from neuralrt.accel.blas import MemoryReport
from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.errors import ConfigError, DeviceError, SceneError
from neuralrt.geometry.procedural import sphere
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel
from neuralrt.rays import Rays
from neuralrt.scene.loader import load_dict, load_scene

cpu_only_torch = pytest.mark.skipif(torch.cuda.is_available(), reason="needs a torch that cannot use cuda")


@pytest.fixture(scope="module")
def mesh():
    return sphere(1)


@pytest.fixture(scope="module")
def model_file(mesh, tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "sphere.nrt"
    LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq")).save(path)
    return path


def _rays(n=2):
    return Rays(torch.tensor([[0.0, 0.0, 3.0]]).expand(n, 3), torch.tensor([[0.0, 0.0, -1.0]]).expand(n, 3))


def _scene(objects, **extra):
    return {"camera": {"position": [0, 0, 3], "resolution": [8, 8]},
            "materials": [{"name": "w", "type": "diffuse", "albedo": [0.7, 0.7, 0.7]}],
            "objects": objects, "environment": {"color": [1, 1, 1]}, **extra}


def _one_line(info) -> str:
    text = str(info.value)
    assert "\n" not in text
    return text


# -- devices ---------------------------------------------------------------------------------------
def test_check_device_names_the_device_and_resolves_it():
    assert devices.check_device("cpu") == torch.device("cpu")
    with pytest.raises(DeviceError, match=r"^device='tpu': not a torch device \(use cpu or cuda\)$"):
        devices.check_device("tpu")
    with pytest.raises(DeviceError, match=r"device='meta': unsupported device type 'meta'"):
        devices.check_device("meta")
    assert rays_module.resolve_device is devices.resolve_device  # one helper, re-exported where it was


@cpu_only_torch
def test_cuda_on_a_cpu_only_torch_is_a_device_error():
    with pytest.raises(DeviceError, match=r"^device='cuda': (this torch .* without CUDA|no CUDA device)"):
        devices.check_device("cuda")


@pytest.mark.parametrize("device,message", [("tpu", "not a torch device"), ("meta", "unsupported device type 'meta'")]
                         + ([] if torch.cuda.is_available() else [("cuda", "CUDA")]))
def test_entry_points_check_the_device_first(device, message, mesh, model_file, tmp_path, capsys):
    pattern = rf"^device='{device}': .*{message}"  # (from Python: as the argument is spelled there)
    with pytest.raises(DeviceError, match=pattern):
        MeshBLAS(mesh, device=device)
    assert "Mitsuba" not in capsys.readouterr().err  # no backend was picked for it
    with pytest.raises(DeviceError, match=pattern):
        neuralrt.load_model(model_file, device=device)
    with pytest.raises(DeviceError, match=pattern):
        LSNIFModel.load(model_file, device=device)
    with pytest.raises(DeviceError, match=pattern):
        neuralrt.load_model(tmp_path / "missing.nrt", device=device)  # before the file is read
    with pytest.raises(DeviceError, match=pattern):
        load_dict(_scene([{"mesh": mesh, "material": "w"}]), device=device)
    with pytest.raises(DeviceError, match=pattern):
        load_scene("builtin:cornell-statue", device=device)


# -- paths -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad,got", [(None, "NoneType"), (["m.nrt"], "list"), ("", "an empty string")])
def test_a_model_path_must_be_a_path(bad, got):
    with pytest.raises(ConfigError, match=rf"^path: expected a path \(str or os.PathLike\), got {got}$"):
        neuralrt.load_model(bad)
    with pytest.raises(ConfigError, match=rf"^path: expected a path \(str or os.PathLike\), got {got}$"):
        LSNIFModel.load(bad)


def test_load_dict_base_dir_and_load_scene_path_must_be_paths(mesh):
    with pytest.raises(ConfigError, match=r"^base_dir: expected a path \(str or os.PathLike\), got list$"):
        load_dict(_scene([{"mesh": "sphere.obj", "material": "w"}]), base_dir=["x"])
    with pytest.raises(ConfigError, match=r"^path_or_builtin: expected a path .*, got list$"):
        load_scene(["scene.toml"])


@pytest.mark.parametrize("edit,key", [
    (lambda s: s["objects"].__setitem__(0, {"mesh": "", "material": "w"}), "objects.0.mesh"),
    (lambda s: s["objects"][0].update(model="  "), "objects.0.model"),
    (lambda s: s.update(environment={"image": ""}), "environment.image"),
    (lambda s: s["materials"][0].update(albedo=""), "materials.0.albedo"),
])
def test_an_empty_path_in_a_scene_names_its_key(edit, key, tmp_path):
    import json

    scene = _scene([{"generator": {"name": "sphere"}, "material": "w"}])
    edit(scene)
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    with pytest.raises(SceneError, match=rf"^{re.escape(str(tmp_path / 'scene.json'))}: {key}: empty path$"):  # the path as given
        load_scene(tmp_path / "scene.json")
    with pytest.raises(SceneError, match=rf"^scene: {key}: empty path$"):
        load_dict(scene, base_dir=tmp_path)


def test_a_nul_character_in_a_scene_path_names_its_key(tmp_path):
    import json

    scene = _scene([{"mesh": "ball\u0000.obj", "material": "w"}])  # was "ValueError: embedded null byte"
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    with pytest.raises(SceneError, match=r": objects\.0\.mesh: a path cannot hold a NUL character$"):
        load_scene(tmp_path / "scene.json")


@pytest.mark.parametrize("suffix, text", [(".json", "[" * 100_000 + "]" * 100_000), (".toml", "a = " + "[" * 100_000 + "]" * 100_000)])
def test_a_scene_nested_too_deeply_is_one_line(tmp_path, suffix, text):
    (tmp_path / f"scene{suffix}").write_text(text)  # was a RecursionError traceback
    with pytest.raises(SceneError, match=rf"not valid {suffix[1:].upper()}: nested too deeply$"):
        load_scene(tmp_path / f"scene{suffix}")


# -- Rays --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("make,message", [
    (lambda: Rays(torch.zeros(2, 3), torch.zeros(3, 3)), r"ray directions \(3, 3\) do not match origins \(2, 3\)"),
    (lambda: Rays(torch.zeros(2, 2), torch.zeros(2, 2)), r"ray origins must have shape \[\.\.\., 3\], got \(2, 2\)"),
    (lambda: Rays(torch.zeros(2, 3), torch.ones(2, 3), batch_shape=(3,)), r"batch_shape \(3,\) does not hold 2 rays"),
    (lambda: Rays(torch.zeros(2, 3), torch.ones(2, 3), t_min=torch.zeros(3)), r"ray t_min of shape \(3,\) does not broadcast"),
    (lambda: Rays(torch.zeros(2, 3), torch.ones(2, 3), t_max=torch.zeros(2, 1)), r"ray t_max of shape \(2, 1\) does not broadcast"),
    (lambda: Rays("abc", "def"), r"ray origins: expected a float tensor or array, got str"),
    (lambda: Rays(torch.zeros(2, 3), None), r"ray directions: expected a float tensor or array, got NoneType"),
])
def test_bad_rays_are_config_errors(make, message):
    with pytest.raises(ConfigError, match=message) as info:
        make()
    assert isinstance(info.value, ValueError)  # callers catching ValueError keep working
    _one_line(info)


def test_ray_intervals_take_a_scalar_one_value_per_ray_or_a_broadcast():
    o, d = torch.zeros(2, 4, 3), torch.ones(2, 4, 3)
    assert Rays(o, d, t_min=0.5).t_min.tolist() == [0.5] * 8
    assert Rays(o, d, t_max=torch.arange(8.0)).t_max.tolist() == list(range(8))
    assert Rays(o, d, t_max=torch.arange(4.0)).t_max.tolist() == [0, 1, 2, 3] * 2
    assert Rays(o, d, t_max=torch.tensor([[1.0], [2.0]])).t_max.tolist() == [1.0] * 4 + [2.0] * 4


def test_rays_on_the_meta_device_are_a_device_error(mesh):
    with pytest.raises(DeviceError, match=r"ray origins are on meta: neuralrt computes on cpu or cuda"):
        Rays(torch.zeros(2, 3, device="meta"), torch.ones(2, 3, device="meta"))
    with pytest.raises(DeviceError, match=r"ray directions are on meta"):
        Rays(torch.zeros(2, 3), torch.ones(2, 3, device="meta"))
    with pytest.raises(DeviceError, match=r"^device='meta': unsupported device type 'meta'"):
        _rays().to("meta")  # (Rays.to checks the device first)


# -- BLAS entry points ------------------------------------------------------------------------------
@pytest.mark.parametrize("bad,got", [("sphere.obj", "str"), (None, "NoneType"), (np.zeros((3, 3)), "ndarray")])
def test_mesh_blas_takes_a_mesh(bad, got):
    with pytest.raises(ConfigError, match=rf"^mesh: expected a neuralrt.Mesh, got {got} \(read a mesh file with neuralrt.load_mesh\(path\)\)$"):
        MeshBLAS(bad)


def test_blas_queries_take_rays(mesh, model_file):
    exact, neural = MeshBLAS(mesh), neuralrt.load_model(model_file)
    for blas in (exact, neural):
        with pytest.raises(ConfigError, match=r"^intersect: expected neuralrt.Rays, got Tensor$"):
            blas.intersect(torch.zeros(2, 3))
        with pytest.raises(ConfigError, match=r"expected neuralrt.Rays, got Tensor$"):
            blas.occluded(torch.zeros(2, 3))  # (LSNIF's own occluded: through NeuralBLAS._check_device)
        assert blas.intersect(_rays()).hit.shape == (2,)  # (the check leaves good rays alone)
    with pytest.raises(ConfigError, match=r"^occluded: expected neuralrt.Rays, got NoneType$"):
        exact.occluded(None)


# -- in-memory objects of load_dict ------------------------------------------------------------------
class _Model:
    """A BLAS of the documented shape (`load_dict`: bounds, intersect, occluded, memory_bytes,
    secondary_offset, material_names); tests spoil one attribute at a time."""

    def __init__(self, mesh, **spoil):
        exact = MeshBLAS(mesh)
        self.bounds, self.secondary_offset, self.material_names = exact.bounds, exact.secondary_offset, ["default"]
        self.intersect, self.occluded = exact.intersect, exact.occluded
        self.memory_bytes = lambda: MemoryReport({"weights": 1})
        for name, value in spoil.items():
            if value is _Model.DELETE:
                delattr(self, name)
            else:
                setattr(self, name, value)

    DELETE = object()


@pytest.mark.filterwarnings("ignore:.*cannot check that the model belongs")
def test_a_custom_model_of_the_documented_shape_loads(mesh):
    scene = load_dict(_scene([{"model": _Model(mesh), "material": "w"}]))
    assert neuralrt.scene_memory(scene).total > 0


@pytest.mark.parametrize("spoil,message", [
    ({"bounds": None}, r"bounds must be a neuralrt.AABB, got NoneType"),
    ({"bounds": 3}, r"bounds must be a neuralrt.AABB, got int"),
    ({"memory_bytes": _Model.DELETE, "secondary_offset": _Model.DELETE}, r"no memory_bytes, secondary_offset"),
    ({"intersect": 1}, r"intersect must be methods"),
    ({"secondary_offset": float("nan")}, r"secondary_offset must be a finite number >= 0, got nan"),
    ({"secondary_offset": "0.1"}, r"secondary_offset must be a finite number >= 0, got str"),
    ({"material_names": "abc"}, r"material_names must be a list of str, got str"),
    ({"material_names": []}, r"material_names must name each material slot"),
])
def test_a_custom_model_is_checked_when_given(spoil, message, mesh):
    with pytest.raises(SceneError, match=rf"^scene: objects.0.model: expected a model file path or a BLAS, got _Model \(.*{message}"):
        load_dict(_scene([{"model": _Model(mesh, **spoil), "material": "w"}]))


def test_a_mesh_given_as_a_model_says_where_it_goes(mesh):
    with pytest.raises(SceneError, match=r"objects.0.model: .*got Mesh \(no .*; a Mesh goes in 'mesh'\)"):
        load_dict(_scene([{"model": mesh, "material": "w"}]))


@pytest.mark.parametrize("bad,got", [(np.zeros((3, 3)), "ndarray"), (123, "int")])
def test_an_in_memory_mesh_of_another_type_is_one_line(bad, got):
    with pytest.raises(SceneError, match=rf"^scene: objects.0.mesh: expected a mesh file path or a neuralrt.Mesh, got {got}$") as info:
        load_dict(_scene([{"mesh": bad, "material": "w"}]))
    _one_line(info)


def test_validation_messages_stay_one_line_for_array_values():
    with pytest.raises(SceneError, match=r"^scene: camera.position") as info:
        load_dict(_scene([{"generator": {"name": "sphere"}, "material": "w"}], camera={"position": np.zeros((3, 3))}))
    _one_line(info)


def test_lsnif_occluded_names_a_non_rays_argument():
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel

    model = LSNIFModel.from_mesh(sphere(1), LSNIFConfig.preset("lq"))
    with pytest.raises(ConfigError, match="expected neuralrt.Rays, got NoneType"):
        model.occluded(None)


def test_load_dict_objects_must_be_a_list():
    from neuralrt.scene.loader import load_dict

    with pytest.raises(SceneError, match="objects: expected a list of objects, got generator"):
        load_dict({"objects": ({"generator": {"name": "sphere"}} for _ in range(2))})


def test_nif_seed_is_bounded_like_the_training_seed():
    from neuralrt.methods.nif_config import NIFConfig

    NIFConfig(training={"seed": (1 << 63) - 1})
    with pytest.raises(ConfigError, match="training.seed"):
        NIFConfig(training={"seed": 1 << 63})


def test_meshblas_threads_and_scene_queries_check_their_arguments():
    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.geometry.procedural import sphere

    for bad, message in ((0, "must be at least 1, got 0"), ("2", "must be an integer, got '2'"), (2.5, "must be an integer")):
        with pytest.raises(ConfigError, match=f"^threads: {message}"):  # (clamped or cast silently)
            MeshBLAS(sphere(1), threads=bad)
    scene = load_dict({"objects": [{"generator": {"name": "sphere"}}]})
    with pytest.raises(ConfigError, match=r"^intersect: expected neuralrt.Rays, got Tensor$"):  # (an AttributeError)
        scene.accel.intersect(torch.zeros(3, 3))
    with pytest.raises(ConfigError, match=r"^occluded: expected neuralrt.Rays, got Tensor$"):
        scene.accel.occluded(torch.zeros(3, 3))


def test_an_exact_blas_and_a_scene_copy_and_pickle():
    """(copy, deepcopy and pickle raised a TypeError: __new__ needs the mesh)"""
    import copy
    import pickle

    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.geometry.procedural import sphere
    from neuralrt.rays import Rays

    blas = MeshBLAS(sphere(2), threads=1)
    rays = Rays(torch.tensor([[0.0, 0.0, 3.0]]), torch.tensor([[0.0, 0.0, -1.0]]))
    for other in (copy.copy(blas), copy.deepcopy(blas), pickle.loads(pickle.dumps(blas))):
        assert type(other) is type(blas) and other.threads == 1 and other is not blas
        assert torch.equal(other.intersect(rays).t, blas.intersect(rays).t)
    scene = copy.deepcopy(load_dict({"objects": [{"generator": {"name": "sphere"}}]}))
    assert bool(scene.accel.intersect(rays).hit[0])


def _zero_size_hdr(path):
    path.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 0 +X 0\n")
    return path


@pytest.mark.parametrize("call, error, message", [
    # (from a second fuzzing trial: each was a raw exception from numpy, torch or the OS)
    (lambda tmp: neuralrt.load_model(tmp / "m.nrt", device=10**30), DeviceError, "not a torch device"),
    (lambda tmp: api.import_scene(tmp / "a.glb", tmp / "a\x00.toml"), ConfigError, "cannot hold a NUL character"),
    (lambda tmp: api.render("procedural:statue:0", tmp / "o.exr", primary=np.array([1, 2])), SceneError,
     "primary must be 'exact' or 'neural'"),
    (lambda tmp: Rays(torch.zeros(5, 3), torch.ones(5, 3), batch_shape=torch.tensor(5)), ConfigError, "batch_shape: expected"),
    (lambda tmp: neuralrt.get_method([]), ConfigError, "unknown method"),
    (lambda tmp: neuralrt.Mesh(vertices="x", faces=[[0, 1, 2]]), neuralrt.errors.MeshError, "vertices are not numbers"),
    (lambda tmp: neuralrt.Mesh(vertices=np.eye(3), faces=[[0, 1, 2]], face_material_ids=[2**31]),
     neuralrt.errors.MeshError, "face_material_ids are not int32 indices"),
    (lambda tmp: api.convert("builtin:cornell-statue?detail=0", tmp / "s.toml", threads_per_model=2**31),
     ConfigError, "threads_per_model: must be at most 4096"),
    (lambda tmp: neuralrt.io.images.read_image(_zero_size_hdr(tmp / "zero.hdr")), neuralrt.errors.ImageError,
     r"the image has no pixels \(0 x 0\)"),
])
def test_raw_exceptions_a_fuzzer_found_are_ours(tmp_path, call, error, message):
    with pytest.raises(error, match=message):
        call(tmp_path)


def test_numpy_sizes_are_sizes():
    # (the batch_shape check first took Python ints only: pinhole_rays(np.int64(4), ...) was refused)
    rays = neuralrt.pinhole_rays(np.int64(4), np.int64(3), 40.0, (0, 0, 3), (0, 0, 0), (0, 1, 0))
    assert rays.batch_shape == (3, 4) and all(type(d) is int for d in rays.batch_shape)
    assert Rays(torch.zeros(6, 3), torch.ones(6, 3), batch_shape=(np.int64(2), 3)).batch_shape == (2, 3)

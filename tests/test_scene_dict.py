"""Scenes built in Python (`load_dict`): in-memory meshes and models, validation at build time,
the BLAS `material_names` contract, ``primary="neural"`` building no BVH for neural objects, and
the honest memory report."""

import numpy as np
import pytest
import torch
import trimesh

from neuralrt.accel.blas import MemoryReport
from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.errors import SceneError
from neuralrt.geometry.mesh import Mesh, MeshMaterial
from neuralrt.render.integrator import render
from neuralrt.scene import loader as loader_module
from neuralrt.scene.loader import load_dict


def _two_part_mesh():
    """Two unit boxes side by side: material "shell" (left) and "core" (right)."""
    a, b = trimesh.creation.box(extents=(1, 1, 1)), trimesh.creation.box(extents=(1, 1, 1))
    b.apply_translation([1.5, 0, 0])
    v = np.concatenate([a.vertices, b.vertices])
    f = np.concatenate([a.faces, b.faces + len(a.vertices)])
    ids = np.repeat([0, 1], len(a.faces))
    return Mesh(v, f, face_material_ids=ids, materials=[MeshMaterial("shell"), MeshMaterial("core")], name="pair")


class StandInModel:
    """A BLAS that answers like a mesh but is a "model" (a Python object, not a MeshBLAS)."""

    def __init__(self, mesh, names):
        self._exact = MeshBLAS(mesh)
        self.bounds, self.secondary_offset, self.material_names = self._exact.bounds, self._exact.secondary_offset, names
        self.mesh_hash, self.mesh_name = mesh.content_hash(), mesh.name  # what it was "trained" on

    def intersect(self, rays):
        return self._exact.intersect(rays)

    def occluded(self, rays):
        return self._exact.occluded(rays)

    def memory_bytes(self):
        return MemoryReport({"weights": 1000})


# (a library of materials: the lamp is unused by most scenes here, which is a warning)
pytestmark = pytest.mark.filterwarnings("ignore:.*emissive material 'lamp' is used by no object")

MATERIALS = [{"name": "white", "type": "diffuse", "albedo": [0.8, 0.8, 0.8]},
             {"name": "core", "type": "diffuse", "albedo": [0.8, 0.1, 0.1]},
             {"name": "lamp", "type": "emissive", "emission": [5, 5, 5]}]


def _scene_dict(mesh, **obj):
    return {"camera": {"position": [0.75, 0, 5], "look_at": [0.75, 0, 0], "resolution": [16, 8]},
            "materials": MATERIALS, "objects": [{"mesh": mesh, **obj}], "environment": {"color": [1, 1, 1]}}


def test_in_memory_mesh_and_its_material_slots():
    mesh = _two_part_mesh()
    scene = load_dict(_scene_dict(mesh, materials={"shell": "white"}, transform={"translate": [0, 0.5, 0]}))
    inst = scene.accel.instances[0]
    names = scene.materials.names
    assert [names[i] for i in inst.material_map.tolist()] == ["white", "core"]  # map, then same name
    assert float(inst.world_bounds.lo[1]) == pytest.approx(0.0)
    assert render(scene, spp=1, progress=False).coverage.max() == 1.0


@pytest.mark.parametrize("edit,message", [
    (lambda d: d["objects"][0].update(material="gold"), r"scene: objects.0.material: unknown material 'gold'"),
    (lambda d: d["objects"][0].update(transform={"translate": [0, float("nan"), 0]}), r"scene: objects.0.transform.translate.1: .*finite"),
    (lambda d: d["objects"][0].update(model=42), r"scene: objects.0.model: expected a model file path or a BLAS, got int"),
    (lambda d: d["camera"].update(fov=0), r"scene: camera.fov"),
    (lambda d: d["objects"][0].update(material="lamp", model=StandInModel(_two_part_mesh(), ["shell", "core"])),
     r"scene: objects.0.model: emissive objects .* must stay exact meshes"),
])
def test_errors_are_raised_at_build_time_naming_the_key(edit, message):
    d = _scene_dict(_two_part_mesh())
    edit(d)
    with pytest.raises(SceneError, match=message) as info:
        load_dict(d)
    assert "\n" not in str(info.value)


@pytest.mark.filterwarnings("ignore:.*cannot check that the model belongs")  # model-only: nothing to check against
def test_model_only_object_gets_one_slot_per_model_material(tmp_path):
    """The loader maps a model's own material names (`material_names`, the BLAS contract), not one
    'default' slot: a model-only object keeps its materials."""
    from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel

    model = LSNIFModel.from_mesh(_two_part_mesh(), LSNIFConfig.preset("lq"))
    assert model.material_names == ["shell", "core"]
    model.save(tmp_path / "pair.nrt")
    (tmp_path / "scene.toml").write_text(
        '[[materials]]\nname = "core"\ntype = "diffuse"\nalbedo = [0.8, 0.1, 0.1]\n\n'
        '[[objects]]\nmodel = "pair.nrt"\n')
    scene = loader_module.load_scene(tmp_path / "scene.toml")
    names = scene.materials.names
    assert [names[i] for i in scene.accel.instances[0].material_map.tolist()] == ["default", "core"]


def test_a_model_on_another_mesh_is_an_error_unless_allowed():
    from neuralrt.errors import MeshMismatchError
    from neuralrt.methods import MeshMismatchWarning

    other = Mesh(*_quad(), name="floor")
    d = {"materials": MATERIALS, "objects": [{"mesh": other, "model": StandInModel(_two_part_mesh(), ["shell", "core"])}]}
    with pytest.raises(MeshMismatchError, match=r"scene: objects.0.model: the model was trained on another mesh \('pair'"):
        load_dict(d)
    with pytest.warns(MeshMismatchWarning, match=r"objects.0.model: the model was trained on another mesh .*used anyway"):
        assert load_dict(d, allow_mesh_mismatch=True).accel.instances[0].camera_blas.mesh is other
    with pytest.warns(MeshMismatchWarning, match="objects.0.model: cannot check"):
        load_dict({"materials": MATERIALS, "objects": [{"model": StandInModel(other, ["floor"])}]})


@pytest.mark.filterwarnings("ignore:.*cannot check that the model belongs")  # model-only: nothing to check against
def test_emissive_model_slots_are_rejected_after_loading():
    model = StandInModel(_two_part_mesh(), ["shell", "lamp"])
    with pytest.raises(SceneError, match="objects.0.model: emissive objects"):
        load_dict({"materials": MATERIALS, "objects": [{"model": model}]})


def test_primary_neural_builds_no_bvh_for_neural_objects(monkeypatch):
    built = []
    real = loader_module.MeshBLAS
    monkeypatch.setattr(loader_module, "MeshBLAS", lambda mesh, device=None: built.append(mesh.name) or real(mesh, device=device))
    mesh, floor = _two_part_mesh(), Mesh(*_quad(), name="floor")
    model = StandInModel(mesh, ["shell", "core"])
    d = {"materials": MATERIALS, "objects": [{"mesh": mesh, "model": model}, {"mesh": floor, "material": "white"}]}
    neural = load_dict(d, primary="neural")
    assert built == ["floor"] and neural.accel.instances[0].camera_blas is None
    with pytest.raises(ValueError, match="loaded with primary='neural'"):
        render(neural, spp=1, primary="exact", progress=False)
    assert render(neural, spp=1, progress=False).spp == 1  # renders the way it was loaded
    built.clear()
    hybrid = load_dict(d, primary="exact")
    assert sorted(built) == ["floor", "pair"] and isinstance(hybrid.accel.instances[0].camera_blas, real)


def test_out_of_range_material_index_is_a_build_time_error():
    from dataclasses import replace

    from neuralrt.accel.tlas import Instance, SceneAccel
    from neuralrt.rays import Transform

    scene = load_dict(_scene_dict(_two_part_mesh()))
    bad = Instance(scene.accel.instances[0].blas, Transform(), torch.tensor([0, 7]))
    with pytest.raises(SceneError, match=r"material index 7 is out of range \(the scene has 4 materials\)"):
        replace(scene, accel=SceneAccel([bad]))


def _quad():
    v = np.array([[-3, -1, -3], [3, -1, -3], [3, -1, 3], [-3, -1, 3]], np.float32)
    return v, np.array([[0, 2, 1], [0, 3, 2]])


def test_scene_memory_says_what_neural_objects_cost_and_replace():
    from neuralrt.scene.memory import scene_memory

    mesh, floor = _two_part_mesh(), Mesh(*_quad(), name="floor")
    model = StandInModel(mesh, ["shell", "core"])
    objects = [{"mesh": mesh, "model": model}, {"mesh": mesh, "model": model, "transform": {"translate": [0, 2, 0]}},
               {"mesh": floor, "material": "white"}]
    exact_pair, exact_floor = MeshBLAS(mesh).memory_bytes().total, MeshBLAS(floor).memory_bytes().total
    hybrid = load_dict({"materials": MATERIALS, "objects": objects}, primary="exact")
    mem = scene_memory(hybrid)
    assert (mem.exact_bytes, mem.neural_bytes, mem.camera_bytes) == (exact_floor, 1000, exact_pair)  # instanced: once
    assert mem.replaced_bytes == exact_pair and mem.saved_bytes == -1000  # hybrid keeps the BVH: costs more
    assert mem.saved_bytes_primary_neural == exact_pair - 1000  # (models answering camera rays too: the claim)
    assert mem.as_dict()["saved_bytes_primary_neural"] == exact_pair - 1000
    assert mem.total == hybrid.accel.memory_bytes().total and mem.neural_objects == 2
    neural = scene_memory(load_dict({"materials": MATERIALS, "objects": objects}, primary="neural"))
    assert (neural.camera_bytes, neural.replaced_bytes, neural.primary) == (0, None, "neural")
    assert neural.total == exact_floor + 1000 + neural.instances_bytes


def test_a_texture_where_no_uvs_are_is_a_warning(tmp_path):
    """A neural object's hits carry no UVs, nor do a UV-less mesh's: the texture showed one texel, silently."""
    import warnings

    from PIL import Image

    Image.fromarray(np.full((4, 4, 3), 200, np.uint8)).save(tmp_path / "t.png")
    textured = [{"name": "tex", "type": "diffuse", "albedo": str(tmp_path / "t.png")}]
    mesh = _two_part_mesh()  # (no UVs)
    with pytest.warns(UserWarning, match=r"objects.0: material 'tex' has a texture, but the mesh has no UVs"):
        load_dict({"materials": textured, "objects": [{"mesh": mesh, "material": "tex"}]})
    with pytest.warns(UserWarning, match=r"objects.0: material 'tex' has a texture, but a neural model's hits carry no UVs"):
        load_dict({"materials": textured, "objects": [{"mesh": mesh, "model": StandInModel(mesh, ["shell", "core"]),
                                                       "material": "tex"}]})
    # Where a kept mesh with UVs answers camera rays, they show the texture; with primary="neural" nothing does.
    quad = Mesh(np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32), np.array([[0, 1, 2], [0, 2, 3]]),
                uvs=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32), name="quad")
    for primary, clause in (("exact", True), ("neural", False)):
        with pytest.warns(UserWarning, match="they show one texel") as caught:
            load_dict({"materials": textured, "objects": [{"mesh": quad, "model": StandInModel(quad, ["default"]),
                                                           "material": "tex"}]}, primary=primary)
        assert any("answered by the kept mesh show the texture" in str(w.message) for w in caught) == clause
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a plane has UVs: no warning
        load_dict({"materials": textured, "objects": [{"generator": {"name": "plane"}, "material": "tex"}]})


def test_a_spec_holding_in_memory_objects_is_not_saved(tmp_path):
    """save_scene wrote mesh = "../<in-memory mesh 'pair'>", a file that then failed to load."""
    from neuralrt.scene.scene import save_scene

    scene = load_dict({"objects": [{"mesh": _two_part_mesh()}]})
    with pytest.raises(SceneError, match=r"objects.0.mesh: an in-memory mesh or model \(load_dict\) has no file to name"):
        save_scene(scene.spec, tmp_path / "s.toml")
    assert not list(tmp_path.iterdir())


def test_an_emissive_material_no_object_uses_is_a_warning():
    """A misspelt slot falls back to 'default': the scene's light was gone without a word."""
    import warnings

    d = _scene_dict(_two_part_mesh())
    d["materials"] = [MATERIALS[0], {"name": "light", "type": "emissive", "emission": [5, 5, 5]}]
    with pytest.warns(UserWarning, match=r"scene: emissive material 'light' is used by no object: no light comes from it"):
        load_dict(d)
    d["objects"].append({"generator": {"name": "sphere"}, "material": "light", "transform": {"translate": [0, 3, 0]}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_dict(d)


def test_byte_identical_copies_of_a_model_file_are_one_model(tmp_path):
    # Each copy was loaded again: the same model twice in memory, its bytes counted twice.
    import shutil

    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.lsnif import LSNIFModel
    from neuralrt.methods.lsnif_config import LSNIFConfig
    from neuralrt.scene.memory import scene_memory

    mesh = sphere(1)
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq"))
    model.save(tmp_path / "a.nrt")
    shutil.copy(tmp_path / "a.nrt", tmp_path / "copy.nrt")
    model.training_record = {"note": "another run"}  # (another header: another model, however alike)
    model.save(tmp_path / "other.nrt")
    objects = [{"mesh": mesh, "model": str(tmp_path / name), "transform": {"translate": [3 * k, 0, 0]}}
               for k, name in enumerate(["a.nrt", "copy.nrt", "other.nrt"])]
    scene = load_dict({"objects": objects}, primary="neural")
    a, copy, other = (inst.blas.memory_owner for inst in scene.accel.instances)
    assert a is copy and other is not a
    assert scene_memory(scene).neural_bytes == 2 * model.memory_bytes().total

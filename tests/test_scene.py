"""Scene files: loading TOML/JSON, one-line errors naming file and key, relative paths, instancing
(one BLAS per mesh), built-in scenes, save/load round trips."""

import json

import numpy as np
import pytest
import torch
import trimesh

from neuralrt.errors import SceneError
from neuralrt.io.images import write_png
from neuralrt.render.materials import MaterialKind
from neuralrt.scene import loader as loader_module
from neuralrt.scene.builtins import BUILTIN_SCENES, list_builtins
from neuralrt.scene.loader import load_scene, load_scene_spec
from neuralrt.scene.scene import save_scene

SCENE = """
[camera]
position = [0, 1, 4]
look_at = [0, 0, 0]
fov = 30
resolution = [32, 24]

[[materials]]
name = "white"
type = "diffuse"
albedo = [0.5, 0.5, 0.5]

[[materials]]
name = "gold"
type = "conductor"
albedo = [1.0, 0.8, 0.3]
roughness = 0.2

[[materials]]
name = "lamp"
type = "emissive"
emission = [4, 4, 4]

[[objects]]
name = "a"
mesh = "meshes/box.ply"
material = "white"

[[objects]]
name = "b"
mesh = "meshes/box.ply"
material = "gold"
transform = { translate = [1, 0, 0], rotate = [0, 45, 0], scale = 0.5 }

[[objects]]
name = "c"
mesh = "./meshes/../meshes/box.ply"
material = "white"
transform = { translate = [-1, 0, 0] }

[[objects]]
name = "lamp"
mesh = "meshes/box.ply"
material = "lamp"
transform = { translate = [0, 3, 0], scale = 2.0 }

[environment]
color = [0.2, 0.2, 0.2]
"""


@pytest.fixture
def scene_dir(tmp_path):
    (tmp_path / "meshes").mkdir()
    trimesh.creation.box(extents=(1, 1, 1)).export(tmp_path / "meshes" / "box.ply")
    (tmp_path / "scene.toml").write_text(SCENE)
    return tmp_path


def test_load_toml_scene(scene_dir):
    scene = load_scene(scene_dir / "scene.toml")
    assert (scene.camera.width, scene.camera.height) == (32, 24)
    assert len(scene.accel.instances) == 4
    assert [int(k) for k in scene.materials.kind[:3]] == [MaterialKind.DIFFUSE, MaterialKind.CONDUCTOR, MaterialKind.EMISSIVE]
    assert scene.lights.kinds == ["area", "environment"]
    # The lamp (a unit box scaled by 2) emits from all 12 triangles: 6 faces of area 4.
    assert float(scene.lights.area.area.sum()) == pytest.approx(24.0, rel=1e-5)
    # Instance b: 0.5 scale rotated 45 degrees about y, at x = 1.
    lo, hi = scene.accel.instances[1].world_bounds.lo, scene.accel.instances[1].world_bounds.hi
    torch.testing.assert_close(hi - lo, torch.tensor([0.5 * 2**0.5, 0.5, 0.5 * 2**0.5]), atol=1e-5, rtol=0)


def test_instancing_builds_each_mesh_once(scene_dir, monkeypatch):
    calls = []
    real = loader_module.load_mesh
    monkeypatch.setattr(loader_module, "load_mesh", lambda p, *more: calls.append(p) or real(p, *more))
    scene = load_scene(scene_dir / "scene.toml")
    assert len(calls) == 1  # four objects, three spellings of one path
    assert len({id(i.blas) for i in scene.accel.instances}) == 1


def test_generators_are_shared_by_parameters():
    spec = {"objects": [{"generator": {"name": "sphere", "params": {"subdivisions": 1}}},
                        {"generator": {"name": "sphere", "params": {"subdivisions": 1}}, "transform": {"translate": [2, 0, 0]}},
                        {"generator": {"name": "sphere", "params": {"subdivisions": 2}}}]}
    scene = loader_module.build_scene(loader_module.validate_spec(spec, "test"))
    ids = [id(i.blas) for i in scene.accel.instances]
    assert ids[0] == ids[1] != ids[2]


def test_json_scene_and_relative_paths_resolve_against_the_file(scene_dir, tmp_path_factory, monkeypatch):
    import tomllib

    data = tomllib.loads(SCENE)
    (scene_dir / "scene.json").write_text(json.dumps(data))
    monkeypatch.chdir(tmp_path_factory.mktemp("elsewhere"))
    scene = load_scene(str(scene_dir / "scene.json"), resolution=(8, 6))
    assert len(scene.accel.instances) == 4 and (scene.camera.width, scene.camera.height) == (8, 6)


@pytest.mark.parametrize(
    "edit,message",
    [
        (lambda s: s.replace('name = "a"', 'name = "a"\ncolour = 1'), r"scene.toml: objects.0.colour: Extra inputs are not permitted"),
        (lambda s: s.replace("scale = 0.5", "scale = 0"), r"scene.toml: objects.1.transform.scale: scale must be finite and non-zero"),
        (lambda s: s.replace('material = "gold"', 'material = "silver"'), r"scene.toml: objects.1.material: unknown material 'silver'"),
        (lambda s: s.replace("roughness = 0.2", "roughness = -1"), r"scene.toml: materials.1.roughness: Input should be greater than 0 \(got -1\)"),
        (lambda s: s.replace('type = "diffuse"', 'type = "glass"'), r"scene.toml: materials.0: .*'diffuse', 'conductor', 'plastic', 'emissive'"),
        (lambda s: s.replace("fov = 30", "fov = 200"), r"scene.toml: camera.fov: Input should be less than 180"),
        (lambda s: s.replace("resolution = [32, 24]", "resolution = [32]"), r"scene.toml: camera.resolution"),
        (lambda s: s.replace('name = "lamp"\ntype', 'name = "white"\ntype'), r"scene.toml: materials.2.name: duplicate material name 'white'"),
        (lambda s: s.replace('mesh = "meshes/box.ply"\nmaterial = "white"', 'mesh = "meshes/nope.ply"\nmaterial = "white"'),
         r"scene.toml: objects.0.mesh: .*nope.ply: mesh file not found"),
        (lambda s: s.replace("[environment]\ncolor = [0.2, 0.2, 0.2]", '[environment]\nimage = "sky.hdr"'), r"scene.toml: environment.image: .*sky.hdr: image file not found"),
        (lambda s: s.replace("[environment]\n", '[environment]\nimage = "sky.hdr"\n'), r"scene.toml: environment: give exactly one of color or image"),
        (lambda s: s.replace('name = "a"', 'name = "a"\nmodel = "a.nrt"'), r"scene.toml: objects.0.model: .*a.nrt: model file not found"),
        (lambda s: s.replace('name = "lamp"\nmesh', 'name = "lamp"\nmodel = "scene.toml"\nmesh'), r"scene.toml: objects.3.model: emissive objects"),
        (lambda s: s.replace('albedo = [0.5, 0.5, 0.5]', 'albedo = "missing.png"'), r"scene.toml: materials.0.albedo: .*missing.png: image file not found"),
        (lambda s: s + "\n[[objects]]\nname = 'x'\n", r"scene.toml: objects.4: .*needs a mesh, a generator or a model"),
        (lambda s: s.replace("[camera]", "[camera\n"), r"scene.toml: not valid TOML"),
        (lambda s: s.replace("translate = [1, 0, 0]", "translate = [nan, 0, 0]"), r"scene.toml: objects.1.transform.translate.0: .*finite"),
        (lambda s: s.replace("rotate = [0, 45, 0]", "rotate = [0, inf, 0]"), r"scene.toml: objects.1.transform.rotate.1: .*finite"),
        (lambda s: s.replace("translate = [-1, 0, 0]", "matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -inf], [0, 0, 0, 1]]"),
         r"scene.toml: objects.2.transform.matrix.2.3: .*finite"),
        (lambda s: s.replace("position = [0, 1, 4]", "position = [0, nan, 4]"), r"scene.toml: camera.position.1: .*finite"),
    ],
)
def test_errors_are_one_line_and_name_file_and_key(scene_dir, edit, message):
    (scene_dir / "scene.toml").write_text(edit(SCENE))
    with pytest.raises(SceneError, match=message) as info:
        load_scene(scene_dir / "scene.toml")
    assert "\n" not in str(info.value)


def test_missing_file_and_unknown_builtin(tmp_path):
    with pytest.raises(SceneError, match="nope.toml: scene file not found"):
        load_scene(tmp_path / "nope.toml")
    (tmp_path / "s.yaml").write_text("x")
    with pytest.raises(SceneError, match="unknown scene file type"):
        load_scene(tmp_path / "s.yaml")
    with pytest.raises(SceneError, match="builtin:nope: unknown built-in scene"):
        load_scene("builtin:nope")
    with pytest.raises(SceneError, match="unknown option"):
        load_scene("builtin:hairball?size=3")
    with pytest.raises(SceneError, match=r"builtin:hairball: detail must be in 0..8, got 99"):
        load_scene("builtin:hairball?detail=99")
    with pytest.raises(SceneError, match=r"builtin:instances: detail must be in 0..6, got 7"):  # its statue is at detail - 1
        load_scene("builtin:instances", detail=7)
    with pytest.raises(SceneError, match="detail given 2 times"):
        load_scene("builtin:hairball?detail=1&detail=2")


def test_textured_albedo(scene_dir):
    tex = np.zeros((2, 2, 3), np.float32)
    tex[:, :, 0] = 1.0  # red
    write_png(scene_dir / "red.png", tex)
    (scene_dir / "scene.toml").write_text(SCENE.replace("albedo = [0.5, 0.5, 0.5]", 'albedo = "red.png"'))
    with pytest.warns(UserWarning, match="has a texture, but the mesh has no UVs"):  # (the table is what is tested)
        scene = load_scene(scene_dir / "scene.toml")
    value = scene.materials.albedo_at(torch.tensor([0]), torch.tensor([[0.3, 0.6]]))
    torch.testing.assert_close(value, torch.tensor([[1.0, 0.0, 0.0]]))


def test_builtins_listed_and_loadable_at_small_detail():
    names = [n for n, _ in list_builtins()]
    assert names == list(BUILTIN_SCENES) and {"cornell-statue", "hairball", "foliage", "instances"} <= set(names)
    for name in names:
        scene = load_scene(f"builtin:{name}?detail=0", resolution=(8, 8))
        assert scene.lights.area is not None or scene.lights.environment is not None, name
        assert all(d for _, d in list_builtins())
    inst = load_scene("builtin:instances", detail=0)
    assert len(inst.accel.instances) >= 30 and len(inst.accel.unique_blases) <= 5  # many copies of a few meshes


def test_builtin_detail_scales_triangles():
    small, _, _ = load_scene_spec("builtin:hairball?detail=0")
    big, _, _ = load_scene_spec("builtin:hairball", detail=3)
    assert small.objects[0].generator.params["detail"] == 0 and big.objects[0].generator.params["detail"] == 3


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_save_scene_round_trip(scene_dir, tmp_path_factory, suffix):
    spec, _, _ = load_scene_spec(scene_dir / "scene.toml")
    out = tmp_path_factory.mktemp("saved") / f"copy{suffix}"
    save_scene(spec, out)
    again, _, _ = load_scene_spec(out)
    assert again == spec  # same keys and values, paths re-resolved to the same absolute files
    text = out.read_text()
    assert str(scene_dir) not in text  # paths were written relative to the new file
    scene = load_scene(out)
    assert len(scene.accel.instances) == 4


def test_save_builtin_round_trip(tmp_path):
    spec, _, _ = load_scene_spec("builtin:instances?detail=0")
    save_scene(spec, tmp_path / "inst.toml")
    again, _, _ = load_scene_spec(tmp_path / "inst.toml")
    assert again == spec
    with pytest.raises(SceneError, match="must end in .toml or .json"):
        save_scene(spec, tmp_path / "inst.yaml")


def test_reference_generator_of_an_installed_copy_prints_the_page(tmp_path, monkeypatch, capsys):
    """Installed in site-packages, the source tree's docs folder is not there: the page is printed
    (writing it failed with a traceback); a path given is written."""
    from neuralrt.scene import schemadoc

    assert schemadoc._in_source_tree()  # (this checkout)
    monkeypatch.setattr(schemadoc, "_in_source_tree", lambda: False)
    schemadoc.main([])
    assert capsys.readouterr().out == schemadoc.scene_reference()
    schemadoc.main([str(tmp_path / "page.md")])
    assert (tmp_path / "page.md").read_text(encoding="utf-8") == schemadoc.scene_reference()


def test_reference_page_is_current_and_its_example_loads(tmp_path):
    """docs/scenes.md equals what `python -m neuralrt.scene.schemadoc` generates; its TOML example loads."""
    from neuralrt.io.images import write_hdr
    from neuralrt.scene.schemadoc import default_path, scene_reference

    page = scene_reference()
    assert default_path().read_text(encoding="utf-8") == page, "regenerate: python -m neuralrt.scene.schemadoc"
    example = page.split("```toml\n", 1)[1].split("```", 1)[0]
    (tmp_path / "meshes").mkdir()
    trimesh.creation.icosphere(subdivisions=1).export(tmp_path / "meshes" / "statue.ply")
    write_hdr(tmp_path / "sky.hdr", np.full((4, 8, 3), 0.5, np.float32))
    (tmp_path / "example.toml").write_text(example)
    scene = load_scene(tmp_path / "example.toml", resolution=(8, 8))
    assert len(scene.accel.instances) == 2 and scene.lights.kinds == ["area", "environment"]


@pytest.mark.parametrize("command", ["info", "render"])
def test_nan_transform_is_one_line_from_the_cli(scene_dir, capsys, command):
    """Issue 7: NaN in translate gave a traceback in `render` and `info`."""
    from neuralrt.cli import main

    (scene_dir / "scene.toml").write_text(SCENE.replace("translate = [1, 0, 0]", "translate = [1, nan, 0]"))
    args = [command, str(scene_dir / "scene.toml")] + (["-o", str(scene_dir / "out" / "x.exr")] if command == "render" else [])
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"neuralrt: error: {scene_dir / 'scene.toml'}: objects.1.transform.translate.1:") and "\n" not in err
    assert not (scene_dir / "out").exists()


def test_cornell_box_walls_have_their_scene_colours_once():
    """The generator's slots carry no colour: the walls had each colour twice (0.73^2 = 0.53 white)."""
    from neuralrt.render.integrator import render as render_scene

    scene = load_scene("builtin:cornell-statue?detail=0", resolution=(32, 32))
    albedo = render_scene(scene, spp=1, progress=False, max_depth=1).albedo
    assert np.allclose(albedo[16, 2], [0.63, 0.065, 0.05], atol=1e-6)  # left wall: "red"
    assert np.allclose(albedo[16, 29], [0.14, 0.45, 0.091], atol=1e-6)  # right wall: "green"
    assert np.allclose(albedo[2, 16], [0.73, 0.73, 0.73], atol=1e-6)  # ceiling ("white"), beside the light

"""`neuralrt import`: a glTF scene as a scene file (`neuralrt.scene.gltf_import`), and the scene
object's ``gltf_mesh`` that it writes."""

import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from gltf_files import edited_glb, street_glb
from neuralrt import api
from neuralrt.errors import MeshError, NeuralRTError, SceneError
from neuralrt.geometry.mesh import load_mesh
from neuralrt.scene.gltf_import import CANDELA_PER_WATT_SR, DISTANT
from neuralrt.scene.loader import load_scene, load_scene_spec
from neuralrt.scene.material_rules import scene_materials

DATA = Path(__file__).parent / "data"
pytestmark = pytest.mark.filterwarnings("ignore:.*the emission of material 'lamp' is not read")


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    folder = tmp_path_factory.mktemp("street")
    return street_glb(folder / "street.glb")


def _world_triangles(mesh, matrix=np.eye(4)):
    corners = mesh.vertices[mesh.faces].astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
    return np.array(sorted(map(tuple, np.round(corners.reshape(len(mesh.faces), 9), 4))))


def _placed_triangles(spec):
    parts = [_world_triangles(load_mesh(o.mesh, o.gltf_mesh, lit=("lamp",)),
                              np.array(o.transform.to_transform().matrix.tolist(), np.float64)) for o in spec.objects]
    return np.array(sorted(map(tuple, np.concatenate(parts))))


def test_each_node_is_an_instance_of_its_mesh_placed_as_the_whole_file_reads(street, tmp_path):
    facts = api.import_scene(street, tmp_path / "scenes" / "street.toml")
    assert facts["objects"] == 6 and facts["meshes"] == 4  # (three houses: one mesh)
    spec, _, _ = load_scene_spec(tmp_path / "scenes" / "street.toml")
    assert [o.name for o in spec.objects] == ["ground", "house0", "house1", "house2", "ball", "lamp"]
    assert {o.gltf_mesh for o in spec.objects[1:4]} == {spec.objects[1].gltf_mesh}
    assert spec.objects[0].mesh == str(street)  # (written relative to the scene's folder, read back absolute)
    relative = Path(os.path.relpath(street, tmp_path / "scenes")).as_posix()
    assert f'mesh = "{relative}"' in (tmp_path / "scenes" / "street.toml").read_text()
    np.testing.assert_allclose(_placed_triangles(spec), _world_triangles(load_mesh(street)), atol=2e-4)
    info = api.info(tmp_path / "scenes" / "street.toml")
    assert info["instances"] == 6 and info["unique_blas"] == 4


def test_the_camera_lights_and_materials_are_the_files(street, tmp_path):
    api.import_scene(street, tmp_path / "street.json")
    spec, _, _ = load_scene_spec(tmp_path / "street.json")
    camera = spec.camera
    assert camera.position == pytest.approx((0, 2, 8)) and camera.fov == pytest.approx(math.degrees(0.8))
    assert tuple(camera.resolution) == (384, 256)
    facing = np.subtract(camera.look_at, camera.position)
    angle = 2 * math.atan2(0.0998, 0.995)  # (the node turns -z about x, down by this)
    np.testing.assert_allclose(facing / np.linalg.norm(facing), [0, -math.sin(angle), -math.cos(angle)], atol=1e-6)
    bulb, sun = spec.lights
    assert bulb.position == pytest.approx((2, 4, 2)) and bulb.intensity == pytest.approx([30000 / CANDELA_PER_WATT_SR] * 3)
    lo, hi = np.array([-5.0, -0.1, -5.0]), np.array([5.0, 3.025, 5.0])
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    np.testing.assert_allclose(sun.position, centre + [0, DISTANT * radius, 0], rtol=1e-6, atol=1e-9)  # (it shines straight down)
    irradiance = np.array(sun.intensity) / (DISTANT * radius) ** 2  # at the centre, W/m^2
    np.testing.assert_allclose(irradiance, np.array([1, 0.95, 0.9]) * 1500 / CANDELA_PER_WATT_SR, rtol=1e-6)
    kinds = {m.name: m for m in scene_materials(spec)}
    assert kinds["default"].type == "diffuse" and tuple(kinds["default"].albedo) == (0.8, 0.8, 0.8)  # (as a lone mesh's)
    assert kinds["brick"].type == "plastic" and kinds["brick"].roughness == pytest.approx(0.49)
    assert kinds["chrome"].type == "conductor" and kinds["chrome"].roughness == pytest.approx(0.04)
    assert kinds["lamp"].type == "emissive" and tuple(kinds["lamp"].emission) == pytest.approx((1.0, 0.9, 0.7))
    assert spec.environment is None


def test_the_imported_scene_renders_with_its_lamp_as_a_light_and_no_warning(street, tmp_path):
    api.import_scene(street, tmp_path / "street.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (the lamp's emission is used: not "not read")
        scene = load_scene(tmp_path / "street.toml")
    assert scene.lights.area is not None and scene.lights.points is not None
    with pytest.warns(UserWarning, match="the emission of material 'lamp' is not read"):
        load_mesh(street)  # (alone, a mesh file's emission is unread, and said so)


def test_a_file_without_lights_is_lit_and_framed_as_a_lone_mesh(tmp_path):
    path = street_glb(tmp_path / "dark.glb", lights=False)
    path = edited_glb(path, lambda h: h["materials"][2].pop("emissiveFactor"))
    facts = api.import_scene(path, tmp_path / "dark.toml")
    assert facts["camera"] == "framed" and facts["lit_as_a_lone_mesh"] and facts["emissive_materials"] == 0
    spec, _, _ = load_scene_spec(tmp_path / "dark.toml")
    assert spec.environment is not None and len(spec.lights) == 1


def test_alpha_cut_out_materials_are_said_to_render_opaque(tmp_path):
    """``alphaMode`` MASK or BLEND (leaves, fences) is not read: import and a lone render say so."""
    def cut_out(header):
        header["materials"][0]["alphaMode"] = "MASK"
        header["materials"][1]["alphaMode"] = "OPAQUE"
    path = edited_glb(street_glb(tmp_path / "leafy.glb"), cut_out)
    with pytest.warns(UserWarning, match=r"the alpha of '\w+' \(alphaMode MASK or BLEND\) is not read: its surfaces "
                                         r"render opaque") as caught:
        api.import_scene(path, tmp_path / "leafy.toml")
    assert sum("alphaMode" in str(w.message) for w in caught) == 1 and path.name in str(caught[0].message)
    with pytest.warns(UserWarning, match=r"alphaMode MASK or BLEND"), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*merged mesh")
        load_scene(str(path), resolution=(4, 4))
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        warnings.filterwarnings("ignore", message=".*(emission|merged mesh)")
        load_scene(str(street_glb(tmp_path / "plain.glb")), resolution=(4, 4))  # (no cut-out material: no note)


def test_gpu_instances_become_objects(tmp_path):
    facts = api.import_scene(DATA / "gltfpack_instances.glb", tmp_path / "i.toml")
    spec, _, _ = load_scene_spec(tmp_path / "i.toml")
    assert facts["meshes"] == 1 and facts["objects"] == len(spec.objects) == 3
    np.testing.assert_allclose(_placed_triangles(spec), _world_triangles(load_mesh(DATA / "gltfpack_instances.glb")),
                               atol=2e-4)


def test_gltf_mesh_loads_one_mesh_alone_by_index_or_name(street):
    house = load_mesh(street, 1)
    assert house.name == "street-1" and house.num_triangles == 12
    lo, hi = house.bounds
    np.testing.assert_allclose(lo, [-0.5, -1, -0.5]) and np.testing.assert_allclose(hi, [0.5, 1, 0.5])  # (its own space)
    assert [m.name for m in house.materials] == ["brick"]
    assert load_mesh(street, "house").content_hash() == house.content_hash()


@pytest.mark.parametrize("choice, message", [
    (9, "gltf_mesh: the file has no mesh 9 (it has 6: 0 to 5)"),
    ("nothing", "gltf_mesh: no mesh of the file is named 'nothing'"),
    (1.5, "gltf_mesh: a glTF mesh is named by its index or its name, not float 1.5"),
])
def test_gltf_mesh_that_names_no_mesh_is_an_error(street, choice, message):
    with pytest.raises(MeshError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_mesh(street, choice)


def test_gltf_mesh_of_a_file_that_is_no_gltf_is_an_error(tmp_path):
    import trimesh

    trimesh.creation.box().export(tmp_path / "box.obj")
    with pytest.raises(MeshError, match="gltf_mesh: only a glTF file"):
        load_mesh(tmp_path / "box.obj", 0)


def test_gltf_mesh_in_a_scene_file_is_checked(street, tmp_path):
    (tmp_path / "no_mesh.toml").write_text('[[objects]]\ngltf_mesh = 0\ngenerator = { name = "box" }\n')
    with pytest.raises(SceneError, match="gltf_mesh chooses a mesh of the glTF file that mesh names"):
        load_scene(tmp_path / "no_mesh.toml")
    (tmp_path / "bad.toml").write_text(f'[[objects]]\nmesh = "{street.as_posix()}"\ngltf_mesh = 12\n')
    with pytest.raises(SceneError, match=r"objects.0.mesh: .*gltf_mesh: the file has no mesh 12"):
        load_scene(tmp_path / "bad.toml")
    (tmp_path / "negative.toml").write_text(f'[[objects]]\nmesh = "{street.as_posix()}"\ngltf_mesh = -1\n')
    with pytest.raises(SceneError, match="gltf_mesh"):
        load_scene(tmp_path / "negative.toml")


def _cycle(header):
    header["nodes"][0]["children"] = [1]
    header["nodes"][1]["children"] = [0]


@pytest.mark.parametrize("edit, message", [
    (_cycle, "node 0 is its own ancestor"),
    (lambda h: h["nodes"][1].update(mesh=40), "node 1 draws mesh 40, which the file does not have"),
    (lambda h: h["nodes"][1].update(matrix=[1, 2, 3]), "node 1's transform cannot be read"),
    (lambda h: h["scenes"][0]["nodes"].append(99), "names node 99, which the file does not have"),
    (lambda h: h["cameras"][0]["perspective"].update(yfov=4.0), "camera 0: yfov must be in"),
    # (what the scene could not load is found here, not at its render)
    (lambda h: h["meshes"][h["nodes"][4]["mesh"]]["primitives"][0].update(material=99),
     r"cannot read mesh: not a valid glTF file: an index past the end of its data \(IndexError.*\(glTF mesh \d\)"),
    (lambda h: h["nodes"][0].update(matrix=[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 1e30, 0, 0, 1]),
     r"its meshes reach 1e\+30 from the origin"),
    (lambda h: h["extensions"]["KHR_lights_punctual"]["lights"][0].update(intensity=1e300),
     r"point light 'bulb' at node \d+: its position must lie within 1e\+18 and its intensity within 1e\+20"),
    # (JSON of the wrong type is named, not a traceback)
    (lambda h: h["nodes"][1].update(children=2), "node 1's children must be a list of node indices, not int"),
    (lambda h: h["scenes"][0].update(nodes=3), "scene 0's nodes must be a list of node indices, not int"),
    (lambda h: h["extensions"]["KHR_lights_punctual"].update(lights={"0": {}}), "KHR_lights_punctual's lights must be a list"),
    (lambda h: h.update(scene=5), "the default scene is 5, but the file has 1 scene"),
    # (from a fuzzing trial: a KeyError, a MemoryError and TypeErrors before)
    (lambda h: [h.pop(k, None) for k in ("nodes", "scenes", "scene")], "no node of its scene draws a mesh"),
    (lambda h: h["accessors"][h["meshes"][0]["primitives"][0]["indices"]].update(bufferView=-1),
     r"cannot read glTF mesh 0: accessor \d+ names buffer view -1, which the file does not have"),
    (lambda h: h["bufferViews"][0].update(byteLength=2**40), "buffer view 0 reaches past the end of buffer 0"),
    (lambda h: h["materials"][0].update(name=[[1, 2, 3]]), "material 0's name must be text, not list"),
    (lambda h: h["nodes"][1].update(name={"a": 1}), "node 1's name must be text, not dict"),
])
def test_a_malformed_scene_is_one_error(street, tmp_path, edit, message):
    path = tmp_path / "bad.glb"
    path.write_bytes(street.read_bytes())
    edited_glb(path, edit)
    with pytest.raises(SceneError, match=message):
        api.import_scene(path, tmp_path / "bad.toml")
    assert not (tmp_path / "bad.toml").exists()


def test_a_node_that_cannot_place_its_mesh_is_left_out_with_a_warning(street, tmp_path):
    path = tmp_path / "flat.glb"
    path.write_bytes(street.read_bytes())
    edited_glb(path, lambda h: h["nodes"][4].update(matrix=[1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]))
    with pytest.warns(UserWarning, match=r"node 4 \('ball'\) is left out"):
        facts = api.import_scene(path, tmp_path / "flat.toml")
    assert facts["objects"] == 5


def test_a_camera_or_mesh_its_node_cannot_place_is_left_out_in_one_line(street, tmp_path):
    path = tmp_path / "odd.glb"
    path.write_bytes(street.read_bytes())

    def edit(header):
        camera = next(n for n in header["nodes"] if "camera" in n)
        camera["scale"] = [0.0, 0.0, 0.0]
        header["nodes"][4]["matrix"] = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, float("nan"), 0, 0, 1]

    edited_glb(path, edit)
    with pytest.warns(UserWarning) as caught:
        facts = api.import_scene(path, tmp_path / "odd.toml")
    said = [str(w.message) for w in caught]
    assert any("camera 0 at node" in m and "gives it no view direction" in m for m in said), said
    assert any(m.endswith("node 4 ('ball') is left out: its world matrix cannot place a mesh (it holds numbers that are "
                          "not finite)") for m in said), said
    assert facts["camera"] == "framed" and facts["objects"] == 5


def test_a_node_whose_mesh_draws_no_triangles_is_left_out_with_a_warning(street, tmp_path):
    """Points and lines (which rays cannot hit) are left out: a node drawing only them, with a warning
    naming it; a mesh mixing them with triangles, with a note on the primitives."""
    path = tmp_path / "lines.glb"
    path.write_bytes(street.read_bytes())

    def edit(header):
        header["meshes"][header["nodes"][4]["mesh"]]["primitives"][0]["mode"] = 1  # (the ball: lines)
        ground = header["meshes"][header["nodes"][0]["mesh"]]["primitives"]
        ground.append({**ground[0], "mode": 0})  # (the ground: triangles, and the same vertices as points)

    edited_glb(path, edit)
    with pytest.warns(UserWarning) as caught:
        facts = api.import_scene(path, tmp_path / "lines.toml")
    said = [str(w.message) for w in caught]
    assert any(r"node 4 ('ball') is left out: mesh" in m and "draws no triangles" in m for m in said), said
    assert any("1 primitive(s) of points or lines are left out" in m for m in said), said
    assert facts["objects"] == 5


def test_other_files_and_outputs_are_refused(street, tmp_path):
    with pytest.raises(SceneError, match="a glTF file"):
        api.import_scene(DATA / "README.md", tmp_path / "x.toml")
    with pytest.raises(NeuralRTError, match="does not exist|not found|no such"):
        api.import_scene(tmp_path / "missing.glb", tmp_path / "x.toml")
    with pytest.raises(SceneError, match="must end in .toml or .json"):
        api.import_scene(street, tmp_path / "x.yaml")


def test_cli_import_prints_facts_and_errors_in_one_line(street, tmp_path):
    run = [sys.executable, "-m", "neuralrt", "import"]
    done = subprocess.run(run + [str(street), "-o", str(tmp_path / "s.toml"), "--json"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["objects"] == 6
    bad = subprocess.run(run + [str(tmp_path / "missing.glb"), "-o", str(tmp_path / "t.toml")], capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.startswith("neuralrt: error: ") and len(bad.stderr.splitlines()) == 1


def test_saved_scenes_say_no_default_again_and_read_back_the_same(street, tmp_path):
    from neuralrt.scene.scene import save_scene

    api.import_scene(street, tmp_path / "a.toml")
    text = (tmp_path / "a.toml").read_text()
    assert "translate" not in text and "[objects.materials]" not in text  # (a matrix places each object)
    assert "    [1.0, 0.0, 0.0, -2.0],\n" in text  # (a matrix row on one line)
    spec, _, _ = load_scene_spec(tmp_path / "a.toml")
    spec.objects[1].transform = {"translate": [1.0, 2.0, 3.0], "rotate": [0.0, 0.0, 0.0], "scale": 1.0}
    save_scene(spec, tmp_path / "b.toml")
    again, _, _ = load_scene_spec(tmp_path / "b.toml")
    assert again == spec and "rotate" not in (tmp_path / "b.toml").read_text()
    save_scene(spec, tmp_path / "b.json")
    assert load_scene_spec(tmp_path / "b.json")[0] == spec


def test_meshes_that_name_the_same_accessors_are_one(tmp_path):
    import trimesh
    from trimesh.transformations import translation_matrix

    scene = trimesh.Scene()
    for k in range(3):  # (trimesh writes a mesh per node, all three naming one POSITION and indices)
        scene.add_geometry(trimesh.creation.box(), node_name=f"box{k}", geom_name="box", transform=translation_matrix([2 * k, 0, 0]))
    scene.export(tmp_path / "boxes.glb")
    facts = api.import_scene(tmp_path / "boxes.glb", tmp_path / "boxes.toml")
    assert facts["objects"] == 3 and facts["meshes"] == 1
    spec, _, _ = load_scene_spec(tmp_path / "boxes.toml")
    np.testing.assert_allclose(_placed_triangles(spec), _world_triangles(load_mesh(tmp_path / "boxes.glb")), atol=2e-4)


def test_rendering_a_gltf_scene_as_one_mesh_says_what_goes_unused(street, tmp_path):
    from neuralrt.scene.gltf_import import unused_scene_note

    note = unused_scene_note(street)
    assert note == (f"{street}: rendered as one merged mesh, framed and lit (1 mesh drawn by several nodes is copied; "
                    f"1 camera and 2 lights are not used): `neuralrt import {street} -o {street.with_suffix('.toml')}` "
                    f"writes a scene that keeps them")
    with pytest.warns(UserWarning, match="rendered as one merged mesh"):
        load_scene(str(street), resolution=(8, 8))
    assert unused_scene_note(DATA / "gltfpack_ball.glb") is None  # (one node, one mesh)
    assert unused_scene_note(DATA / "README.md") is None


def test_nodes_under_turned_and_scaled_parents_are_placed_as_the_whole_file_reads(street, tmp_path):
    def nest(header):  # (the houses under a parent turned about y, scaled and moved, as exporters nest them)
        houses = [1, 2, 3]
        header["nodes"].append({"name": "block", "children": houses, "translation": [0.5, 0.0, -2.0],
                                "rotation": [0.0, 0.3826834, 0.0, 0.9238795], "scale": [1.5, 1.0, 0.5]})
        roots = header["scenes"][0]["nodes"]
        header["scenes"][0]["nodes"] = [n for n in roots if n not in houses] + [len(header["nodes"]) - 1]

    path = tmp_path / "nested.glb"
    path.write_bytes(street.read_bytes())
    edited_glb(path, nest)
    api.import_scene(path, tmp_path / "nested.toml")
    spec, _, _ = load_scene_spec(tmp_path / "nested.toml")
    assert len(spec.objects) == 6
    np.testing.assert_allclose(_placed_triangles(spec), _world_triangles(load_mesh(path)), atol=2e-4)


def _textured_pair_glb(path):
    """Two meshes, a big red-textured ball and a small blue-textured box, in one .glb (images in its binary chunk)."""
    import trimesh
    from PIL import Image
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    scene = trimesh.Scene()
    for name, mesh, colour, x in (("ball", trimesh.creation.icosphere(4), (255, 0, 0), 0.0),
                                  ("box", trimesh.creation.box(), (0, 0, 255), 3.0)):
        image = Image.new("RGB", (4, 4), colour)
        mesh.visual = TextureVisuals(uv=np.random.default_rng(0).random((len(mesh.vertices), 2)),
                                     material=PBRMaterial(name=name, baseColorTexture=image))
        scene.add_geometry(mesh, node_name=name, geom_name=name, transform=trimesh.transformations.translation_matrix([x, 0, 0]))
    scene.export(path)
    return path


def test_one_mesh_of_a_file_is_read_from_its_own_bytes_with_its_own_texture(tmp_path):
    from gltf_files import glb_as_gltf
    from neuralrt.geometry.gltf_json import gltf_header, gltf_mesh_index, mesh_alone
    from neuralrt.geometry.gltf_pack import packed_alone

    glb = _textured_pair_glb(tmp_path / "pair.glb")
    header = gltf_header(glb)
    box = gltf_mesh_index(header, "box")
    packed = packed_alone(mesh_alone(header, box), glb)
    assert len(packed) < glb.stat().st_size / 4  # (the ball's 2,562 vertices and its image are left out)
    for name, colour in (("ball", [1, 0, 0]), ("box", [0, 0, 1])):
        mesh = load_mesh(glb, name)
        (material,) = mesh.materials
        assert material.name == name and np.allclose(material.texture.reshape(-1, 3).mean(0), colour, atol=1e-3)
        whole = [p for p in load_mesh(glb).materials if p.name == name]
        assert whole and np.allclose(whole[0].texture, material.texture)
    # A .gltf whose meshes are in two .bin files: a missing one fails only the mesh that reads it.
    gltf = glb_as_gltf(glb, tmp_path / "pair.gltf")
    data = json.loads(gltf.read_text())
    box_views = {data["accessors"][a]["bufferView"] for p in data["meshes"][box]["primitives"]
                 for a in [*p["attributes"].values(), p["indices"]]}
    whole = (tmp_path / "pair.bin").read_bytes()
    (tmp_path / "box.bin").write_bytes(whole)
    data["buffers"].append({"uri": "box.bin", "byteLength": len(whole)})
    for v in box_views:
        data["bufferViews"][v]["buffer"] = 1
    gltf.write_text(json.dumps(data))
    (tmp_path / "box.bin").unlink()
    assert load_mesh(gltf, "ball").num_triangles == 5120
    with pytest.raises(MeshError, match=rf"cannot read glTF mesh {box}: buffer 1's file box.bin is not in {tmp_path}"):
        load_mesh(gltf, "box")


def test_numbers_that_are_not_finite_give_their_own_warning_not_numpys(street, tmp_path):
    # (numpy's "invalid value encountered in det" came first, as a warning of its own)
    path = tmp_path / "nan.glb"
    path.write_bytes(street.read_bytes())
    edited_glb(path, lambda h: h["nodes"][4].update(matrix=[float("nan"), 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_mesh(path, lit=("lamp",))
    said = [f"{w.category.__name__}: {w.message}" for w in caught]
    assert not [m for m in said if m.startswith("RuntimeWarning")] and any("is left out" in m for m in said), said

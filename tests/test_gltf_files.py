"""What a glTF file says that trimesh does not read: an error before it misleads (required
compression extensions, sparse accessors), a warning for what is left out (fans, normalised
integer UVs, skins, morph weights, emission), and the MTL's emission likewise."""

import re

import numpy as np
import pytest

from gltf_files import edited_glb, glb_as_gltf, quantized_uvs_glb
from neuralrt.errors import MeshError
from neuralrt.geometry.mesh import load_mesh


def _quads(path, materials=("a", "b")):
    """Two quads, one material each, as a .glb."""
    import trimesh
    from trimesh.visual.material import PBRMaterial

    scene = trimesh.Scene()
    for k, name in enumerate(materials):
        quad = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
        quad.apply_translation([3 * k, 0, 0])
        quad.visual = trimesh.visual.TextureVisuals(uv=np.zeros((4, 2)), material=PBRMaterial(name=name))
        scene.add_geometry(quad)
    scene.export(path)
    return path


def _sparse_position(header):
    position = header["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    header["accessors"][position]["sparse"] = {"count": 1, "indices": {"bufferView": 0, "componentType": 5125},
                                               "values": {"bufferView": 0}}


@pytest.mark.parametrize("edit, error", [
    (lambda h: h.update(extensionsUsed=["KHR_draco_mesh_compression"], extensionsRequired=["KHR_draco_mesh_compression"]),
     "it needs the glTF extension KHR_draco_mesh_compression (Draco-compressed geometry), which trimesh does not read"),
    (lambda h: h.update(extensionsRequired=["KHR_texture_transform", "EXT_meshopt_compression"]),
     "it needs the glTF extension EXT_meshopt_compression"),
    (_sparse_position, "the POSITION of mesh 0 is a sparse accessor"),
])
def test_what_trimesh_cannot_read_is_an_error_naming_it(tmp_path, edit, error):
    # (a Draco file gave "mesh is degenerate (all 2 triangles have zero area)"; sparse values were ignored)
    path = edited_glb(_quads(tmp_path / "quads.glb"), edit)
    with pytest.raises(MeshError, match=re.escape(f"quads.glb: cannot read mesh: {error}")):
        load_mesh(path)


def _fan(header):
    header["meshes"][0]["primitives"][0]["mode"] = 6


def _normalised_uvs(header):
    """Mesh 0's UVs as normalised unsigned shorts, mesh 1's floats: stored two ways, the parts
    trimesh makes cannot be told apart (stored one way throughout, they are read: test below)."""
    second = header["meshes"][1]["primitives"][0]["attributes"]
    header["accessors"].append(dict(header["accessors"][second["TEXCOORD_0"]]))  # (trimesh may share one accessor)
    second["TEXCOORD_0"] = len(header["accessors"]) - 1
    uv = header["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]
    header["accessors"][uv].update(componentType=5123, normalized=True)


def _ushort_colours_without_material(header):
    primitive = header["meshes"][0]["primitives"][0]
    primitive.pop("material", None)
    primitive["attributes"]["COLOR_0"] = primitive["attributes"]["POSITION"]  # (only its declared type matters here)
    header["accessors"][primitive["attributes"]["POSITION"]]["componentType"] = 5123


@pytest.mark.parametrize("edit, note", [
    (_fan, "1 primitive(s) drawn as triangle fans are left out"),
    (_normalised_uvs, "are normalised unsigned shorts, which trimesh reads unscaled"),  # (mesh 0's, mesh 1's)
    (lambda h: h.update(skins=[{"joints": [0]}]), "skins are not applied"),
    (lambda h: h["meshes"][0].update(weights=[0.0, 1.0]), "the morph target weights of 1 mesh(es) are not applied"),
    (lambda h: h["materials"][1].update(emissiveFactor=[1.0, 0.5, 0.0]),
     "the emission of material 'b' is not read: give the slot an emissive scene material to make it a light"),
    (_ushort_colours_without_material, "the vertex colours of mesh 0 are unsigned shorts on a primitive without a material"),
    (lambda h: h["accessors"][h["meshes"][0]["primitives"][0]["attributes"]["POSITION"]].update(normalized=True),
     "the positions of mesh 0 are normalised integers, which trimesh reads unscaled"),
])
def test_what_trimesh_leaves_out_is_a_warning_naming_it(tmp_path, edit, note):
    path = edited_glb(_quads(tmp_path / "quads.glb"), edit)
    with pytest.warns(UserWarning, match=rf"quads.glb: .*{re.escape(note)}"):
        try:
            load_mesh(path)
        except MeshError:
            pass  # (the edit may leave the file unreadable past the note: the note came first)


def test_a_plain_gltf_loads_without_a_word(tmp_path):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_mesh(_quads(tmp_path / "quads.glb")).num_triangles == 4


def test_an_mtl_emission_is_a_warning(tmp_path):
    (tmp_path / "lamp.mtl").write_text("newmtl lamp\nKd 1 1 1\nKe 4 4 4\nnewmtl dark\nKd 1 1 1\nKe 0 0 0\n")
    (tmp_path / "lamp.obj").write_text("mtllib lamp.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\n"
                                       "usemtl lamp\nf 1/1 2/1 3/1\nusemtl dark\nf 2/1 4/1 3/1\n")
    with pytest.warns(UserWarning) as caught:
        load_mesh(tmp_path / "lamp.obj")
    assert [str(w.message) for w in caught if "emission" in str(w.message)] == [
        f"{tmp_path / 'lamp.obj'}: the emission of material 'lamp' (Ke) is not read: give the slot an emissive scene "
        f"material to make it a light"]


def test_percent_encoded_uris_name_the_files_they_encode(tmp_path):
    # Blender writes "my%20data.bin" for "my data.bin" (URIs are percent-encoded): a buffer so
    # named was an error "FileNotFoundError: my%20data.bin" (an image, left out).
    import json

    import trimesh
    from PIL import Image
    from trimesh.visual.material import PBRMaterial

    quad = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    quad.visual = trimesh.visual.TextureVisuals(uv=np.full((4, 2), 0.5), material=PBRMaterial(
        name="paint", baseColorTexture=Image.new("RGB", (2, 2), (255, 0, 0))))
    files = trimesh.Scene(quad).export(file_type="gltf")
    header = json.loads(files.pop("model.gltf"))
    for k, buffer in enumerate(header["buffers"]):  # (trimesh writes the image into a buffer)
        spaced = f"my data {k}.bin"
        (tmp_path / spaced).write_bytes(files[buffer["uri"]])
        buffer["uri"] = spaced.replace(" ", "%20")
    (tmp_path / "quad.gltf").write_text(json.dumps(header))
    mesh = load_mesh(tmp_path / "quad.gltf")
    np.testing.assert_allclose(mesh.materials[0].texture[0, 0], [1, 0, 0])


def test_a_primitive_without_normals_is_shaded_flat(tmp_path):
    # The glTF spec: "When normals are not specified, client implementations MUST calculate flat
    # normals" (they were smooth: a box rendered as a blob).
    import trimesh

    def without_normals(header):
        for mesh in header["meshes"]:
            for primitive in mesh["primitives"]:
                primitive["attributes"].pop("NORMAL", None)

    trimesh.creation.box().export(tmp_path / "box.glb")
    mesh = load_mesh(edited_glb(tmp_path / "box.glb", without_normals))
    assert mesh.num_triangles == 12 and len(mesh.vertices) == 36
    np.testing.assert_allclose(mesh.vertex_normals, np.repeat(mesh.face_normals(), 3, axis=0), atol=1e-6)
    assert set(map(tuple, np.abs(mesh.vertex_normals).round(6))) == {(1, 0, 0), (0, 1, 0), (0, 0, 1)}


def test_the_base_colour_factor_is_read_as_written(tmp_path):
    # (trimesh keeps it in 8 bits: a linear 0.0015 became 0, 0.003 became 0.0039)
    def dark(header):
        header["materials"][0].setdefault("pbrMetallicRoughness", {})["baseColorFactor"] = [0.0015, 0.003, 0.5, 1.0]

    mesh = load_mesh(edited_glb(_quads(tmp_path / "quads.glb"), dark))
    by_name = {m.name: m for m in mesh.materials}
    np.testing.assert_allclose(by_name["a"].base_color, [0.0015, 0.003, 0.5], rtol=1e-6)
    np.testing.assert_array_equal(by_name["b"].base_color, [1, 1, 1])


@pytest.mark.parametrize("component, step", [(5121, 1 / 255), (5123, 1 / 65535), (5120, 1 / 127), (5122, 1 / 32767)])
def test_normalised_integer_uvs_are_scaled_as_the_file_means(tmp_path, component, step):
    """UVs stored as normalised integers throughout (gltfpack's, KHR_mesh_quantization's signed ones):
    trimesh reads them unscaled (v wrapped around in the integer type); they are read as the
    float UVs they stand for, and the texture lands where it did (this warned before)."""
    import warnings

    import torch
    import trimesh
    from PIL import Image

    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.rays import Rays

    stripes = np.zeros((4, 8, 3), np.uint8)
    stripes[:, :4], stripes[:, 4:] = (230, 20, 20), (20, 40, 230)
    quad = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    quad.visual = trimesh.visual.TextureVisuals(uv=[[0.25, 0.1], [0.75, 0.1], [0.75, 0.9], [0.25, 0.9]],
                                                image=Image.fromarray(stripes))
    quad.export(tmp_path / "float.glb")
    (tmp_path / "float.glb").rename(tmp_path / "quantized.glb")
    quad.export(tmp_path / "float.glb")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        exact, quantized = load_mesh(tmp_path / "float.glb"), load_mesh(quantized_uvs_glb(tmp_path / "quantized.glb", component))
    np.testing.assert_allclose(quantized.uvs, exact.uvs, atol=step)
    rays = Rays(torch.tensor([[0.3, 0.5, 1.0], [0.7, 0.5, 1.0]]), torch.tensor([[0.0, 0.0, -1.0]] * 2))
    albedo = MeshBLAS(quantized).intersect(rays).albedo
    assert torch.allclose(albedo, MeshBLAS(exact).intersect(rays).albedo)
    assert albedo[0, 0] > 10 * albedo[0, 2] and albedo[1, 2] > 10 * albedo[1, 0]  # red left, blue right


def _striped_ball():
    """The mesh tests/data/gltfpack_ball.glb was made from (``gltfpack -i ball.glb -o gltfpack_ball.glb``,
    gltfpack 1.3 from npm, defaults: positions as unsigned shorts placed by its node, UVs as
    normalised unsigned shorts with a KHR_texture_transform, one unnamed material): a UV sphere
    textured red | blue by longitude, green near one pole."""
    import trimesh
    from PIL import Image

    ball = trimesh.creation.uv_sphere(count=[12, 12])
    u = (np.arctan2(ball.vertices[:, 1], ball.vertices[:, 0]) / (2 * np.pi)) % 1.0
    v = (ball.vertices[:, 2] + 1) / 2
    texture = np.zeros((16, 16, 3), np.uint8)
    texture[:, :8], texture[:, 8:], texture[:4] = (230, 20, 20), (20, 40, 230), (20, 200, 20)
    mesh = trimesh.Trimesh(ball.vertices, ball.faces, process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.stack([u, v], 1), image=Image.fromarray(texture))
    return mesh


@pytest.mark.parametrize("name", ["gltfpack_ball.glb", "gltfpack_ball_vpn.glb"])  # (-vpn: normalised positions)
def test_a_gltfpack_file_reads_as_the_mesh_it_was_packed_from(tmp_path, name):
    """gltfpack's output (KHR_mesh_quantization, normalised UVs dequantized by a texture transform
    of its one unnamed material; with -vpn, normalised positions too) hit and coloured as the float
    original: before, its UVs (and -vpn's positions) were read unscaled and the transform was not
    applied (a warning each)."""
    import warnings
    from pathlib import Path

    import torch

    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.rays import Rays

    _striped_ball().export(tmp_path / "ball.glb")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        packed = load_mesh(Path(__file__).parent / "data" / name)
    original = load_mesh(tmp_path / "ball.glb")
    g = torch.Generator().manual_seed(0)
    origins = torch.randn(4000, 3, generator=g)
    origins = 3 * origins / origins.norm(dim=1, keepdim=True)
    directions = torch.nn.functional.normalize(-origins + 0.3 * torch.randn(4000, 3, generator=g), dim=1)
    rays = Rays(origins, directions)
    a, b = MeshBLAS(original).intersect(rays), MeshBLAS(packed).intersect(rays)
    assert (a.hit == b.hit).float().mean() > 0.995 and a.hit.float().mean() > 0.3  # (positions: 16 bits)
    both = a.hit & b.hit
    far = (a.albedo[both] - b.albedo[both]).abs().amax(dim=1) > 0.05
    assert far.float().mean() < 0.01  # (measured: 0 of them)


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_unnamed_materials_placing_their_maps_differently_are_told_apart(tmp_path, suffix):
    """trimesh names every unnamed material None: two of them with different texture transforms
    could not be matched to their parts (a warning, both transforms dropped); the file is read
    under names of its own, and each part gets its material's transform, as if they were named."""
    import warnings

    import trimesh
    from PIL import Image
    from trimesh.visual.material import PBRMaterial

    def write(path, named):
        scene = trimesh.Scene()
        for k in range(2):
            quad = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
            quad.apply_translation([2 * k, 0, 0])
            image = Image.fromarray(np.full((4, 4, 3), 60 + 100 * k, np.uint8))
            quad.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]],
                                                        material=PBRMaterial(name=f"m{k}", baseColorTexture=image))
            scene.add_geometry(quad)
        scene.export(path)

        def edit(header):
            for k, material in enumerate(header["materials"]):
                material["pbrMetallicRoughness"]["baseColorTexture"]["extensions"] = {
                    "KHR_texture_transform": {"scale": [2.0 + k, 1.0]}}
                if not named:
                    material.pop("name")
        return edited_glb(path, edit)

    named_path, unnamed_path = write(tmp_path / "named.glb", True), write(tmp_path / "unnamed.glb", False)
    if suffix == ".gltf":
        named_path = glb_as_gltf(named_path, tmp_path / "named.gltf")
        unnamed_path = glb_as_gltf(unnamed_path, tmp_path / "unnamed.gltf")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        named, unnamed = load_mesh(named_path), load_mesh(unnamed_path)
    np.testing.assert_allclose(unnamed.uvs, named.uvs)
    assert unnamed.uvs[:, 0].max() > 2.5  # (the second quad's u scaled by 3: transforms applied)
    assert sorted(m.name for m in unnamed.materials) == ["material0", "material1"]


def _three_boxes():
    """The scene tests/data/gltfpack_instances.glb was made from (``gltfpack -i boxes.glb -o
    gltfpack_instances.glb -mi``): one box on three nodes, each turned and moved its own way."""
    import trimesh

    scene = trimesh.Scene()
    box = trimesh.creation.box((0.5, 0.3, 0.2))
    for k in range(3):
        placed = trimesh.transformations.rotation_matrix(0.4 * k, [0, 0, 1])
        placed[:3, 3] = [1.5 * k, 0.2 * k, 0.1 * k]
        scene.add_geometry(box, node_name=f"box{k}", geom_name="box", transform=placed)
    return scene


@pytest.mark.parametrize("as_gltf", [False, True])
def test_gpu_instances_are_read_as_nodes(tmp_path, as_gltf):
    """EXT_mesh_gpu_instancing (gltfpack -mi; trimesh reads no instances): each instance's
    TRANSLATION, ROTATION (normalised shorts here) and SCALE place one copy, as the nodes of the
    scene it was packed from did (an error before). From a .glb's binary chunk or a .gltf's .bin."""
    import warnings
    from pathlib import Path

    import torch

    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.rays import Rays

    packed_path = Path(__file__).parent / "data" / "gltfpack_instances.glb"
    if as_gltf:
        packed_path = glb_as_gltf(packed_path, tmp_path / "instances.gltf")
    _three_boxes().export(tmp_path / "boxes.glb")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        packed, source = load_mesh(packed_path), load_mesh(tmp_path / "boxes.glb")
    assert packed.num_triangles == source.num_triangles == 36
    np.testing.assert_allclose(packed.bounds, source.bounds, atol=1e-4)
    centres = torch.tensor([[1.5 * k, 0.2 * k, 0.1 * k] for k in range(3)], dtype=torch.float32).repeat_interleave(300, 0)
    g = torch.Generator().manual_seed(0)
    origins = centres + 2.0 * torch.nn.functional.normalize(torch.randn(900, 3, generator=g), dim=1)
    directions = torch.nn.functional.normalize(centres - origins + 0.1 * torch.randn(900, 3, generator=g), dim=1)
    a, b = MeshBLAS(source).intersect(Rays(origins, directions)), MeshBLAS(packed).intersect(Rays(origins, directions))
    assert a.hit.float().mean() > 0.5 and (a.hit == b.hit).float().mean() > 0.995
    assert (a.t[a.hit & b.hit] - b.t[a.hit & b.hit]).abs().max() < 1e-3


def test_gpu_instances_that_cannot_be_read_are_one_line(tmp_path):
    from pathlib import Path

    broken = tmp_path / "broken.glb"
    broken.write_bytes((Path(__file__).parent / "data" / "gltfpack_instances.glb").read_bytes())
    for count in (10**6, 10**10):  # (10^10: a MemoryError traceback, after gigabytes, before the count was checked)
        edited_glb(broken, lambda h: h["accessors"][h["nodes"][0]["extensions"]["EXT_mesh_gpu_instancing"]["attributes"][
            "TRANSLATION"]].update(count=count))
        with pytest.raises(MeshError, match=f"broken.glb: cannot read mesh: its EXT_mesh_gpu_instancing instances cannot "
                                            f"be read .*declares {count:,} values, more than"):
            load_mesh(broken)


def test_a_buffer_uri_leading_out_of_the_files_folder_is_refused(tmp_path):
    """A scene object's one mesh of a glTF (``gltf_mesh``) read its buffers from wherever their uri
    led: ``../``, an absolute path, /proc. trimesh refuses them for a whole file; so does the
    per-mesh reader, in one line, and no byte of the outside file becomes geometry."""
    import json
    from pathlib import Path

    source = tmp_path / "inside" / "quad.gltf"
    source.parent.mkdir()
    glb_as_gltf(_quads(tmp_path / "q.glb"), source)
    outside = tmp_path / "secret.bin"
    outside.write_bytes((source.with_suffix(".bin")).read_bytes())  # (a file the mesh could read, were it allowed)
    for uri in ("../secret.bin", str(outside), "/proc/self/environ"):
        header = json.loads(source.read_text())
        header["buffers"][0]["uri"] = uri
        source.write_text(json.dumps(header))
        with pytest.raises(MeshError, match=re.escape(f"buffer 0's uri {uri!r} leads out of the file's folder")):
            load_mesh(source, 0)
        with pytest.raises(MeshError):
            load_mesh(source)  # (trimesh's own rule, for the whole file)
    assert Path(outside).is_file()

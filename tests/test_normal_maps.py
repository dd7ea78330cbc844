"""Tangent-space normal maps: analytic tilts on a UV-mapped quad (u and v directions, mirrored UVs),
the CPU (numpy) and torch implementations against each other, glTF loading (texels kept as stored,
not sRGB-decoded), the mesh hash, the render
(Lambert with the mapped normal) and bad normal maps."""

import math
import re

import numpy as np
import pytest
import torch

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.accel.mesh_blas_attributes import MeshAttributeTables, closest_hit_records
from neuralrt.accel.normal_mapping import mapped_normals_numpy, mapped_normals_torch
from neuralrt.errors import MeshError
from neuralrt.geometry.mesh import Mesh, MeshMaterial, load_mesh
from neuralrt.geometry.procedural import sphere
from neuralrt.geometry.tangents import vertex_tangents
from neuralrt.rays import Rays
from gltf_files import edited_glb

QUAD_VERTICES = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)  # faces +z
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])
QUAD_UVS = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)  # u along +x, v along +y


def _texel(m) -> np.ndarray:
    return (np.asarray(m, np.float32) + 1.0) / 2.0


def _quad(texel, uvs=QUAD_UVS) -> Mesh:
    return Mesh(QUAD_VERTICES, QUAD_FACES, uvs=uvs, materials=[MeshMaterial("bumpy", normal_map=np.tile(texel, (4, 4, 1)))])


def _normals_at_centre(mesh: Mesh) -> np.ndarray:
    rays = Rays(torch.tensor([[0.1, 0.2, 3.0], [-0.4, -0.3, 3.0]]), torch.tensor([[0.0, 0.0, -1.0]] * 2))
    hits = MeshBLAS(mesh).intersect(rays)
    assert bool(hits.hit.all())
    return hits.normal.numpy()


S, C = math.sin(math.radians(30)), math.cos(math.radians(30))


@pytest.mark.parametrize("encoded, uvs, expected", [
    ((0, 0, 1), QUAD_UVS, (0, 0, 1)),  # a flat map changes nothing
    ((S, 0, C), QUAD_UVS, (S, 0, C)),  # red tilts towards increasing u (+x)
    ((0, S, C), QUAD_UVS, (0, S, C)),  # green towards increasing v (+y): "green up"
    ((S, 0, C), QUAD_UVS * [-1, 1], (-S, 0, C)),  # u mirrored: increasing u is -x
    ((0, S, C), QUAD_UVS * [1, -1], (0, -S, C)),  # v mirrored: the handedness w flips the bitangent
])
def test_a_constant_normal_map_tilts_normals_by_its_texel(encoded, uvs, expected):
    got = _normals_at_centre(_quad(_texel(encoded), uvs.astype(np.float32)))
    np.testing.assert_allclose(got, np.tile(expected, (2, 1)), atol=2e-3)  # (8-bit-free float texels; bilinear of a constant)


def test_numpy_and_torch_implementations_agree():
    rng = np.random.default_rng(4)
    normal = rng.normal(size=(500, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    tangent = np.concatenate([rng.normal(size=(500, 3)), np.sign(rng.normal(size=(500, 1)))], axis=1).astype(np.float32)
    texel = rng.uniform(0, 1, size=(500, 3)).astype(np.float32)
    tangent[:5, :3] = normal[:5] * 2.0  # degenerate frames: the normal is kept
    a = mapped_normals_numpy(normal, tangent, texel)
    b = mapped_normals_torch(*(torch.from_numpy(x) for x in (normal, tangent, texel))).numpy()
    np.testing.assert_allclose(a, b, atol=1e-6)
    np.testing.assert_allclose(a[:5], normal[:5])
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-6)


def _textured_sphere() -> Mesh:
    base = sphere(2)
    d = base.vertices / np.linalg.norm(base.vertices, axis=1, keepdims=True)
    uvs = np.stack([0.5 + np.arctan2(d[:, 2], d[:, 0]) / (2 * np.pi), 0.5 + np.arcsin(np.clip(d[:, 1], -1, 1)) / np.pi], 1)
    ramp = np.linspace(0.2, 0.8, 16, dtype=np.float32)
    normal_map = np.stack(np.broadcast_arrays(ramp[None, :], ramp[:, None], np.float32(0.9)), -1).astype(np.float32)
    return Mesh(base.vertices, base.faces, uvs=uvs.astype(np.float32), materials=[MeshMaterial("bumpy", normal_map=normal_map)])


def test_the_cpu_hit_path_and_the_torch_attributes_path_agree_on_a_sphere():
    mesh = _textured_sphere()
    rng = np.random.default_rng(5)
    faces = rng.integers(0, len(mesh.faces), 300)
    bu, bv = rng.uniform(0.05, 0.45, 300).astype(np.float32), rng.uniform(0.05, 0.45, 300).astype(np.float32)
    corners = mesh.vertices[mesh.faces[faces]]
    points = (1 - bu - bv)[:, None] * corners[:, 0] + bu[:, None] * corners[:, 1] + bv[:, None] * corners[:, 2]
    normals = mesh.face_normals()[faces]
    rays = Rays(torch.from_numpy(points + 2 * normals), torch.from_numpy(-normals))
    cpu = MeshBLAS(mesh).intersect(rays)
    assert bool(cpu.hit.all()) and torch.equal(cpu.primitive_id, torch.from_numpy(faces))
    tables = MeshAttributeTables(mesh, torch.device("cpu"))
    other = closest_hit_records(tables, torch.from_numpy(faces), cpu.t, torch.from_numpy(bu), torch.from_numpy(bv))
    np.testing.assert_allclose(cpu.normal.numpy(), other.normal.numpy(), atol=2e-4)  # (Embree's barycentrics vs ours)
    plain = MeshBLAS(Mesh(mesh.vertices, mesh.faces, uvs=mesh.uvs)).intersect(rays)
    assert float((cpu.normal - plain.normal).norm(dim=1).median()) > 0.1  # the map does turn them


def test_tangents_follow_u_and_record_mirroring():
    flipped = vertex_tangents(QUAD_VERTICES, QUAD_FACES, np.tile([0, 0, 1.0], (4, 1)), QUAD_UVS * [1, -1])
    np.testing.assert_allclose(flipped, np.tile([1, 0, 0, -1], (4, 1)), atol=1e-6)
    no_uvs = vertex_tangents(QUAD_VERTICES, QUAD_FACES, np.tile([0, 0, 1.0], (4, 1)), np.zeros((4, 2)))
    np.testing.assert_allclose(np.linalg.norm(no_uvs[:, :3], axis=1), 1.0, atol=1e-6)  # a frame anyway
    np.testing.assert_allclose(no_uvs[:, 2], 0.0, atol=1e-6)


def _glb(path, normal_image=None, base_image=None, uvs=QUAD_UVS):
    import trimesh
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    material = PBRMaterial(name="bumpy", baseColorFactor=[255, 255, 255, 255], normalTexture=normal_image,
                           baseColorTexture=base_image)
    visual = TextureVisuals(uv=uvs, material=material)
    trimesh.Trimesh(QUAD_VERTICES, QUAD_FACES, visual=visual, process=False).export(str(path))
    return path


def _image(rgb, size=4, mode="RGB"):
    from PIL import Image

    return Image.fromarray(np.tile(np.array(rgb, np.uint8), (size, size, 1))).convert(mode)


def test_gltf_normal_texture_is_loaded_as_stored(tmp_path):
    loaded = load_mesh(_glb(tmp_path / "quad.glb", _image([200, 128, 230])))
    np.testing.assert_allclose(loaded.materials[0].normal_map[0, 0], np.array([200, 128, 230]) / 255.0, rtol=1e-6)
    expected = np.array([200, 128, 230]) / 255.0 * 2 - 1
    np.testing.assert_allclose(_normals_at_centre(loaded)[0], expected / np.linalg.norm(expected), atol=1e-5)


@pytest.mark.parametrize("image, why", [
    (_image([90, 90, 90], mode="L"), "it is a grey (L) image"),  # a height map, most likely
    (_image([128, 128, 0]), "its texels point into the surface on average (mean blue 0.000, below 0.5)"),
])
def test_what_cannot_be_a_tangent_space_normal_map_is_left_out_with_a_warning(tmp_path, image, why):
    with pytest.warns(UserWarning, match=rf"quad.glb: the normal map of material 'bumpy' is left out: {re.escape(why)}"):
        loaded = load_mesh(_glb(tmp_path / "quad.glb", image))
    assert loaded.materials[0].normal_map is None


def test_an_image_without_uvs_is_left_out_with_a_warning(tmp_path):
    with pytest.warns(UserWarning, match="the normal map of material 'bumpy' is left out: the mesh has no UVs"):
        loaded = load_mesh(_glb(tmp_path / "quad.glb", _image([128, 128, 255]), uvs=None))
    assert loaded.materials[0].normal_map is None


@pytest.mark.parametrize("slot", ["normalTexture", "baseColorTexture"])
def test_a_damaged_image_inside_a_glb_is_a_warning_naming_it(tmp_path, slot):
    # It was an OSError with no file name, from trimesh's copy of the material (outside any check).
    rng = np.random.default_rng(0)
    from PIL import Image

    noise = Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8))
    path = _glb(tmp_path / "quad.glb", **{"normal_image" if slot == "normalTexture" else "base_image": noise})
    data = bytearray(path.read_bytes())
    start = data.find(b"IDAT")
    data[start + 40:start + 400] = bytes(360)
    path.write_bytes(bytes(data))
    what = "normal map" if slot == "normalTexture" else "texture"
    with pytest.warns(UserWarning, match=rf"quad.glb: the 64x64 {what} of material 'bumpy' could not be decoded \(OSError"):
        loaded = load_mesh(path)
    assert loaded.materials[0].normal_map is None and loaded.materials[0].texture is None


@pytest.mark.parametrize("texel", [(128, 128, 0), (0, 0, 0), (128, 128, 128), (127, 127, 127)])
def test_texels_that_encode_no_direction_keep_the_interpolated_normal(texel):
    # 8 bits cannot store 0.5: a grey texel decoded to (0.004, 0.004, 0.004) turned normals by 55 degrees.
    normal, tangent = np.array([[0, 0, 1.0]], np.float32), np.array([[1, 0, 0, 1.0]], np.float32)
    encoded = np.array([texel], np.float32) / 255
    np.testing.assert_array_equal(mapped_normals_numpy(normal, tangent, encoded), normal)
    np.testing.assert_array_equal(mapped_normals_torch(*(torch.from_numpy(x) for x in (normal, tangent, encoded))).numpy(), normal)


def test_info_names_the_textured_and_normal_mapped_materials(tmp_path):
    from neuralrt import api

    facts = api.info(_glb(tmp_path / "quad.glb", _image([200, 128, 230])))
    assert facts["uvs"] and facts["normal_mapped_materials"] == ["bumpy"] and facts["textured_materials"] == []


def test_a_normal_map_changes_the_mesh_hash():
    # (so a model trained without it is not taken for one of the mapped mesh: training's targets
    # are MeshBLAS.intersect's normals, mapped)
    flat = Mesh(QUAD_VERTICES, QUAD_FACES, uvs=QUAD_UVS)
    tilted = _quad(_texel((S, 0, C)))
    assert flat.content_hash() != tilted.content_hash()
    assert Mesh(QUAD_VERTICES, QUAD_FACES, uvs=QUAD_UVS, materials=[MeshMaterial("bumpy")]).content_hash() \
        != tilted.content_hash()


def test_a_normal_mapped_plane_renders_with_the_mapped_normal():
    """A point light straight above: radiance = albedo / pi * I * cos(mapped normal, light) / d^2."""
    from neuralrt.render.integrator import render
    from neuralrt.scene.loader import load_dict

    def centre_pixel(mesh):
        scene = load_dict({
            "camera": {"position": [0, 0, 3], "look_at": [0, 0, 0], "fov": 10, "resolution": [3, 3]},
            "materials": [{"name": "bumpy", "albedo": [0.5, 0.5, 0.5]}],
            "objects": [{"mesh": mesh}], "lights": [{"position": [0, 0, 2], "intensity": [4, 4, 4]}],
        })
        return float(np.asarray(render(scene, spp=16, max_depth=1, progress=False).image)[1, 1, 0])

    flat = centre_pixel(_quad(_texel((0, 0, 1))))
    tilted = centre_pixel(_quad(_texel((S, 0, C))))
    assert flat == pytest.approx(0.5 / math.pi * 4 / 4, rel=0.02)
    assert tilted == pytest.approx(flat * C, rel=0.02)


@pytest.mark.parametrize("normal_map, message", [
    (np.zeros((4, 4)), r"material 'bumpy' normal_map must be \[H, W, 3\], got shape \[4, 4\]"),
    (np.full((2, 2, 3), np.nan), "material 'bumpy' normal_map holds NaN or infinite values"),
])
def test_a_bad_normal_map_is_a_mesh_error(normal_map, message):
    with pytest.raises(MeshError, match=message):
        Mesh(QUAD_VERTICES, QUAD_FACES, uvs=QUAD_UVS, materials=[MeshMaterial("bumpy", normal_map=normal_map)])


# --- OBJ: the MTL's norm / map_Bump / bump statements --------------------------------------


def _obj(folder, statement, images=(("n.png", (200, 128, 230)),)):
    """A UV-mapped quad OBJ whose material has ``statement`` in its MTL, and the images it names."""
    for name, rgb in images:
        _image(rgb if isinstance(rgb, tuple) else (rgb,) * 3, mode="RGB" if isinstance(rgb, tuple) else "L").save(folder / name)
    (folder / "quad.mtl").write_text(f"newmtl bumpy\nKd 1 1 1\n{statement}\n")
    lines = ["mtllib quad.mtl"] + [f"v {x} {y} {z}" for x, y, z in QUAD_VERTICES] + [f"vt {u} {v}" for u, v in QUAD_UVS]
    lines += ["usemtl bumpy"] + [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in QUAD_FACES]
    (folder / "quad.obj").write_text("\n".join(lines) + "\n")
    return folder / "quad.obj"


@pytest.mark.parametrize("statement", ["norm n.png", "map_Bump n.png", "bump -bm 1 n.png", "map_bump -clamp on -bm 1.0 n.png",
                                       "norm n.png\nmap_Bump other.png"])  # norm first
def test_an_obj_materials_normal_map_is_loaded_as_stored(tmp_path, statement):
    # Blender and most exporters write a normal map as map_Bump (their importers read it as one).
    loaded = load_mesh(_obj(tmp_path, statement, images=(("n.png", (200, 128, 230)), ("other.png", (0, 128, 255)))))
    np.testing.assert_allclose(loaded.materials[0].normal_map[0, 0], np.array([200, 128, 230]) / 255.0, rtol=1e-6)
    expected = np.array([200, 128, 230]) / 255.0 * 2 - 1
    np.testing.assert_allclose(_normals_at_centre(loaded)[0], expected / np.linalg.norm(expected), atol=1e-5)


@pytest.mark.parametrize("scale", [0.5, 2.0, -1.0])
def test_bm_scales_the_maps_x_and_y_as_gltf_scale_does(tmp_path, scale):
    loaded = load_mesh(_obj(tmp_path, f"map_Bump -bm {scale} n.png"))
    m = np.array([200, 128, 230]) / 255.0 * 2 - 1
    expected = m * [scale, scale, 1]
    np.testing.assert_allclose(_normals_at_centre(loaded)[0], expected / np.linalg.norm(expected), atol=1e-5)


@pytest.mark.parametrize("statement, images, why", [
    ("bump h.png", (("h.png", 90),), "it is a grey (L) image"),
    ("map_Bump h.png", (("h.png", (90, 90, 90)),), "its red, green and blue are equal everywhere"),
    ("map_Bump -imfchan l n.png", (), "reads one channel (-imfchan l): a height map"),
    ("map_Bump -s 2 2 n.png", (), "moves or scales the map's UVs (-s 2 2)"),
    ("map_Bump -o 0.5 n.png", (), "moves or scales the map's UVs (-o 0.5)"),
    ("map_Bump -warp 1 n.png", (), "has an option -warp that is not an MTL map option"),
    ("map_Bump -bm", (), "has too few values after -bm, or no file name"),
    ("norm missing.png", (), "its file 'missing.png' (norm) could not be read (FileNotFoundError"),
    ("norm quad.mtl", (), "its file 'quad.mtl' (norm) could not be read (UnidentifiedImageError"),
])
def test_what_an_obj_material_names_but_cannot_be_used_is_left_out_with_a_warning(tmp_path, statement, images, why):
    path = _obj(tmp_path, statement, images=images or (("n.png", (200, 128, 230)),))
    with pytest.warns(UserWarning, match=rf"quad.obj: the normal map of material 'bumpy' is left out: .*{re.escape(why)}"):
        loaded = load_mesh(path)
    assert loaded.materials[0].normal_map is None


def test_the_bm_scale_keeps_texels_that_encode_no_direction():
    from neuralrt.geometry.obj_files import scaled_normal_texels

    texels = np.array([[[0.5, 0.5, 0.0], [128 / 255] * 3, _texel((S, 0, C))]], np.float32)
    scaled = scaled_normal_texels(texels, 3.0)
    np.testing.assert_array_equal(scaled[0, :2], texels[0, :2])
    m = scaled[0, 2] * 2 - 1
    np.testing.assert_allclose(m, np.array([3 * S, 0, C]) / math.hypot(3 * S, C), atol=1e-6)


# --- glTF: what trimesh reads but drops (normalTexture.scale, KHR_texture_transform, texCoord) ---


def _transform(offset=(0.0, 0.0), rotation=0.0, scale=(1.0, 1.0)):
    return {"extensions": {"KHR_texture_transform": {"offset": list(offset), "rotation": rotation, "scale": list(scale)}}}


@pytest.mark.parametrize("named", [True, False])  # (one unnamed material, as gltfpack writes, is matched too)
def test_gltf_normal_texture_scale_is_applied(tmp_path, named):
    path = _glb(tmp_path / "quad.glb", _image([200, 128, 230]))
    edited_glb(path, lambda h: h["materials"][0]["normalTexture"].update(scale=0.5) or named or h["materials"][0].pop("name"))
    m = np.array([200, 128, 230]) / 255.0 * 2 - 1
    expected = m * [0.5, 0.5, 1]
    np.testing.assert_allclose(_normals_at_centre(load_mesh(path))[0], expected / np.linalg.norm(expected), atol=1e-5)


def test_gltf_texture_transform_places_the_base_colour_texture_as_the_extension_defines(tmp_path):
    # An 8x8 texture whose red and green grow with each texel's column and row: the albedo at a hit
    # says where the image was sampled. Expected: scale, then rotate (u' = u cos r + v sin r,
    # v' = v cos r - u sin r: the spec's example of offset [0, 1], rotation pi/2, scale 0.5 reads
    # the lower-left quadrant), then offset, in glTF's UVs (v down); bilinear between texel centres.
    from PIL import Image

    from neuralrt.io.images import srgb_to_linear

    cols, rows = np.meshgrid(np.arange(8), np.arange(8))
    ramp = np.stack([cols * 255 / 7, rows * 255 / 7, np.zeros_like(cols)], axis=-1).round().astype(np.uint8)
    path = _glb(tmp_path / "quad.glb", base_image=Image.fromarray(ramp))
    offset, rotation, scale = (0.2, 0.3), 0.3, (0.5, 0.4)
    edited_glb(path, lambda h: h["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"].update(
        _transform(offset, rotation, scale)))
    points = np.array([[0.0, 0.0], [0.3, -0.4], [-0.5, 0.6], [0.7, 0.7]])
    rays = Rays(torch.tensor(np.c_[points, np.full(4, 3.0)], dtype=torch.float32), torch.tensor([[0.0, 0.0, -1.0]] * 4))
    albedo = MeshBLAS(load_mesh(path)).intersect(rays).albedo.numpy()
    u, v = (points[:, 0] + 1) / 2, 1 - (points[:, 1] + 1) / 2  # glTF's UVs of the quad: v down
    su, sv = u * scale[0], v * scale[1]
    c, s = math.cos(rotation), math.sin(rotation)
    x, y = (su * c + sv * s + offset[0]) * 8 - 0.5, (sv * c - su * s + offset[1]) * 8 - 0.5  # in texels
    assert (x > 0).all() and (x < 7).all() and (y > 0).all() and (y < 7).all()  # (no wrapping)
    linear = srgb_to_linear(ramp[..., :2] / 255.0)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    expected = ((1 - fy) * ((1 - fx) * linear[y0, x0] + fx * linear[y0, x0 + 1])
                + fy * ((1 - fx) * linear[y0 + 1, x0] + fx * linear[y0 + 1, x0 + 1]))
    np.testing.assert_allclose(albedo[:, :2], expected, atol=2e-4)


@pytest.mark.parametrize("edit, note", [
    (lambda h: h["materials"][0]["normalTexture"].update(texCoord=1), "the normalTexture of material 'bumpy' maps UV set 1"),
    (lambda h: h["materials"][0]["normalTexture"].update(_transform(offset=(0.5, 0))),
     "the normalTexture of material 'bumpy' is placed by its baseColorTexture's KHR_texture_transform: the two are "
     "placed differently"),
    (lambda h: h["materials"][0]["normalTexture"].update(_transform(scale=(1.0,))),
     "the KHR_texture_transform of the normalTexture of material 'bumpy' is not applied (offset and scale must be two"),
])
def test_what_a_gltf_places_but_cannot_be_applied_is_a_warning(tmp_path, edit, note):
    path = edited_glb(_glb(tmp_path / "quad.glb", _image([200, 128, 230]), base_image=_image([200, 20, 20])), edit)
    with pytest.warns(UserWarning, match=re.escape(f"quad.glb: {note}")):
        loaded = load_mesh(path)
    np.testing.assert_array_equal(loaded.uvs, QUAD_UVS[QUAD_FACES.ravel()])  # as they were (per corner: flat normals)


def test_maps_placed_differently_follow_the_base_colour_map(tmp_path):
    """Two transforms, one UV set: the colour (what shows) is placed right, the normal map with it, and
    a warning says so (gltfpack scales both maps' transforms: dropping both misplaced both)."""
    def both(path, base, normal):
        edited_glb(path, lambda h: h["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"].update(base)
                   or h["materials"][0]["normalTexture"].update(normal))
        return path

    images = dict(normal_image=_image([200, 128, 230]), base_image=_image([200, 20, 20]))
    base = _transform(offset=(0.25, 0.1), scale=(2.0, 2.0))
    alike = load_mesh(both(_glb(tmp_path / "alike.glb", **images), base, base))
    with pytest.warns(UserWarning, match="the normal map is misplaced"):
        differ = load_mesh(both(_glb(tmp_path / "differ.glb", **images), base, _transform(scale=(16.0, 16.0))))
    np.testing.assert_allclose(differ.uvs, alike.uvs)
    assert not np.allclose(differ.uvs, QUAD_UVS[QUAD_FACES.ravel()])

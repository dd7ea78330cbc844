"""OBJ and MTL text that trimesh misread, read as the file means (`neuralrt.geometry.obj_files`):
relative face indices, comments after values, byte-order marks, one-value colours, several
MTL files, map options, and texture names spelt as another system spells them."""

import re

import numpy as np
import pytest

from neuralrt.geometry.mesh import load_mesh
from neuralrt.geometry.obj_files import clean_obj_text
from neuralrt.io.images import srgb_to_linear

BOM = "\ufeff"


def _write(folder, obj, mtl=None, mtl_name="m.mtl"):
    if mtl is not None:
        (folder / mtl_name).write_text(mtl, encoding="utf-8")
    (folder / "m.obj").write_text(obj, encoding="utf-8")
    return folder / "m.obj"


def test_relative_indices_count_back_from_the_last_vertex_read(tmp_path):
    # (trimesh counted them from the end of the file: object A vanished, B was there twice)
    obj = "o A\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf -3/-1 -2/-1 -1/-1\no B\nv 10 0 0\nv 11 0 0\nv 10 1 0\nf -3 -2 -1\n"
    mesh = load_mesh(_write(tmp_path, obj))
    np.testing.assert_array_equal(np.sort(mesh.triangles()[:, :, 0].ravel()), [0, 0, 1, 10, 10, 11])


@pytest.mark.parametrize("obj", [
    f"{BOM}v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",  # a BOM before the first statement (an IndexError)
    "v 0 0 0 # origin\nv 1 0 0\nv 0 1 0\nf 1 2 3   # the one face\n",  # comments after values (a ValueError)
])
def test_a_bom_or_comments_after_values_read_as_without(tmp_path, obj):
    mesh = load_mesh(_write(tmp_path, obj))
    np.testing.assert_array_equal(mesh.triangles()[0], [[0, 0, 0], [1, 0, 0], [0, 1, 0]])


_QUAD = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"


@pytest.mark.parametrize("mtl", [
    "newmtl grey\nKd 0.5 0.5 0.5 # mid grey\n",  # (was trimesh's placeholder grey 0.133, no warning)
    f"{BOM}newmtl grey\nKd 0.5 0.5 0.5\n",  # (was white, the material renamed material0, no warning)
    "newmtl grey\nKd 0.5\n",  # one value for all three, as the MTL spec allows (the file was dropped)
])
def test_mtl_colours_read_as_the_file_means(tmp_path, mtl):
    mesh = load_mesh(_write(tmp_path, "mtllib m.mtl\n" + _QUAD + "usemtl grey\nf 1/1 2/2 3/3\n", mtl))
    assert [m.name for m in mesh.materials] == ["grey"]
    np.testing.assert_allclose(mesh.materials[0].base_color, srgb_to_linear(np.full(3, 0.5, np.float32)), rtol=1e-6)


def test_several_mtl_files_on_one_mtllib_line_are_all_read(tmp_path):
    (tmp_path / "a.mtl").write_text("newmtl red\nKd 1 0 0\n")
    (tmp_path / "b.mtl").write_text("newmtl blue\nKd 0 0 1\n")
    mesh = load_mesh(_write(tmp_path, "mtllib a.mtl b.mtl\n" + _QUAD + "usemtl red\nf 1 2 3\nusemtl blue\nf 1 3 4\n"))
    colours = {m.name: m.base_color.tolist() for m in mesh.materials}
    assert colours == {"red": [1, 0, 0], "blue": [0, 0, 1]}


def _textured(folder, statement, image_path="tex.png"):
    from PIL import Image

    (folder / image_path).parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (2, 2), (255, 0, 0)).save(folder / image_path)
    return _write(folder, "mtllib m.mtl\n" + _QUAD + "usemtl paint\nf 1/1 2/2 3/3\n", f"newmtl paint\nKd 1 1 1\n{statement}\n")


@pytest.mark.parametrize("statement, image_path", [
    ("map_Kd -s 1 1 1 -o 0 0 0 -bm 1 tex.png", "tex.png"),  # default options, as exporters write them
    ("map_Kd textures\\red.png", "textures/red.png"),  # a Windows path
    ("map_Kd TEX.PNG", "tex.png"),  # another letter case (a file system that ignores case)
    ("map_Kd C:\\Users\\artist\\tex.png", "tex.png"),  # a Windows absolute path: the file beside the mesh
])
def test_a_texture_is_found_as_the_file_means_it(tmp_path, statement, image_path):
    mesh = load_mesh(_textured(tmp_path, statement, image_path))
    np.testing.assert_allclose(mesh.materials[0].texture[0, 0], [1, 0, 0])


def test_a_texture_whose_options_move_its_uvs_is_left_out_with_a_warning(tmp_path):
    with pytest.warns(UserWarning, match=re.escape("m.obj: the texture of material 'paint' is left out: its statement "
                                                   "map_Kd moves or scales the map's UVs (-s 2 2)")):
        mesh = load_mesh(_textured(tmp_path, "map_Kd -s 2 2 tex.png"))
    assert mesh.materials[0].texture is None


def test_ordinary_obj_text_is_read_as_it_is():
    assert clean_obj_text(b"# exported\nv -1 -2 -3\nv 1 0 0\nv 0 1 0\nvn 0 0 -1\nf 1//1 2//1 3//1\n") is None


def test_a_hash_inside_a_name_is_part_of_the_name(tmp_path):
    # Only a "#" after a space or tab starts a comment: "lib#a.mtl", "paint#1" and "tex#1.png"
    # were cut at it (the material file and texture not found); "####" header lines are comments.
    from PIL import Image

    Image.new("RGB", (2, 2), (255, 0, 0)).save(tmp_path / "tex#1.png")
    (tmp_path / "lib#a.mtl").write_text("newmtl paint#1\nKd 0 0 1 # blue\nnewmtl tex#1\nKd 1 1 1\nmap_Kd tex#1.png\n")
    obj = "#### exported\nmtllib lib#a.mtl\n" + _QUAD + "usemtl paint#1\nf 1/1 2/2 3/3\nusemtl tex#1\nf 1/1 3/3 4/4\n"
    mesh = load_mesh(_write(tmp_path, obj))
    by_name = {m.name: m for m in mesh.materials}
    assert set(by_name) == {"paint#1", "tex#1"}
    np.testing.assert_allclose(by_name["paint#1"].base_color, [0, 0, 1])
    np.testing.assert_allclose(by_name["tex#1"].texture[0, 0], [1, 0, 0])
    assert clean_obj_text(b"####\n# header\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n") is None  # (read as it is: fast)


def test_a_bom_in_any_of_several_mtl_files_is_no_statement(tmp_path):
    # (the second file's BOM glued "newmtl blue" to its mark: red took blue's colour, blue was white)
    (tmp_path / "a.mtl").write_text("newmtl red\nKd 1 0 0\n", encoding="utf-8")
    (tmp_path / "b.mtl").write_text(f"{BOM}newmtl blue\nKd 0 0 1\n", encoding="utf-8")
    mesh = load_mesh(_write(tmp_path, "mtllib a.mtl b.mtl\n" + _QUAD + "usemtl red\nf 1 2 3\nusemtl blue\nf 1 3 4\n"))
    assert {m.name: m.base_color.tolist() for m in mesh.materials} == {"red": [1, 0, 0], "blue": [0, 0, 1]}


def test_relative_indices_on_a_continued_line_count_from_where_the_face_is(tmp_path):
    obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 \\\n-1\nv 5 5 5\nv 6 5 5\nv 5 6 5\nf -3 -2 -1\n"
    np.testing.assert_array_equal(load_mesh(_write(tmp_path, obj)).faces, [[0, 1, 2], [3, 4, 5]])


@pytest.mark.parametrize("statement, why", [
    ("norm -bm nan n.png", "has -bm nan: not a finite number"),
    ("map_Bump -imfchan r n.png", "reads one channel (-imfchan r)"),
])
def test_odd_map_options_are_named(tmp_path, statement, why):
    from PIL import Image

    Image.new("RGB", (2, 2), (128, 128, 255)).save(tmp_path / "n.png")
    path = _write(tmp_path, "mtllib m.mtl\n" + _QUAD + "usemtl paint\nf 1/1 2/2 3/3\n", f"newmtl paint\n{statement}\n")
    with pytest.warns(UserWarning, match=re.escape(why)):
        load_mesh(path)


def test_imfchan_on_a_colour_map_is_ignored(tmp_path):
    mesh = load_mesh(_textured(tmp_path, "map_Kd -imfchan r tex.png"))
    np.testing.assert_allclose(mesh.materials[0].texture[0, 0], [1, 0, 0])


def test_a_usemtl_naming_no_material_is_a_warning(tmp_path):
    # (its faces rendered white without a word; a material file that cannot be read was warned already)
    path = _write(tmp_path, "mtllib m.mtl\n" + _QUAD + "usemtl Typo\nf 1 2 3\nusemtl grey\nf 1 3 4\n",
                  "newmtl grey\nKd 0.5 0.5 0.5\n")
    with pytest.warns(UserWarning, match=re.escape("m.obj: usemtl 'Typo' names no material of its material file(s)")):
        load_mesh(path)
    import warnings

    (tmp_path / "m.mtl").unlink()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_mesh(path)
    assert [str(w.message).split(": ", 1)[1] for w in caught] == [
        "material file m.mtl could not be read; its faces render white"]


@pytest.mark.parametrize("order, normal_z", [("1 2 3 4 5 6", 1.0), ("6 5 4 3 2 1", -1.0), ("-6 -5 -4 -3 -2 -1", 1.0)])
def test_a_concave_polygon_is_split_inside_it_and_keeps_its_side(tmp_path, order, normal_z):
    # An L of area 3 whose first corner is next to its reflex corner: trimesh's fan covered the
    # notch (area 4). Ear clipping keeps to the polygon, wound as the file winds it.
    obj = "v 2 1 0\nv 1 1 0\nv 1 2 0\nv 0 2 0\nv 0 0 0\nv 2 0 0\n" + f"f {order}\n"
    mesh = load_mesh(_write(tmp_path, obj))
    assert mesh.num_triangles == 4
    assert mesh.face_areas().sum() == pytest.approx(3.0)
    np.testing.assert_allclose(mesh.face_normals()[:, 2], normal_z)
    centroids = mesh.triangles().mean(axis=1)
    assert not ((centroids[:, 0] > 1) & (centroids[:, 1] > 1)).any()  # nothing in the notch


def test_relative_indices_after_an_absolute_one_are_found_too(tmp_path):
    # (only faces whose first index was relative were rewritten: "f 1 -2 -1" was counted from the file's end)
    obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 -2 -1\nv 5 5 5\nv 6 5 5\nv 5 6 5\nf 4 -2 -1\n"
    np.testing.assert_array_equal(load_mesh(_write(tmp_path, obj)).faces, [[0, 1, 2], [3, 4, 5]])


def _coloured_grid(materials: bool, uvs: bool) -> tuple[str, dict]:
    """A 4x4 grid of vertices whose colour follows its position (so a colour found on a loaded
    vertex says whether it came from that vertex), two material groups, optional UVs and normals."""
    lines, colour_at = [], {}
    for j in range(4):
        for i in range(4):
            rgb = (i / 3, j / 3, 0.25 + 0.25 * ((i + j) % 3))
            colour_at[(float(i), float(j))] = rgb
            lines.append(f"v {i} {j} 0 {rgb[0]:.6f} {rgb[1]:.6f} {rgb[2]:.6f}")
            lines.append(f"vt {i / 3} {j / 3}")  # (one per vertex; with UVs and normals trimesh unmerges)
    lines.append("vn 0 0 1")
    faces = []
    for j in range(3):
        for i in range(3):
            a, b, c, d = (j * 4 + i + 1, j * 4 + i + 2, (j + 1) * 4 + i + 2, (j + 1) * 4 + i + 1)
            corner = "{0}/{0}/1" if uvs else "{0}"
            faces.append((j, [" ".join(["f", *(corner.format(k) for k in tri)]) for tri in ((a, b, c), (a, c, d))]))
    for group in (0, 1):
        if materials:
            lines.append(f"usemtl {'red' if group == 0 else 'blue'}")
        lines += [f for j, pair in faces if (j == 0) == (group == 0) for f in pair]
    return ("mtllib m.mtl\n" if materials else "") + "\n".join(lines) + "\n", colour_at


@pytest.mark.parametrize("uvs", [False, True])
def test_vertex_colours_beside_materials_are_kept(tmp_path, uvs):
    """``v x y z r g b`` in a file with materials (a coloured scan as MeshLab writes it): trimesh
    dropped the colours of every part with a material; each vertex now keeps its own, as without."""
    text, colour_at = _coloured_grid(materials=True, uvs=uvs)
    mesh = load_mesh(_write(tmp_path, text, mtl="newmtl red\nKd 1 0 0\n\nnewmtl blue\nKd 0 0 1\n"))
    assert sorted(m.name for m in mesh.materials) == ["blue", "red"] and mesh.num_triangles == 18
    assert mesh.vertex_colors is not None
    expected = np.array([colour_at[(float(x), float(y))] for x, y, _ in mesh.vertices], np.float32)
    np.testing.assert_allclose(mesh.vertex_colors, srgb_to_linear(np.round(expected * 255) / 255), atol=1e-6)
    plain_text, _ = _coloured_grid(materials=False, uvs=uvs)
    (tmp_path / "plain").mkdir()
    plain = load_mesh(_write(tmp_path / "plain", plain_text))
    by_position = {tuple(v): c for v, c in zip(plain.vertices.tolist(), plain.vertex_colors.tolist())}
    assert all(by_position[tuple(v)] == c for v, c in zip(mesh.vertices.tolist(), mesh.vertex_colors.tolist()))


def test_a_file_without_vertex_colours_is_parsed_once(tmp_path, monkeypatch):
    import trimesh.exchange.obj

    def no_second_parse(*args, **kwargs):
        raise AssertionError("parsed again")

    monkeypatch.setattr(trimesh.exchange.obj, "load_obj", no_second_parse)  # (trimesh.load holds its own reference)
    text, _ = _coloured_grid(materials=True, uvs=True)
    text = re.sub(r"(?m)^(v \S+ \S+ \S+) .*$", r"\1", text)
    mesh = load_mesh(_write(tmp_path, text, mtl="newmtl red\nKd 1 0 0\n\nnewmtl blue\nKd 0 0 1\n"))
    assert mesh.vertex_colors is None and len(mesh.materials) == 2

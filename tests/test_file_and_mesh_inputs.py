"""Files, signals and meshes as a new user brings them (found by two trials): a full disk, SIGTERM,
symlinked outputs, names too long for the filesystem, corrupted cached models, UV meshes without
materials, attribute arrays of the wrong shape, meshes float32 cannot trace, a needle's surface pool."""

import os
import re
import signal
import time

import numpy as np
import pytest
import torch

from neuralrt import api, cli
from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.errors import ConfigError, MeshError, NeuralRTError
from neuralrt.geometry.mesh import Mesh, load_mesh
from neuralrt.geometry.procedural import sphere
from neuralrt.io.files import check_output_file, write_atomically
from neuralrt.methods.lsnif import LSNIFModel
from neuralrt.methods.lsnif_config import LSNIFConfig
from neuralrt.scene.loader import load_scene


# -- writing files --------------------------------------------------------------------------------


def test_writing_through_a_symlink_writes_its_target(tmp_path):
    (tmp_path / "real").mkdir()
    link = tmp_path / "link.txt"
    link.symlink_to(tmp_path / "real" / "target.txt")  # dangling until written
    write_atomically(link, lambda tmp: open(tmp, "w").write("data"))
    assert link.is_symlink() and (tmp_path / "real" / "target.txt").read_text() == "data"


def test_a_name_too_long_with_its_temporary_sibling_is_refused_up_front(tmp_path):
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    fits_alone = "m" * (limit - 8) + ".nrt"  # fits, but not as `.NAME.xxxxxxxx.tmp.nrt`
    with pytest.raises(NeuralRTError, match=r"name is too long"):
        check_output_file(tmp_path / fits_alone, "model file")
    check_output_file(tmp_path / "short.nrt", "model file")


def test_a_full_disk_is_an_oserror_naming_the_model_file(tmp_path, monkeypatch):
    from safetensors import SafetensorError

    import safetensors.torch

    def full(*args, **kwargs):
        raise SafetensorError("Error while serializing: I/O error: No space left on device (os error 28)")

    monkeypatch.setattr(safetensors.torch, "save_file", full)
    model = LSNIFModel.from_mesh(sphere(1), LSNIFConfig.preset("lq"))
    with pytest.raises(OSError) as info:
        model.save(tmp_path / "m.nrt")
    assert info.value.filename == str(tmp_path / "m.nrt") and "No space left on device" in info.value.strerror
    assert list(tmp_path.iterdir()) == []  # no temporary file left


def test_a_final_checkpoint_that_cannot_be_written_keeps_the_model(tmp_path, monkeypatch):
    from neuralrt.training import trainer
    from neuralrt.training.api import train

    real = trainer.save_checkpoint

    def full_at_the_end(path, model, opt, sampler, step, record, identity, checkpoint_every):
        if step == 4:
            raise OSError(28, "No space left on device", str(path))
        real(path, model, opt, sampler, step, record, identity, checkpoint_every)

    monkeypatch.setattr(trainer, "save_checkpoint", full_at_the_end)
    config = LSNIFConfig.preset("lq").with_training(steps=4, batch_size=256)
    with pytest.warns(UserWarning, match="the final checkpoint could not be written .*training goes on to write the model"):
        model = train(sphere(1), config, progress=False, checkpoint=tmp_path / "m.nrt.ckpt")
    assert model.training_record["steps"] == 4


def test_sigterm_stops_a_command_as_ctrl_c_does(tmp_path, monkeypatch, capsys):
    mesh = tmp_path / "ball.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    stale = tmp_path / "m.nrt.ckpt"
    stale.write_bytes(b"an earlier run's")

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler interrupts this
        raise AssertionError("SIGTERM did not stop the command")

    monkeypatch.setattr(api, "train", terminated)
    previous = signal.getsignal(signal.SIGTERM)
    assert cli.main(["train", str(mesh), "-o", str(tmp_path / "m.nrt"), "--quiet"]) == 128 + signal.SIGTERM
    err = capsys.readouterr().err
    # The checkpoint there is an earlier run's: the hint must not send the user to --resume it.
    assert err.strip() == "neuralrt: terminated (no checkpoint was written yet: run the command again to start over)"
    assert signal.getsignal(signal.SIGTERM) == previous


def test_ctrl_c_while_the_command_imports_torch_is_one_line(monkeypatch, capsys):
    """The console script imports the CLI inside `neuralrt.launch.main`: a Ctrl-C in torch's ~1 s
    import was a traceback from inside torch."""
    import builtins

    from neuralrt import launch

    real_import = builtins.__import__

    def interrupted(name, *args, **kwargs):
        if name == "cli":
            raise KeyboardInterrupt
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", interrupted)
    assert launch.main() == 130
    assert capsys.readouterr().err == "neuralrt: interrupted\n"


def test_importing_the_package_imports_no_torch():
    """What the command's Ctrl-C cover relies on (and a cheap `import neuralrt`)."""
    import subprocess
    import sys

    code = "import sys, neuralrt; print('torch' in sys.modules, neuralrt.Rays.__name__, 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "Rays", "True"]


# -- converted scenes -----------------------------------------------------------------------------


def test_a_corrupted_cached_model_is_not_reused(tmp_path):
    from neuralrt.scene.convert import cached_model_is_valid

    config = LSNIFConfig.preset("lq")
    mesh = sphere(1)
    path = LSNIFModel.from_mesh(mesh, config).save(tmp_path / "m.nrt")
    assert cached_model_is_valid(path, mesh.content_hash(), config)
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF  # inside the arrays: the header still reads
    path.write_bytes(bytes(data))
    assert not cached_model_is_valid(path, mesh.content_hash(), config)


def test_the_group_round_trip_uses_a_private_folder(tmp_path):
    from neuralrt.scene.convert import _obj_round_trip

    again = _obj_round_trip(sphere(1), tmp_path)
    assert again.num_triangles == sphere(1).num_triangles and list(tmp_path.iterdir()) == []


# -- meshes -----------------------------------------------------------------------------------------


def test_uvs_without_a_material_are_white_not_trimesh_grey(tmp_path):
    (tmp_path / "uv.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nf 1/1 2/2 3/3\n")
    material = load_mesh(tmp_path / "uv.obj").materials[0]
    assert material.texture is None and np.array_equal(material.base_color, np.ones(3, np.float32))


@pytest.mark.parametrize("kwargs,message", [
    ({"vertex_colors": np.ones((1, 3))}, r"vertex_colors must have shape \[12, 3\] \(one per vertex\), got \[1, 3\]"),
    ({"uvs": np.zeros((12, 3))}, r"uvs must have shape \[12, 2\]"),
    ({"vertex_normals": np.ones((5, 3))}, r"vertex_normals must have shape \[12, 3\]"),
    # (NaN colours rendered black and stopped training as a diverged loss; NaN UVs and normals passed too)
    ({"vertex_colors": np.where(np.arange(12)[:, None] < 2, np.nan, 0.5) * np.ones(3)}, r"^mesh: vertex_colors of 2 vertices are NaN or infinite$"),
    ({"uvs": np.full((12, 2), np.inf)}, r"uvs of 12 vertices are NaN or infinite"),
    ({"vertex_normals": np.full((12, 3), np.nan)}, r"vertex_normals of 12 vertices are NaN or infinite"),
])
def test_per_vertex_arrays_must_match_the_vertices(kwargs, message):
    ball = sphere(0)
    with pytest.raises(MeshError, match=message):
        Mesh(ball.vertices, ball.faces, **kwargs)


@pytest.mark.parametrize("faces,message", [
    ([[0, 1, 2**33 + 2]], "face indices out of range"),  # int32 would wrap it to 2
    ([[0.5, 1, 2]], "face indices must be whole numbers"),
    ([["a", 1, 2]], "face indices must be whole numbers"),
])
def test_face_indices_are_not_silently_changed(faces, message):
    with pytest.raises(MeshError, match=message):
        Mesh(np.eye(3), np.array(faces))
    assert Mesh(np.eye(3), np.array([[0.0, 1.0, 2.0]])).faces.tolist() == [[0, 1, 2]]  # whole floats are indices


def test_meshblas_refuses_a_mesh_float32_cannot_trace():
    ball = sphere(1)
    with pytest.raises(MeshError, match="bounding-box diagonal"):
        MeshBLAS(Mesh(ball.vertices.astype(np.float64) * 1e20, ball.faces))


def test_load_mesh_of_no_path_is_a_config_error():
    with pytest.raises(ConfigError, match="path: expected a path"):
        load_mesh(None)


def test_a_needle_fills_what_it_can_of_the_surface_pool_with_a_warning():
    from neuralrt.training.ray_distribution import BoxRayDistribution

    import trimesh

    needle = trimesh.creation.cylinder(radius=1e-3, height=10, sections=8)
    mesh = Mesh(np.asarray(needle.vertices), np.asarray(needle.faces), name="needle")
    with pytest.warns(UserWarning, match=r"needle: 64 x 65536 rays .* found [\d,]+ of 65,536 surface points"):
        rays = BoxRayDistribution(MeshBLAS(mesh), pool_size=1 << 16)
    assert 0 < len(rays.pool_points) < 1 << 16
    batch = rays.sample(512)
    assert torch.isfinite(batch.rays.origins).all()


def _glb(path, *meshes):
    import trimesh

    trimesh.Scene(list(meshes)).export(path)
    return path


def test_materials_of_one_name_but_different_colours_stay_apart(tmp_path):
    import trimesh
    from trimesh.visual.material import PBRMaterial

    red, blue = trimesh.creation.box(), trimesh.creation.box()
    blue.apply_translation([3, 0, 0])
    red.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(name="paint", baseColorFactor=[255, 0, 0, 255]))
    blue.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(name="paint", baseColorFactor=[0, 0, 255, 255]))
    mesh = load_mesh(_glb(tmp_path / "paint.glb", red, blue))
    colours = sorted(tuple(m.base_color.round(3)) for m in mesh.materials)
    assert colours == [(0.0, 0.0, 1.0), (1.0, 0.0, 0.0)] and sorted(set(mesh.face_material_ids.tolist())) == [0, 1]


def test_a_part_left_out_of_a_file_is_a_warning(tmp_path):
    import trimesh

    good, bad = trimesh.creation.box(), trimesh.creation.icosphere(1)
    vertices = bad.vertices.copy()
    vertices[0] = np.nan
    bad = trimesh.Trimesh(vertices, bad.faces, process=False)
    with pytest.warns(UserWarning, match=r"part \d of 2 \(node 'geometry_\d'\) is left out \(1 vertices have NaN or Inf coordinates \(in float32, where beyond 3.4e38 is Inf\)\)"):
        mesh = load_mesh(_glb(tmp_path / "part.glb", good, bad))
    assert mesh.num_triangles == 12


def test_a_16_bit_grey_texture_keeps_its_gradient(tmp_path):
    from PIL import Image

    Image.fromarray(np.tile(np.linspace(0, 65535, 16), (16, 1)).astype(np.uint16)).save(tmp_path / "g16.png")
    (tmp_path / "t.mtl").write_text("newmtl tex\nKd 1 1 1\nmap_Kd g16.png\n")
    (tmp_path / "t.obj").write_text("mtllib t.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nusemtl tex\nf 1/1 2/2 3/3\n")
    row = load_mesh(tmp_path / "t.obj").materials[0].texture[0, :, 0]
    assert row[0] == 0 and row[-1] == pytest.approx(1.0) and np.all(np.diff(row) > 0)  # (was 0, then all 1)


def test_per_face_colours_are_kept_exactly(tmp_path):
    import trimesh

    ball = trimesh.creation.icosphere(1)
    colours = np.zeros((len(ball.faces), 4), np.uint8)
    colours[:, 3], colours[::2, 0], colours[1::2, 2] = 255, 255, 255  # red and blue faces, alternating
    ball.visual.face_colors = colours
    ball.export(tmp_path / "faces.ply")
    mesh = load_mesh(tmp_path / "faces.ply")  # (were dropped: every face white)
    assert mesh.num_triangles == len(ball.faces) and len(mesh.vertices) == 3 * len(ball.faces)
    per_face = mesh.vertex_colors[mesh.faces[:, 0]]
    assert np.array_equal(per_face[::2], np.tile([1, 0, 0], (len(per_face[::2]), 1)))
    assert np.array_equal(per_face[1::2], np.tile([0, 0, 1], (len(per_face[1::2]), 1)))
    assert np.allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1, atol=1e-5)  # smooth normals, per corner


_TRIANGLE_OBJ = "v 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nusemtl tex\nf 1/1 2/2 3/3\n"


def test_a_missing_texture_or_material_file_is_a_warning(tmp_path):
    """trimesh drops them with a debug line: the mesh rendered white with no word why."""
    import logging

    (tmp_path / "t.mtl").write_text("newmtl tex\nKd 1 1 1\nmap_Kd gone.png\n")
    (tmp_path / "t.obj").write_text("mtllib t.mtl\n" + _TRIANGLE_OBJ)
    (tmp_path / "n.obj").write_text("mtllib gone.mtl\n" + _TRIANGLE_OBJ)
    logger = logging.getLogger("trimesh.util")
    level, filters = logger.level, list(logger.filters)
    with pytest.warns(UserWarning, match=r"t\.obj: a texture could not be read \(FileNotFoundError: gone\.png\)"):
        assert load_mesh(tmp_path / "t.obj").materials[0].texture is None
    with pytest.warns(UserWarning, match=r"n\.obj: material file gone\.mtl could not be read; its faces render white"):
        load_mesh(tmp_path / "n.obj")
    assert (logger.level, logger.filters) == (level, filters)  # trimesh's logger as it was
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from PIL import Image

        Image.new("RGB", (2, 2), (255, 0, 0)).save(tmp_path / "gone.png")
        assert load_mesh(tmp_path / "t.obj").materials[0].texture is not None  # no warning when it is there


def test_a_material_file_or_texture_that_is_a_fifo_is_a_warning_not_a_hang(tmp_path):
    # Opening the FIFO blocked every command for ever (mtllib, or map_Kd).
    import os
    import threading

    os.mkfifo(tmp_path / "pipe")
    (tmp_path / "m.obj").write_text("mtllib pipe\n" + _TRIANGLE_OBJ)
    (tmp_path / "t.mtl").write_text("newmtl tex\nKd 1 1 1\nmap_Kd pipe\n")
    (tmp_path / "t.obj").write_text("mtllib t.mtl\n" + _TRIANGLE_OBJ)
    caught = []

    def load_both():
        import warnings

        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            caught.extend([load_mesh(tmp_path / "m.obj"), load_mesh(tmp_path / "t.obj")])
        caught.extend(str(w.message) for w in seen)

    loader = threading.Thread(target=load_both, daemon=True)
    loader.start()
    loader.join(60)
    assert not loader.is_alive(), "load_mesh blocked on a FIFO"
    assert any("m.obj: material file pipe could not be read" in m for m in caught[2:])
    assert any("t.obj: a texture could not be read (OSError: pipe is not a regular file)" in m for m in caught[2:])


def test_a_texture_that_cannot_be_decoded_is_a_warning_naming_it(tmp_path):
    # trimesh decodes textures lazily, in neuralrt's code: a PNG whose data ends early was a bare
    # OSError traceback (and one too large for memory an allocator's traceback).
    from PIL import Image

    Image.new("RGB", (64, 64), (200, 10, 10)).save(tmp_path / "cut.png")
    data = (tmp_path / "cut.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    (tmp_path / "t.mtl").write_text("newmtl tex\nKd 1 1 1\nmap_Kd cut.png\n")
    (tmp_path / "t.obj").write_text("mtllib t.mtl\n" + _TRIANGLE_OBJ)
    with pytest.warns(UserWarning, match=r"t\.obj: the 64x64 texture of material 'tex' could not be decoded \(OSError: .*\); "
                                          r"its material renders with its base colour"):
        assert load_mesh(tmp_path / "t.obj").materials[0].texture is None


def test_a_texture_larger_than_the_memory_left_is_a_warning_not_an_allocation(tmp_path, monkeypatch):
    import neuralrt.devices
    from PIL import Image

    Image.new("RGB", (8, 8), (200, 10, 10)).save(tmp_path / "t.png")
    (tmp_path / "t.mtl").write_text("newmtl tex\nKd 1 1 1\nmap_Kd t.png\n")
    (tmp_path / "t.obj").write_text("mtllib t.mtl\n" + _TRIANGLE_OBJ)
    monkeypatch.setattr(neuralrt.devices, "available_bytes", lambda device: 1000)  # 8x8 pixels need 2,304 bytes
    with pytest.warns(UserWarning, match=r"the 8x8 texture of material 'tex' could not be decoded \(decoding it needs 2 KiB "
                                          r"of memory, 1 KiB is available on cpu\)"):
        assert load_mesh(tmp_path / "t.obj").materials[0].texture is None


def test_ctrl_c_while_trimesh_reads_a_material_file_stops_the_load(tmp_path, monkeypatch):
    # trimesh catches BaseException around the MTL and logs it: a SIGTERM became a warning.
    from neuralrt.geometry import mesh as mesh_module

    real = mesh_module.regular_files_resolver

    def interrupted(path):
        resolver = real(path)
        resolver.get = lambda name: (_ for _ in ()).throw(KeyboardInterrupt())
        return resolver

    monkeypatch.setattr(mesh_module, "regular_files_resolver", interrupted)
    (tmp_path / "t.mtl").write_text("newmtl tex\nKd 1 1 1\n")
    (tmp_path / "t.obj").write_text("mtllib t.mtl\n" + _TRIANGLE_OBJ)
    with pytest.raises(KeyboardInterrupt):
        load_mesh(tmp_path / "t.obj")


def test_gltf_colours_follow_the_gltf_spec(tmp_path):
    """baseColorFactor is linear and white when absent; the texture is sRGB, multiplied by it (trimesh's
    to_simple read the factor as sRGB, and an absent one as its 0.4 grey)."""
    import trimesh
    from PIL import Image
    from trimesh.visual.material import PBRMaterial

    half, plain, textured = (trimesh.creation.box() for _ in range(3))
    plain.apply_translation([3, 0, 0])
    textured.apply_translation([6, 0, 0])
    half.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(name="half", baseColorFactor=[0.5, 0.5, 0.5, 1.0]))
    plain.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(name="plain"))
    texture = Image.new("RGB", (2, 2), (255, 255, 255))
    textured.visual = trimesh.visual.TextureVisuals(
        uv=np.full((len(textured.vertices), 2), 0.5),
        material=PBRMaterial(name="tex", baseColorFactor=[0.25, 0.5, 1.0, 1.0], baseColorTexture=texture))
    mesh = load_mesh(_glb(tmp_path / "pbr.glb", half, plain, textured))
    by_name = {m.name: m for m in mesh.materials}
    assert np.allclose(by_name["half"].base_color, 0.5, atol=2 / 255) and by_name["half"].texture is None
    assert np.array_equal(by_name["plain"].base_color, [1, 1, 1])
    assert np.allclose(by_name["tex"].texture[0, 0], [0.25, 0.5, 1.0], atol=2 / 255)


def test_gltf_vertex_colours_are_linear_and_kept_beside_a_material(tmp_path):
    """COLOR_0 is linear (glTF spec) and multiplies the base colour: it was decoded as sRGB (128 ->
    0.216), and dropped where the primitive has a material (trimesh keeps it in the visual's
    vertex_attributes, which Scene.dump's copies lose)."""
    import trimesh
    from trimesh.visual.material import PBRMaterial

    grey = np.array([[128, 128, 128, 255]] * 8, np.uint8)
    bare, painted = trimesh.creation.box(), trimesh.creation.box()
    bare.visual = trimesh.visual.ColorVisuals(bare, vertex_colors=grey)
    painted.apply_translation([3, 0, 0])
    painted.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(name="half", baseColorFactor=[0.5, 0.5, 0.5, 1.0]))
    painted.visual.vertex_attributes["color"] = grey
    for mesh in (bare, painted):
        loaded = load_mesh(_glb(tmp_path / "coloured.glb", mesh))
        np.testing.assert_allclose(loaded.vertex_colors, 128 / 255, atol=1e-6)
        assert api.info(tmp_path / "coloured.glb")["vertex_colors"] is True
    from neuralrt.rays import Rays

    rays = Rays(torch.tensor([[3.0, 0.0, 4.0]]), torch.tensor([[0.0, 0.0, -1.0]]))
    assert MeshBLAS(loaded).intersect(rays).albedo[0, 0].item() == pytest.approx(0.5 * 128 / 255, abs=2 / 255)


@pytest.mark.parametrize("kind", ["glb", "obj"])
def test_the_files_normals_are_kept_in_every_part(tmp_path, kind):
    """A glTF (always a trimesh Scene) or an OBJ of two materials (a Scene of two parts): the file's
    tilted normals were replaced by computed ones (Scene.dump's copies drop trimesh's cache); a
    glTF node's rotation turns them."""
    import trimesh
    from trimesh.visual.material import PBRMaterial

    tilted, turned = (0.6, 0.0, 0.8), (0.0, 0.6, 0.8)  # turned: tilted, rotated 90 degrees about z
    corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    if kind == "glb":
        scene = trimesh.Scene()
        for k in range(2):
            quad = trimesh.Trimesh(corners + [3 * k, 0, 0], [[0, 1, 2], [0, 2, 3]], vertex_normals=np.tile(tilted, (4, 1)),
                                   process=False)
            quad.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(name=f"m{k}"))
            scene.add_geometry(quad, transform=trimesh.transformations.rotation_matrix(np.pi / 2 * k, [0, 0, 1]))
        scene.export(tmp_path / "quads.glb")
        loaded, expected = load_mesh(tmp_path / "quads.glb"), {tilted, turned}
    else:
        (tmp_path / "quads.mtl").write_text("newmtl m0\nKd 1 1 1\nnewmtl m1\nKd 1 0 0\n")
        lines = ["mtllib quads.mtl"] + [f"v {x} {y} {z}" for x, y, z in corners] + ["vn 0.6 0 0.8"]
        lines += ["usemtl m0", "f 1//1 2//1 3//1", "usemtl m1", "f 1//1 3//1 4//1"]
        (tmp_path / "quads.obj").write_text("\n".join(lines) + "\n")
        loaded, expected = load_mesh(tmp_path / "quads.obj"), {tilted}
    assert len(loaded.materials) == 2
    assert {tuple(round(float(x), 5) for x in n) for n in loaded.vertex_normals} == expected


def test_an_interrupt_during_trimeshs_import_is_raised_after_it(tmp_path, monkeypatch):
    """trimesh's optional imports catch BaseException: an interrupt inside them was swallowed (from
    any thread: masking the main thread let torch's threads take it)."""
    import sys

    from neuralrt.geometry.mesh import import_trimesh

    (tmp_path / "trimesh.py").write_text(
        "import signal\ntry:\n    signal.raise_signal(signal.SIGINT)\n    reached = True\nexcept BaseException:\n"
        "    reached = False  # (swallowed, as trimesh's optional imports do)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(sys.modules, "trimesh", sys.modules.get("trimesh"))  # (restored, or removed, afterwards)
    del sys.modules["trimesh"]
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # (Python's: an earlier test may have set another)
    try:
        with pytest.raises(KeyboardInterrupt):
            import_trimesh()
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # (the handler is back)
    finally:
        signal.signal(signal.SIGINT, before)
    fake = sys.modules["trimesh"]
    assert fake.__file__ == str(tmp_path / "trimesh.py") and fake.reached  # (the import ran through, uninterrupted)


def _cut(path, fraction=0.6):
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * fraction)])


@pytest.mark.parametrize("name,export,declared", [
    ("m.ply", {"encoding": "ascii"}, r"its header declares 162 vertices and 320 faces, 162 and \d+ were read"),
    # (the ASCII reader loaded what precedes the cut, with no word)
    ("m.stl", {}, r"its header declares 320 triangles \(16084 bytes\), the file has 9650 bytes"),
    # (binary STL: loaded nothing, "no triangles", not why)
])
def test_a_mesh_file_cut_short_is_one_line_naming_the_counts(tmp_path, capsys, name, export, declared):
    import trimesh

    path = tmp_path / name
    trimesh.creation.icosphere(2).export(str(path), **export)
    assert load_mesh(path).num_triangles == 320  # whole, it loads
    _cut(path)
    with pytest.raises(MeshError, match="file is truncated or malformed: " + declared):
        load_mesh(path)
    assert cli.main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"neuralrt: error: {path}: file is truncated")


def test_a_header_that_claims_more_faces_than_the_file_holds(tmp_path):
    off = tmp_path / "m.off"
    off.write_text("OFF\n# a comment\n3 1000000000000 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(MeshError, match="declares 3 vertices and 1000000000000 faces, 3 and 1 were read"):
        load_mesh(off)
    # a polygon is read as several triangles: more faces than declared is a whole file
    quad = tmp_path / "q.ply"
    quad.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
                    "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    assert load_mesh(quad).num_triangles == 2


def test_a_ply_cut_inside_its_last_record_is_truncated(tmp_path):
    ply = tmp_path / "m.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
                   "0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n3 0 2")  # the last face lost its last corner
    with pytest.raises(MeshError, match="declares 4 vertices and 2 faces, 4 and 1 were read"):
        load_mesh(ply)


@pytest.mark.parametrize("prefix, keyword", [(b"", b"SOLID"), (b"\xef\xbb\xbf", b"solid")])
def test_an_ascii_stl_is_not_read_as_a_binary_count(tmp_path, prefix, keyword):
    # Upper-case keywords and a byte order mark made its first bytes a huge "triangle count" (the re-trial).
    facet = b"facet normal 0 0 1\n outer loop\n  vertex 0 0 0\n  vertex 1 0 0\n  vertex 0 1 0\n endloop\nendfacet\n"
    path = tmp_path / "m.stl"
    path.write_bytes(prefix + keyword + b" part\n" + facet.upper() + b"ENDSOLID part\n")
    assert load_mesh(path).num_triangles == 1


def test_a_whole_file_with_faces_that_are_not_triangles_is_not_called_truncated(tmp_path):
    # The reader leaves out a face of two corners; the file holds every record it declares.
    ply = tmp_path / "m.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
                   "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n2 0 1\n")
    off = tmp_path / "m.off"
    off.write_text("OFF\n# a comment\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n2 0 1\n")
    assert load_mesh(ply).num_triangles == 1 and load_mesh(off).num_triangles == 1


_OFF_QUAD = "0 0 0{}\n1 0 0{}\n1 1 0{}\n0 1 0{}\n"


@pytest.mark.parametrize("vertex, faces, expected", [
    (" 128 128 128 255", "3 0 1 2\n3 0 2 3\n", "vertex"),  # COFF: RGBA after each position, 0-255
    ("", "3 0 1 2 255 0 0\n3 0 2 3 0 0 255\n", "face"),  # a colour after each face's corners
    ("", "3 0 1 2 1.0 0.0 0.0 1.0\n3 0 2 3 0.0 0.0 1.0 1.0\n", "face"),  # the same as 0-1 floats
])
def test_off_colours_are_read(tmp_path, vertex, faces, expected):
    # (trimesh's OFF reader reads positions and faces only: a coloured OFF rendered white)
    from neuralrt.io.images import srgb_to_linear

    (tmp_path / "c.off").write_text(("COFF" if vertex else "OFF") + "\n4 2 0\n" + _OFF_QUAD.format(*[vertex] * 4) + faces)
    mesh = load_mesh(tmp_path / "c.off")
    if expected == "vertex":
        np.testing.assert_allclose(mesh.vertex_colors, srgb_to_linear(np.full((4, 3), 128 / 255, np.float32)), rtol=1e-6)
    else:  # per face, exactly: each face its own three vertices
        np.testing.assert_allclose(mesh.vertex_colors[mesh.faces[:, 0]], [[1, 0, 0], [0, 0, 1]], atol=1e-6)


def test_colours_a_reader_cannot_place_or_read_are_warnings(tmp_path):
    (tmp_path / "p.off").write_text("OFF\n4 1 0\n" + _OFF_QUAD.format(*[""] * 4) + "4 0 1 2 3 255 0 0\n")
    with pytest.warns(UserWarning, match="p.off: its face colours are not read: some faces are polygons"):
        assert load_mesh(tmp_path / "p.off").vertex_colors is None
    header = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar diffuse_red\nproperty uchar diffuse_green\nproperty uchar diffuse_blue\n"
              "element face 1\nproperty list uchar int vertex_indices\nend_header\n")
    (tmp_path / "d.ply").write_text(header + "0 0 0 255 0 0\n1 0 0 255 0 0\n0 1 0 255 0 0\n3 0 1 2\n")
    with pytest.warns(UserWarning, match=re.escape("d.ply: its vertex colours (diffuse_red, ...) are not read")):
        load_mesh(tmp_path / "d.ply")


def test_a_gltf_whose_json_is_cut_short_says_so(tmp_path):
    (tmp_path / "cut.gltf").write_text('{"asset": {"version": "2.0"}, "meshes": [')
    with pytest.raises(MeshError, match=r"cut.gltf: cannot read mesh: its glTF JSON cannot be read \(cut short, or not glTF\)"):
        load_mesh(tmp_path / "cut.gltf")


def test_rendering_a_mesh_too_large_for_float32_alone_names_the_mesh(tmp_path):
    from neuralrt.scene.loader import load_scene

    (tmp_path / "huge.obj").write_text("v 0 0 0\nv 1e30 0 0\nv 0 1e30 0\nf 1 2 3\n")
    with pytest.raises(NeuralRTError, match=r"huge.obj: bounding-box diagonal 1.41e\+30 is outside"):
        load_scene(str(tmp_path / "huge.obj"))


def test_a_loop_of_links_is_named_as_one(tmp_path):
    # (a mesh path in a scene that is a loop of links: Path.resolve raised "RuntimeError: Symlink loop")
    (tmp_path / "a.obj").symlink_to("b.obj")
    (tmp_path / "b.obj").symlink_to("a.obj")
    with pytest.raises(MeshError, match=r"a\.obj: a loop of symbolic links, not a mesh file"):
        load_mesh(tmp_path / "a.obj")
    scene = tmp_path / "s.toml"
    scene.write_text('[[objects]]\nmesh = "a.obj"\n')
    with pytest.raises(NeuralRTError, match=r"objects\.0\.mesh: .*a\.obj: a loop of symbolic links"):
        load_scene(scene)


def test_what_trimesh_logs_as_a_warning_is_one_line_not_a_traceback(tmp_path, capfd):
    # (Python's last-resort handler printed trimesh's "failed to extract face_normals" with a traceback)
    facet = "facet normal 0 0 {n}\nouter loop\nvertex 0 0 {z}\nvertex 1 0 {z}\nvertex 0 1 {z}\nendloop\nendfacet\n"
    path = tmp_path / "odd.stl"
    path.write_text("solid x\n" + facet.format(n=1, z=0) + facet.format(n="zz", z=1) + "endsolid x\n")
    with pytest.warns(UserWarning, match=r"odd\.stl: trimesh: failed to extract face_normals \(ValueError: "):
        mesh = load_mesh(path)
    assert mesh.num_triangles == 2 and "Traceback" not in capfd.readouterr().err


def test_a_file_a_mesh_names_outside_its_folder_is_refused_in_our_words(tmp_path):
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "mesh").mkdir()
    (tmp_path / "elsewhere" / "m.mtl").write_text("newmtl red\nKd 1 0 0\n")
    (tmp_path / "mesh" / "m.mtl").symlink_to(tmp_path / "elsewhere" / "m.mtl")
    (tmp_path / "mesh" / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl red\nf 1 2 3\n")
    with pytest.warns(UserWarning, match=r"material file m\.mtl could not be read \(OutsideFolderError: 'm\.mtl' leads "
                                         r"out of the folder of m\.obj \(a link elsewhere.*copy the file there\)"):
        load_mesh(tmp_path / "mesh" / "m.obj")
    import trimesh  # a .gltf whose .bin is a link out of its folder: said so, not "not a valid glTF file"

    files = trimesh.exchange.gltf.export_gltf(trimesh.creation.box())
    for name, data in files.items():
        (tmp_path / ("elsewhere" if name.endswith(".bin") else "mesh") / name).write_bytes(data)
    bin_name = next(name for name in files if name.endswith(".bin"))
    (tmp_path / "mesh" / bin_name).symlink_to(tmp_path / "elsewhere" / bin_name)
    with pytest.raises(MeshError, match=r"model\.gltf: cannot read mesh: '.*\.bin' leads out of the folder of model\.gltf"):
        load_mesh(tmp_path / "mesh" / "model.gltf")


def test_a_scene_file_that_is_not_utf8_names_its_line(tmp_path):
    path = tmp_path / "s.toml"
    path.write_bytes(b'[camera]\n# caf\xe9\n')
    with pytest.raises(NeuralRTError, match=r"s\.toml: not UTF-8 text \(byte 0xe9 on line 2\): scene files are UTF-8"):
        load_scene(path)

"""The CLI and the Python API mirror each other: every command on tiny inputs, JSON interfaces, errors."""

import json
import subprocess
import sys

import pytest
import trimesh

from neuralrt.cli import main


def _json(capsys) -> dict:
    return json.loads(capsys.readouterr().out)


def test_python_dash_m_help():
    out = subprocess.run([sys.executable, "-m", "neuralrt", "--help"], capture_output=True, text=True, check=True).stdout
    for command in ("render", "compare", "info", "train", "eval", "convert", "demo"):
        assert command in out


def test_render_builtin_writes_images_and_aovs(tmp_path, capsys):
    out = tmp_path / "img.exr"
    assert main(["render", "builtin:cornell-statue?detail=0", "-o", str(out), "--spp", "1", "--res", "16x12",
                 "--quiet", "--json"]) == 0
    result = _json(capsys)
    assert result["resolution"] == [16, 12] and result["spp"] == 1
    for suffix in ("", "_albedo", "_normal", "_depth"):
        assert (tmp_path / f"img{suffix}.exr").is_file() and (tmp_path / f"img{suffix}.png").is_file()


def test_list_builtins(capsys):
    assert main(["render", "--list-builtins"]) == 0
    out = capsys.readouterr().out
    for name in ("cornell-statue", "hairball", "foliage", "instances"):
        assert f"builtin:{name}" in out


def test_info_mesh_and_scene_json(tmp_path, capsys):
    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=3).export(path)
    assert main(["info", str(path), "--json"]) == 0
    info = _json(capsys)
    assert info["triangles"] == 1280
    assert info["bvh_a_bytes"] > 0 and info["bvh_b_bytes"] > 0 and info["mesh_bytes"] == 642 * 12 + 1280 * 12
    assert main(["info", "builtin:instances?detail=0", "--json"]) == 0
    scene = _json(capsys)
    assert scene["instances"] == 38 and scene["unique_blas"] == 5  # 36 copies of 3 meshes + floor + light


def test_train_info_eval_round_trip(tmp_path, capsys):
    mesh = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=3).export(mesh)
    model = tmp_path / "ball.nrt"
    args = ["train", str(mesh), "-o", str(model), "--preset", "lq", "--steps", "30", "--batch", "1024", "--quiet", "--json"]
    assert main(args) == 0
    trained = _json(capsys)
    assert trained["training"]["steps"] == 30 and not (tmp_path / "ball.nrt.ckpt").exists()

    assert main(["info", str(model), "--json"]) == 0
    info = _json(capsys)
    assert info["method"] == "lsnif" and info["memory_bytes"] == sum(info["memory_parts"].values())
    assert set(info["memory_parts"]) == {"voxels", "encoder", "mlp"}

    assert main(["eval", str(model), str(mesh), "--rays", "2048", "--no-images", "--json"]) == 0
    metrics = _json(capsys)
    for part in ("outside", "surface"):
        for key in ("accuracy", "false_positive_rate", "false_negative_rate", "t_error_median", "t_error_p90",
                    "normal_error_deg_median", "normal_error_deg_p90"):
            assert key in metrics[part]
        assert metrics[part]["accuracy"] > 0.8


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["render", "/nope/scene.toml", "-o", "x.exr"], "scene file not found"),
        (["render", "builtin:nope", "-o", "x.exr"], "unknown built-in scene"),
        (["info", "/nope/mesh.obj"], "not found"),
        (["train", "/nope/mesh.obj", "-o", "m.nrt"], "not found"),
        (["info", "/nope/model.nrt"], "model.nrt"),
    ],
)
def test_bad_input_is_one_line(argv, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("neuralrt: error:") and needle in err and "\n" not in err


def test_resume_without_checkpoint(tmp_path, capsys):
    mesh = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=1).export(mesh)
    assert main(["train", str(mesh), "-o", str(tmp_path / "m.nrt"), "--resume"]) == 2
    assert "no checkpoint" in capsys.readouterr().err

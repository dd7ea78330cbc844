"""benchmarks/run_gpu.sh checks its stages before it unpacks or runs anything (a device call that
names a wrong stage costs machine minutes)."""

import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "run_gpu.sh"

pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), *args], cwd=cwd, capture_output=True, text=True, timeout=30)


def test_no_stage_prints_the_usage(tmp_path):
    result = _run(cwd=tmp_path)
    assert result.returncode == 2 and result.stderr.startswith("usage: run_gpu.sh STAGE...")


def test_an_unknown_stage_after_good_ones_stops_before_any_work(tmp_path):
    (tmp_path / ".gpu-deps").mkdir()  # present: the stage check alone must stop it
    result = _run("pairs", "scaling", "sclaing", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == "neuralrt: error: unknown stage sclaing (nbvh, tests, devices, nif, scaling or pairs)"
    assert result.stdout == "" and sorted(p.name for p in tmp_path.iterdir()) == [".gpu-deps"]  # no $OUT made


def test_missing_gpu_deps_is_one_line(tmp_path):
    result = _run("tests", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip().startswith("neuralrt: error: .gpu-deps missing")
    assert not (tmp_path / "gpu-out").exists()


def test_a_gpu_stage_without_mitsuba_stops_before_any_work(tmp_path):
    """A bundle carried without Mitsuba (wheels only) does for scaling and pairs, not for the stages that need OptiX."""
    (tmp_path / ".gpu-deps").mkdir()
    result = _run("scaling", "nif", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == ("neuralrt: error: stage nif needs Mitsuba (OptiX): .gpu-deps/mitsuba.tgz missing "
                                     "(only scaling and pairs run without it)")
    assert result.stdout == "" and sorted(p.name for p in tmp_path.iterdir()) == [".gpu-deps"]

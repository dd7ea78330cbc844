"""OMP_WAIT_POLICY: `import neuralrt` sets PASSIVE unless the user chose a value; nowhere else sets it."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _policy_after_import(env_value: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if env_value is not None:
        env["OMP_WAIT_POLICY"] = env_value
    code = "import neuralrt, os; print(os.environ['OMP_WAIT_POLICY'])"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout.strip()


def test_default_is_passive_and_a_user_value_wins():
    assert _policy_after_import(None) == "PASSIVE"
    assert _policy_after_import("ACTIVE") == "ACTIVE"


def test_set_in_one_place_only():
    setters = []
    for folder in ("src", "tests", "benchmarks"):
        for path in (ROOT / folder).rglob("*.py"):
            if path.resolve() == Path(__file__).resolve():
                continue
            text = path.read_text()
            if 'environ.setdefault("OMP_WAIT_POLICY"' in text or 'environ["OMP_WAIT_POLICY"] =' in text:
                setters.append(path.relative_to(ROOT).as_posix())
    assert setters == ["src/neuralrt/__init__.py"]

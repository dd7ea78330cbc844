"""How OpenMP threads wait: `import neuralrt` sets a libgomp spin (GOMP_SPINCOUNT) and
KMP_BLOCKTIME=0 unless the user chose a value (an OMP_WAIT_POLICY of theirs included); nowhere else sets them."""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME")


def _after_import(**user) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in _VARIABLES}
    env.update(user)
    code = f"import json, os, neuralrt; print(json.dumps({{k: os.environ.get(k) for k in {_VARIABLES!r}}}))"
    return json.loads(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout)


def test_default_spin_and_a_user_value_wins():
    assert _after_import() == {"OMP_WAIT_POLICY": None, "GOMP_SPINCOUNT": "30000", "KMP_BLOCKTIME": "0"}
    assert _after_import(GOMP_SPINCOUNT="100000")["GOMP_SPINCOUNT"] == "100000"
    assert _after_import(KMP_BLOCKTIME="200") == {"OMP_WAIT_POLICY": None, "GOMP_SPINCOUNT": "30000", "KMP_BLOCKTIME": "200"}
    # A wait policy of the user's decides alone: neuralrt adds no spin count or block time to it
    assert _after_import(OMP_WAIT_POLICY="PASSIVE") == {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": None, "KMP_BLOCKTIME": None}
    assert _after_import(OMP_WAIT_POLICY="ACTIVE")["OMP_WAIT_POLICY"] == "ACTIVE"


def test_set_in_one_place_only():
    setters = []
    for folder in ("src", "tests", "benchmarks"):
        for path in (ROOT / folder).rglob("*.py"):
            if path.resolve() == Path(__file__).resolve():
                continue
            text = path.read_text()
            if any(f'environ.setdefault("{name}"' in text or f'environ["{name}"] =' in text for name in _VARIABLES):
                setters.append(path.relative_to(ROOT).as_posix())
    assert setters == ["src/neuralrt/__init__.py"]

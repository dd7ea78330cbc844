"""`benchmarks/profile_cpu_jit.py` names numba's JIT code for perf: its demangling, the engine's
functions (compiled or loaded from the cache) and the map's format."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import profile_cpu_jit  # noqa: E402

from neuralrt.methods.lsnif_walk_simd import walk_scratch  # noqa: E402


def test_numba_names_read_as_dotted_parts():
    assert profile_cpu_jit.readable("_ZN8neuralrt7methods15lsnif_walk_simd11_walk_lanesB4v157B40c8tJTIeF") == (
        "neuralrt.methods.lsnif_walk_simd._walk_lanes"
    )
    assert profile_cpu_jit.readable("cfunc._ZN8neuralrt4rays3fooE") == "neuralrt.rays.foo"
    assert profile_cpu_jit.readable("NRT_incref") == "NRT_incref"


def test_the_map_names_a_kernel_at_its_address(tmp_path, monkeypatch):
    walk_scratch(8)  # a neuralrt kernel in the engine
    functions = profile_cpu_jit.jit_functions()
    named = {name: address for address, name in functions.items()}
    assert "neuralrt.methods.lsnif_walk_simd.walk_scratch" in named
    assert not any("NumbaEnv" in name for name in named)
    monkeypatch.setattr(profile_cpu_jit, "Path", lambda _: tmp_path / "perf.map")
    path = profile_cpu_jit.write_perf_map(functions)
    rows = [line.split(" ", 2) for line in path.read_text().splitlines()]
    starts = [int(start, 16) for start, _, _ in rows]
    assert starts == sorted(functions) and all(int(size, 16) > 0 for _, size, _ in rows)
    assert named["neuralrt.methods.lsnif_walk_simd.walk_scratch"] in starts

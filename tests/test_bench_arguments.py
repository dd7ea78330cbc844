"""Benchmark scripts refuse bad arguments before any work: one line ``<script>: error: ...`` on
stderr, exit status 2, no traceback and nothing written to the results folder; `_common.write_results`
checks the results name and writes atomically.

A few cases per script run the script as a real subprocess (its own imports, its own exit status);
the other cases run the script's code in this process (``runpy``, the same ``__main__`` path) to
stay fast, with the scripts' work (building or loading a mesh or a model, a BVH, training) made to
fail the test if it starts. Every mesh is procedural: nothing here needs ../shared/meshes. The
CUDA-only scripts' "needs a GPU" cases run where there is none. Also: every script's ``--help``
shows its docstring's whole first paragraph, and every script imports neuralrt before torch.
"""

from __future__ import annotations

import ast
import functools
import importlib
import json
import os
import runpy
import stat
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import torch

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
REAL_RESULTS = BENCH / "results"
sys.path.insert(0, str(BENCH))

import _common  # noqa: E402

from neuralrt.errors import ConfigError, NeuralRTError  # noqa: E402

NO_CUDA = not torch.cuda.is_available()
SCRIPTS = sorted(p.name for p in BENCH.glob("*.py") if not p.name.startswith("_"))
A_FOLDER = str(BENCH)  # (an --out that is a folder)


def _snapshot(folder: Path) -> dict:
    return {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.iterdir()} if folder.is_dir() else {}


_REAL_BEFORE = _snapshot(REAL_RESULTS)


def _assert_one_error_line(script: str, code, stderr: str, expect: str) -> None:
    lines = stderr.strip().splitlines()
    assert code == 2, (code, stderr)
    assert "Traceback" not in stderr, stderr
    assert len(lines) == 1, stderr
    assert lines[0].startswith(f"{script}: error: "), stderr
    assert expect in lines[0], stderr


# --- real subprocesses: one or two cases per script ----------------------------------------------

SUBPROCESS_CASES = [
    ("bench_lsnif.py", ["procedural:statue:0", "nonexistent.off"], "nonexistent.off: mesh file not found"),
    ("bench_lsnif.py", ["procedural:statue:0", "--name", "trial_a/b"], "argument --name: 'trial_a/b'"),
    ("bench_nbvh.py", ["procedural:statue:0", "--device", "bogus"], "--device bogus"),
    ("bench_lsnif_cpu.py", ["procedural:statue:0", "--rays", "0"], "argument --rays: must be at least 1"),
    ("bench_training.py", ["--mesh", "procedural:statue:0", "--steps", "0"], "argument --steps: must be at least 1"),
    ("bench_training_seeds.py", ["--seeds", "3-1"], "argument --seeds: '3-1'"),
    ("bench_methods.py", ["procedural:statue:0", "--variants", "lsnif:bogus"], "unknown lsnif preset 'bogus'"),
    ("bench_nif.py", ["--scenes", "bogus:2"], "builtin:bogus: unknown built-in scene"),
    ("bench_scenes.py", ["--res", "0"], "argument --res: must be at least 1"),
    ("bench_scenes.py", ["--scenes", "builtin:bogus"], "builtin:bogus: unknown built-in scene"),
    ("bench_render.py", ["--threads", "0"], "argument --threads: must be at least 1"),
    ("bench_scaling.py", ["--threads", "-1"], "argument --threads: must be at least 1"),
    ("bench_convert_executors.py", ["--repeats", "0"], "argument --repeats: must be at least 1"),
    ("bench_simd_stores.py", ["--name", "../../x"], "argument --name: '../../x'"),
    # the tester's reproductions (each was a traceback and exit 1, two of them after the meshes were built)
    ("bench_mesh_blas.py", ["--rays", "-5"], "argument --rays: must be at least 1, got -5"),
    ("bench_memory.py", ["--large", "statue:99"], "--large 'statue:99': DETAIL must be an integer in 0..5"),
    ("bench_nbvh_secondary_lod.py", ["nosuch.nrt", "procedural:statue:0"], "nosuch.nrt: model file not found"),
    ("bench_devices.py", ["--methods", "nif", "--device", "cpu"], "unknown method 'nif'"),
    # the CUDA-only scripts on a machine without a GPU
    *([("bench_lsnif_kernels_cuda.py", [], "needs a CUDA device"),
       ("bench_nbvh_cuda.py", ["--device", "cuda"], "--device cuda: ")] if NO_CUDA else []),
]


@pytest.fixture(scope="module")
def subprocess_results(tmp_path_factory):
    """All subprocess cases, run a few at a time (each is mostly imports), with the results folder
    moved to an empty temporary one: (exit status, stderr) per case, and that folder."""
    results = tmp_path_factory.mktemp("results")
    env = dict(os.environ, NEURALRT_BENCH_RESULTS=str(results))
    env.pop("TRITON_INTERPRET", None)

    def run(case):
        script, args, _ = case
        done = subprocess.run([sys.executable, str(BENCH / script), *args], capture_output=True, text=True, env=env,
                              cwd=tmp_path_factory.getbasetemp(), timeout=120)
        return done.returncode, done.stderr

    with ThreadPoolExecutor(max_workers=max(2, min(4, os.cpu_count() or 2))) as pool:
        outcomes = list(pool.map(run, SUBPROCESS_CASES))
    return outcomes, results


@pytest.mark.parametrize("index", range(len(SUBPROCESS_CASES)),
                         ids=[f"{s}:{' '.join(a)}" for s, a, _ in SUBPROCESS_CASES])
def test_script_refuses_bad_argument_in_one_line(subprocess_results, index):
    outcomes, results = subprocess_results
    script, _, expect = SUBPROCESS_CASES[index]
    code, stderr = outcomes[index]
    _assert_one_error_line(script, code, stderr, expect)
    assert not any(results.iterdir()), list(results.iterdir())


# --- the same entry points in this process: the remaining cases -----------------------------------

IN_PROCESS_CASES = [
    # bench_lsnif: mesh specs, presets, counts, names (defects 1, 2, 4)
    ("bench_lsnif.py", ["procedural:statue"], "procedural:statue: not a procedural mesh spec"),
    ("bench_lsnif.py", ["procedural:sphere:2"], "sphere has no detail level"),
    ("bench_lsnif.py", ["procedural:statue:9"], "DETAIL must be an integer in 0..5"),
    ("bench_lsnif.py", ["procedural:statue:0", "procedural:hairball:0@loop1"], "DETAIL must be an integer in 0..8"),
    ("bench_lsnif.py", ["procedural:statue:0", "--presets", "lq", "bogus"], "unknown lsnif preset 'bogus'"),
    ("bench_lsnif.py", ["procedural:statue:0", "--batch", "-5"], "argument --batch: must be at least 1"),
    ("bench_lsnif.py", ["procedural:statue:0", "--name", "../../x"], "argument --name"),
    ("bench_lsnif.py", ["procedural:statue:0", "--name", ""], "argument --name: '': must not be empty"),
    ("bench_lsnif.py", ["procedural:statue:0", "--name", ".hidden"], "must not start with '.'"),
    ("bench_lsnif.py", ["procedural:statue:0", "--remeasure-inference"], "--remeasure-inference needs --models-dir"),
    # bench_nbvh
    ("bench_nbvh.py", ["nonexistent.off"], "nonexistent.off: mesh file not found"),
    ("bench_nbvh.py", ["procedural:statue:0", "--presets", "cpu", "bogus"], "unknown nbvh preset 'bogus'"),
    ("bench_nbvh.py", ["procedural:statue:0", "--set", "training.steps=-1"], "training.steps"),
    ("bench_nbvh.py", ["procedural:statue:0", "--set", "nosuch.key=1"], "unknown config section 'nosuch'"),
    ("bench_nbvh.py", ["procedural:statue:0", "--name", "a/b"], "argument --name"),
    ("bench_nbvh.py", ["--lods", "nonexistent.nrt"], "argument --lods: expected 2 arguments"),
    ("bench_nbvh.py", [], "give the MESHES to train and measure"),
    ("bench_nbvh.py", ["procedural:statue:0", "--lods", "m.nrt", "procedural:statue:0"], "no MESHES beside it"),
    ("bench_nbvh.py", ["--lods", "nosuch.nrt", "procedural:statue:0", "--name", "a/b"], "argument --name"),
    # bench_lsnif_cpu
    ("bench_lsnif_cpu.py", ["procedural:statue:0", "nonexistent.off"], "nonexistent.off: mesh file not found"),
    ("bench_lsnif_cpu.py", ["procedural:statue:0", "--presets", "hq", "bogus"], "unknown lsnif preset 'bogus'"),
    # bench_training
    ("bench_training.py", ["--mesh", "nonexistent.off"], "nonexistent.off: mesh file not found"),
    ("bench_training.py", ["--mesh", "procedural:statue:0", "--preset", "bogus"], "unknown lsnif preset 'bogus'"),
    ("bench_training.py", ["--mesh", "procedural:statue:0", "--repeats", "0"], "argument --repeats"),
    # bench_training_seeds
    ("bench_training_seeds.py", ["--seeds", "bogus"], "argument --seeds: 'bogus'"),
    ("bench_training_seeds.py", ["--preset", "bogus"], "unknown lsnif preset 'bogus'"),
    ("bench_training_seeds.py", ["--steps", "0"], "argument --steps"),
    ("bench_training_seeds.py", ["--mesh", "procedural:sphere:2"], "sphere has no detail level"),
    # bench_methods
    ("bench_methods.py", ["nonexistent.off"], "nonexistent.off: mesh file not found"),
    ("bench_methods.py", ["procedural:statue:0", "--variants", "bogus:hq"], "unknown method 'bogus'"),
    ("bench_methods.py", ["procedural:statue:0", "--variants", "nbvh:cpu:tx"], "variant 'nbvh:cpu:tx'"),
    ("bench_methods.py", ["procedural:statue:0", "--steps", "lsnif"], "--steps lsnif: expected METHOD=N"),
    ("bench_methods.py", ["procedural:statue:0", "--batch", "nbvh=0"], "--batch nbvh=0: N must be at least 1"),
    ("bench_methods.py", ["procedural:statue:0", "--decimate-only", "--decimate"], "--decimate lsnif:hq"),
    # bench_nif
    ("bench_nif.py", ["--device", "bogus"], "--device bogus"),
    ("bench_nif.py", ["--scenes", "hairball:2"], "no statue to put NIF on"),
    ("bench_nif.py", ["--scenes", "mesh:nonexistent.off@loop1"], "nonexistent.off: mesh file not found"),
    ("bench_nif.py", ["--pair-fraction", "2"], "pair_fraction"),
    ("bench_nif.py", ["--spp", "0"], "argument --spp"),
    # bench_scenes
    ("bench_scenes.py", ["--scenes", "nosuch.toml"], "nosuch.toml: scene file not found"),
    ("bench_scenes.py", ["--variants", "lsnif:bogus"], "unknown lsnif preset 'bogus'"),
    ("bench_scenes.py", ["--variants", "lsnif:hq", "--decimate", "lsnif:lq"], "--decimate lsnif:lq: not one of --variants"),
    ("bench_scenes.py", ["--name", "x/y"], "argument --name"),
    # bench_reference
    ("bench_reference.py", ["--seeds", "1"], "argument --seeds: must be an integer in 2..1000, got 1"),
    ("bench_reference.py", ["--scenes", "cornell,,sky"], "an empty item"),
    ("bench_reference.py", ["--scenes", "cornell,nosuch.toml"], "nosuch.toml: scene file not found"),
    ("bench_reference.py", ["--resolution", "0"], "argument --resolution"),
    # bench_mesh_load (before any file is written)
    ("bench_mesh_load.py", ["--formats", "obj,dae"], "--formats: unknown format 'dae'"),
    ("bench_mesh_load.py", ["--subdivisions", "10"], "argument --subdivisions: must be an integer in 1..9, got 10"),
    ("bench_mesh_load.py", ["--name", "a/b"], "argument --name: 'a/b'"),
    # bench_render
    ("bench_render.py", ["--scenes", "bogus"], "builtin:bogus: unknown built-in scene"),
    ("bench_render.py", ["--scenes", "hairball,,foliage"], "an empty item"),
    ("bench_render.py", ["--resolution", "0"], "argument --resolution"),
    # bench_scaling (all before the first per-thread-count process)
    ("bench_scaling.py", ["--threads", "0"], "argument --threads: must be at least 1"),
    ("bench_scaling.py", ["--train-mesh", "procedural:statue"], "not a procedural mesh spec"),
    ("bench_scaling.py", ["--presets", "hq", "bogus"], "unknown lsnif preset 'bogus'"),
    # bench_convert_executors (defect 3)
    ("bench_convert_executors.py", ["--repeats", "-1"], "argument --repeats"),
    ("bench_convert_executors.py", ["--runs", ","], "--runs ','"),
    ("bench_convert_executors.py", ["--runs", "local,bogus"], "unknown run(s) bogus"),
    ("bench_convert_executors.py", ["--name", "a/b"], "argument --name"),
    # bench_mesh_blas (the tester's defects 1, 4: counts, detail, --subdivide and --name checked first)
    ("bench_mesh_blas.py", ["--rays", "0"], "argument --rays: must be at least 1"),
    ("bench_mesh_blas.py", ["--repeats", "x"], "argument --repeats: expected an integer, got 'x'"),
    ("bench_mesh_blas.py", ["--statue-detail", "9"], "argument --statue-detail: must be an integer in 0..5, got 9"),
    ("bench_mesh_blas.py", ["--subdivide", "bunny00.off"], "argument --subdivide: 'bunny00.off': expected FILE:LOOP_STEPS"),
    ("bench_mesh_blas.py", ["--name", "a/b"], "argument --name: 'a/b'"),
    # bench_tlas
    ("bench_tlas.py", ["--rays", "-1"], "argument --rays: must be at least 1"),
    ("bench_tlas.py", ["--statue-detail", "-1"], "argument --statue-detail: must be an integer in 0..5"),
    ("bench_tlas.py", ["--name", ""], "argument --name: '': must not be empty"),
    # bench_memory
    ("bench_memory.py", ["--large", "statue"], "--large 'statue': not a procedural mesh: use NAME:DETAIL"),
    ("bench_memory.py", ["--large", "sphere:2"], "--large 'sphere:2': 'sphere' has no detail level"),
    ("bench_memory.py", ["--subdivide", "bunny00.off:-1"], "argument --subdivide: 'bunny00.off:-1'"),
    ("bench_memory.py", ["--meshes", str(BENCH / "_common.py")], "argument --meshes"),
    ("bench_memory.py", ["--no-large", "--name", "../x"], "argument --name: '../x'"),
    # bench_gltf_import
    ("bench_gltf_import.py", ["--grid", "0"], "argument --grid: must be an integer in 1..64"),
    ("bench_gltf_import.py", ["--mesh", "nonexistent.off"], "nonexistent.off: mesh file not found"),
    ("bench_gltf_import.py", ["--spp", "-2"], "argument --spp: must be at least 1"),
    ("bench_gltf_import.py", ["--name", "a/b"], "argument --name: 'a/b'"),
    # bench_lsnif_kernels
    ("bench_lsnif_kernels.py", ["nonexistent.off"], "nonexistent.off: mesh file not found"),
    ("bench_lsnif_kernels.py", ["procedural:statue:0", "procedural:statue:9"], "DETAIL must be an integer in 0..5"),
    ("bench_lsnif_kernels.py", ["procedural:statue:0", "--threads", "100000"], "argument --threads: 100000 is more than numba's"),
    ("bench_lsnif_kernels.py", ["procedural:statue:0", "--max-points", "0"], "argument --max-points: must be an integer in 1..256"),
    ("bench_lsnif_kernels.py", ["procedural:statue:0", "--name", "a/b"], "argument --name: 'a/b'"),
    # bench_lsnif_offset
    ("bench_lsnif_offset.py", ["nosuch.nrt", "procedural:statue:0"], "nosuch.nrt: model file not found"),
    ("bench_lsnif_offset.py", ["m.nrt", "procedural:statue:0", "--offsets", "0", "-1"], "argument --offsets: must be a number >= 0"),
    ("bench_lsnif_offset.py", ["m.nrt", "procedural:statue:0", "--self-distance", "0"], "argument --self-distance"),
    ("bench_lsnif_offset.py", ["m.nrt", "procedural:statue:0", "--name", "a/b"], "argument --name: 'a/b'"),
    ("bench_nbvh.py", ["--offsets", "nosuch.nrt", "procedural:statue:0"], "nosuch.nrt: model file not found"),
    # bench_nbvh_secondary_lod
    ("bench_nbvh_secondary_lod.py", ["m.nrt", "procedural:statue:0", "--res", "0"], "argument --res: must be at least 1"),
    ("bench_nbvh_secondary_lod.py", ["m.nrt", "procedural:statue:0", "--name", ".x"], "argument --name: '.x'"),
    ("bench_nbvh_secondary_lod.py", ["m.nrt"], "the following arguments are required: mesh"),
    # bench_devices (--device cpu: the same checks with or without a GPU)
    ("bench_devices.py", ["--device", "bogus"], "not a torch device"),
    ("bench_devices.py", ["--device", "cpu", "--methods", "lsnif,nif"], "unknown method 'nif'"),
    ("bench_devices.py", ["--device", "cpu", "--meshes", "statue:2,statue:9"], "--meshes 'statue:9': DETAIL must be an integer in 0..5"),
    ("bench_devices.py", ["--device", "cpu", "--meshes", "blob"], "--meshes 'blob': not a procedural mesh"),
    ("bench_devices.py", ["--device", "cpu", "--steps", "0"], "argument --steps: must be at least 1"),
    ("bench_devices.py", ["--device", "cpu", "--rays-log2", "40"], "argument --rays-log2: must be an integer in 0..30"),
    ("bench_devices.py", ["--device", "cpu", "--method-steps", "lsnif=0"], "--method-steps lsnif=0: N must be at least 1"),
    ("bench_devices.py", ["--device", "cpu", "--method-steps", "nbvh=5"], "nbvh, which is not in --methods lsnif"),
    ("bench_devices.py", ["--device", "cpu", "--methods", "lsnif,nbvh", "--method-meshes", "nbvh"], "--method-meshes nbvh: expected METHOD="),
    ("bench_devices.py", ["--device", "cpu", "--methods", "lsnif,nbvh", "--method-meshes", "nbvh=statue:1+hairball:9"],
     "--method-meshes 'hairball:9': DETAIL must be an integer in 0..8"),
    ("bench_devices.py", ["--device", "cpu", "--skip", "train,bogus"], "--skip train,bogus: unknown section(s) bogus"),
    ("bench_devices.py", ["--device", "cpu", "--scene", "builtin:bogus"], "builtin:bogus: unknown built-in scene"),
    ("bench_devices.py", ["--device", "cpu", "--out", A_FOLDER], "is a folder, not a results file"),
    # bench_exact_backends
    ("bench_exact_backends.py", ["--meshes", "statue:2,hairball"], "--meshes 'hairball': not a procedural mesh: use NAME:DETAIL"),
    ("bench_exact_backends.py", ["--rays-log2", "-1"], "argument --rays-log2: must be an integer in 0..30"),
    ("bench_exact_backends.py", ["--repeats", "0"], "argument --repeats: must be at least 1"),
    ("bench_exact_backends.py", ["--out", A_FOLDER], "is a folder, not a results file"),
    # bench_lsnif_kernels_cuda (checked before the GPU is looked for)
    ("bench_lsnif_kernels_cuda.py", ["--presets", "hq", "gpu"], "argument --presets: invalid choice: 'gpu'"),
    ("bench_lsnif_kernels_cuda.py", ["--detail", "9"], "argument --detail: must be an integer in 0..8"),
    ("bench_lsnif_kernels_cuda.py", ["--profile", "input,0,2"], "argument --profile: 'input,0,2': expected STAGE,BLOCK,WARPS"),
    ("bench_lsnif_kernels_cuda.py", ["--budget-s", "0"], "argument --budget-s: must be a positive number"),
    ("bench_lsnif_kernels_cuda.py", ["--out", A_FOLDER], "is a folder, not a results file"),
    # bench_nbvh_cuda
    ("bench_nbvh_cuda.py", ["--mesh", "statue:9"], "--mesh 'statue:9': DETAIL must be an integer in 0..5"),
    ("bench_nbvh_cuda.py", ["--device", "cpu", "--preset", "bogus"], "unknown nbvh preset 'bogus'"),
    ("bench_nbvh_cuda.py", ["--device", "cpu", "--model", "nosuch.nrt"], "nosuch.nrt: model file not found"),
    ("bench_nbvh_cuda.py", ["--steps", "0"], "argument --steps: must be at least 1"),
    ("bench_nbvh_cuda.py", ["--rays-log2", "99"], "argument --rays-log2: must be an integer in 0..30"),
    ("bench_nbvh_cuda.py", ["--count-step"], "--count-step runs the CUDA path on CPU tensors: set TRITON_INTERPRET=1"),
    ("bench_nbvh_cuda.py", ["--count-step", "--count-batch", "0"], "argument --count-batch: must be at least 1"),
    ("bench_nbvh_cuda.py", ["--compile-only", "--arch", "9"], "argument --arch: must be an integer in 50..130"),
    ("bench_nbvh_cuda.py", ["--compile-only", "--out", A_FOLDER], "is a folder, not a results file"),
    # profile_cpu_jit
    ("profile_cpu_jit.py", ["--rays", "0"], "argument --rays: must be at least 1"),
    ("profile_cpu_jit.py", ["--seconds", "0"], "argument --seconds: must be a positive number"),
    ("profile_cpu_jit.py", ["procedural:statue:0", "--model", "nosuch.nrt"], "nosuch.nrt: model file not found"),
    # the CUDA-only scripts without a GPU: one line, before any work
    *([("bench_lsnif_kernels_cuda.py", ["--quick"], "needs a CUDA device"),
       ("bench_nbvh_cuda.py", [], "--device cpu: the CUDA code path runs on the CPU only under the Triton interpreter"),
       ("bench_devices.py", ["--device", "cuda"], "--device cuda: ")] if NO_CUDA else []),
]

# What the scripts' work starts with: a test fails if one is called before the arguments are checked.
WORK = {
    "neuralrt.geometry.procedural": ("make_procedural", "statue", "hairball", "foliage", "sphere"),
    "neuralrt.geometry.mesh": ("load_mesh",),
    "neuralrt.geometry.bvh": ("build_bvh",),
    "neuralrt.methods": ("load_model",),
    "neuralrt.training.api": ("train",),
}


@functools.cache
def _modules_binding_work() -> tuple[str, ...]:
    """neuralrt modules whose top level imports one of WORK's functions by name (``from
    ..geometry.mesh import load_mesh``): first imported while the stand-ins are in, they would keep
    one for good, and a later test would fail (the scene loader did, after `bench_reference.py`)."""
    src = Path(__file__).resolve().parents[1] / "src"
    names = {name for names in WORK.values() for name in names}
    found = []
    for path in sorted((src / "neuralrt").rglob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.ImportFrom) and any(alias.name in names for alias in node.names):
                found.append(".".join(path.relative_to(src).with_suffix("").parts))
                break
    return tuple(found)


@pytest.fixture
def no_work(monkeypatch):
    """The scripts' work fails the test if it starts; helper modules (bench_lsnif, ...) first imported
    meanwhile (bound to the stand-ins) are forgotten afterwards, and neuralrt's modules that bind
    a WORK function on import are imported before. TRITON_INTERPRET is unset."""
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    for module in _modules_binding_work():
        importlib.import_module(module)
    before = set(sys.modules)

    def started(*args, **kwargs):
        raise AssertionError("the script's work started before every argument was checked")

    for module, names in WORK.items():
        for name in names:
            monkeypatch.setattr(importlib.import_module(module), name, started)
    from neuralrt.accel.mesh_blas import MeshBLAS

    monkeypatch.setattr(MeshBLAS, "__new__", staticmethod(started))  # (the class stays: subclasses are defined on import)
    yield
    for name in set(sys.modules) - before:
        if name.startswith("bench_"):
            del sys.modules[name]


@pytest.fixture
def results_dir(tmp_path, monkeypatch):
    folder = tmp_path / "results"
    monkeypatch.setattr(_common, "RESULTS_DIR", folder)
    monkeypatch.chdir(tmp_path)
    return folder


@pytest.mark.parametrize("script,args,expect", IN_PROCESS_CASES, ids=[f"{s}:{' '.join(a)}" for s, a, _ in IN_PROCESS_CASES])
def test_script_checks_before_work(script, args, expect, results_dir, no_work, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", [str(BENCH / script), *args])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(BENCH / script), run_name="__main__")
    _assert_one_error_line(script, exit_info.value.code, capsys.readouterr().err, expect)
    assert not results_dir.exists() or not any(results_dir.iterdir())


@pytest.mark.parametrize("script,args", [
    ("bench_nbvh_secondary_lod.py", ["bad.nrt", "procedural:statue:0"]),
    ("bench_lsnif_offset.py", ["bad.nrt", "procedural:statue:0"]),
    ("bench_nbvh_cuda.py", ["--device", "cpu", "--model", "bad.nrt"]),
    ("profile_cpu_jit.py", ["procedural:statue:0", "--model", "bad.nrt"]),
])
def test_a_broken_model_file_is_one_line_before_work(script, args, results_dir, no_work, monkeypatch, capsys):
    Path("bad.nrt").write_bytes(b"not a model file at all")  # (the current folder: results_dir's parent)
    monkeypatch.setattr(sys, "argv", [str(BENCH / script), *args])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(BENCH / script), run_name="__main__")
    _assert_one_error_line(script, exit_info.value.code, capsys.readouterr().err, "bad.nrt: ")
    assert not results_dir.exists()


def _first_paragraph(script: str) -> str:
    return ast.get_docstring(ast.parse((BENCH / script).read_text()), clean=False)


@pytest.mark.parametrize("script", SCRIPTS)
def test_help_shows_the_whole_first_paragraph(script, monkeypatch, capsys):
    """Not the docstring's first line, cut off mid-sentence."""
    monkeypatch.setenv("COLUMNS", "10000")  # (argparse wraps at the terminal's width)
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    monkeypatch.setattr(sys, "argv", [str(BENCH / script), "--help"])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(BENCH / script), run_name="__main__")
    assert exit_info.value.code == 0
    wanted = _common.description(_first_paragraph(script))
    assert wanted and wanted.endswith((".", "?", ")")), wanted
    assert wanted in " ".join(capsys.readouterr().out.split())


def test_description_is_the_first_paragraph_on_one_line():
    assert _common.description("""One sentence over
    two lines.

    Second paragraph.""") == "One sentence over two lines."
    assert _common.description(None) == ""


_LOADS_OPENMP = ("torch", "numba", "triton", "drjit", "mitsuba", "bench_")


def _top_level_imports(tree: ast.Module):
    """Module-level imports in order (also those under a top-level ``if``/``try``): the module names."""
    for node in tree.body:
        nodes = ast.walk(node) if isinstance(node, (ast.If, ast.Try)) else [node]
        for inner in nodes:
            if isinstance(inner, ast.Import):
                yield from (alias.name for alias in inner.names)
            elif isinstance(inner, ast.ImportFrom) and inner.level == 0:
                yield inner.module


@pytest.mark.parametrize("script", SCRIPTS)
def test_scripts_import_neuralrt_before_torch(script):
    """neuralrt sets how OpenMP threads wait (GOMP_SPINCOUNT) before torch loads libgomp (README,
    "Benchmarks"): every script imports it before torch, numba, triton or another benchmark module."""
    imports = list(_top_level_imports(ast.parse((BENCH / script).read_text())))
    assert "neuralrt" in imports, f"{script} does not import neuralrt"
    first = imports.index("neuralrt")
    early = [name for name in imports[:first] if name.split(".")[0].startswith(_LOADS_OPENMP)]
    assert not early, f"{script} imports {early} before neuralrt"


# --- _common -------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["", "a/b", "../../x", "/abs", ".hidden", "a\\b", "tab\there"])
def test_write_results_refuses_names_outside_the_results_folder(name, results_dir):
    with pytest.raises(ConfigError, match="results name"):
        _common.write_results(name, [{"a": 1}])
    assert not results_dir.exists() or not any(results_dir.iterdir())


def test_write_results_is_atomic_and_respects_umask(results_dir):
    old = os.umask(0o022)
    try:
        path = _common.write_results("trial_a", [{"a": 1}], {"settings": {"x": 2}})
    finally:
        os.umask(old)
    assert path == results_dir / "trial_a.json"
    data = json.loads(path.read_text())
    assert data["rows"] == [{"a": 1}] and data["settings"] == {"x": 2} and data["benchmark"] == "trial_a"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert [p.name for p in results_dir.iterdir()] == ["trial_a.json"]  # no temporary file left

    with pytest.raises(TypeError):  # a value JSON cannot hold: the earlier file stays whole
        _common.write_results("trial_a", [{"a": object()}])
    assert json.loads(path.read_text())["rows"] == [{"a": 1}]
    assert [p.name for p in results_dir.iterdir()] == ["trial_a.json"]


def test_concurrent_writes_of_one_name_do_not_clash(results_dir):
    errors = []

    def write(i):
        try:
            for _ in range(5):
                _common.write_results("same", [{"writer": i}])
        except Exception as exc:  # noqa: BLE001 (reported below)
            errors.append(exc)

    threads = [threading.Thread(target=write, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert json.loads((results_dir / "same.json").read_text())["rows"][0]["writer"] in range(4)
    assert [p.name for p in results_dir.iterdir()] == ["same.json"]


def test_read_results_refuses_a_broken_file(results_dir):
    results_dir.mkdir()
    (results_dir / "broken.json").write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read the earlier results"):
        _common.read_results("broken")
    assert _common.read_results("absent") == {}


def test_procedural_detail_limits_match_the_generators():
    from neuralrt.geometry import procedural

    assert _common.procedural_detail() is procedural.MAX_DETAIL
    for name, limit in procedural.MAX_DETAIL.items():
        with pytest.raises(NeuralRTError, match=rf"0\.\.{limit}\b"):
            getattr(procedural, name)(detail=limit + 1)  # (checked before any geometry is made)


def test_mesh_specs_parse_without_loading():
    assert _common.parse_mesh_spec("procedural:hairball:3") == ("procedural", "hairball", 3)
    for bad in ("procedural:statue", "procedural:sphere:2", "procedural:statue:x", "procedural:statue:-1", "", "nonexistent.off@loop2"):
        with pytest.raises(NeuralRTError):
            _common.parse_mesh_spec(bad)


def test_results_folder_untouched():
    """Nothing above wrote to benchmarks/results (keep last in this file)."""
    assert _snapshot(REAL_RESULTS) == _REAL_BEFORE

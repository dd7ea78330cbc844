"""Profile CPU inference with `perf`, numba's compiled functions named.

perf cannot name the code numba compiles at run time (it shows ``[JIT] tid N`` and raw
addresses), so this script writes ``/tmp/perf-<pid>.map``, perf's map of JIT code: the address
and size of every function in the libraries numba built for neuralrt in this process (the
kernels, their inlined and linked callees, the parallel loops' bodies). It then calls
``intersect`` (or ``occluded``) on the same rays in a loop for ``--seconds``; record it from a
second shell and read it by function::

    python benchmarks/profile_cpu_jit.py procedural:hairball:6 --preset lq --seconds 40 &
    perf record -e cpu-clock -F 10000 -p <the pid it prints> -o lq.data -- sleep 15
    perf report -i lq.data --sort=sym

The model is untrained (LSNIF with a random table, as `bench_lsnif_cpu.py` times it; N-BVH at
its inference LoD: the work per ray is a trained LSNIF model's, not a trained N-BVH's, whose cut
decides how many leaves a ray visits), or ``--model`` a trained one (its method, from the file). docs/lsnif.md, "Session 37", has
the profile this gave and what it led to.
"""

from __future__ import annotations

import os
import re
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (ArgumentParser, check_mesh_spec, check_model_file, check_presets, description,  # noqa: E402
                     positive_float, positive_int, run_main)
from bench_lsnif import resolve_mesh  # noqa: E402

from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.methods import load_model  # noqa: E402
from neuralrt.methods.registry import get_method  # noqa: E402
from neuralrt.training.ray_distribution import BoxRayDistribution  # noqa: E402

_MAX_SIZE = 1 << 18  # a function's extent where the next known one is far (or none follows)


def readable(mangled: str) -> str:
    """numba's Itanium-style name as dotted parts (``_ZN8neuralrt7methods...`` ->
    ``neuralrt.methods...``); other names unchanged."""
    if "_ZN" not in mangled:
        return mangled
    parts, rest = [], mangled[mangled.index("_ZN") + 3 :]
    while rest and rest[0].isdigit():
        digits = re.match(r"\d+", rest).group()
        start = len(digits)
        parts.append(rest[start : start + int(digits)])
        rest = rest[start + int(digits) :]
    return ".".join(parts) or mangled


def jit_functions() -> dict[int, str]:
    """Address -> name of every function in numba's JIT engine so far: compiled in this process
    or loaded from its cache (numba's private ``JitEngine._defined_symbols``: the one list that
    holds both; a cached library keeps no LLVM module to list), its environment objects left out."""
    from numba.core.registry import cpu_target

    engine = cpu_target.target_context.codegen()._engine
    found: dict[int, str] = {}
    for symbol in engine._defined_symbols:
        if "NumbaEnv" in symbol:
            continue
        address = engine.get_function_address(symbol)
        if address:
            found[address] = readable(symbol)
    return found


def write_perf_map(functions: dict[int, str], pid: int | None = None) -> Path:
    """perf's ``/tmp/perf-<pid>.map`` for ``functions`` (each extends to the next, at most
    `_MAX_SIZE` bytes); returns its path."""
    path = Path(f"/tmp/perf-{pid or os.getpid()}.map")
    starts = sorted(functions)
    lines = []
    for i, start in enumerate(starts):
        size = min(starts[i + 1] - start, _MAX_SIZE) if i + 1 < len(starts) else _MAX_SIZE
        lines.append(f"{start:x} {size:x} {functions[start]}\n")
    path.write_text("".join(lines))
    return path


def build_model(mesh, method: str, preset: str):
    """An untrained model of ``method`` at ``preset`` (the registry's configs, as the CLI builds them)."""
    config = get_method(method).config(preset)
    if method == "lsnif":
        from neuralrt.methods.lsnif import LSNIFModel

        model = LSNIFModel.from_mesh(mesh, config)
        with torch.no_grad():  # a trained table's spread, so that the network's work is typical
            model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(0))
        model.round_to_storage_precision_()
        return model
    from neuralrt.methods.nbvh import NBVHModel

    return NBVHModel.from_mesh(mesh, config)


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("mesh", nargs="?", default="procedural:hairball:6", help="a mesh file or procedural:NAME:DETAIL")
    parser.add_argument("--method", choices=["lsnif", "nbvh"], default="lsnif")
    parser.add_argument("--preset", default=None, help="the method's preset (default: lq for LSNIF, cpu for N-BVH)")
    parser.add_argument("--rays", type=positive_int, default=1 << 17)
    parser.add_argument("--seconds", type=positive_float, default=30.0, help="how long to call the query after the map is written")
    parser.add_argument("--query", choices=["intersect", "occluded"], default="intersect")
    parser.add_argument("--model", default=None, help="a trained model file of this mesh (.nrt) instead of an untrained model")
    args = parser.parse_args(argv)
    preset = args.preset or ("lq" if args.method == "lsnif" else "cpu")
    check_mesh_spec(args.mesh)  # all before the mesh is built
    check_presets(args.method, [preset])
    if args.model:
        check_model_file(args.model)
    mesh = resolve_mesh(args.mesh)
    model = load_model(args.model) if args.model else build_model(mesh, args.method, preset)
    rays = BoxRayDistribution(MeshBLAS(mesh), model.box, seed=4242, pool_size=1 << 16).sample(args.rays).rays
    query = getattr(model, args.query)
    query(rays)  # compiles (or loads) every kernel the query uses
    path = write_perf_map(jit_functions())
    print(f"pid {os.getpid()}: {args.query} on {args.rays} rays for {args.seconds:.0f} s; JIT names in {path}", flush=True)
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < args.seconds:
        query(rays)
        calls += 1
    elapsed = time.perf_counter() - start
    print(f"{calls} calls, {1e3 * elapsed / calls:.2f} ms each")
    return 0


if __name__ == "__main__":
    run_main(main)

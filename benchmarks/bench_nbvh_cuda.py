"""N-BVH on CUDA: the Triton kernels against the torch ops they replaced, and against OptiX, on the same rays.

1. **train**: the ``--preset`` (default ``paper``: 2^18 rays per step) for ``--steps`` on ``--mesh``
   with the current (Triton) path: wall time, nodes (issue 9's target: 10,000 steps in <= 2 min on
   an H100). ``--model FILE`` loads a trained model instead.
2. **stages**, each timed with device events (median of ``--repeats``), Triton vs torch, with a check
   that both give the same answer and the floor of each stage (bytes through device memory over the
   measured copy bandwidth, FLOPs over the measured bf16 GEMM rate; the hash table and the cut's
   nodes are counted as cache-resident, their gathers are reported apart as ``l2_bytes``):
   ``list_leaves`` and ``first_leaves`` on one inference chunk of the rays (identical lists required), the
   hash grid forward on the first leaves' chord points and forward + backward on a training batch
   (2^18 queries of 3 points), and the whole ``intersect`` / ``occluded`` of the model: Triton path
   (what CUDA runs now), the earlier torch path (torch traversal, torch grid, torch wavefront), and
   OptiX closest / any hit on the same rays (Mitsuba 3).
3. JSON: benchmarks/results/nbvh_cuda_<device>.json (or ``--out``), with machine, versions, load.

    python benchmarks/bench_nbvh_cuda.py [--mesh statue:2] [--steps 1000] [--rays-log2 22] [--repeats 20]
    python benchmarks/bench_nbvh_cuda.py --compile-only      # no GPU needed: compile for sm_90, ptxas registers/spills
    TRITON_INTERPRET=1 python benchmarks/bench_nbvh_cuda.py --device cpu --preset cpu --steps 10 --rays-log2 7 \
        --repeats 1 --out /tmp/smoke.json   # a smoke run of the script on the CPU: numbers meaningless (stages run
                                            # under the interpreter, and "triton" whole queries are the numba path)
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import inspect
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import neuralrt  # noqa: E402,F401  (sets the process-wide defaults first)
from _common import RESULTS_DIR, machine_info, print_table  # noqa: E402

STAGE_COLUMNS = ["stage", "items", "triton_ms", "torch_ms", "speedup", "same", "floor_ms", "triton_x_floor"]
WHOLE_COLUMNS = ["query", "rays", "triton_Mrays/s", "torch_Mrays/s", "optix_Mrays/s", "triton_x_optix", "mlp_rows_per_ray",
                 "hit_agreement_torch", "hit_agreement_optix"]
MLP_FLOPS_PER_ROW = 2 * (96 * 64 + 3 * 64 * 64 + 64 * 8)  # N-BVH's 4 x 64 MLP (8 outputs)


def _mesh(spec: str):
    from neuralrt.geometry.procedural import make_procedural

    name, _, detail = spec.partition(":")
    return make_procedural(name, **({"detail": int(detail)} if detail else {}))


def median_ms(fn, device: torch.device, repeats: int, warmup: int = 2) -> float:
    """Median of ``repeats`` calls: CUDA events around each on a GPU, the host clock elsewhere."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
        else:
            t = time.perf_counter()
            fn()
            times.append(1e3 * (time.perf_counter() - t))
    return statistics.median(times)


def ceilings(device: torch.device) -> dict:
    """Measured device-memory bandwidth (copy, read + write counted) and bf16 GEMM rate."""
    n = 1 << (28 if device.type == "cuda" else 22)
    x = torch.rand(n, device=device)
    y = torch.empty_like(x)
    copy_ms = median_ms(lambda: y.copy_(x), device, 10)
    m = 8192 if device.type == "cuda" else 512
    a, b = (torch.randn(m, m, device=device, dtype=torch.bfloat16) for _ in range(2))
    gemm_ms = median_ms(lambda: a @ b, device, 10)
    return {"bytes_per_s": 2 * n * 4 / (copy_ms * 1e-3), "bf16_flops_per_s": 2 * m**3 / (gemm_ms * 1e-3)}


def _floor_ms(bytes_: float, flops: float, ceil: dict) -> float:
    return 1e3 * max(bytes_ / ceil["bytes_per_s"], flops / ceil["bf16_flops_per_s"])


@contextlib.contextmanager
def torch_path():
    """The CUDA path before the Triton kernels: torch traversal, torch hash grid, torch wavefront loop."""
    import neuralrt.methods.nbvh as nbvh_module
    from neuralrt.methods.nbvh_traversal import first_leaves_torch, list_leaves_torch
    from neuralrt.neural.hash_grid import HashGrid, hash_grid_torch

    saved = (nbvh_module.list_leaves, nbvh_module.first_leaves, nbvh_module.NBVHModel._closest, HashGrid.forward)
    nbvh_module.list_leaves, nbvh_module.first_leaves = list_leaves_torch, first_leaves_torch
    nbvh_module.NBVHModel._closest = nbvh_module.NBVHModel._closest_torch
    HashGrid.forward = lambda self, points: hash_grid_torch(points, self.table, self.layout)
    try:
        yield
    finally:
        nbvh_module.list_leaves, nbvh_module.first_leaves, nbvh_module.NBVHModel._closest, HashGrid.forward = saved


@contextlib.contextmanager
def count_mlp_rows(model):
    rows = [0]
    forward = model.network.forward

    def counting(x, *a, **k):
        rows[0] += len(x)
        return forward(x, *a, **k)

    model.network.forward = counting
    try:
        yield rows
    finally:
        del model.network.forward


def bench_stages(model, rays, device, repeats: int, ceil: dict) -> list[dict]:
    from neuralrt.methods.nbvh_traversal import first_leaves_torch, list_leaves_torch
    from neuralrt.methods.nbvh_traversal_triton import first_leaves_triton, list_leaves_triton
    from neuralrt.neural.hash_grid import hash_grid_torch
    from neuralrt.neural.hash_grid_triton import hash_grid_triton

    rows = []
    rays = rays[: model.config.inference.chunk_size]  # what one inference call hands the stages (2^20 in `paper`)
    _, o, d, t_max, _, _ = model._unit_rays(rays)
    n = len(o)
    inf = model.config.inference
    level = torch.full((n,), inf.lod, dtype=torch.int8, device=device)
    dil = torch.full((n,), inf.box_dilation, device=device)
    cut = model.cut_arrays()
    args = (o, d, t_max, cut, level, dil)
    ray_bytes = n * (12 + 12 + 4 + 1 + 4)

    a, b = list_leaves_triton(*args), list_leaves_torch(*args)
    same = all(torch.equal(getattr(a, f), getattr(b, f)) for f in ("start", "node", "t0", "t1"))
    e = len(a.node)
    rows.append({"stage": "list_leaves", "items": n, "entries": e, "node_bytes": model.num_nodes * 33,
                 "triton_ms": median_ms(lambda: list_leaves_triton(*args), device, repeats),
                 "torch_ms": median_ms(lambda: list_leaves_torch(*args), device, repeats), "same": same,
                 # two walks read the rays, counts written and read, start written, the entries written
                 "floor_ms": _floor_ms(2 * ray_bytes + 8 * n * 3 + 16 * e, 0, ceil)})  # fmt: skip

    a, b = first_leaves_triton(*args), first_leaves_torch(*args)
    same = all(torch.equal(x, y) for x, y in zip(a, b))
    rows.append({"stage": "first_leaves", "items": n, "triton_ms": median_ms(lambda: first_leaves_triton(*args), device, repeats),
                 "torch_ms": median_ms(lambda: first_leaves_torch(*args), device, repeats), "same": same,
                 "floor_ms": _floor_ms(ray_bytes + 16 * n, 0, ceil)})  # fmt: skip

    # Hash grid on the first leaves' chord points {0, 1/2, 1} (the first wavefront step's queries).
    node, t0, t1 = a
    has = node >= 0
    frac = torch.tensor([0.0, 0.5, 1.0], device=device)
    t = t0[has, None] + frac * (t1 - t0)[has, None]
    points = (o[has, None, :] + t[..., None] * d[has, None, :]).contiguous()
    grid = model.encoder
    table = grid.table.detach().float().contiguous()
    q, levels, feats = len(points), len(grid.layout.resolutions), grid.features_per_level
    with torch.no_grad():
        x, y = hash_grid_triton(points, table, grid.layout), hash_grid_torch(points, table, grid.layout)
        rows.append({"stage": "hash_grid_forward", "items": q, "table_bytes": table.numel() * 4,
                     "triton_ms": median_ms(lambda: hash_grid_triton(points, table, grid.layout), device, repeats),
                     "torch_ms": median_ms(lambda: hash_grid_torch(points, table, grid.layout), device, repeats),
                     "same": float((x - y).abs().max()) < 1e-5, "max_abs_diff": float((x - y).abs().max()),
                     "l2_bytes": q * 3 * levels * 8 * feats * 4,
                     "floor_ms": _floor_ms(q * 3 * (12 + levels * feats * 4), 0, ceil)})  # fmt: skip

    # Forward + backward of a training batch (2^18 queries of 3 points, the paper preset's).
    batch = points[: 1 << 18]
    upstream = torch.randn(len(batch), 3 * levels * feats, device=device)

    def train_pass(encode):
        with torch.enable_grad():
            leaf = table.clone().requires_grad_()
            (g,) = torch.autograd.grad((encode(batch, leaf, grid.layout) * upstream).sum(), leaf)
        return g

    g_tri, g_torch = train_pass(hash_grid_triton), train_pass(hash_grid_torch)
    rel = float((g_tri - g_torch).norm() / g_torch.norm().clamp(min=1e-30))
    qb = len(batch)
    rows.append({"stage": "hash_grid_fwd_bwd", "items": qb, "triton_ms": median_ms(lambda: train_pass(hash_grid_triton), device, repeats),
                 "torch_ms": median_ms(lambda: train_pass(hash_grid_torch), device, repeats), "same": rel < 1e-5,
                 "grad_rel_diff": rel, "l2_bytes": 2 * qb * 3 * levels * 8 * feats * 4,
                 # points and upstream read, features written, the table gradient zeroed, written, read once
                 "floor_ms": _floor_ms(qb * 3 * (12 + 2 * levels * feats * 4) + 3 * table.numel() * 4, 0, ceil)})  # fmt: skip
    for row in rows:
        row["speedup"] = row["torch_ms"] / row["triton_ms"]
        row["triton_x_floor"] = row["triton_ms"] / row["floor_ms"] if row["floor_ms"] > 0 else None
    return rows


def bench_whole(model, mesh, rays, device, repeats: int, ceil: dict) -> list[dict]:
    from neuralrt.accel.mesh_blas import MeshBLAS

    exact = MeshBLAS(mesh, device=device)
    n = len(rays)
    whole = []
    for query in ("intersect", "occluded"):
        fn, exact_fn = getattr(model, query), getattr(exact, query)
        with count_mlp_rows(model) as mlp_rows:
            new = fn(rays)
        t_new = median_ms(lambda: fn(rays), device, repeats)
        with torch_path():
            old = fn(rays)
            t_old = median_ms(lambda: fn(rays), device, max(3, repeats // 4))
        ref = exact_fn(rays)
        t_exact = median_ms(lambda: exact_fn(rays), device, repeats)
        hit = (lambda h: h.hit) if query == "intersect" else (lambda h: h)
        agree_old = float((hit(new) == hit(old)).float().mean())
        agree_exact = float((hit(new) == hit(ref)).float().mean())
        q = mlp_rows[0]
        # Per MLP row: step input kernel (ray, pointer, leaf: 48 B in; 96 bf16 out), 4 GEMMs (bf16
        # activations in and out), output (32 B) and decode (48 B); per ray its leaf list (16 B an entry, ~3 per row).
        row_bytes = 48 + 192 + 192 + 3 * 2 * 128 + 32 + 48
        floor = _floor_ms(q * row_bytes + n * 60, q * MLP_FLOPS_PER_ROW, ceil)
        whole.append({"query": query, "rays": n, "triton_Mrays/s": n / t_new / 1e3, "torch_Mrays/s": n / t_old / 1e3,
                      "optix_Mrays/s": n / t_exact / 1e3, "triton_x_optix": t_exact / t_new, "mlp_rows_per_ray": q / n,
                      "hit_agreement_torch": agree_old, "hit_agreement_optix": agree_exact, "triton_ms": t_new,
                      "floor_ms": floor, "triton_x_floor": t_new / floor})  # fmt: skip
    return whole


KERNELS = {  # (module, kernel, signature, constexprs) for --compile-only
    "list count": ("neuralrt.methods.nbvh_traversal_triton", "_list_kernel", "list", {"WRITE": False, "STACK": 64, "BLOCK": 64}),
    "list fill+sort": ("neuralrt.methods.nbvh_traversal_triton", "_list_kernel", "list", {"WRITE": True, "STACK": 64, "BLOCK": 64}),
    "first leaf": ("neuralrt.methods.nbvh_traversal_triton", "_first_kernel", "first", {"STACK": 64, "BLOCK": 64}),
    "hash grid forward": ("neuralrt.neural.hash_grid_triton", "_forward_kernel", "hash_fwd", dict(L=8, F=4, FP=4, BLOCK=128)),
    "hash grid backward": ("neuralrt.neural.hash_grid_triton", "_backward_kernel", "hash_bwd", dict(L=8, F=4, FP=4, BLOCK=128)),
    "step input (bf16)": ("neuralrt.methods.nbvh_wavefront_triton", "_step_input_kernel", "step_in", dict(L=8, F=4, FP=4, BLOCK=64)),
    "step decode": ("neuralrt.methods.nbvh_wavefront_triton", "_step_decode_kernel", "step_out",
                    dict(OUTPUTS=8, OP=8, ANY_HIT=False, BLOCK=64)),
}
_RAYS_CUT = dict(o_ptr="*fp32", inv_ptr="*fp32", tmax_ptr="*fp32", level_ptr="*i8", dil_ptr="*fp32", lo_ptr="*fp32", hi_ptr="*fp32",
                 children_ptr="*i32", lod_ptr="*i8", live_ptr="*i8")  # fmt: skip
_HASH = dict(res_ptr="*i32", size_ptr="*i32", offset_ptr="*i32", dense_ptr="*i32")
SIGNATURES = {
    "list": {**_RAYS_CUT, "count_ptr": "*i64", "start_ptr": "*i64", "node_out": "*i64", "t0_out": "*fp32", "t1_out": "*fp32",
             "stack_ptr": "*i32", "overflow_ptr": "*i32", "n": "i32", "rounds": "i32"},
    "first": {**_RAYS_CUT, "node_out": "*i64", "t0_out": "*fp32", "t1_out": "*fp32", "stack_ptr": "*i32", "stack_f_ptr": "*fp32",
              "overflow_ptr": "*i32", "n": "i32", "rounds": "i32"},
    "hash_fwd": {"pts_ptr": "*fp32", "table_ptr": "*fp32", **_HASH, "out_ptr": "*fp32", "n_points": "i32"},
    "hash_bwd": {"pts_ptr": "*fp32", "grad_out_ptr": "*fp32", **_HASH, "grad_table_ptr": "*fp32", "n_points": "i32"},
    "step_in": {"active_ptr": "*i64", "ptr_ptr": "*i64", "t0_ptr": "*fp32", "t1_ptr": "*fp32", "o_ptr": "*fp32", "d_ptr": "*fp32",
                "table_ptr": "*fp32", **_HASH, "x_ptr": "*bf16", "n_active": "i32", "frac0": "fp32", "frac1": "fp32", "frac2": "fp32"},
    "step_out": {"active_ptr": "*i64", "ptr_ptr": "*i64", "start_ptr": "*i64", "t0_ptr": "*fp32", "t1_ptr": "*fp32",
                 "t_max_ptr": "*fp32", "out_ptr": "*fp32", "best_t_ptr": "*fp32", "best_out_ptr": "*fp32", "keep_ptr": "*i8",
                 "n_active": "i32", "threshold": "fp32", "depth_pad": "fp32", "reversed_min": "fp32"},
}


def compile_only(arch: int) -> list[dict]:
    """Compile every kernel for sm_``arch`` (no GPU needed) and read ptxas's registers and spills."""
    if os.environ.get("TRITON_INTERPRET") == "1":
        raise SystemExit("neuralrt: error: --compile-only needs TRITON_INTERPRET unset")
    import importlib

    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    bin_dir = Path(triton.__file__).parent / "backends" / "nvidia" / "bin"
    rows = []
    for name, (module, kernel, sig, consts) in KERNELS.items():
        fn = getattr(importlib.import_module(module), kernel)
        signature = {**SIGNATURES[sig], **{k: "constexpr" for k in consts}}
        # As the launches: one lane per thread, pointers 16-byte aligned (the JIT specializes fresh
        # torch tensors so; without it no load is vectorized).
        params = list(inspect.signature(fn.fn).parameters)
        attrs = {(params.index(a),): [["tt.divisibility", 16]] for a, t in signature.items() if t.startswith("*")}
        options = {"num_warps": max(1, consts["BLOCK"] // 32)}
        compiled = triton.compile(ASTSource(fn, signature, consts, attrs), target=GPUTarget("cuda", arch, 32), options=options)
        ptx_ops = collections.Counter(re.findall(r"^\s*(?:@%p\d+\s+)?((?:atom|red|ld\.global|st\.global|ld\.shared|ld\.local)[\w.]*)",
                                                 compiled.asm["ptx"], re.M))  # fmt: skip
        report = ""
        with tempfile.TemporaryDirectory() as tmp:
            ptx = Path(tmp) / "k.ptx"
            ptx.write_text(compiled.asm["ptx"])
            for ptxas in (bin_dir / "ptxas", bin_dir / "ptxas-blackwell"):  # newer Triton's PTX needs the newer ptxas
                run = subprocess.run([str(ptxas), f"-arch=sm_{arch}{'a' if arch >= 90 else ''}", "-v", str(ptx), "-o",
                                      str(Path(tmp) / "k.cubin")], capture_output=True, text=True)  # fmt: skip
                if run.returncode == 0:
                    report = run.stderr
                    break
        regs = re.search(r"Used (\d+) registers", report)
        spill = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", report)
        rows.append({"kernel": name, "num_warps": compiled.metadata.num_warps, "registers": int(regs.group(1)) if regs else None,
                     "spill_stores": int(spill.group(1)) if spill else None, "spill_loads": int(spill.group(2)) if spill else None,
                     "memory_ops": " ".join(f"{k} x{v}" for k, v in sorted(ptx_ops.items()))})  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--mesh", default="statue:2", help="procedural mesh (name:detail)")
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--steps", type=int, default=1000, help="training steps (the paper preset has 10,000)")
    parser.add_argument("--model", type=Path, default=None, help="a trained .nrt of --mesh instead of training")
    parser.add_argument("--rays-log2", type=int, default=22)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--compile-only", action="store_true")
    parser.add_argument("--arch", type=int, default=90, help="with --compile-only: the sm_ version")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    payload = {"benchmark": "nbvh_cuda", "machine": machine_info(), "load_before": os.getloadavg(),
               "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    device = torch.device(args.device)
    out = args.out or RESULTS_DIR / (f"nbvh_cuda_compile_sm{args.arch}.json" if args.compile_only else f"nbvh_cuda_{device.type}.json")

    def save() -> None:  # after every section: a run cut short by its time limit keeps what it measured
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(payload, indent=2, default=float) + "\n")
        tmp.replace(out)

    if args.compile_only:
        import triton

        payload["triton"] = triton.__version__
        payload["kernels"] = compile_only(args.arch)
        save()
        print_table(payload["kernels"], ["kernel", "num_warps", "registers", "spill_stores", "spill_loads", "memory_ops"])
        print(f"wrote {out}")
        return
    from bench_mesh_blas import random_rays

    from neuralrt.methods import get_method, load_model
    from neuralrt.training.api import train

    name = torch.cuda.get_device_name(device) if device.type == "cuda" else payload["machine"]["cpu"]
    payload["device"] = name
    payload["torch"], payload["cuda"] = torch.__version__, torch.version.cuda
    payload["ceilings"] = ceil = ceilings(device)
    mesh = _mesh(args.mesh)
    if args.model is not None:
        model = load_model(args.model).to(device)
        payload["train"] = {"model": str(args.model)}
    else:
        config = get_method("nbvh").config(args.preset, device=device.type, steps=args.steps)
        start = time.perf_counter()
        model = train(mesh, config, progress=False, device=device)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds = time.perf_counter() - start
        tc = config.training
        payload["train"] = {"preset": args.preset, "steps": tc.steps, "batch": tc.batch_size, "train_s": seconds,
                            "s_per_1000_steps": 1000 * seconds / tc.steps, "nodes": model.num_nodes}  # fmt: skip
    save()
    print(f"{name} ({device.type}); train: {payload['train']}")
    rays = random_rays(mesh, 1 << args.rays_log2).to(device)
    with torch.no_grad():
        payload["stages"] = bench_stages(model, rays, device, args.repeats, ceil)
        save()
        print_table(payload["stages"], STAGE_COLUMNS)
        payload["whole"] = bench_whole(model, mesh, rays, device, args.repeats, ceil)
    payload["load_after"] = os.getloadavg()
    save()
    print()
    print_table(payload["whole"], WHOLE_COLUMNS)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

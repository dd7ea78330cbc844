"""N-BVH on CUDA: the training step and its pieces, the Triton kernels against the torch ops they replaced, and OptiX.

1. **train**: ``--steps`` steps (default 10,000) of the ``--preset``'s schedule (default ``paper``:
   2^18 rays per step, splits until 3,000) on ``--mesh``, stopped at ``--train-budget-s`` (the
   steps done and their time are reported, with the 10,000-step time projected from the
   steady-state step below); issue 9's target: 10,000 steps in <= 2 min on an H100.
   ``--model FILE`` loads a trained model instead.
2. **step**: ``--step-repeats`` training steps after the cut is complete (what 7,000 of the
   paper's 10,000 steps are), each cut into its pieces by device events (median per piece, and
   host time per piece): ``draw`` (the sampler without its ground truth: the Triton kernel, the
   Morton sort, object-space rays), ``truth`` (OptiX closest hits and their attributes),
   ``forward`` (chord points, hash grid, MLP, loss), ``backward``, ``optimizer`` (fused Adam),
   ``stats`` (node statistics, h_max), ``read`` (the trainer's one ``loss.item()``); host syncs
   per piece (``torch.cuda.set_sync_debug_mode``) and the sampler's yield.
3. **stages**, each timed with device events (median of ``--repeats``), Triton vs torch, with a check
   that both give the same answer and the floor of each stage (bytes through device memory over the
   measured copy bandwidth, FLOPs over the measured bf16 GEMM rate; the hash table and the cut's
   nodes are counted as cache-resident, their gathers are reported apart as ``l2_bytes``):
   ``list_leaves`` and ``first_leaves`` on one inference chunk of the rays (identical lists required), the
   hash grid forward on the first leaves' chord points and forward + backward on a training batch
   (2^18 queries of 3 points), and the whole ``intersect`` / ``occluded`` of the model: Triton path
   (what CUDA runs now), the earlier torch path (torch traversal, torch grid, torch wavefront), and
   OptiX closest / any hit on the same rays (Mitsuba 3).
4. JSON: benchmarks/results/nbvh_cuda_<device>.json (or ``--out PATH``), with machine, versions, load;
   written after every section.

Every argument is checked before any work. Without a GPU, only ``--compile-only`` and the runs under
``TRITON_INTERPRET=1`` below work (anything else is one error line).

    python benchmarks/bench_nbvh_cuda.py [--mesh statue:2] [--steps 10000] [--train-budget-s 240] [--rays-log2 22]
    python benchmarks/bench_nbvh_cuda.py --compile-only      # no GPU needed: compile for sm_90, ptxas registers/spills
    TRITON_INTERPRET=1 python benchmarks/bench_nbvh_cuda.py --count-step --device cpu   # no GPU needed: torch ops,
        # Triton launches and host syncs of one `paper`-shaped training step (small batch) per piece, the CUDA code
        # path on CPU tensors under the interpreter (launch and sync counts do not depend on the device)
    TRITON_INTERPRET=1 python benchmarks/bench_nbvh_cuda.py --device cpu --preset cpu --steps 10 --rays-log2 7 \
        --repeats 1 --step-repeats 2 --out /tmp/smoke.json   # a smoke run of the script on the CPU: numbers
                                            # meaningless (stages run under the interpreter, and "triton" whole
                                            # queries are the numba path)
"""

from __future__ import annotations

import collections
import contextlib
import importlib.util
import inspect
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (RESULTS_DIR, ArgumentParser, check_device, check_model_file, check_output_file,  # noqa: E402
                     check_presets, description, fail, int_in, machine_info, make_short_procedural,
                     parse_short_procedural, positive_float, positive_int, print_table, run_main, write_json)

STAGE_COLUMNS = ["stage", "items", "triton_ms", "torch_ms", "speedup", "same", "floor_ms", "triton_x_floor"]
WHOLE_COLUMNS = ["query", "rays", "triton_Mrays/s", "torch_Mrays/s", "optix_Mrays/s", "triton_x_optix", "mlp_rows_per_ray",
                 "hit_agreement_torch", "hit_agreement_optix"]
MLP_FLOPS_PER_ROW = 2 * (96 * 64 + 3 * 64 * 64 + 64 * 8)  # N-BVH's 4 x 64 MLP (8 outputs)


def _mesh(spec: str):
    return make_short_procedural(spec, "--mesh")


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


STEP_PIECES = ["draw", "truth", "forward", "backward", "optimizer", "stats", "read"]


class _TruthPieces:
    """The sampler's exact BLAS, with ``mark("truth")`` before its query and ``mark("draw")`` after."""

    def __init__(self, truth, mark):
        self.truth, self.mark = truth, mark

    def intersect(self, rays):
        self.mark("truth")
        hits = self.truth.intersect(rays)
        self.mark("draw")
        return hits


def training_step_in_pieces(model, sampler, opt, step: int, batch: int, mark) -> float:
    """One step of `train_model` (draw, loss, backward, Adam, the model's statistics, the loss read)
    with ``mark(piece)`` where each piece starts; returns the loss."""
    truth = sampler.truth
    sampler.truth = _TruthPieces(truth, mark)
    try:
        mark("draw")
        b = sampler.sample(batch)
        mark("forward")
        result = model.training_step(b.rays, b.truth)
        mark("backward")
        opt.zero_grad(set_to_none=True)
        result.loss.backward()
        mark("optimizer")
        opt.step()
        mark("stats")
        model.after_training_step(step, opt)
        mark("read")
        loss = result.loss.item()
        mark(None)
    finally:
        sampler.truth = truth
    return loss


def _optimizer(model):
    tc = model.config.training
    return torch.optim.Adam(model.parameters(), lr=tc.learning_rate, betas=tuple(tc.adam_betas), eps=tc.adam_eps,
                            weight_decay=tc.adam_l2, fused=next(model.parameters()).device.type in ("cuda", "cpu"))  # fmt: skip


def bench_step(model, mesh, device, repeats: int) -> dict:
    """Median device time (events) and host time of each piece of a training step after the cut is complete."""
    import warnings

    from neuralrt.accel.mesh_blas import MeshBLAS

    model.train()
    sampler = model.training_rays(MeshBLAS(mesh, device=device), device)
    opt = _optimizer(model)
    batch = model.config.training.batch_size
    step = model.config.training.steps  # past the last split: the schedule adds nothing
    rows = []
    cuda = device.type == "cuda"
    for k in range(repeats + 2):
        events, host = [], []

        def mark(piece):
            if cuda:
                e = torch.cuda.Event(enable_timing=True)
                e.record()
                events.append((piece, e))
            host.append((piece, time.perf_counter()))

        training_step_in_pieces(model, sampler, opt, step + k, batch, mark)
        if cuda:
            torch.cuda.synchronize(device)
        if k < 2:  # warm-up: compilation, allocator
            continue
        row = collections.defaultdict(float)
        for (piece, t0), (_, t1) in zip(host[:-1], host[1:]):
            row[f"{piece}_host_ms"] += 1e3 * (t1 - t0)
        if cuda:
            for (piece, e0), (_, e1) in zip(events[:-1], events[1:]):
                row[f"{piece}_ms"] += e0.elapsed_time(e1)
            row["step_ms"] = events[0][1].elapsed_time(events[-1][1])
        row["step_host_ms"] = 1e3 * (host[-1][1] - host[0][1])
        rows.append(row)
    out = {key: statistics.median(r[key] for r in rows) for key in rows[0]}
    out["steps_timed"], out["batch"], out["yield"] = len(rows), batch, sampler.last_yield()
    if cuda:  # host syncs per piece, as torch sees them (OptiX's own waits are not torch's)
        syncs = collections.Counter()
        piece = [None]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")

            def mark_syncs(p):
                for w in caught:
                    if "synchroniz" in str(w.message):
                        syncs[piece[0]] += 1
                caught.clear()
                piece[0] = p

            try:
                training_step_in_pieces(model, sampler, opt, step + repeats + 2, batch, mark_syncs)
            finally:
                torch.cuda.set_sync_debug_mode(0)
        out["torch_syncs"] = dict(syncs)
    model.eval()
    return out


_NO_LAUNCH = re.compile(r"^(view|_unsafe_view|alias|detach|empty|empty_like|empty_strided|new_empty|new_empty_strided|as_strided|expand|"
                        r"reshape|_reshape_alias|unsqueeze|squeeze|select|slice|t|transpose|permute|split|split_with_sizes|unbind|"
                        r"lift_fresh|set_|resize_|_to_copy_noop|result_type|is_same_size|sym_size|sym_stride|sym_numel|"
                        r"_has_compatible_shallow_copy_type|unfold|diagonal|narrow|chunk|view_as|expand_as|"
                        r"_local_scalar_dense)$")  # fmt: skip
_SYNC_OPS = {"_local_scalar_dense", "nonzero", "masked_select", "is_nonzero", "repeat_interleave", "_unique2", "unique_dim",
             "unique_consecutive", "nonzero_static"}  # fmt: skip


def count_step(args) -> dict:
    """Torch ops (about one kernel launch each on CUDA; views and allocations excluded), Triton
    launches and host syncs per piece of one training step, the CUDA code path run on CPU tensors
    under the interpreter: the sampler's Triton implementation (when this checkout has one, else
    the old host loop with the Triton first-leaf walk), the Triton hash grid. The exact BLAS is
    Embree here (OptiX on CUDA): its row is not the CUDA one."""
    from torch.utils._python_dispatch import TorchDispatchMode

    import neuralrt.methods.nbvh as nbvh_module
    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.methods import get_method
    from neuralrt.methods.nbvh_traversal_triton import first_leaves_triton
    from neuralrt.neural.hash_grid import HashGrid
    from neuralrt.neural.hash_grid_triton import hash_grid_triton

    mesh = _mesh(args.mesh)
    config = get_method("nbvh").config(args.preset, device="cpu", batch_size=args.count_batch)
    config = config.model_copy(update={"encoding": config.encoding.model_copy(update={"levels": 3})})  # the interpreter's time
    model = get_method("nbvh").model_class.from_mesh(mesh, config)
    nbvh_module.first_leaves = first_leaves_triton  # what CUDA rays take
    HashGrid.forward = lambda self, points: hash_grid_triton(points, self.table, self.layout)
    sampler = model.training_rays(MeshBLAS(mesh, device="cpu"), torch.device("cpu"))
    if hasattr(sampler, "implementation"):
        sampler.implementation = "triton"
    opt = _optimizer(model)
    from neuralrt.methods import nbvh_traversal_triton

    kernel_type = type(nbvh_traversal_triton._first_kernel)
    counts = collections.defaultdict(collections.Counter)
    piece = [None]
    run = kernel_type.run

    def counting_run(self, *a, **k):
        counts[piece[0]]["triton_launches"] += 1
        return run(self, *a, **k)

    class Count(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, a=(), kw=None):
            name = func.__name__.split(".")[0]
            c = counts[piece[0]]
            if not _NO_LAUNCH.match(name):
                c["torch_ops"] += 1
            if name in _SYNC_OPS or (name in ("index", "index_put", "index_put_") and any(
                    isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (a[1] if len(a) > 1 else []) if i is not None)):
                c["syncs"] += 1
                c[f"sync:{name}"] += 1
            return func(*a, **(kw or {}))

    def mark(p):
        piece[0] = p

    tolist, to_numpy = torch.Tensor.tolist, torch.Tensor.numpy

    def host_read(method):  # reads that bypass the dispatcher: a sync on CUDA each
        def read(self, *a, **k):
            counts[piece[0]]["syncs"] += 1
            counts[piece[0]][f"sync:{method.__name__}"] += 1
            return method(self, *a, **k)

        return read

    kernel_type.run = counting_run
    torch.Tensor.tolist, torch.Tensor.numpy = host_read(tolist), host_read(to_numpy)
    try:
        # Step 1 first: the tree depth, the level cache and compilation happen once; the counted step is the second.
        training_step_in_pieces(model, sampler, opt, 1, args.count_batch, mark)
        counts.clear()
        with Count():
            training_step_in_pieces(model, sampler, opt, 2, args.count_batch, mark)
    finally:
        kernel_type.run = run
        torch.Tensor.tolist, torch.Tensor.numpy = tolist, to_numpy
    rows = []
    for p in STEP_PIECES:
        c = counts.get(p, collections.Counter())
        rows.append({"piece": p, "torch_ops": c["torch_ops"], "triton_launches": c["triton_launches"], "syncs": c["syncs"],
                     "sync_ops": " ".join(f"{k[5:]} x{v}" for k, v in sorted(c.items()) if k.startswith("sync:"))})  # fmt: skip
    total = {"piece": "total", **{k: sum(r[k] for r in rows) for k in ("torch_ops", "triton_launches", "syncs")}, "sync_ops": ""}
    return {"rows": rows + [total], "batch": args.count_batch, "sampler": getattr(sampler, "implementation", "cpu loop (old)")}


KERNELS = {  # (module, kernel, signature, constexprs) for --compile-only
    "list count": ("neuralrt.methods.nbvh_traversal_triton", "_list_kernel", "list", {"WRITE": False, "STACK": 64, "BLOCK": 64}),
    "list fill+sort": ("neuralrt.methods.nbvh_traversal_triton", "_list_kernel", "list", {"WRITE": True, "STACK": 64, "BLOCK": 64}),
    "first leaf": ("neuralrt.methods.nbvh_traversal_triton", "_first_kernel", "first", {"STACK": 64, "BLOCK": 64}),
    "hash grid forward": ("neuralrt.neural.hash_grid_triton", "_forward_kernel", "hash_fwd", dict(L=8, F=4, FP=4, BLOCK=128)),
    "hash grid backward": ("neuralrt.neural.hash_grid_triton", "_backward_kernel", "hash_bwd", dict(L=8, F=4, FP=4, BLOCK=128)),
    "step input (bf16)": ("neuralrt.methods.nbvh_wavefront_triton", "_step_input_kernel", "step_in", dict(L=8, F=4, FP=4, BLOCK=64)),
    "step decode": ("neuralrt.methods.nbvh_wavefront_triton", "_step_decode_kernel", "step_out",
                    dict(OUTPUTS=8, OP=8, ANY_HIT=False, BLOCK=64)),
    "training sampler": ("neuralrt.methods.nbvh_rays_triton", "_sample_kernel", "sample", {"STACK": 40, "BLOCK": 64, "LEVELS": 7}),
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
    "sample": {"center_ptr": "*fp32", "extent_ptr": "*fp32", "reg_ptr": "*i8", "box_scale": "fp32", "dil_base": "fp32",
               "dil_jitter": "fp32", "lo_ptr": "*fp32", "hi_ptr": "*fp32", "children_ptr": "*i32", "lod_ptr": "*i8", "live_ptr": "*i8",
               "loss_sum_ptr": "*fp64", "samples_ptr": "*fp64", "alive_ptr": "*fp64", "h_max_ptr": "*fp64", "min_acceptance": "fp32",
               "start_out": "*fp32", "dir_out": "*fp32", "length_out": "*fp32", "node_out": "*i64", "code_out": "*i32",
               "rounds_out": "*i32", "flag_ptr": "*i32", "stack_ptr": "*i32", "stack_f_ptr": "*fp32", "n": "i32", "quota": "i32",
               "seed": "i32", "call_base": "i64", "max_rounds": "i32"},
    "step_out": {"active_ptr": "*i64", "ptr_ptr": "*i64", "start_ptr": "*i64", "t0_ptr": "*fp32", "t1_ptr": "*fp32",
                 "t_max_ptr": "*fp32", "out_ptr": "*fp32", "best_t_ptr": "*fp32", "best_out_ptr": "*fp32", "keep_ptr": "*i8",
                 "n_active": "i32", "threshold": "fp32", "depth_pad": "fp32", "reversed_min": "fp32"},
}


def compile_only(arch: int) -> list[dict]:
    """Compile every kernel for sm_``arch`` (no GPU needed) and read ptxas's registers and spills."""
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


class _Budget(Exception):
    pass


def train_with_budget(mesh, args, device) -> tuple:
    """`neuralrt.training.api.train` for ``--steps`` steps of the preset's schedule, stopped after
    ``--train-budget-s`` seconds: (model, figures)."""
    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.methods import get_method
    from neuralrt.training.trainer import train_model

    spec = get_method("nbvh")
    config = spec.config(args.preset, device=device.type)
    tc = config.training
    model = spec.model_class.from_mesh(mesh, config).to(device)
    sampler = model.training_rays(MeshBLAS(mesh, device=device), device)
    done = [0]
    start = time.perf_counter()

    def on_step(step, opt):
        model.after_training_step(step, opt)
        done[0] = step + 1
        if time.perf_counter() - start > args.train_budget_s and done[0] < args.steps:
            raise _Budget

    record = None
    with contextlib.suppress(_Budget):
        record = train_model(model, sampler, steps=min(args.steps, tc.steps), batch_size=tc.batch_size, learning_rate=tc.learning_rate,
                             adam_betas=tc.adam_betas, adam_eps=tc.adam_eps, adam_l2=tc.adam_l2, lr_decay_final=tc.lr_decay_final, progress=False,
                             on_step=on_step)  # fmt: skip
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - start
    model.eval()
    info = {"preset": args.preset, "schedule_steps": tc.steps, "steps_done": done[0], "batch": tc.batch_size, "train_s": seconds,
            "s_per_1000_steps": 1000 * seconds / max(done[0], 1), "live_nodes": model.live_nodes(), "stopped_by_budget": record is None,
            "hit_accuracy": record.hit_accuracy if record else None}  # fmt: skip
    return model, info


def check_arguments(args) -> torch.device:
    """Every argument, for the mode asked for, before any work (a bad one is one line): the device."""
    interpreted = os.environ.get("TRITON_INTERPRET") == "1"
    if args.out is not None:
        check_output_file(args.out, "results file")
    if args.compile_only:
        if interpreted:
            fail("--compile-only compiles for the GPU: unset TRITON_INTERPRET")
        if importlib.util.find_spec("triton") is None:
            fail("--compile-only needs Triton (not installed)")
        return torch.device("cpu")
    parse_short_procedural(args.mesh, "--mesh")
    if args.count_step:
        if not interpreted:
            fail("--count-step runs the CUDA path on CPU tensors: set TRITON_INTERPRET=1")
        check_presets("nbvh", [args.preset], device="cpu", batch_size=args.count_batch)
        return torch.device("cpu")
    device = check_device(args.device)
    check_presets("nbvh", [args.preset], device=device.type)
    if args.model is not None:
        check_model_file(args.model, method="nbvh")
    if device.type != "cuda" and not interpreted:
        fail(f"--device {args.device}: the CUDA code path runs on the CPU only under the Triton interpreter "
             "(TRITON_INTERPRET=1, a smoke run); without a GPU, --compile-only")
    return device


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--mesh", default="statue:2", help="procedural mesh (name:detail)")
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--steps", type=positive_int, default=10_000, help="training steps to run of the preset's schedule")
    parser.add_argument("--train-budget-s", type=positive_float, default=240.0, help="stop training after this many seconds")
    parser.add_argument("--step-repeats", type=positive_int, default=20, help="training steps timed piece by piece")
    parser.add_argument("--count-step", action="store_true", help="count ops, launches and syncs of one step (CPU, interpreter)")
    parser.add_argument("--count-batch", type=positive_int, default=1024, help="with --count-step: rays per step")
    parser.add_argument("--model", type=Path, default=None, help="a trained .nrt of --mesh instead of training")
    parser.add_argument("--rays-log2", type=int_in(0, 30), default=22)
    parser.add_argument("--repeats", type=positive_int, default=20)
    parser.add_argument("--compile-only", action="store_true")
    parser.add_argument("--arch", type=int_in(50, 130), default=90, help="with --compile-only: the sm_ version (90: H100)")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON path (default benchmarks/results/nbvh_cuda_<device type>.json, nbvh_cuda_compile_sm<ARCH>.json "
                             "with --compile-only, /tmp/nbvh_count_step.json with --count-step)")
    args = parser.parse_args()
    device = check_arguments(args)
    payload = {"benchmark": "nbvh_cuda", "machine": machine_info(), "load_before": os.getloadavg(),
               "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    out = args.out or RESULTS_DIR / (f"nbvh_cuda_compile_sm{args.arch}.json" if args.compile_only else f"nbvh_cuda_{device.type}.json")

    def save() -> None:  # after every section: a run cut short by its time limit keeps what it measured
        write_json(out, payload)

    if args.count_step:
        payload["count"] = count_step(args)
        out = args.out or Path("/tmp/nbvh_count_step.json")
        save()
        print(f"sampler: {payload['count']['sampler']}, batch {args.count_batch}")
        print_table(payload["count"]["rows"], ["piece", "torch_ops", "triton_launches", "syncs", "sync_ops"])
        return
    if args.compile_only:
        import triton

        payload["triton"] = triton.__version__
        payload["kernels"] = compile_only(args.arch)
        save()
        print_table(payload["kernels"], ["kernel", "num_warps", "registers", "spill_stores", "spill_loads", "memory_ops"])
        print(f"wrote {out}")
        return
    from bench_mesh_blas import random_rays

    from neuralrt.methods import load_model

    name = torch.cuda.get_device_name(device) if device.type == "cuda" else payload["machine"]["cpu"]
    payload["device"] = name
    payload["torch"], payload["cuda"] = torch.__version__, torch.version.cuda
    payload["ceilings"] = ceil = ceilings(device)
    mesh = _mesh(args.mesh)
    if args.model is not None:
        model = load_model(args.model).to(device)
        payload["train"] = {"model": str(args.model)}
    else:
        model, payload["train"] = train_with_budget(mesh, args, device)
    save()
    print(f"{name} ({device.type}); train: {payload['train']}")
    payload["step"] = step = bench_step(model, mesh, device, args.step_repeats)
    train_info = payload["train"]
    if "steps_done" in train_info and "step_ms" in step:  # the rest of the schedule at the steady-state step time
        rest = train_info["schedule_steps"] - train_info["steps_done"]
        train_info["projected_s_for_schedule"] = train_info["train_s"] + rest * step["step_ms"] / 1e3
    save()
    flat = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in step.items() if not isinstance(v, dict)}
    print_table([flat], list(flat))
    print(f"torch syncs per piece: {step.get('torch_syncs')}; train: {train_info}")
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
    run_main(main)

"""How LSNIF's CPU training and inference scale with cores: the same work at 1, 2, 4, 8, 16 threads.

    python benchmarks/bench_scaling.py [--threads 1 2 4 8 16] [--train-mesh procedural:statue:2]
        [--infer-mesh procedural:hairball:6] [--presets hq lq] [--steps 40] [--rays 262144]
        [--repeats 5] [--train-batches 32768 65536] [--profile] [--name scaling_cpu]

Each thread count runs in its own process, pinned to that many cores (``os.sched_setaffinity``
before torch and numba load) with ``NUMBA_NUM_THREADS`` / ``OMP_NUM_THREADS`` set, so numba's
kernels, torch's GEMMs and the Embree chunks (which follow numba's thread count) all see the same
machine size. In each process:
- training: a fresh model per preset (same seed) trained ``--steps`` steps after a 5-step warm-up,
  the batch drawn ahead on the background thread and drawn in turn (``neuralrt train`` times both
  in its first steps and keeps the faster, `training.prefetch`: the figure without a mode is the
  faster); best of 2 runs each, rays/s =
  rays drawn / wall time of the loop (as bench_training.py); with ``--train-batches``, also at
  those batch sizes, drawing the same rays in fewer steps (a step's fixed costs, paid once per
  step on the loop's thread, shrink per ray); with ``--profile``, one more run per batch size
  and mode (drawn ahead, in turn) under `StageTimer`: ms per step in each stage, on the loop's
  thread and on the drawing one;
  with ``--scatters``, the encoder's backward alone on one batch of each size, per scatter;
- inference: an untrained model on the mesh's real occupancy (random table, rounded to its storage
  precision as `train` returns a model: the speed does not depend on the weights) and Embree on the same ``--rays`` rays (`BoxRayDistribution`), interleaved,
  best of ``--repeats``: ``intersect`` and ``occluded`` rays/s of both; with ``--switches``, LSNIF's
  also with each setting (``lsnif_intersect[MIN_RAYS_PER_THREAD=0]_hq_rays/s``), in the same rounds.
The table gives each figure's speed-up over the 2-thread process (the issue's "2-core rate") and
over 1 thread; with ``--profile`` and both 1 and 2 threads, a second table gives each stage's
serial part (Amdahl from the two timings) and the best speed-up 16 threads could give over 2 with
it. Writes benchmarks/results/<--name>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first, as in every benchmark: it sets how OpenMP threads wait before torch loads OpenMP)

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _common import (ArgumentParser, check_mesh_spec, check_presets, description, fail, positive_int,  # noqa: E402
                     prog, result_name, run_main)

SCATTERS = ("auto", "row_ranges", "buckets", "saved_rows", "thread_tables")  # SparseHashGrid.backward_scatter


def _at_batch(config, batch: int, default_steps: int):
    """``config`` at ``batch`` rays per step, and the steps that draw the rays of ``default_steps``
    steps at its own batch (fewer, larger steps; at least 8)."""
    sized = config.model_copy(update={"training": config.training.model_copy(update={"batch_size": batch})})
    return sized, max(8, default_steps * config.training.batch_size // batch)


def _scatter_times(mesh, truth, config, args) -> dict:
    """The encoder's backward (autograd into the table) of one real batch per training batch size,
    with each of ``--scatters``; best of 8 runs (the first also compiles), ms. Every scatter's gradient is checked equal to the first's."""
    import torch

    from neuralrt.methods.lsnif import LSNIFModel

    model = LSNIFModel.from_mesh(mesh, config)
    draw = model.training_rays(truth, torch.device("cpu"))
    encoder = model.encoder
    times = {}
    for batch in sorted({config.training.batch_size, *args.train_batches}):
        rows = model.prepare_training_batch(draw.sample(batch).rays)
        inputs = (rows.features.points, rows.features.face_axis, rows.distances, torch.bfloat16)
        upstream = torch.randn(encoder(*inputs, rows=rows.keep).shape, generator=torch.Generator().manual_seed(0)).to(torch.bfloat16)
        first = None
        for scatter in args.scatters:
            encoder.backward_scatter = scatter
            best = float("inf")
            for _ in range(8):  # the first compiles / warms
                out = encoder(*inputs, rows=rows.keep)
                t0 = time.perf_counter()
                (grad,) = torch.autograd.grad(out, encoder.table, upstream)
                best = min(best, time.perf_counter() - t0)
            first = grad if first is None else first
            if not torch.equal(grad, first):
                raise SystemExit(f"neuralrt: error: the {scatter} scatter's gradient differs from the {args.scatters[0]} one's")
            times[f"batch{batch}_{scatter}"] = round(1e3 * best, 3)
    return times


def _switch_settings(text: str) -> list[tuple[str, bool | int | None]]:
    """``NAME=VALUE[,NAME=VALUE...]`` as (name, value) pairs: each NAME ``chunk_size`` or a
    module-level switch of `lsnif_fused_cpu`, each VALUE True, False, None or a whole number
    (argparse.ArgumentTypeError otherwise)."""
    from neuralrt.methods import lsnif_fused_cpu

    constants = {"True": True, "False": False, "None": None}
    settings = []
    for item in text.split(","):
        name, sep, value = item.partition("=")
        if not sep or not (name == "chunk_size" or (name.isupper() and hasattr(lsnif_fused_cpu, name))):
            raise argparse.ArgumentTypeError(f"{item!r}: want NAME=VALUE, NAME chunk_size or a switch of lsnif_fused_cpu")
        if value not in constants and not value.isdigit():
            raise argparse.ArgumentTypeError(f"{item!r}: VALUE is True, False, None or a whole number")
        settings.append((name, constants[value] if value in constants else int(value)))
    return settings


def _switch_argument(text: str) -> str:
    """An argparse type: ``text`` where `_switch_settings` accepts it (before any process starts)."""
    _switch_settings(text)
    return text


def _with_switch(model, switch: str, call):
    """``call`` run with the settings of ``switch`` (`_switch_settings`: ``chunk_size`` is the
    model's inference chunk, other names `lsnif_fused_cpu`'s switches), then restored."""
    from neuralrt.methods import lsnif_fused_cpu

    settings = [(model.config.inference if name == "chunk_size" else lsnif_fused_cpu, name, value)
                for name, value in _switch_settings(switch)]  # fmt: skip

    def run():
        saved = [(owner, name, getattr(owner, name)) for owner, name, _ in settings]
        for owner, name, value in settings:
            setattr(owner, name, value)
        try:
            return call()
        finally:
            for owner, name, value in saved:
                setattr(owner, name, value)

    return run


def _child(args) -> dict:
    """One thread count: pin, then import and measure (runs in its own process)."""
    import numba  # (neuralrt, imported at the top, set how OpenMP threads wait before torch loads OpenMP)
    import torch

    from bench_lsnif import resolve_mesh
    from _stage_timer import StageTimer
    from bench_training import _train

    from neuralrt.accel.mesh_blas import MeshBLAS
    from neuralrt.methods.lsnif import LSNIFModel
    from neuralrt.methods.lsnif_config import LSNIFConfig
    from neuralrt.training.ray_distribution import BoxRayDistribution

    torch.set_num_threads(args.child)
    row: dict = {"threads": args.child, "numba_threads": numba.get_num_threads(), "torch_threads": torch.get_num_threads(),
                 "cores_pinned": len(os.sched_getaffinity(0)), "load_before": os.getloadavg()[0]}
    train_mesh = resolve_mesh(args.train_mesh)
    train_truth = MeshBLAS(train_mesh)
    def train_rate(config, steps: int, key: str) -> None:
        """Rays/s drawing each batch ahead and in turn (best of 2 runs each; the default,
        ``overlap_sampling=None``, times both in its first steps and keeps the faster): the
        faster under ``key``, each under ``key`` with ``[ahead]`` / ``[in turn]``."""
        for mode, label in ((True, "ahead"), (False, "in turn")):
            runs = [_train(train_mesh, train_truth, config, steps, mode) for _ in range(2)]
            row[key.replace("_rays/s", f"[{label}]_rays/s")] = max(n / wall for wall, n in runs)
        row[key] = max(row[key.replace("_rays/s", f"[{label}]_rays/s")] for label in ("ahead", "in turn"))

    for preset in [] if args.skip_training else args.presets:
        config = LSNIFConfig.preset(preset)
        _train(train_mesh, train_truth, config, 5, True)  # warm-up: numba compilation, thread pools
        train_rate(config, args.steps, f"train_{preset}_rays/s")
        default_batch = config.training.batch_size
        for batch in args.train_batches:
            if batch == default_batch:
                continue
            sized, steps = _at_batch(config, batch, args.steps)
            _train(train_mesh, train_truth, sized, 2, True)  # warm-up at this batch (oneDNN kernels for its row counts)
            train_rate(sized, steps, f"train_{preset}_batch{batch}_rays/s")
        if args.profile:
            for batch in sorted({default_batch, *args.train_batches}):
                sized, steps = _at_batch(config, batch, args.steps)
                for mode, label in ((True, "ahead"), (False, "in turn")):
                    with StageTimer() as timer:
                        wall, _ = _train(train_mesh, train_truth, sized, steps, mode)
                    row[f"train_{preset}_batch{batch}[{label}]_stages_ms_per_step"] = timer.per_step(wall, steps)

        if args.scatters:
            row[f"encoder_backward_{preset}_ms"] = _scatter_times(train_mesh, train_truth, config, args)

    mesh = resolve_mesh(args.infer_mesh)
    exact = MeshBLAS(mesh)
    for preset in args.presets:
        model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset(preset))
        with torch.no_grad():
            model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(0))
        model.round_to_storage_precision_()  # as `train` returns a model and a file loads it (the float16 table reads)
        rays = BoxRayDistribution(exact, model.box, seed=4242, pool_size=1 << 16).sample(args.rays).rays
        calls = {"lsnif_intersect": lambda: model.intersect(rays), "lsnif_occluded": lambda: model.occluded(rays),
                 "embree_intersect": lambda: exact.intersect(rays), "embree_occluded": lambda: exact.occluded(rays)}
        for switch in args.switches:
            calls[f"lsnif_intersect[{switch}]"] = _with_switch(model, switch, lambda: model.intersect(rays))
            calls[f"lsnif_occluded[{switch}]"] = _with_switch(model, switch, lambda: model.occluded(rays))
        for fn in calls.values():  # compile / warm caches
            fn()
        best = dict.fromkeys(calls, float("inf"))
        for _ in range(args.repeats):
            for key, fn in calls.items():
                t0 = time.perf_counter()
                fn()
                best[key] = min(best[key], time.perf_counter() - t0)
        for key, seconds in best.items():
            row[f"{key}_{preset}_rays/s"] = args.rays / seconds  # Embree per preset too: each preset draws its own rays
    row["load_after"] = os.getloadavg()[0]
    row["numba_threading_layer"] = numba.threading_layer()  # (known once a parallel kernel has run)
    return row


def _write(args, rows: list[dict], show: bool) -> Path:
    """The table (each figure against the 2-thread and 1-thread processes, where run) and the JSON."""
    from _common import machine_info, print_table, write_results

    figures = [k for k in rows[0] if k.endswith("rays/s")]
    base2 = next((r for r in rows if r["threads"] == 2), None)
    base1 = next((r for r in rows if r["threads"] == 1), None)
    table = []
    for r in rows:
        for k in figures:
            table.append({"threads": r["threads"], "figure": k, "rays/s": r[k],
                          "vs_2_threads": r[k] / base2[k] if base2 else None, "vs_1_thread": r[k] / base1[k] if base1 else None})
    serial = _serial_parts(base1, base2) if base1 and base2 else []
    if show:
        print_table(table, ["threads", "figure", "rays/s", "vs_2_threads", "vs_1_thread"])
        if serial:
            print("\nSerial time per step from the 1- and 2-thread stage timers (Amdahl, the rest taken as perfectly parallel):")
            print_table(serial, ["profile", "stage", "ms_1_thread", "ms_2_threads", "serial_ms", "bound_16_vs_2"])
    return write_results(args.name, table, {"machine": machine_info(), "per_process": rows, "serial_parts": serial,
                                            "settings": {k: v for k, v in vars(args).items() if k != "child"}})


def _serial_parts(one: dict, two: dict) -> list[dict]:
    """Per profiled stage (``--profile``): its time at 1 and 2 threads, the serial part those imply
    (t1 = s + p, t2 = s + p / 2, so s = 2 t2 - t1, clamped to [0, t2]) and the best speed-up over 2
    threads that 16 could then give (t2 / (s + p / 16)): an upper bound, as the parallel part is
    taken to scale perfectly. The step's "wall" row bounds the issue's 16-core target (>= 5x)."""
    parts = []
    for key, stages in two.items():
        if not key.endswith("_stages_ms_per_step") or key not in one:
            continue
        for stage, t2 in stages.items():
            t1 = one[key].get(stage)
            if t1 is None or "[drawing thread]" in stage or t2 <= 0:
                continue
            s = min(max(2 * t2 - t1, 0.0), t2)
            p = max(t1 - s, 0.0)
            parts.append({"profile": key.removesuffix("_stages_ms_per_step"), "stage": stage.strip(), "ms_1_thread": t1,
                          "ms_2_threads": t2, "serial_ms": s, "bound_16_vs_2": t2 / (s + p / 16) if s + p > 0 else None})
    return parts


def main() -> None:
    ap = ArgumentParser(description=description(__doc__))
    ap.add_argument("--threads", type=positive_int, nargs="+", default=[1, 2, 4, 8, 16])
    ap.add_argument("--train-mesh", default="procedural:statue:2")
    ap.add_argument("--infer-mesh", default="procedural:hairball:6")
    ap.add_argument("--presets", nargs="+", default=["hq", "lq"])
    ap.add_argument("--steps", type=positive_int, default=40)
    ap.add_argument("--train-batches", type=positive_int, nargs="*", default=[],
                    help="training rays/s also at these batch sizes (the same rays drawn: fewer steps)")
    ap.add_argument("--profile", action="store_true",
                    help="one more training run per preset and batch size with stage timers: ms per step in each stage")
    ap.add_argument("--scatters", nargs="*", default=[], choices=SCATTERS,
                    help="also time the encoder's backward with these table-gradient scatters (row_ranges, buckets, saved_rows)")
    ap.add_argument("--skip-training", action="store_true", help="inference alone")
    ap.add_argument("--switches", nargs="*", type=_switch_argument, default=[],
                    help="inference also with each of these settings (NAME=VALUE[,NAME=VALUE...]: switches of lsnif_fused_cpu "
                         "such as HIDDEN_LAYERS_IN_DECODE=True, or chunk_size=N), interleaved with the default")
    ap.add_argument("--rays", type=positive_int, default=1 << 18)
    ap.add_argument("--repeats", type=positive_int, default=5)
    ap.add_argument("--name", type=result_name, default="scaling_cpu")
    ap.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print("RESULT " + json.dumps(_child(args)), flush=True)
        return

    # Every check here, before the first process starts (a bad argument is one line, not each child's traceback).
    check_mesh_spec(args.train_mesh)
    check_mesh_spec(args.infer_mesh)
    check_presets("lsnif", args.presets, "--presets")
    cores = sorted(os.sched_getaffinity(0))
    counts = [n for n in args.threads if n <= len(cores)]
    if not counts:
        fail(f"no thread count in {' '.join(map(str, args.threads))} fits this machine's {len(cores)} cores")
    rows = []
    for n in counts:
        env = dict(os.environ, NUMBA_NUM_THREADS=str(n), OMP_NUM_THREADS=str(n), MKL_NUM_THREADS=str(n))
        pin = f"import os, sys, runpy; os.sched_setaffinity(0, {cores[:n]}); sys.argv = {[str(Path(__file__))] + sys.argv[1:] + ['--child', str(n)]}; runpy.run_path(sys.argv[0], run_name='__main__')"
        t0 = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", pin], env=env, capture_output=True, text=True)
        lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
        if done.returncode or not lines:
            sys.stderr.write(done.stdout[-4000:] + done.stderr[-4000:])
            sys.exit(f"{prog()}: error: the {n}-thread process failed (exit {done.returncode})")
        row = json.loads(lines[-1][len("RESULT "):])
        row["process_s"] = time.perf_counter() - t0
        rows.append(row)
        print(f"{n:3d} threads: " + ", ".join(f"{k} {v:,.0f}" for k, v in row.items() if k.endswith("rays/s")), flush=True)
        _write(args, rows, show=False)  # after each process: a run cut short keeps what it measured
    print(f"wrote {_write(args, rows, show=True)}")


if __name__ == "__main__":
    run_main(main)

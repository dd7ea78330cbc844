"""LSNIF training throughput on the CPU: today's step against the step before a CPU speed-up,
alternating in one run.

    python benchmarks/bench_training.py [--mesh PATH|procedural:NAME:DETAIL] [--steps 60] [--repeats 3] [--preset hq]
        [--pair step|mlp|previous|saved_rows|rows|saved_rows_and_index|prepare_ahead|row_bucket|draw_priority|overlap|overlap_trial|loss_threads|scatter|draw_threads|loss_chunks|draw_pool|float32_walk]
        [--draw-threads 1] [--name training_cpu_step]

Configurations (both draw the next batch on a background thread, the default before session 40,
except in ``overlap`` and ``overlap_trial``), by ``--pair``:
- ``step`` (default): ``before`` runs the output layer and the loss as torch ops
  (`lsnif_loss.training_loss_torch`) and casts the encoder's fp32 output to the MLP's bf16
  (``SparseHashGrid.low_precision_output = False``); ``after`` runs them as numba passes
  (`training_loss_numba`: outputs, terms, figures and the gradients of the hidden activations and
  the output layer together) and the encoder writes bf16 itself (and reads the bf16 gradient as it is);
- ``mlp``: ``before`` trains the bf16 hidden layers under ``torch.autocast``
  (``MLP.low_precision_training = "autocast"``), ``after`` as one autograd function (bit-equal);
- ``previous``: per-thread gradient tables and the torch selection against row ranges and the
  numba selection;
- ``saved_rows``: the encoder backward hashing every point again (``backward_scatter =
  "row_ranges"``) against scattering from the rows and weights the forward saved (``"saved_rows"``);
- ``rows``: the network rays' points copied before the encoder (``LSNIFModel.training_rows_by_index
  = False``) against the encoder reading them through their index (``True``);
- ``saved_rows_and_index``: both of the two above together;
- ``prepare_ahead``: the voxel walk and the network-ray selection inside the step against computed
  with the batch on its drawing thread (`LSNIFModel.prepare_training_batch`).
- ``draw_priority``: the batches drawn by a thread of normal priority against one of idle priority
  (`prefetch.IDLE_PRIORITY`; Linux);
- ``overlap``: each batch drawn in turn by the loop's thread (``train_model(overlap_sampling=False)``)
  against drawn ahead on the background thread (``True``);
- ``overlap_trial``: drawn in turn against the default (``None``: the run's first steps time both
  modes, then it keeps the faster, checked again every `prefetch.RECHECK_EVERY` steps;
  `prefetch.BatchSource`); use runs far longer than the trial's 74 steps;
- ``loss_threads``: the loss pass (`training_loss_numba`) on one thread, as it ran before its row
  chunks went parallel, against on all of numba's threads;
- ``scatter``: the encoder backward's row-range scatter against the bucketed one (on any host).
- ``draw_threads``: the batch drawing thread's numba passes and Embree chunks on all of numba's
  threads against on ``--draw-threads`` (1; its own count: `numba.set_num_threads` is per calling
  thread; with 1, torch's OpenMP regions on that thread run on it alone too, so it starts no
  OpenMP team of its own);
- ``loss_chunks``: the loss passes' rows in chunks of `lsnif_loss.CHUNK_ROWS` (1,024) against
  chunks of 256 (a 2^13-ray batch's ~5,400 network rays make 6 chunks of 1,024, fewer than 16
  threads).
- ``draw_pool``: the drawing thread's Embree chunks on the pool the loop's thread started with the
  first batch (normal priority) against on a pool of its own, whose threads it starts (so they run
  at its idle priority: a thread starts with its starter's scheduling policy);
- ``float32_walk``: the batches' voxel walk in float64 (`featurize_rays_numba`) against the
  16-lane float32 walk of the fused inference pass (`lsnif_features_simd`; ``LSNIFModel.float32_walk``);
- ``row_bucket``: the bf16 GEMMs on the batch's own row count (a new oneDNN kernel nearly every
  step) against rows padded to a multiple of 256 (`mlp.ROW_BUCKET`).
The other switches are today's in both.

Each run trains a fresh model (same seed) for ``--steps`` steps after one warm-up run (numba
compilation); rays/s is rays drawn / wall time of the whole loop; ``paired`` ratios are each
``after`` run over the ``before`` run just before it. Also records one more run of each under
`StageTimer` (ms per step in each stage, per thread), and the 1-minute load average before and after.
Writes benchmarks/results/<--name>.json (training_cpu.json holds the earlier pair's run).
"""

from __future__ import annotations

import ctypes
import os
import statistics
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import numba
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (ArgumentParser, check_mesh_spec, check_presets, description, machine_info,  # noqa: E402
                     positive_int, print_table, result_name, run_main, write_results)
from _stage_timer import StageTimer  # noqa: E402
from bench_lsnif import resolve_mesh  # noqa: E402

from neuralrt import host_threads  # noqa: E402
from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.methods import lsnif as lsnif_module  # noqa: E402
from neuralrt.methods import lsnif_loss as lsnif_loss_module  # noqa: E402
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel  # noqa: E402
from neuralrt.methods.lsnif_features import select_network_rays, select_network_rays_torch  # noqa: E402
from neuralrt.methods.lsnif_loss import training_loss, training_loss_torch  # noqa: E402
from neuralrt.neural import mlp as mlp_module  # noqa: E402
from neuralrt.training import prefetch as prefetch_module  # noqa: E402
from neuralrt.training.trainer import train_model  # noqa: E402

CONFIGS = ("before", "after")


PAIR = "step"  # --pair
DRAW_THREADS = 1  # --draw-threads
CHUNK_ROWS = lsnif_loss_module.CHUNK_ROWS
SMALL_CHUNK_ROWS = 256  # loss_chunks' after


def _configure(model: LSNIFModel, config: str) -> None:
    """Switch the model's CPU training step to one configuration (see the module docstring)."""
    before = config == "before"
    if PAIR == "previous":
        model.encoder.backward_scatter = "thread_tables" if before else "row_ranges"
        lsnif_module.select_network_rays = select_network_rays_torch if before else select_network_rays
    elif PAIR == "saved_rows":
        model.encoder.backward_scatter = "row_ranges" if before else "saved_rows"
    elif PAIR in ("rows", "saved_rows_and_index"):
        model.training_rows_by_index = not before
        if PAIR == "saved_rows_and_index":
            model.encoder.backward_scatter = "row_ranges" if before else "saved_rows"
    elif PAIR == "prepare_ahead":
        if before:
            model.prepare_training_batch = lambda rays: None  # the loop hands nothing: the step computes it
    elif PAIR == "draw_priority":
        prefetch_module.IDLE_PRIORITY = not before
    elif PAIR == "row_bucket":
        mlp_module.ROW_BUCKET["cpu"] = 1 if before else 256
    elif PAIR in ("overlap", "overlap_trial"):
        pass  # the loop's own switch (`_train`)
    elif PAIR == "loss_threads":
        lsnif_module.training_loss = _on_one_thread(training_loss) if before else training_loss
    elif PAIR == "draw_threads":
        prefetch_module._lower_priority = _priority_default if before else _lower_priority_and_draw_threads
    elif PAIR == "loss_chunks":
        lsnif_loss_module.CHUNK_ROWS = CHUNK_ROWS if before else SMALL_CHUNK_ROWS
    elif PAIR == "draw_pool":
        host_threads.thread_pool = _thread_pool_default if before else _thread_pool_per_policy
    elif PAIR == "scatter":
        model.encoder.backward_scatter = "row_ranges" if before else "buckets"
    elif PAIR == "mlp":
        model.network.low_precision_training = "autocast" if before else "function"
    elif PAIR == "float32_walk":
        model.float32_walk = not before
    else:
        lsnif_module.training_loss = training_loss_torch if before else training_loss
        model.encoder.low_precision_output = not before


_priority_default = prefetch_module._lower_priority


_thread_pool_default = host_threads.thread_pool


def _thread_pool_per_policy(purpose: str, workers: int):
    """`host_threads.thread_pool` with one pool per scheduling policy of the calling thread."""
    return _thread_pool_default(f"{purpose}-policy{os.sched_getscheduler(0)}", workers)


def _lower_priority_and_draw_threads() -> None:
    _priority_default()
    numba.set_num_threads(min(DRAW_THREADS, numba.config.NUMBA_NUM_THREADS))
    if DRAW_THREADS == 1:
        _torch_openmp_on_one_thread()


def _torch_openmp_on_one_thread() -> None:
    """torch's OpenMP parallel regions on the calling thread to one thread (the thread count is an
    OpenMP setting of each thread; torch's wheel bundles its own libgomp): so the drawing thread
    starts no OpenMP team of its own, which would make libgomp throttle every thread's spinning
    (more OpenMP threads than cores; docs/lsnif.md, session 40)."""
    lib = Path(torch.__file__).parent / "lib" / "libgomp.so.1"
    if lib.exists():
        ctypes.CDLL(str(lib)).omp_set_num_threads(1)


def _on_one_thread(fn):
    """``fn`` with numba's thread count set to 1 for the call (numba's count is per calling thread)."""

    def wrapped(*args, **kwargs):
        threads = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            return fn(*args, **kwargs)
        finally:
            numba.set_num_threads(threads)

    return wrapped


DRAWN_AHEAD: list = []  # each run's `TrainingRecord.batches_drawn_ahead`


def _train(mesh, truth, config, steps: int, overlap: bool | None, variant: str = "after") -> tuple[float, int]:
    if PAIR in ("overlap", "overlap_trial"):
        overlap = False if variant == "before" else (True if PAIR == "overlap" else None)
    model = LSNIFModel.from_mesh(mesh, config)
    _configure(model, variant)
    rays = model.training_rays(truth, torch.device("cpu"))
    tc = config.training
    t0 = time.perf_counter()
    record = train_model(model, rays, steps=steps, batch_size=tc.batch_size, learning_rate=tc.learning_rate,
                         adam_betas=tc.adam_betas, adam_eps=tc.adam_eps, adam_l2=tc.adam_l2, lr_decay_final=tc.lr_decay_final,
                         progress=False, on_step=model.after_training_step, overlap_sampling=overlap)
    DRAWN_AHEAD.append(record.batches_drawn_ahead)
    return time.perf_counter() - t0, record.rays


def _profile(mesh, truth, config, steps: int, variant: str) -> dict:
    """One more run of ``variant`` under `StageTimer`: ms per step in each stage, per thread."""
    with StageTimer() as timer:
        wall, _ = _train(mesh, truth, config, steps, True, variant)
    return {"wall_s": round(wall, 4), "steps": steps, "ms_per_step": timer.per_step(wall, steps)}


def main() -> None:
    ap = ArgumentParser(description=description(__doc__))
    ap.add_argument("--mesh", default="/work/shared/meshes/bunny00.off")
    ap.add_argument("--preset", default="hq")
    ap.add_argument("--steps", type=positive_int, default=60)
    ap.add_argument("--repeats", type=positive_int, default=3)
    ap.add_argument("--name", type=result_name, default="training_cpu_step")
    ap.add_argument("--pair", choices=("step", "mlp", "previous", "saved_rows", "rows", "saved_rows_and_index", "prepare_ahead", "row_bucket", "draw_priority", "overlap", "overlap_trial", "loss_threads", "scatter", "draw_threads", "loss_chunks", "draw_pool", "float32_walk"), default="step", help="which before/after pair (module docstring)")
    ap.add_argument("--draw-threads", type=positive_int, default=1, help="the drawing thread's numba threads in draw_threads' after")
    args = ap.parse_args()
    check_mesh_spec(args.mesh)  # every check before the warm-up trainings
    check_presets("lsnif", [args.preset])
    global PAIR, DRAW_THREADS
    PAIR, DRAW_THREADS = args.pair, args.draw_threads
    mesh = resolve_mesh(args.mesh)  # a path, or procedural:NAME:DETAIL (machines without ../shared)
    truth = MeshBLAS(mesh)
    config = LSNIFConfig.preset(args.preset)
    load_before = os.getloadavg()[0]
    for variant in CONFIGS:  # warm-up: numba compilation, thread pools
        _train(mesh, truth, config, 5, True, variant)
    rows = []
    for rep in range(args.repeats):
        for variant in CONFIGS:
            wall, n = _train(mesh, truth, config, args.steps, True, variant)
            rows.append({"repeat": rep, "config": variant, "steps": args.steps, "batch": config.training.batch_size,
                         "wall_s": round(wall, 4), "rays_per_s": round(n / wall), "drawn_ahead": DRAWN_AHEAD[-1]})
    profiles = {variant: _profile(mesh, truth, config, args.steps, variant) for variant in CONFIGS}
    load_after = os.getloadavg()[0]
    print_table(rows, ["repeat", "config", "steps", "batch", "wall_s", "rays_per_s", "drawn_ahead"])
    best = {c: max(r["rays_per_s"] for r in rows if r["config"] == c) for c in CONFIGS}
    median = {c: statistics.median(r["rays_per_s"] for r in rows if r["config"] == c) for c in CONFIGS}
    # Each "after" run against the "before" run just before it (same load, as near as we can get).
    paired = [b["rays_per_s"] / a["rays_per_s"] for a, b in zip(rows[::2], rows[1::2])]
    summary = {
        "mesh": Path(args.mesh).name, "triangles": int(len(mesh.faces)), "preset": args.preset, "pair": args.pair,
        **({"draw_threads": args.draw_threads} if args.pair == "draw_threads" else {}),
        **({"chunk_rows_before_after": [CHUNK_ROWS, SMALL_CHUNK_ROWS]} if args.pair == "loss_chunks" else {}),
        "torch_threads": torch.get_num_threads(), "numba_threads": numba.get_num_threads(),
        "load_1min_before_after": [round(load_before, 2), round(load_after, 2)],
        "best_rays_per_s": best, "after_over_before_best": round(best["after"] / best["before"], 3),
        "median_rays_per_s": median,
        "paired_ratios_after_over_before": [round(r, 3) for r in paired],
        "median_paired_ratio": round(statistics.median(paired), 3),
        "profile_ms_per_step": profiles,
    }
    print(summary)
    path = write_results(args.name, rows, {"machine": machine_info(), "summary": summary})
    print(f"wrote {path}")


if __name__ == "__main__":
    run_main(main)

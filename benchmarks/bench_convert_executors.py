"""`neuralrt convert` of a scene with 8 unique meshes, trained by the local executor and by Ray on
this machine: wall time and CPU utilisation of the whole command.

    flock /tmp/neuralrt-bench.lock python benchmarks/bench_convert_executors.py [--steps 300] [--preset hq]
        [--runs local,ray,ray-2cpu] [--repeats 2] [--name convert_executors]

Each run is the real command in a fresh process (`python -m neuralrt convert ... --quiet --json`,
its own empty models folder), so each pays what a user pays: imports, numba's cached kernels,
and for Ray starting a local instance and its workers. Runs:

- ``local``: one model after another in the command's process (torch and numba: all cores);
- ``ray``: the default Ray settings, one task per core (``--cpus-per-model 1``, 1 thread each);
- ``ray-2cpu``: ``--cpus-per-model 2`` (one task at a time, 2 threads each), Ray's overhead alone.

CPU utilisation = CPU seconds of the command's process tree (it, and for Ray the raylet, GCS and
workers), sampled from /proc every 0.2 s, over wall time x cores. The machine's busy fraction
over the same interval (/proc/stat) and the load average say how much else was running. Also
checks that every run wrote the same model arrays. Writes benchmarks/results/NAME.json (``--name``,
default convert_executors).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (ArgumentParser, check_presets, description, positive_int, print_table, result_name,  # noqa: E402
                     run_main, write_results)

from neuralrt.errors import ConfigError  # noqa: E402
from neuralrt.io.model_file import read_header  # noqa: E402

# 8 unique meshes, 10k-76k triangles (generator, params); the trainings dominate, not the meshes.
MESHES = [
    ("statue", {"detail": 2, "seed": 0}), ("statue", {"detail": 2, "seed": 1}), ("statue", {"detail": 1, "seed": 2}),
    ("hairball", {"detail": 1, "seed": 0}), ("hairball", {"detail": 1, "seed": 1}),
    ("foliage", {"detail": 1, "seed": 0}), ("foliage", {"detail": 1, "seed": 1}),
    ("sphere", {"subdivisions": 5}),
]
RUNS = {
    "local": ["--executor", "local"],
    "ray": ["--executor", "ray"],
    "ray-2cpu": ["--executor", "ray", "--cpus-per-model", "2"],
}
_TICK = os.sysconf("SC_CLK_TCK")


def write_scene(folder: Path) -> Path:
    lines = ['[camera]\nposition = [0, 1, 12]\nlook_at = [0, 0, 0]\nresolution = [32, 32]\n',
             '[[materials]]\nname = "white"\ntype = "diffuse"\nalbedo = [0.7, 0.7, 0.7]\n']
    for i, (name, params) in enumerate(MESHES):
        args = ", ".join(f"{k} = {v}" for k, v in params.items())
        lines.append(f'[[objects]]\nname = "{name}{i}"\ngenerator = {{ name = "{name}", params = {{ {args} }} }}\n'
                     f'material = "white"\ntransform = {{ translate = [{2.5 * (i % 4) - 4}, {2.5 * (i // 4)}, 0] }}\n')
    lines.append('[environment]\ncolor = [0.2, 0.2, 0.2]\n')
    path = folder / "scene.toml"
    path.write_text("\n".join(lines))
    return path


def _proc_table() -> dict[int, tuple[int, int, float]]:
    """pid -> (parent pid, start time, CPU seconds) of every process."""
    table = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            text = Path(f"/proc/{name}/stat").read_text()
        except OSError:
            continue
        fields = text[text.rindex(")") + 2:].split()  # after "pid (comm) "
        table[int(name)] = (int(fields[1]), int(fields[19]), (int(fields[11]) + int(fields[12])) / _TICK)
    return table


def _machine_busy() -> tuple[float, float]:
    """(busy, total) jiffies of all cores since boot (/proc/stat)."""
    values = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = values[3] + values[4]
    return sum(values) - idle, sum(values)


class TreeCPU:
    """CPU seconds used by a process and all its descendants while it runs (sampled: the last
    value seen of each process; processes that outlive the root are followed while sampled)."""

    def __init__(self, root: int, interval: float = 0.2):
        self.root, self.interval = root, interval
        self.seen: dict[tuple[int, int], float] = {}  # (pid, start time) -> CPU seconds
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        table = _proc_table()
        children: dict[int, list[int]] = {}
        for pid, (ppid, _, _) in table.items():
            children.setdefault(ppid, []).append(pid)
        tree, todo = set(), [self.root]
        while todo:
            pid = todo.pop()
            if pid in table and pid not in tree:
                tree.add(pid)
                todo.extend(children.get(pid, []))
        tree |= {pid for pid, start in self.seen if pid in table and table[pid][1] == start}  # reparented ones
        for pid in tree:
            self.seen[(pid, table[pid][1])] = table[pid][2]

    def _run(self) -> None:
        while not self.stop.is_set():
            self._sample()
            self.stop.wait(self.interval)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join()

    @property
    def seconds(self) -> float:
        return float(sum(self.seen.values()))

    @property
    def processes(self) -> int:
        return len(self.seen)


def run_once(name: str, scene: Path, folder: Path, args) -> dict:
    out = folder / name / "scene.toml"
    cmd = [sys.executable, "-m", "neuralrt", "convert", str(scene), "-o", str(out), "--preset", args.preset,
           "--steps", str(args.steps), "--seed", "0", "--min-triangles", "1000", "--quiet", "--json", *RUNS[name]]
    load = os.getloadavg()[0]
    busy0 = _machine_busy()
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with TreeCPU(proc.pid) as tree:
        stdout, stderr = proc.communicate()
        wall = time.perf_counter() - start
        time.sleep(1.0)  # Ray's processes end just after the command; count them to the end
    busy1 = _machine_busy()
    if proc.returncode != 0:
        raise SystemExit(f"{name}: exit {proc.returncode}\n{stderr[-2000:]}")
    report = json.loads(stdout.strip().splitlines()[-1])
    cores = os.cpu_count()
    models = report["models"]
    return {
        "run": name,
        "wall_s": wall,
        "train_s_sum": sum(m["train_seconds"] for m in models),
        "cpu_s": tree.seconds,
        "cpu_utilisation": tree.seconds / (wall * cores),
        "machine_busy": (busy1[0] - busy0[0]) / max(busy1[1] - busy0[1], 1),
        "processes": tree.processes,
        "models": len(models),
        "load_before": load,
        "load_after": os.getloadavg()[0],
        "per_model_s": {Path(m["model_path"]).stem: round(m["train_seconds"], 2) for m in models},
        "arrays": {Path(m["model_path"]).name: read_header(m["model_path"])["arrays_sha256"] for m in models},
        "command": " ".join(cmd[1:]),
    }


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--steps", type=positive_int, default=300, help="training steps per model (preset's batch)")
    parser.add_argument("--preset", default="hq")
    parser.add_argument("--runs", default="local,ray,ray-2cpu", help=f"comma-separated, from {', '.join(RUNS)}")
    parser.add_argument("--repeats", type=positive_int, default=1, help="rounds; every other round runs in reverse order")
    parser.add_argument("--name", type=result_name, default="convert_executors", help="results file: benchmarks/results/NAME.json")
    args = parser.parse_args()
    names = [n.strip() for n in args.runs.split(",") if n.strip()]
    unknown = [n for n in names if n not in RUNS]
    if unknown:
        raise ConfigError(f"--runs {args.runs}: unknown run(s) {', '.join(unknown)} (choose from {', '.join(RUNS)})")
    if not names:
        raise ConfigError(f"--runs {args.runs!r}: no run named (choose from {', '.join(RUNS)}, comma-separated)")
    check_presets("lsnif", [args.preset], steps=args.steps)  # (the command's default method)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-convert-") as tmp:
        folder = Path(tmp)
        scene = write_scene(folder)
        for round_ in range(args.repeats):
            for name in names if round_ % 2 == 0 else names[::-1]:
                print(f"round {round_}: {name} ...", flush=True)
                rows.append({"round": round_, **run_once(f"{name}", scene, folder / f"r{round_}", args)})
    for round_ in range(args.repeats):  # ratios against the local run of the same round
        same = [r for r in rows if r["round"] == round_]
        base = next((r for r in same if r["run"] == "local"), same[0])
        for r in same:
            r["wall_vs_local"] = r["wall_s"] / base["wall_s"]
            r["same_arrays_as_local"] = r["arrays"] == base["arrays"]
    print_table(rows, ["round", "run", "wall_s", "wall_vs_local", "train_s_sum", "cpu_s", "cpu_utilisation", "machine_busy",
                       "processes", "load_before", "same_arrays_as_local"])
    path = write_results(args.name, rows, {
        "meshes": [f"{n}({', '.join(f'{k}={v}' for k, v in p.items())})" for n, p in MESHES],
        "preset": args.preset, "steps": args.steps, "repeats": args.repeats,
        "notes": "wall and CPU of the whole command in a fresh process; cpu_utilisation = process-tree CPU seconds / "
                 "(wall x cores); machine_busy = all cores' busy fraction (includes other users)",
    })
    print(f"wrote {path}")


if __name__ == "__main__":
    run_main(main)

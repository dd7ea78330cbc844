"""Shared benchmark helpers: machine description, a plain-text table, JSON results, and the
argument checks every script runs before any long work.

Bad input is one line on stderr, ``<script>: error: <problem>``, and exit status 2, before anything
is trained, rendered or written (never a traceback, never a partial results file): scripts parse
with `ArgumentParser` (argument errors as that one line; ``description(__doc__)``, the docstring's
first paragraph, as its description), use the argparse types below (`positive_int`, `int_in`,
`detail_level`, `result_name`, ...), check meshes, presets, scenes, model files and output files up
front (`check_mesh_spec`, `parse_short_procedural`, `check_presets`, `check_scene`,
`check_model_file`, `check_output_file`) and run their ``main`` through `run_main`, which turns any
`neuralrt.errors.NeuralRTError` into the one line. Results go through `write_results` (``--name``)
or, for the scripts that take ``--out PATH``, `write_json`; both write atomically.

Every script imports neuralrt before torch (neuralrt sets how OpenMP threads wait before torch loads
libgomp); this module imports neither at the top, so ``--help`` stays quick.

``NEURALRT_BENCH_RESULTS`` (an environment variable) moves the results folder (tests use it).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import sys
from importlib import metadata
from pathlib import Path

RESULTS_DIR = Path(os.environ.get("NEURALRT_BENCH_RESULTS") or Path(__file__).resolve().parent / "results")
SHARED_MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"

_PACKAGES = ("neuralrt", "numpy", "torch", "numba", "embreex", "trimesh")


def machine_info() -> dict:
    """CPU (its name, and LLVM's name for its microarchitecture, what numba compiles for: a
    virtual machine may name both an AMD Zen 4 and a Zen 5 "AMD EPYC"), core count, OS, Python and
    key package versions, and the UTC date."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    try:
        import llvmlite.binding as llvm

        cpu_arch = llvm.get_host_cpu_name()
    except (ImportError, RuntimeError):
        cpu_arch = None
    versions = {}
    for name in _PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "cpu": cpu,
        "cpu_arch": cpu_arch,
        "cores": os.cpu_count(),
        "os": platform.platform(),
        "python": platform.python_version(),
        "versions": versions,
        "date_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:,.3g}" if abs(value) < 100 else f"{value:,.0f}"
    if isinstance(value, int):
        return f"{value:,}"
    return str(value)


def run_seconds(fn, repeats: int) -> list[float]:
    """Wall seconds of each of ``repeats`` calls of ``fn`` (take the min where the machine is shared
    and the least disturbed run is wanted, the median for a typical one)."""
    import time

    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def print_table(rows: list[dict], columns: list[str]) -> None:
    """Print ``rows`` (dicts) as an aligned text table with the given column order."""
    cells = [[_fmt(r.get(c, "")) for c in columns] for r in rows]
    widths = [max([len(c)] + [len(row[i]) for row in cells]) for i, c in enumerate(columns)]
    print("  ".join(c.rjust(w) for c, w in zip(columns, widths)))
    print("  ".join("-" * w for w in widths))
    for row in cells:
        print("  ".join(v.rjust(w) for v, w in zip(row, widths)))


def write_results(name: str, rows: list[dict], extra: dict | None = None) -> Path:
    """Write ``{"benchmark", "machine", "rows", **extra}`` to ``benchmarks/results/<name>.json``
    atomically (a unique temporary file beside it, mode 0o666 less the umask, then one rename: a
    crash or a concurrent run leaves the old file or a whole new one). ``name`` must be a plain
    file stem (`name_problem`), else a `neuralrt.errors.ConfigError`, before anything is written."""
    from neuralrt.errors import ConfigError
    from neuralrt.io.files import write_atomically

    problem = name_problem(name)
    if problem:
        raise ConfigError(f"results name {name!r}: {problem}")
    payload = {"benchmark": name, "machine": machine_info(), **(extra or {}), "rows": rows}
    text = json.dumps(payload, indent=2, default=float) + "\n"  # (before the file: an unserialisable value writes nothing)
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.json"
    write_atomically(path, lambda tmp: Path(tmp).write_text(text))
    return path


def save_figure(fig, path: Path) -> Path:
    """``fig.savefig(path)`` atomically (as `write_results`; the format from ``path``'s suffix)."""
    from neuralrt.io.plots import write_figure

    return write_figure(fig, path)


def read_results(name: str) -> dict:
    """The results file ``name`` (`write_results`) as written, ``{}`` when there is none; a file
    that is not a JSON object is a one-line `neuralrt.errors.ConfigError` (runs merge into it)."""
    from neuralrt.errors import ConfigError

    problem = name_problem(name)
    if problem:
        raise ConfigError(f"results name {name!r}: {problem}")
    path = RESULTS_DIR / f"{name}.json"
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the earlier results to merge into ({exc}); move it away or use another --name") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: not a results file (a JSON object); move it away or use another --name")
    return data


# --- arguments ----------------------------------------------------------------------------------


def description(doc: str | None) -> str:
    """A script's ``--help`` description: the whole first paragraph of its docstring ``doc`` (up to the
    first blank line), on one line (argparse wraps it), not its first line cut off mid-sentence."""
    paragraph = (doc or "").strip().split("\n\n")[0]
    return " ".join(paragraph.split())


def prog() -> str:
    """The script's name as argparse shows it (``bench_lsnif.py``)."""
    return os.path.basename(sys.argv[0]) or "benchmark"


class ArgumentParser(argparse.ArgumentParser):
    """Argument errors as one line ``<script>: error: ...`` and exit 2 (argparse prints the usage too)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def fail(message: str):
    """End the script with the one error line and exit 2 (for checks outside argparse and neuralrt)."""
    print(f"{prog()}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def run_main(main, *args):
    """Run ``main(*args)`` and exit with what it returns; a `neuralrt.errors.NeuralRTError` (bad input
    found by the up-front checks, or later) ends the script as one line and exit 2, not a traceback.
    neuralrt's messages name arguments as command-line flags (``--device cuda``), as the CLI's do."""
    from neuralrt.arguments import spelled_as_flags

    try:
        with spelled_as_flags():
            result = main(*args)
    except Exception as exc:
        errors = sys.modules.get("neuralrt.errors")  # (none raised if neuralrt was never imported)
        if errors is None or not isinstance(exc, errors.NeuralRTError):
            raise
        fail(str(exc))
    raise SystemExit(result)


def name_problem(name) -> str | None:
    """None when ``name`` can name a results file in the results folder (a plain file stem), else why not."""
    if not isinstance(name, str) or not name:
        return "must not be empty"
    if "/" in name or "\\" in name or (os.altsep and os.altsep in name):
        return "must be a plain file name, without a folder (no / or \\)"
    if name.startswith("."):
        return "must not start with '.'"
    if not name.isprintable():
        return "must not contain control characters"
    return None


def result_name(text: str) -> str:
    """argparse type of ``--name``: a plain file stem (results go to the results folder as NAME.json)."""
    problem = name_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(f"{text!r}: {problem}")
    return text


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (counts, repeats, resolutions, thread counts)."""
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def nonnegative_int(text: str) -> int:
    """argparse type: an integer >= 0 (a count where 0 skips a part, a detail level)."""
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, got {value}")
    return value


def seed_int(text: str) -> int:
    """argparse type: a seed, an integer in [0, 2^63)."""
    value = nonnegative_int(text)
    if value >= 1 << 63:
        raise argparse.ArgumentTypeError(f"must be below 2^63, got {value}")
    return value


def int_in(lo: int, hi: int):
    """argparse type factory: an integer in ``lo..hi`` (a log2 of a ray count, a detail level, ...)."""

    def check(text: str) -> int:
        value = _integer(text)
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer in {lo}..{hi}, got {value}")
        return value

    check.__name__ = f"integer in {lo}..{hi}"
    return check


def detail_level(generator: str):
    """argparse type factory: a detail level of the procedural mesh ``generator`` (0 to its finest,
    `procedural_detail`; neuralrt is imported when an argument is parsed, not for ``--help``)."""

    def check(text: str) -> int:
        return int_in(0, procedural_detail()[generator])(text)

    check.__name__ = f"{generator} detail"
    return check


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def nonnegative_float(text: str) -> float:
    """argparse type: a finite number >= 0 (an offset, a distance where 0 is allowed)."""
    value = _number(text)
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = _number(text)
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


# --- meshes, presets, scenes, devices (checked before any work) ---------------------------------

def procedural_detail() -> dict[str, int]:
    """Procedural meshes a ``procedural:NAME:DETAIL`` spec can name (generators with a detail level)
    and the finest detail each builds (`neuralrt.geometry.procedural.MAX_DETAIL`; imported when
    asked: this module stays light for ``--help``)."""
    from neuralrt.geometry.procedural import MAX_DETAIL

    return MAX_DETAIL


def mesh_specs() -> str:
    """What a mesh argument may be, for error messages."""
    return ("a mesh file (a path, or a file in ../shared/meshes) with an optional @loopK (K Loop subdivisions), "
            f"or procedural:NAME:DETAIL with NAME one of {', '.join(procedural_detail())}")


def parse_mesh_spec(spec: str) -> tuple:
    """``("procedural", NAME, DETAIL)`` or ``("file", path, loops)`` of a benchmark mesh spec:
    ``procedural:NAME:DETAIL``, or a file name in ../shared/meshes or a path, optionally ``@loopK``.
    A bad spec or a missing file is a one-line `neuralrt.errors.MeshError`; nothing is loaded."""
    from neuralrt.errors import MeshError
    from neuralrt.io.files import input_file_problem

    if not isinstance(spec, str) or not spec:
        raise MeshError(f"empty mesh spec (use {mesh_specs()})")
    if spec.startswith("procedural:"):
        from neuralrt.geometry.procedural import parse_procedural_spec

        name, detail = parse_procedural_spec(spec)
        return "procedural", name, detail
    name, at, loop = spec.partition("@loop")
    loops = 0
    if at:
        try:
            loops = int(loop)
        except ValueError:
            loops = -1
        if loops < 0:
            raise MeshError(f"{spec}: @loopK needs K, a whole number of Loop subdivisions >= 0, got {loop!r}")
    if "@" in name:
        raise MeshError(f"{spec}: not a mesh spec (use {mesh_specs()})")
    path = Path(name)
    if not path.exists() and not path.is_absolute() and (SHARED_MESHES / name).exists():
        path = SHARED_MESHES / name
    if not path.exists():
        raise MeshError(f"{name}: mesh file not found (neither a path nor a file in {SHARED_MESHES})")
    problem = input_file_problem(path, "mesh file")
    if problem:
        raise MeshError(problem)
    return "file", path, loops


def parse_short_procedural(spec: str, option: str, detail_required: bool = False) -> tuple[str, dict]:
    """``(NAME, params)`` of a short procedural mesh spec as ``--meshes statue:2,hairball:6`` name them:
    ``NAME:DETAIL`` (NAME a generator with a detail level, DETAIL in its range) or, unless
    ``detail_required``, a generator's ``NAME`` alone (its default parameters); a ``procedural:``
    prefix is allowed. Anything else is a one-line `neuralrt.errors.MeshError` naming ``option``;
    nothing is built."""
    from neuralrt.errors import MeshError
    from neuralrt.geometry.procedural import GENERATORS

    limits = procedural_detail()
    text = spec[len("procedural:"):] if isinstance(spec, str) and spec.startswith("procedural:") else spec
    name, colon, detail = text.partition(":") if isinstance(text, str) else ("", "", "")
    forms = ", ".join(f"{n}:0..{d}" for n, d in limits.items())
    if not colon:
        if detail_required or name not in GENERATORS:
            alone = "" if detail_required else f", or one of {', '.join(sorted(GENERATORS))} alone"
            raise MeshError(f"{option} {spec!r}: not a procedural mesh: use NAME:DETAIL ({forms}){alone}")
        return name, {}
    if name not in limits:
        raise MeshError(f"{option} {spec!r}: {name!r} has no detail level: use NAME:DETAIL with NAME one of {', '.join(limits)}")
    try:
        level = int(detail)
    except ValueError:
        level = None
    if level is None or not 0 <= level <= limits[name]:
        raise MeshError(f"{option} {spec!r}: DETAIL must be an integer in 0..{limits[name]} for {name}, got {detail!r}")
    return name, {"detail": level}


def make_short_procedural(spec: str, option: str = "mesh"):
    """The `Mesh` of a short procedural spec (`parse_short_procedural`)."""
    from neuralrt.geometry.procedural import make_procedural

    name, params = parse_short_procedural(spec, option)
    return make_procedural(name, **params)


def subdivided_file(text: str) -> tuple[str, int]:
    """argparse type of ``--subdivide FILE:LOOP_STEPS`` (a shared mesh file and its Loop subdivisions):
    ``(FILE, LOOP_STEPS)``; whether FILE exists is the script's question (a missing one is skipped)."""
    name, colon, steps = text.rpartition(":")
    try:
        count = int(steps) if colon and name else -1
    except ValueError:
        count = -1
    if count < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected FILE:LOOP_STEPS with LOOP_STEPS an integer >= 0, e.g. bunny00.off:2")
    return name, count


def check_mesh_spec(spec: str) -> str:
    """``spec`` when `parse_mesh_spec` accepts it (its one-line error otherwise)."""
    parse_mesh_spec(spec)
    return spec


def load_mesh_spec(spec: str):
    """The `Mesh` of a benchmark mesh spec (`parse_mesh_spec`)."""
    kind, name, detail = parse_mesh_spec(spec)
    if kind == "procedural":
        from neuralrt.geometry.procedural import make_procedural

        return make_procedural(name, detail=detail)
    from neuralrt.geometry.mesh import load_mesh

    mesh = load_mesh(name)
    return mesh.subdivided(detail) if detail else mesh


def check_presets(method: str, presets, flag: str = "--preset", **training) -> list:
    """The configs of ``method``'s ``presets`` with the training keys ``training`` (None: the
    preset's); an unknown method or preset (named as ``flag``) or a bad value is a one-line `ConfigError`."""
    from neuralrt.errors import ConfigError
    from neuralrt.methods import get_method

    spec = get_method(method)
    unknown = [preset for preset in presets if preset not in spec.presets]
    if unknown:
        raise ConfigError(f"{flag}: unknown {method} preset {unknown[0]!r} (choose from {', '.join(spec.presets)})")
    return [spec.config(preset, **training) for preset in presets]


def check_device(device: str):
    """``device`` as a torch device this process can use, else a one-line `DeviceError`."""
    from neuralrt.devices import check_device as check

    return check(device)


def check_scene(scene: str, detail: int | None = None):
    """The spec of ``scene`` (``builtin:NAME[?detail=N]`` or a .toml/.json scene file) when it names
    a valid scene (`load_scene_spec`: syntax and keys; no mesh is built, but procedural detail levels
    are checked), else a one-line `SceneError`."""
    from neuralrt.errors import SceneError
    from neuralrt.scene.loader import load_scene_spec

    spec, _, label = load_scene_spec(scene, detail=detail)
    limits = procedural_detail()
    for i, obj in enumerate(spec.objects):
        gen = obj.generator
        level = gen.params.get("detail") if gen is not None and gen.name in limits else None
        if level is not None and not (isinstance(level, int) and 0 <= level <= limits[gen.name]):
            raise SceneError(f"{label}: objects.{i} ({obj.name}): {gen.name} detail must be an integer in "
                             f"0..{limits[gen.name]}, got {level!r}")
    return spec


def check_model_file(path, method: str | None = None) -> dict:
    """The header of the model file ``path`` (only the header is read); a missing, unreadable or
    corrupted file, or (with ``method``) another method's model, is a one-line `ModelFileError`."""
    from neuralrt.io.model_file import read_header

    return read_header(path, method=method)


def check_output_file(path, what: str) -> None:
    """A one-line error unless a file can be written at ``path`` (its folder writable or creatable;
    nothing is created)."""
    from neuralrt.io.files import check_output_file as check

    check(path, what)


def write_json(path, payload: dict, default=float) -> Path:
    """``payload`` as JSON at ``path`` (a ``--out`` file anywhere), atomically as `write_results`
    (``default``: `json.dumps`'s, for values JSON has no type for)."""
    from neuralrt.io.files import write_atomically

    text = json.dumps(payload, indent=2, default=default) + "\n"  # (before the file: an unserialisable value writes nothing)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_atomically(path, lambda tmp: Path(tmp).write_text(text))


def check_output_folder(folder, what: str) -> None:
    """A one-line error unless ``folder`` is, or can be made, a writable folder (nothing is created)."""
    from neuralrt.io.files import check_output_folder as check

    check(folder, what)


def per_method_counts(items: list[str], option: str) -> dict[str, int]:
    """``["lsnif=2000", "nbvh=1000"]`` as ``{"lsnif": 2000, "nbvh": 1000}`` (``--steps`` / ``--batch``
    METHOD=N); a malformed item, an unknown method or N < 1 is a one-line `ConfigError`."""
    from neuralrt.errors import ConfigError
    from neuralrt.methods import get_method

    counts = {}
    for item in items:
        method, eq, value = item.partition("=")
        try:
            count = int(value) if eq else None
        except ValueError:
            count = None
        if count is None:
            raise ConfigError(f"{option} {item}: expected METHOD=N, e.g. lsnif=2000")
        try:
            get_method(method)
        except ConfigError as exc:
            raise ConfigError(f"{option} {item}: {exc}") from None
        if count < 1:
            raise ConfigError(f"{option} {item}: N must be at least 1")
        counts[method] = count
    return counts

"""Our exact path tracer against Mitsuba 3's (scalar_rgb, on the CPU) on the same scenes: how the
images agree (to their seed-to-seed noise) and how long each renderer takes in the same run. Prints
a table and writes benchmarks/results/NAME.json (default reference.json).

    python benchmarks/bench_reference.py [--resolution 64] [--spp 256] [--seeds 8] [--scenes cornell,sky,scene.toml]

Scenes: ``cornell`` (the built-in cornell-statue with its statue made diffuse: Mitsuba's plastic
is another model), ``sky`` (a ball on a floor under a point light and a constant sky), or scene
files of diffuse and emissive materials (`neuralrt.eval.mitsuba_reference`). Each renderer renders
``--seeds`` images of ``--spp`` samples per pixel; per scene:

- ``mean_relative_difference`` and ``mean_z``: ours minus Mitsuba over the image mean, relative
  and in units of its standard error (from the seed spread);
- ``block_chi2``: mean squared z over 4x4-pixel blocks and channels, ~1.4 with 8 seeds when the
  two differ by noise alone (`neuralrt.eval.mitsuba_reference.agreement`);
- ``ours_s`` / ``mitsuba_s``: the median seconds of one render, and ``time_ratio`` = ours / Mitsuba
  (both use every core: our numba kernels and Embree, Mitsuba its own thread pool).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (before torch: sets how OpenMP threads wait)
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (ArgumentParser, check_scene, description, fail, int_in, positive_int, print_table,  # noqa: E402
                     result_name, run_main, write_results)

from neuralrt.eval.mitsuba_reference import agreement, mitsuba_reference_available, reference_render  # noqa: E402
from neuralrt.render.integrator import render  # noqa: E402
from neuralrt.scene.builtins import builtin_spec  # noqa: E402
from neuralrt.scene.loader import build_scene  # noqa: E402
from neuralrt.scene.schema import DiffuseMaterialSpec, SceneSpec  # noqa: E402


def cornell() -> SceneSpec:
    spec = builtin_spec("cornell-statue")
    materials = [DiffuseMaterialSpec(name=m.name, albedo=m.albedo) if m.name == "statue" else m for m in spec.materials]
    return spec.model_copy(update={"materials": materials})


def sky() -> SceneSpec:
    return SceneSpec.model_validate({
        "camera": {"position": [0, 1.0, 3.5], "look_at": [0, 0, 0], "fov": 40},
        "materials": [{"name": "floor", "albedo": [0.5, 0.6, 0.7]}, {"name": "ball", "albedo": [0.8, 0.3, 0.2]}],
        "objects": [
            {"generator": {"name": "plane", "params": {"size": 4}}, "material": "floor", "transform": {"translate": [0, -0.5, 0]}},
            {"generator": {"name": "sphere", "params": {"subdivisions": 4}}, "material": "ball",
             "transform": {"scale": 0.5, "translate": [0.2, 0, 0]}},
        ],
        "lights": [{"position": [1, 2, 1], "intensity": [3, 2.5, 2]}],
        "environment": {"color": [0.2, 0.25, 0.3]},
    })


NAMED = {"cornell": cornell, "sky": sky}


def _spec(name: str) -> tuple[SceneSpec, Path]:
    if name in NAMED:
        return NAMED[name](), Path.cwd()
    return check_scene(name), Path(name).resolve().parent


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def main(argv=None) -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--resolution", type=positive_int, default=64, help="image width and height")
    parser.add_argument("--spp", type=positive_int, default=256, help="samples per pixel of each render")
    parser.add_argument("--seeds", type=int_in(2, 1000), default=8, help="renders per renderer and scene")
    parser.add_argument("--max-depth", type=positive_int, default=None, help="bounces (default: each scene's)")
    parser.add_argument("--scenes", default="cornell,sky", help="comma-separated: cornell, sky or scene files")
    parser.add_argument("--name", type=result_name, default="reference", help="results file: benchmarks/results/NAME.json")
    args = parser.parse_args(argv)
    names = args.scenes.split(",")
    if any(not n.strip() for n in names):
        fail(f"--scenes {args.scenes!r}: an empty item")
    if not mitsuba_reference_available():
        fail("needs mitsuba 3 with its scalar_rgb variant (pip install 'neuralrt[gpu]')")
    specs = {name: _spec(name) for name in names}  # (every scene checked before the first render)

    rows = []
    for name, (spec, folder) in specs.items():
        spec = spec.model_copy(update={"camera": spec.camera.model_copy(update={"resolution": (args.resolution,) * 2})})
        scene = build_scene(spec, folder, label=name)
        reference_render(scene, spp=1, max_depth=args.max_depth)  # (export checked before our renders)
        ours, theirs, ours_s, theirs_s = [], [], [], []
        for seed in range(args.seeds):  # alternating, so both see the same machine load
            result, seconds = _timed(lambda: render(scene, spp=args.spp, seed=seed, max_depth=args.max_depth, progress=False))
            ours.append(np.asarray(result.image))
            ours_s.append(seconds)
            image, seconds = _timed(lambda: reference_render(scene, spp=args.spp, seed=1000 + seed, max_depth=args.max_depth))
            theirs.append(image)
            theirs_s.append(seconds)
        stats = agreement(ours, theirs)
        row = {"scene": name, "max_depth": args.max_depth or scene.settings.max_depth, **stats,
               "ours_s": statistics.median(ours_s), "mitsuba_s": statistics.median(theirs_s)}
        row["time_ratio"] = row["ours_s"] / row["mitsuba_s"]
        rows.append(row)
    print_table(rows, ["scene", "max_depth", "ours_mean", "reference_mean", "mean_relative_difference", "mean_z",
                       "block_chi2", "ours_s", "mitsuba_s", "time_ratio"])
    settings = {"resolution": args.resolution, "spp": args.spp, "seeds": args.seeds, "max_depth": args.max_depth,
                "command": " ".join(["python", "benchmarks/bench_reference.py", *(argv if argv is not None else sys.argv[1:])])}
    print(write_results(args.name, rows, {"settings": settings}))


if __name__ == "__main__":
    run_main(main)

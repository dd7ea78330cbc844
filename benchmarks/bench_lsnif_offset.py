"""How far must a ray leaving a neural hit start to not hit the same surface again?

For a trained LSNIF model: shoot outside rays from the training distribution, take the model's
hits (point and normal), spawn bounce rays there (cosine-weighted around the returned normal),
offset by ``k x diagonal`` along that normal, and trace them with the model and with Embree from the
same origins. A *self-hit* is a neural hit closer than ``--self-distance`` (relative to the
diagonal) where Embree finds nothing that close. Results go to benchmarks/results/NAME.json
(``--name``, default lsnif_offset).

    python benchmarks/bench_lsnif_offset.py MODEL.nrt MESH [--rays 65536] [--name lsnif_offset]
"""

from __future__ import annotations

import sys
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.methods import load_model  # noqa: E402
from neuralrt.rays import Rays  # noqa: E402
from neuralrt.training.ray_distribution import BoxRayDistribution, cosine_weighted_directions  # noqa: E402

from _common import (ArgumentParser, check_mesh_spec, check_model_file, description, nonnegative_float,  # noqa: E402
                     positive_float, positive_int, result_name, run_main)
from bench_lsnif import resolve_mesh  # noqa: E402


def main() -> None:
    from _common import print_table, write_results

    p = ArgumentParser(description=description(__doc__))
    p.add_argument("model")
    p.add_argument("mesh")
    p.add_argument("--rays", type=positive_int, default=1 << 16)
    p.add_argument("--offsets", type=nonnegative_float, nargs="+", default=[0.0, 1e-4, 1e-3, 3e-3, 1e-2])
    p.add_argument("--self-distance", type=positive_float, default=0.02, help="self-hit: neural t*|d| below this x diagonal")
    p.add_argument("--name", type=result_name, default="lsnif_offset", help="results file: benchmarks/results/NAME.json")
    args = p.parse_args()

    check_model_file(args.model)  # both before the model and the mesh are loaded
    check_mesh_spec(args.mesh)
    model = load_model(args.model)
    mesh = resolve_mesh(args.mesh)
    exact = MeshBLAS(mesh)
    diag = model.box.diagonal
    batch = BoxRayDistribution(exact, model.box, seed=777, surface_fraction=0.0).sample(args.rays)
    first = model.intersect(batch.rays)
    idx = torch.nonzero(first.hit).squeeze(1)
    points = batch.rays[idx].point_at(first.t[idx])
    normals = first.normal[idx]
    dirs = cosine_weighted_directions(normals, torch.Generator().manual_seed(5))
    rows = []
    for k in args.offsets:
        rays = Rays(points + k * diag * normals, dirs)
        neural, truth = model.intersect(rays), exact.intersect(rays)
        near = args.self_distance * diag
        self_hit = neural.hit & (neural.t < near) & ~(truth.hit & (truth.t < near))
        rows.append({
            "offset_x_diagonal": k,
            "rays": len(rays),
            "self_hit_rate": float(self_hit.float().mean()),
            "neural_hit_rate": float(neural.hit.float().mean()),
            "exact_hit_rate": float(truth.hit.float().mean()),
            "agreement": float((neural.hit == truth.hit).float().mean()),
        })
    print_table(rows, list(rows[0]))
    path = write_results(args.name, rows, extra={"model": args.model, "mesh": args.mesh,
                                                 "default_offset_x_diagonal": model.config.inference.secondary_offset})
    print(f"wrote {path}")


if __name__ == "__main__":
    run_main(main)

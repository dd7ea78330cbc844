"""NIF stage 2 inputs: from (ray, object) pairs to the outer and inner MLP inputs, in two
implementations with one contract, chosen once per device (`nif_features_for`).

``features(networks, pairs) -> (outer_pair [Po], outer_x [Po, 6], inner_pair [Pi], inner_x [Pi, 13])``:
the pairs whose interval meets their object's box, split by whether the origin lies in it, with
the grid features each MLP reads (`NIFNetworks.outer_features` / ``inner_features``), pairs in
increasing order. `TorchNIFFeatures` chains torch ops (`make_queries`, then one gather per grid):
any device. `NumbaNIFFeatures` does the box test, spherical coordinates and every bilinear
gather in one pass per pair over the CPU tables (zero-copy numpy views), so no [P]-sized
intermediate is written: measured in docs/nif.md. Both compute in float32 from the same formulas;
features agree to rounding (tests/test_nif_features.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from .nif import NIFNetworks, NIFPairs

__all__ = ["TorchNIFFeatures", "NumbaNIFFeatures", "nif_features_for"]


class TorchNIFFeatures:
    """Torch ops on any device."""

    @torch.no_grad()
    def __call__(self, networks: NIFNetworks, pairs: NIFPairs) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        q = networks.queries(pairs)
        return (q.outer_pair, networks.outer_features(q.outer_obj, q.outer_position, q.outer_direction),
                q.inner_pair, networks.inner_features(q.inner_obj, q.inner_position, q.inner_direction, q.inner_distance))


@numba.njit(cache=True, inline="always")
def _sph(x, y, z):
    x, y, z = np.float32(x), np.float32(y), np.float32(z)  # float32 libm calls, as torch's
    length = math.sqrt(x * x + y * y + z * z)
    c = y / length if length > np.float32(0.0) else np.float32(0.0)
    c = min(max(c, np.float32(-1.0)), np.float32(1.0))
    return math.acos(c) * np.float32(1.0 / math.pi), (math.atan2(z, x) + np.float32(math.pi)) * np.float32(0.5 / math.pi)


@numba.njit(cache=True, inline="always")
def _gather2d(table, k, r, u, v, out, row, col):
    """Bilinear lookup of object ``k``'s R x R grid at (u, v) into ``out[row, col:col + N]``."""
    y = min(max(u * (r - 1), 0.0), r - 1.0)
    x = v * r
    y0 = min(math.floor(y), r - 2)
    x0 = math.floor(x)
    fy, fx = y - y0, x - x0
    ix0 = int(x0) % r
    ix1 = (ix0 + 1) % r
    base = (k * r + int(y0)) * r
    for f in range(table.shape[1]):
        top = table[base + ix0, f] * (1.0 - fx) + table[base + ix1, f] * fx
        bottom = table[base + r + ix0, f] * (1.0 - fx) + table[base + r + ix1, f] * fx
        out[row, col + f] = top * (1.0 - fy) + bottom * fy


@numba.njit(cache=True)
def _features(obj, o, d, t_min, t_max, box_lo, box_hi, op_tab, r_op, od_tab, r_od, ip_tab, r_ip, id_tab, r_id, dist_tab, r_dist,
              outer_pair, outer_x, inner_pair, inner_x):
    n_out = 0
    n_in = 0
    inf = np.float32(np.inf)  # float32 throughout, as `nif.make_queries` (a float64 literal would widen the slab test)
    for p in range(obj.shape[0]):
        k = obj[p]
        t_near, t_far = -inf, inf
        inside = True
        for a in range(3):
            lo, hi, oa, da = box_lo[k, a], box_hi[k, a], o[p, a], d[p, a]
            inv = np.float32(1.0) / da if da != 0 else (inf if not math.copysign(1.0, da) < 0 else -inf)
            t0, t1 = (lo - oa) * inv, (hi - oa) * inv
            if math.isnan(t0):  # 0 * inf: origin on the slab plane, parallel direction: inside
                t0 = -inf
            if math.isnan(t1):
                t1 = inf
            t_near = max(t_near, min(t0, t1))
            t_far = min(t_far, max(t0, t1))
            inside = inside and oa >= lo and oa <= hi
        if not (t_near <= t_far and t_far >= t_min[p] and t_near <= t_max[p]):  # [t_min, t_max], both ends included
            continue
        cx, cy, cz = 0.5 * (box_lo[k, 0] + box_hi[k, 0]), 0.5 * (box_lo[k, 1] + box_hi[k, 1]), 0.5 * (box_lo[k, 2] + box_hi[k, 2])
        du, dv = _sph(d[p, 0], d[p, 1], d[p, 2])
        if not inside:
            te = max(t_near, t_min[p])
            pu, pv = _sph(o[p, 0] + te * d[p, 0] - cx, o[p, 1] + te * d[p, 1] - cy, o[p, 2] + te * d[p, 2] - cz)
            _gather2d(op_tab, k, r_op, pu, pv, outer_x, n_out, 0)
            _gather2d(od_tab, k, r_od, du, dv, outer_x, n_out, op_tab.shape[1])
            outer_pair[n_out] = p
            n_out += 1
        else:
            x, y, z = o[p, 0] - cx, o[p, 1] - cy, o[p, 2] - cz
            pu, pv = _sph(x, y, z)
            ex, ey, ez = box_hi[k, 0] - box_lo[k, 0], box_hi[k, 1] - box_lo[k, 1], box_hi[k, 2] - box_lo[k, 2]
            half = max(0.5 * math.sqrt(ex * ex + ey * ey + ez * ez), 1e-30)
            s = min(max(math.sqrt(x * x + y * y + z * z) / half, 0.0), 1.0)
            _gather2d(ip_tab, k, r_ip, pu, pv, inner_x, n_in, 0)
            _gather2d(id_tab, k, r_id, du, dv, inner_x, n_in, ip_tab.shape[1])
            col = ip_tab.shape[1] + id_tab.shape[1]
            xs = min(max(s * (r_dist - 1), 0.0), r_dist - 1.0)
            x0 = min(math.floor(xs), r_dist - 2)
            f = xs - x0
            i0 = k * r_dist + int(x0)
            for c in range(dist_tab.shape[1]):
                inner_x[n_in, col + c] = dist_tab[i0, c] * (1.0 - f) + dist_tab[i0 + 1, c] * f
            inner_pair[n_in] = p
            n_in += 1
    return n_out, n_in


class NumbaNIFFeatures:
    """One fused numba pass per pair over CPU tensors."""

    @torch.no_grad()
    def __call__(self, networks: NIFNetworks, pairs: NIFPairs) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        n = len(pairs)
        net = networks
        outer_pair, inner_pair = np.empty(n, np.int64), np.empty(n, np.int64)
        outer_x = np.empty((n, net.outer_mlp.hidden[0].in_features), np.float32)
        inner_x = np.empty((n, net.inner_mlp.hidden[0].in_features), np.float32)
        grids = (net.outer_position, net.outer_direction, net.inner_position, net.inner_direction, net.inner_distance)
        tables = [x for g in grids for x in (g.table.detach().numpy(), g.resolution)]
        n_out, n_in = _features(
            pairs.obj.numpy(), pairs.origins.detach().contiguous().numpy(), pairs.directions.detach().contiguous().numpy(),
            pairs.t_min.contiguous().numpy(), pairs.t_max.contiguous().numpy(), net.box_lo.numpy(), net.box_hi.numpy(),
            *tables, outer_pair, outer_x, inner_pair, inner_x,
        )
        return (torch.from_numpy(outer_pair[:n_out]), torch.from_numpy(outer_x[:n_out]),
                torch.from_numpy(inner_pair[:n_in]), torch.from_numpy(inner_x[:n_in]))


def nif_features_for(device) -> TorchNIFFeatures | NumbaNIFFeatures:
    """The implementation for ``device``: numba on the CPU, torch elsewhere."""
    return NumbaNIFFeatures() if torch.device(device).type == "cpu" else TorchNIFFeatures()

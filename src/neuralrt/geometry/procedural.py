"""Procedural test meshes: deterministic generators sized by a ``detail`` level.

Every generator returns a `Mesh`; the same parameters (and ``seed``) give bit-identical arrays.
The large variants (millions of triangles) are built with whole-array numpy, in seconds.

Triangle counts per detail level (measured; each generator's docstring repeats its row):

======  ==========  ==========  ==========
detail  statue      hairball    foliage
======  ==========  ==========  ==========
0       8,392       37,248      3,236
1       18,930      74,496      10,736
2       75,720      148,992     40,736
3       302,880     297,984     160,736
4       1,211,520   595,968     640,736
5       4,846,080   1,191,936   2,560,736
6       --          2,383,872   --
======  ==========  ==========  ==========

Generation time on one shared core: statue(4) ~10 s, hairball(6) ~1.6 s, foliage(5) ~3 s.
"""

from __future__ import annotations

import inspect
from typing import Callable

import numpy as np

from ..errors import NeuralRTError
from .mesh import Mesh, MeshMaterial, import_trimesh

__all__ = [
    "GENERATORS",
    "MAX_DETAIL",
    "box",
    "cornell_box",
    "foliage",
    "hairball",
    "make_procedural",
    "parse_procedural_spec",
    "procedural_mesh",
    "plane",
    "sphere",
    "statue",
]


# --- small shared helpers -----------------------------------------------------------------------


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice point (a 64-bit mix)."""
    with np.errstate(over="ignore"):
        h = (ix.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) ^ (iy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F))
        h ^= iz.astype(np.uint64) * np.uint64(0x165667B19E3779F9)
        h ^= np.uint64((seed * 0x27D4EB2F165667C5 + 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF)
        # splitmix64 finaliser: decorrelates neighbouring lattice points
        h ^= h >> np.uint64(30)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(27)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(31)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def _value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [-1, 1] at points ``p`` [N, 3] (trilinear over a hashed lattice)."""
    base = np.floor(p)
    f = p - base
    w = f * f * (3.0 - 2.0 * f)  # smoothstep: C1-continuous across cells
    i = base.astype(np.int64)
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += wx * wy * wz * _hash01(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
    return 2.0 * out - 1.0


def _fbm(p: np.ndarray, octaves: int, base_frequency: float, seed: int, gain: float = 0.5) -> np.ndarray:
    """Fractal sum of value noise; amplitude halves while frequency doubles per octave."""
    total = np.zeros(len(p))
    amplitude, frequency, norm = 1.0, base_frequency, 0.0
    for k in range(octaves):
        total += amplitude * _value_noise(p * frequency + 17.0 * k, seed + 101 * k)
        norm += amplitude
        amplitude *= gain
        frequency *= 2.0
    return total / norm


def _fit_unit_cube(vertices: np.ndarray, base_at_bottom: bool) -> np.ndarray:
    """Scale uniformly into [-1, 1]^3 (a little margin), centred; optionally base resting on y = -1."""
    lo, hi = vertices.min(0), vertices.max(0)
    centre = 0.5 * (lo + hi)
    scale = 1.999 / float((hi - lo).max())
    v = (vertices - centre) * scale
    if base_at_bottom:
        v[:, 1] += -1.0 - v[:, 1].min()
    return np.clip(v, -1.0, 1.0)


# --- simple shapes ------------------------------------------------------------------------------


def box(size=(1.0, 1.0, 1.0)) -> Mesh:
    """Closed axis-aligned box centred at the origin with side lengths ``size`` (x, y, z).

    12 triangles, 24 vertices: each face has its own 4 vertices so shading is flat; outward
    winding and normals. UVs cover [0, 1]^2 on every face.
    """
    s = np.asarray(size, np.float64).reshape(-1)
    if s.shape != (3,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise NeuralRTError(f"box: size must be three positive numbers, got {size!r}")
    h = 0.5 * s
    verts, normals, faces, uvs = [], [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
            u, v = np.zeros(3), np.zeros(3)
            u[u_axis], v[v_axis] = 1.0, 1.0
            if sign < 0:  # keep (u, v, n) right-handed so the winding faces outward
                u, v = v, u
            c = n * h
            corners = [c - u * h - v * h, c + u * h - v * h, c + u * h + v * h, c - u * h + v * h]
            k = len(verts)
            verts += corners
            normals += [n] * 4
            uvs += [(0, 0), (1, 0), (1, 1), (0, 1)]
            faces += [(k, k + 1, k + 2), (k, k + 2, k + 3)]
    return Mesh(np.array(verts), np.array(faces), vertex_normals=np.array(normals), uvs=np.array(uvs), name="box")


def plane(size: float = 1.0) -> Mesh:
    """Square of side ``size`` in the xz-plane at y = 0, centred, facing +y; 2 triangles, UVs in [0, 1]."""
    if isinstance(size, bool) or not isinstance(size, (int, float, np.number)) or not np.isfinite(size) or size <= 0:
        raise NeuralRTError(f"plane: size must be a positive number (a square), got {size!r}")
    h = 0.5 * float(size)
    verts = np.array([(-h, 0, -h), (-h, 0, h), (h, 0, h), (h, 0, -h)])
    uvs = verts[:, [0, 2]] / size + 0.5
    uvs[:, 1] = 1.0 - uvs[:, 1]  # v grows towards -z (away from a camera on +z)
    faces = np.array([(0, 1, 2), (0, 2, 3)])
    normals = np.tile([0.0, 1.0, 0.0], (4, 1))
    return Mesh(verts, faces, vertex_normals=normals, uvs=uvs, name="plane")


def sphere(subdivisions: int = 4, radius: float = 1.0) -> Mesh:
    """Icosphere (trimesh): ``20 * 4**subdivisions`` triangles, exact smooth (radial) normals."""
    trimesh = import_trimesh()

    if int(subdivisions) != subdivisions or not 0 <= subdivisions <= 9:
        raise NeuralRTError(f"sphere: subdivisions must be an integer in 0..9, got {subdivisions!r}")
    if not np.isfinite(radius) or radius <= 0:
        raise NeuralRTError(f"sphere: radius must be a positive number, got {radius!r}")
    tm = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=1.0)
    unit = _unit(np.asarray(tm.vertices, np.float64))
    return Mesh(unit * radius, np.asarray(tm.faces), vertex_normals=unit, name="sphere")


# Linear base colours of the classic Cornell box (as used across path-tracing test scenes).
# Slot names only: the slots carry no colour of their own (white), so the scene's materials of
# these names colour them (builtin:cornell-statue), and mapping a slot to another material
# (`materials = { red = "white" }`) changes its colour. A mesh colour would multiply the scene
# material's albedo: the walls had each colour twice (white 0.73^2 = 0.53).
CORNELL_MATERIALS = (
    ("white", (1.0, 1.0, 1.0)),
    ("red", (1.0, 1.0, 1.0)),
    ("green", (1.0, 1.0, 1.0)),
    ("light", (1.0, 1.0, 1.0)),
)


def cornell_box() -> Mesh:
    """The empty Cornell box in [-1, 1]^3, open at +z (camera at z = +3.9 looking down -z).

    Floor y = -1, ceiling y = +1, back wall z = -1 (white); left wall x = -1 (red); right wall
    x = +1 (green); a light quad at y = 0.998 with |x|, |z| <= 0.25 facing down. Wall normals point
    into the box. Material slots (by `face_material_ids`): "white", "red", "green", "light", all
    white: a scene's materials of those names give the colours.
    """
    mats = {name: i for i, (name, _) in enumerate(CORNELL_MATERIALS)}
    # (centre, inward normal, half-extent, material)
    quads = [
        ((0, -1, 0), (0, 1, 0), 1.0, "white"),  # floor
        ((0, 1, 0), (0, -1, 0), 1.0, "white"),  # ceiling
        ((0, 0, -1), (0, 0, 1), 1.0, "white"),  # back wall
        ((-1, 0, 0), (1, 0, 0), 1.0, "red"),  # left wall
        ((1, 0, 0), (-1, 0, 0), 1.0, "green"),  # right wall
        ((0, 0.998, 0), (0, -1, 0), 0.25, "light"),
    ]
    verts, normals, faces, mat_ids, uvs = [], [], [], [], []
    for centre, normal, half, name in quads:
        c, n = np.asarray(centre, np.float64), np.asarray(normal, np.float64)
        axis = int(np.argmax(np.abs(n)))
        u, v = np.zeros(3), np.zeros(3)
        u[(axis + 1) % 3], v[(axis + 2) % 3] = 1.0, 1.0
        if np.dot(np.cross(u, v), n) < 0:  # winding must agree with the (inward) normal
            u, v = v, u
        k = len(verts)
        verts += [c - half * u - half * v, c + half * u - half * v, c + half * u + half * v, c - half * u + half * v]
        normals += [n] * 4
        uvs += [(0, 0), (1, 0), (1, 1), (0, 1)]
        faces += [(k, k + 1, k + 2), (k, k + 2, k + 3)]
        mat_ids += [mats[name]] * 2
    materials = [MeshMaterial(name, np.asarray(col, np.float32)) for name, col in CORNELL_MATERIALS]
    return Mesh(np.array(verts), np.array(faces), vertex_normals=np.array(normals), uvs=np.array(uvs),
                face_material_ids=np.array(mat_ids), materials=materials, name="cornell_box")


# --- statue: an implicit figure meshed with surface nets, Loop-subdivided, noise-displaced ------


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum: unions of distance fields that blend over a width ``k``."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _capsule(p: np.ndarray, a, b, r: float) -> np.ndarray:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ab = b - a
    t = np.clip(((p - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1) - r


def _ellipsoid(p: np.ndarray, centre, radii) -> np.ndarray:
    """Approximate signed distance to an ellipsoid (exact sign, distance scaled by the min radius)."""
    q = (p - np.asarray(centre)) / np.asarray(radii)
    return (np.linalg.norm(q, axis=1) - 1.0) * float(np.min(radii))


def _figure_sdf(p: np.ndarray, seed: int) -> np.ndarray:
    """A standing figure on a plinth (y up, roughly in [-1, 1]^3); ``seed`` varies the pose a little."""
    rng = np.random.default_rng(seed)
    lift = rng.uniform(0.15, 0.45)  # how high the raised arm reaches
    lean = rng.uniform(-0.06, 0.06)  # contrapposto: hips and head shift sideways
    blend = 0.04
    plinth_q = np.abs(p - np.array([0.0, -0.9, 0.0])) - np.array([0.42, 0.1, 0.32])
    plinth = np.linalg.norm(np.maximum(plinth_q, 0), axis=1) + np.minimum(plinth_q.max(1), 0) - 0.02
    d = _capsule(p, (-0.12 + lean, -0.78, 0.02), (-0.1 + lean, -0.05, 0.0), 0.085)  # left leg
    d = _smooth_min(d, _capsule(p, (0.14, -0.78, -0.04), (0.1 + lean, -0.05, 0.0), 0.085), blend)  # right leg
    d = _smooth_min(d, _ellipsoid(p, (lean, 0.02, 0.0), (0.2, 0.15, 0.13)), 0.08)  # hips
    d = _smooth_min(d, _ellipsoid(p, (0.5 * lean, 0.3, 0.0), (0.22, 0.26, 0.14)), 0.1)  # torso
    d = _smooth_min(d, _capsule(p, (0.0, 0.5, 0.0), (0.0, 0.62, 0.02), 0.06), blend)  # neck
    d = _smooth_min(d, _ellipsoid(p, (-lean, 0.74, 0.03), (0.1, 0.13, 0.11)), 0.04)  # head
    d = _smooth_min(d, _capsule(p, (-0.2, 0.48, 0.0), (-0.3, 0.18, 0.05), 0.055), blend)  # left upper arm
    d = _smooth_min(d, _capsule(p, (-0.3, 0.18, 0.05), (-0.26, -0.1, 0.14), 0.045), blend)  # left forearm
    d = _smooth_min(d, _capsule(p, (0.2, 0.48, 0.0), (0.4, 0.55 + 0.3 * lift, 0.04), 0.055), blend)  # right upper arm
    d = _smooth_min(d, _capsule(p, (0.4, 0.55 + 0.3 * lift, 0.04), (0.36, 0.7 + lift, 0.1), 0.045), blend)  # forearm
    return np.minimum(d, plinth)


def _surface_nets(sdf: np.ndarray, lo: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the zero level set of a sampled field (negative inside) with naive surface nets.

    One vertex per grid cell the surface crosses (the mean of its edge crossings); one quad per
    grid edge with a sign change, joining the four cells around that edge. Whole-array numpy.
    """
    inside = sdf < 0
    nx, ny, nz = sdf.shape
    cell_shape = (nx - 1, ny - 1, nz - 1)
    # Cells (by corner offsets) and the 12 edges of a cell as pairs of corner offsets.
    corners = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    edges = [(a, b) for a in corners for b in corners if sum(b) - sum(a) == 1 and sum(abs(x - y) for x, y in zip(a, b)) == 1]
    acc = np.zeros(cell_shape + (3,))
    cnt = np.zeros(cell_shape)
    for a, b in edges:
        va = sdf[a[0]:a[0] + nx - 1, a[1]:a[1] + ny - 1, a[2]:a[2] + nz - 1]
        vb = sdf[b[0]:b[0] + nx - 1, b[1]:b[1] + ny - 1, b[2]:b[2] + nz - 1]
        cross = (va < 0) != (vb < 0)
        t = np.where(cross, va / np.where(cross, va - vb, 1.0), 0.0)
        offset = np.asarray(a, np.float64)[None, None, None, :] + t[..., None] * (np.asarray(b) - np.asarray(a))
        acc += np.where(cross[..., None], offset, 0.0)
        cnt += cross
    active = cnt > 0
    cell_index = np.full(cell_shape, -1, np.int64)
    cell_index[active] = np.arange(int(active.sum()))
    grid = np.argwhere(active).astype(np.float64)
    vertices = lo + spacing * (grid + acc[active] / cnt[active][:, None])

    quads = []
    for axis in range(3):
        # Grid edges along `axis` starting at point p; the 4 cells around it are offset by -1/0
        # in the two other axes. Only interior edges (all 4 cells exist) can have a sign change.
        u, v = (axis + 1) % 3, (axis + 2) % 3
        sl_a = [slice(1, -1)] * 3
        sl_b = [slice(1, -1)] * 3
        sl_a[axis] = slice(0, -1)
        sl_b[axis] = slice(1, None)
        ia, ib = inside[tuple(sl_a)], inside[tuple(sl_b)]
        flip = ia & ~ib  # inside -> outside along +axis
        keep = ia != ib
        pts = np.argwhere(keep)  # indices into the sliced arrays
        fl = flip[keep]
        p = pts.copy()
        p[:, u] += 1
        p[:, v] += 1  # back to full-grid point indices (the slices started at 1)

        def cell(du: int, dv: int) -> np.ndarray:
            c = p.copy()
            c[:, u] += du
            c[:, v] += dv
            return cell_index[c[:, 0], c[:, 1], c[:, 2]]

        q = np.stack([cell(-1, -1), cell(0, -1), cell(0, 0), cell(-1, 0)], axis=1)
        q = np.where(fl[:, None], q, q[:, ::-1])  # wind so the normal points from inside to outside
        quads.append(q)
    quads = np.concatenate(quads)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return vertices, faces


def _statue_base(seed: int, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.array([-1.05, -1.05, -1.05])
    axis = np.linspace(0.0, 2.1, resolution)
    spacing = float(axis[1] - axis[0])
    gx, gy, gz = np.meshgrid(axis, axis, axis, indexing="ij")
    pts = lo + np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    sdf = _figure_sdf(pts, seed).reshape(resolution, resolution, resolution)
    return _surface_nets(sdf, lo, spacing)


def statue(detail: int = 2, seed: int = 0) -> Mesh:
    """A sculpted standing figure on a plinth with fine noise-displaced surface detail.

    An implicit figure (smooth union of capsules and ellipsoids; ``seed`` varies the pose) is
    meshed with surface nets on a 96^3 grid (64^3 at detail 0), split ``detail - 1`` times at edge
    midpoints (x4 triangles each), projected back onto the implicit surface, and displaced along its normals by fractal value noise whose finest octave
    follows the triangle size. Centred, in [-1, 1]^3, +y up, base on y = -1.

    Triangles (measured, seed 0; other seeds differ slightly below detail 2 and scale the same):
    detail 0: 8,392; 1: 18,930; 2: 75,720; 3: 302,880; 4: 1,211,520 (>= 1M); 5: 4,846,080.
    """
    import_trimesh()  # (first: an interrupt during trimesh's first import was swallowed)
    from trimesh.remesh import subdivide

    detail = _check_detail("statue", detail)
    v, f = _statue_base(seed, 64 if detail == 0 else 96)
    for _ in range(max(detail - 1, 0)):
        v, f = subdivide(v, f)  # midpoint split: the projection below makes it smooth again
    v = _project_to_surface(v, seed)
    f = np.asarray(f, np.int64)
    normals = _vertex_normals(v, f)
    # Sculpted look: broad chisel-like undulation plus fine grain down to ~the triangle size.
    octaves = 4 + max(detail - 1, 0)
    bumps = _fbm(v, octaves=octaves, base_frequency=6.0, seed=seed, gain=0.55)
    ridges = 1.0 - np.abs(_value_noise(v * 14.0, seed + 7))  # sharp creases where noise crosses 0
    v = v + normals * (0.012 * bumps + 0.006 * ridges ** 3)[:, None]
    v = _fit_unit_cube(v, base_at_bottom=True)
    return Mesh(v, f, vertex_normals=_vertex_normals(v, f), name=f"statue-d{detail}")


def _project_to_surface(v: np.ndarray, seed: int, steps: int = 3) -> np.ndarray:
    """Newton steps p <- p - sdf(p) grad / |grad|^2 onto the figure's zero set (central differences)."""
    eps = 1e-4
    for _ in range(steps):
        d = _figure_sdf(v, seed)
        grad = np.stack([(_figure_sdf(v + e, seed) - _figure_sdf(v - e, seed)) / (2 * eps) for e in np.eye(3) * eps], 1)
        g2 = np.maximum((grad * grad).sum(1), 1e-12)
        step = np.clip(d / g2, -0.02, 0.02)  # never jump further than about a base cell
        v = v - step[:, None] * grad
    return v


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals with bincount (fast for millions of faces)."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.stack([np.bincount(f.ravel(), weights=np.repeat(fn[:, k], 3), minlength=len(v)) for k in range(3)], axis=1)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1.0), [0.0, 1.0, 0.0])


# --- hairball: tubes along random smooth curves inside the unit ball ----------------------------

_HAIR_SEGMENTS = 96  # rings per tube minus one
_HAIR_SIDES = 6  # vertices per ring


def hairball(detail: int = 2, seed: int = 0) -> Mesh:
    """A tangle of ``32 * 2**detail`` thin closed tubes along random smooth curves in the unit ball.

    Each curve is a sum of random low-frequency sinusoids squashed radially into radius 0.95; the
    tube (96 segments, 6 sides, capped ends) follows it with rotation-minimising frames.
    ``1164 * 32 * 2**detail`` triangles (measured): detail 0: 37,248; 1: 74,496; 2: 148,992;
    3: 297,984; 4: 595,968; 5: 1,191,936 (>= 1M); 6: 2,383,872 (>= 2M).
    """
    detail = _check_detail("hairball", detail)
    rng = np.random.default_rng([seed, 1])
    n_tubes, n_rings, sides = 32 * 2**detail, _HAIR_SEGMENTS + 1, _HAIR_SIDES
    t = np.linspace(0.0, 1.0, n_rings)

    # Curves: 4 random sinusoids per coordinate, then a tanh squash keeps them inside the ball.
    k = 4
    freq = rng.uniform(0.3, 1.6, (n_tubes, 1, 3, k))
    phase = rng.uniform(0, 2 * np.pi, (n_tubes, 1, 3, k))
    amp = rng.uniform(0.3, 1.0, (n_tubes, 1, 3, k)) / np.arange(1, k + 1)
    centre = rng.normal(0.0, 0.4, (n_tubes, 1, 3))
    raw = centre + (amp * np.sin(2 * np.pi * freq * t[None, :, None, None] + phase)).sum(-1)
    r = np.linalg.norm(raw, axis=-1, keepdims=True)
    radius = rng.uniform(0.004, 0.009, (n_tubes, 1, 1))
    curve = raw * ((0.95 - radius) * np.tanh(r) / np.maximum(r, 1e-9))

    tangent = _unit(np.gradient(curve, axis=1))
    # Rotation-minimising frame by projection: a loop over rings, vectorised over all tubes.
    normal = np.empty_like(curve)
    seed_vec = _unit(rng.normal(size=(n_tubes, 3)))
    n0 = seed_vec - (seed_vec * tangent[:, 0]).sum(-1, keepdims=True) * tangent[:, 0]
    normal[:, 0] = _unit(n0 + 1e-6 * np.array([1.0, 0.0, 0.0]))
    for i in range(1, n_rings):
        prev = normal[:, i - 1]
        normal[:, i] = _unit(prev - (prev * tangent[:, i]).sum(-1, keepdims=True) * tangent[:, i])
    binormal = np.cross(tangent, normal)

    theta = 2 * np.pi * np.arange(sides) / sides
    ring_dir = np.cos(theta)[None, None, :, None] * normal[:, :, None] + np.sin(theta)[None, None, :, None] * binormal[:, :, None]
    ring = curve[:, :, None] + radius[:, :, None] * ring_dir  # [T, R, S, 3]

    # Faces: side quads between consecutive rings, then a triangle fan per end cap.
    per_tube = n_rings * sides + 2
    base = (np.arange(n_tubes) * per_tube)[:, None, None]
    ri, si = np.meshgrid(np.arange(n_rings - 1), np.arange(sides), indexing="ij")
    a = base + ri * sides + si
    b = base + ri * sides + (si + 1) % sides
    c = b + sides
    d = a + sides
    side_faces = np.concatenate([np.stack([a, b, c], -1).reshape(n_tubes, -1, 3), np.stack([a, c, d], -1).reshape(n_tubes, -1, 3)], 1)
    cap0_centre = (np.arange(n_tubes) * per_tube + n_rings * sides)[:, None]
    cap1_centre = cap0_centre + 1
    s = np.arange(sides)[None]
    first = (np.arange(n_tubes) * per_tube)[:, None] + s
    last = first + (n_rings - 1) * sides
    # Fans: (centre, s+1, s) faces -tangent at the start, (centre, s, s+1) faces +tangent at the end.
    cap0 = np.stack([np.broadcast_to(cap0_centre, first.shape), first - s + (s + 1) % sides, first], -1)
    cap1 = np.stack([np.broadcast_to(cap1_centre, last.shape), last, last - s + (s + 1) % sides], -1)
    faces = np.concatenate([side_faces, cap0, cap1], 1).reshape(-1, 3)

    verts = np.concatenate([ring.reshape(n_tubes, -1, 3), curve[:, [0, -1]]], 1).reshape(-1, 3)
    normals = np.concatenate([ring_dir.reshape(n_tubes, -1, 3), np.stack([-tangent[:, 0], tangent[:, -1]], 1)], 1).reshape(-1, 3)
    return Mesh(verts, faces, vertex_normals=normals, name=f"hairball-d{detail}")


# --- foliage: a trunk and a crown of small bent leaves -----------------------------------------

FOLIAGE_MATERIALS = (("bark", (0.30, 0.20, 0.12)), ("leaf", (0.10, 0.35, 0.06)))


def _cylinder(p0, p1, r0: float, r1: float, sides: int, rings: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Open tapered tube from p0 (radius r0) to p1 (radius r1): vertices, faces, normals."""
    p0, p1 = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    axis = _unit(p1 - p0)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    u = _unit(np.cross(axis, helper))
    w = np.cross(axis, u)
    t = np.linspace(0, 1, rings)[:, None, None]
    th = 2 * np.pi * np.arange(sides)[None, :, None] / sides
    radial = np.cos(th) * u + np.sin(th) * w
    verts = (p0 + t * (p1 - p0)) + ((1 - t) * r0 + t * r1) * radial
    ri, si = np.meshgrid(np.arange(rings - 1), np.arange(sides), indexing="ij")
    a, b = ri * sides + si, ri * sides + (si + 1) % sides
    faces = np.concatenate([np.stack([a, b, b + sides], -1).reshape(-1, 3), np.stack([a, b + sides, a + sides], -1).reshape(-1, 3)])
    return verts.reshape(-1, 3), faces, np.broadcast_to(radial, (rings, sides, 3)).reshape(-1, 3)


def foliage(detail: int = 2, seed: int = 0) -> Mesh:
    """A tree: a tapered trunk with 8 branches and ``1250 * 4**detail`` leaves in an ellipsoid crown.

    Each leaf is a diamond of 2 triangles folded slightly along its midrib, facing roughly
    outward; leaves shrink as their number grows (size ~ count^-1/3). Materials "bark" and
    "leaf". Fits in [-1, 1]^3, trunk base at y = -1. ``2 * 1250 * 4**detail + 736`` triangles
    (measured): detail 0: 3,236; 1: 10,736; 2: 40,736; 3: 160,736; 4: 640,736; 5: 2,560,736 (>= 2M).
    """
    detail = _check_detail("foliage", detail)
    rng = np.random.default_rng([seed, 2])
    crown_centre, crown_radii = np.array([0.0, 0.3, 0.0]), np.array([0.7, 0.55, 0.7])

    # Trunk and branches (wood).
    parts = [_cylinder((0, -1.0, 0), (0, 0.15, 0), 0.09, 0.04, 16, 12)]
    for i in range(8):
        ang = 2 * np.pi * (i + rng.uniform(-0.2, 0.2)) / 8
        y0 = rng.uniform(-0.2, 0.1)
        tip = crown_centre + crown_radii * 0.7 * np.array([np.cos(ang), rng.uniform(-0.1, 0.5), np.sin(ang)])
        parts.append(_cylinder((0, y0, 0), tip, 0.03, 0.008, 8, 4))
    wood_v, wood_f, wood_n, offset = [], [], [], 0
    for v, f, n in parts:
        wood_v.append(v)
        wood_f.append(f + offset)
        wood_n.append(n)
        offset += len(v)
    wood_v, wood_f, wood_n = np.concatenate(wood_v), np.concatenate(wood_f), np.concatenate(wood_n)

    # Leaves: positions biased towards the crown surface, outward-ish normals, random spin.
    n_leaves = 1250 * 4**detail
    direction = _unit(rng.normal(size=(n_leaves, 3)))
    depth = rng.uniform(0, 1, n_leaves) ** (1 / 6)
    centre = crown_centre + crown_radii * direction * depth[:, None]
    normal = _unit(direction + rng.normal(0.0, 0.6, (n_leaves, 3)) + np.array([0.0, 0.4, 0.0]))
    helper = _unit(rng.normal(size=(n_leaves, 3)))
    along = _unit(np.cross(normal, helper))  # midrib direction, in the leaf plane
    across = np.cross(normal, along)
    length = 0.07 * (20000 / n_leaves) ** (1 / 3) * rng.uniform(0.7, 1.3, (n_leaves, 1))
    width = 0.45 * length
    bend = rng.uniform(0.05, 0.3, (n_leaves, 1)) * width  # fold the two halves up along the midrib
    base = centre - 0.5 * length * along
    tip = centre + 0.5 * length * along
    left = centre - 0.5 * width * across + bend * normal
    right = centre + 0.5 * width * across + bend * normal
    leaf_v = np.stack([base, left, tip, right], 1).reshape(-1, 3)  # wound counter-clockwise about `normal`
    leaf_n = np.repeat(normal, 4, axis=0)
    k = np.arange(n_leaves)[:, None] * 4 + len(wood_v)
    leaf_f = np.concatenate([np.stack([k, k + 1, k + 2], -1), np.stack([k, k + 2, k + 3], -1)], 1).reshape(-1, 3)

    verts = np.concatenate([wood_v, leaf_v])
    scale = 0.999 / max(1.0, float(np.abs(verts).max()))  # leaves on the crown edge may poke out
    verts = verts * scale
    verts[:, 1] += -1.0 - verts[:, 1].min()
    faces = np.concatenate([wood_f, leaf_f])
    mat = np.concatenate([np.zeros(len(wood_f), np.int32), np.ones(len(leaf_f), np.int32)])
    materials = [MeshMaterial(name, np.asarray(col, np.float32)) for name, col in FOLIAGE_MATERIALS]
    return Mesh(np.clip(verts, -1, 1), faces, vertex_normals=np.concatenate([wood_n, leaf_n]),
                face_material_ids=mat, materials=materials, name=f"foliage-d{detail}")


# --- registry -----------------------------------------------------------------------------------


# The finest detail each detail-levelled generator builds (statue(5): 4.8M triangles; built-in
# scenes and the benchmarks' mesh specs take their bounds from here).
MAX_DETAIL = {"statue": 5, "hairball": 8, "foliage": 6}


def _check_detail(name: str, detail) -> int:
    max_detail = MAX_DETAIL[name]
    if isinstance(detail, bool) or int(detail) != detail or not 0 <= detail <= max_detail:
        raise NeuralRTError(f"{name}: detail must be an integer in 0..{max_detail}, got {detail!r}")
    return int(detail)


GENERATORS: dict[str, Callable[..., Mesh]] = {
    "statue": statue,
    "hairball": hairball,
    "foliage": foliage,
    "box": box,
    "plane": plane,
    "sphere": sphere,
    "cornell_box": cornell_box,
}


def parse_procedural_spec(spec: str) -> tuple[str, int]:
    """``(NAME, DETAIL)`` of a ``procedural:NAME:DETAIL`` mesh spec (NAME a generator with a detail
    level, `MAX_DETAIL`); anything else starting with ``procedural:`` is a one-line `MeshError`."""
    from ..errors import MeshError

    parts = spec.split(":")
    name = parts[1] if len(parts) > 1 else ""
    limit = MAX_DETAIL.get(name)
    if limit is None and name in GENERATORS:  # (sphere, box, ...: parameters, no detail level)
        shape = ", ".join(f"{k}={v.default!r}" for k, v in inspect.signature(GENERATORS[name]).parameters.items())
        raise MeshError(f"{spec}: {name} has no detail level: in Python, neuralrt.geometry.procedural.{name}({shape}); "
                        f"in a scene file, generator = {{ name = \"{name}\" }}")
    if len(parts) != 3 or limit is None:
        raise MeshError(f"{spec}: not a procedural mesh spec: use procedural:NAME:DETAIL with NAME one of "
                        f"{', '.join(f'{n} (DETAIL 0..{d})' for n, d in MAX_DETAIL.items())}")
    try:
        detail = int(parts[2])
    except ValueError:
        detail = None
    if detail is None or not 0 <= detail <= limit:
        raise MeshError(f"{spec}: DETAIL must be an integer in 0..{limit} for {name}, got {parts[2]!r}")
    return name, detail


def procedural_mesh(spec: str) -> Mesh:
    """The mesh a ``procedural:NAME:DETAIL`` spec names (`parse_procedural_spec`)."""
    name, detail = parse_procedural_spec(spec)
    return make_procedural(name, detail=detail)


def make_procedural(name: str, **params) -> Mesh:
    """Build the procedural mesh ``name`` with keyword ``params``; errors name the problem."""
    gen = GENERATORS.get(name)
    if gen is None:
        raise NeuralRTError(f"unknown procedural mesh {name!r} (known: {', '.join(sorted(GENERATORS))})")
    accepted = inspect.signature(gen).parameters
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        raise NeuralRTError(f"procedural mesh {name!r}: unknown parameter(s) {', '.join(unknown)} (accepted: {', '.join(accepted) or 'none'})")
    try:
        return gen(**params)
    except NeuralRTError:
        raise
    except (TypeError, ValueError) as exc:
        raise NeuralRTError(f"procedural mesh {name!r}: bad parameters {params!r} ({exc})") from None

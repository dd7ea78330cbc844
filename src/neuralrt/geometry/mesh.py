"""Triangle meshes: loading with trimesh, validation, and the data the intersectors need.

A `Mesh` holds numpy arrays (the CPU-side source data): Embree builds from them and neural
models are trained against them.
"""

from __future__ import annotations

import hashlib
import io
import math
import warnings
from collections.abc import Container
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from ..errors import MeshError, outside_stacklevel
from ..io.files import input_file_problem
from ..io.images import srgb_to_linear
from .declared_counts import ply_vertex_properties, truncation_problem
from .gltf_json import (dequantized_positions, dequantized_uvs, gltf_file_notes, gltf_header, gltf_material_extras,
                        gltf_mesh_index, expanded_instances, instanced_nodes, mesh_alone, named_materials,
                        position_dequantization, uv_dequantization, with_header)
from .gltf_pack import packed_alone
from .obj_files import clean_obj_text, scaled_normal_texels, used_material_names, vertex_colours_of_parts
from .off_colours import off_colours
from .unread_assets import OutsideFolderError, regular_files_resolver, unread_assets


__all__ = ["Mesh", "MeshMaterial", "load_mesh", "check_float32_extent", "import_trimesh"]


def import_trimesh():
    """``trimesh``, imported the first time with Ctrl-C and SIGTERM held until it is done
    (`neuralrt.interrupts`): its optional imports catch ``BaseException``, so an interrupt landing
    inside them was swallowed and the run went on. Every module of neuralrt that imports from
    trimesh calls this first."""
    import sys

    from ..interrupts import interrupts_held

    if "trimesh" in sys.modules:
        import trimesh  # (waits for a first import another thread still runs)

        return trimesh
    with interrupts_held():
        import trimesh
    return trimesh


@dataclass
class MeshMaterial:
    """A material as the mesh file describes it: a name, a linear base colour, an optional texture
    and an optional tangent-space normal map (both need the mesh's UVs)."""

    name: str = "default"
    base_color: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))  # linear RGB
    texture: np.ndarray | None = None  # [H, W, 3] linear float32, row 0 = top (v = 1)
    normal_map: np.ndarray | None = None  # [H, W, 3] float32 texels in [0, 1] as stored (not sRGB), row 0 = top


@dataclass
class Mesh:
    """An indexed triangle mesh with optional shading normals, UVs, colours and materials.

    Fields (numpy arrays, or anything numpy reads as one: lists, other dtypes, converted on
    construction and checked: a wrong shape, NaN/Inf positions or indices out of range raise a
    one-line `MeshError`):

    - ``vertices`` [V, 3] float32; ``faces`` [F, 3] int32 vertex indices, counter-clockwise seen
      from the front (the normal's side).
    - ``vertex_normals`` [V, 3] float32 unit shading normals (default: smooth ones from the faces).
    - ``uvs`` [V, 2] float32 texture coordinates, v up (None: none).
    - ``vertex_colors`` [V, 3] float32 linear RGB (None: white).
    - ``face_material_ids`` [F] int32 indices into ``materials`` (default: all 0).
    - ``materials``: `MeshMaterial` per slot (name, linear base colour, texture, normal map;
      default: one white ``default``); ``name``: a label for errors and model files.

    `load_mesh` reads one from a file; `neuralrt.geometry.procedural` builds test shapes (``sphere``,
    ``box``, ``plane``) and the built-in scenes' meshes.
    """

    vertices: np.ndarray  # [V, 3] float32
    faces: np.ndarray  # [F, 3] int32
    vertex_normals: np.ndarray | None = None  # [V, 3] float32, unit (smooth shading)
    uvs: np.ndarray | None = None  # [V, 2] float32
    vertex_colors: np.ndarray | None = None  # [V, 3] float32 linear
    face_material_ids: np.ndarray | None = None  # [F] int32 into `materials`
    materials: list[MeshMaterial] = field(default_factory=lambda: [MeshMaterial()])
    name: str = "mesh"

    def __post_init__(self) -> None:
        try:
            self.vertices = _as_float32(self.vertices)
        except (TypeError, ValueError) as exc:
            raise MeshError(f"{self.name}: vertices are not numbers ({exc})") from None
        self.faces = _as_indices(self.faces, self.name)
        validate_arrays(self.vertices, self.faces, self.name)
        if self.face_material_ids is None:
            self.face_material_ids = np.zeros(len(self.faces), np.int32)
        try:
            self.face_material_ids = np.ascontiguousarray(self.face_material_ids, dtype=np.int32)
        except (TypeError, ValueError, OverflowError) as exc:
            raise MeshError(f"{self.name}: face_material_ids are not int32 indices ({exc})") from None
        if not self.materials:
            self.materials = [MeshMaterial()]
        if len(self.face_material_ids) != len(self.faces) or (
            len(self.faces) and (self.face_material_ids.min() < 0 or self.face_material_ids.max() >= len(self.materials))
        ):
            raise MeshError(f"{self.name}: face_material_ids must be one index per face into its {len(self.materials)} "
                            f"materials (got {len(self.face_material_ids)} ids in "
                            f"[{self.face_material_ids.min(initial=0)}, {self.face_material_ids.max(initial=0)}])")
        if self.vertex_normals is None:
            self.vertex_normals = smooth_vertex_normals(self.vertices, self.faces)
        # Per-vertex attributes are read by vertex index in the kernels: a wrong shape reads past the array.
        self.vertex_normals = _per_vertex(self.vertex_normals, 3, "vertex_normals", self)
        self.uvs = _per_vertex(self.uvs, 2, "uvs", self)
        self.vertex_colors = _per_vertex(self.vertex_colors, 3, "vertex_colors", self)
        for material in self.materials:  # (sampled by row and column at hits: a wrong shape reads past it)
            material.texture = _image(material.texture, f"material {material.name!r} texture", self)
            material.normal_map = _image(material.normal_map, f"material {material.name!r} normal_map", self)

    @property
    def num_triangles(self) -> int:
        return int(len(self.faces))

    def __repr__(self) -> str:  # (the dataclass's printed every array: ~20 lines in a notebook)
        extras = [name for name, value in (("normals", self.vertex_normals), ("UVs", self.uvs), ("colours", self.vertex_colors))
                  if value is not None]
        lo, hi = self.bounds if len(self.vertices) else (np.zeros(3), np.zeros(3))
        return (f"Mesh({self.name!r}, {self.num_triangles:,} triangles, {len(self.vertices):,} vertices, "
                f"{len(self.materials)} material(s){', ' + ', '.join(extras) if extras else ''}, "
                f"bounds {np.round(lo, 4).tolist()}..{np.round(hi, 4).tolist()})")

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo [3], hi [3]) float32 numpy arrays. The geometry layer (`Mesh`) speaks numpy, the
        source data on the host; accelerators (`BLAS.bounds`) give an `AABB` of CPU tensors."""
        return self.vertices.min(0), self.vertices.max(0)

    def triangles(self) -> np.ndarray:
        """[F, 3, 3] float32 vertex positions per triangle."""
        return self.vertices[self.faces]

    def face_normals(self) -> np.ndarray:
        """[F, 3] unit geometric normals (zero for degenerate triangles): `unit_face_normals`."""
        return unit_face_normals(self.vertices, self.faces)

    def face_areas(self) -> np.ndarray:
        tri = self.triangles().astype(np.float64)
        return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)

    def content_hash(self) -> str:
        """SHA-256 of the geometry and attributes: identifies the source of a trained model."""
        h = hashlib.sha256()
        for arr in (self.vertices, self.faces, self.face_material_ids, self.vertex_normals, self.uvs, self.vertex_colors):
            h.update(b"|" if arr is None else np.ascontiguousarray(arr).tobytes())
        for m in self.materials:
            h.update(m.name.encode() + np.asarray(m.base_color, np.float32).tobytes())
            if m.texture is not None:
                h.update(np.ascontiguousarray(m.texture).tobytes())
            if m.normal_map is not None:  # (after a marker: a mesh without one hashes as before)
                h.update(b"normal_map" + np.ascontiguousarray(m.normal_map).tobytes())
        return h.hexdigest()

    def nbytes(self) -> int:
        """Bytes of the vertex and index buffers as a renderer stores them (positions + indices)."""
        return int(self.vertices.nbytes + self.faces.nbytes)

    def subdivided(self, iterations: int = 1) -> "Mesh":
        """Loop subdivision by trimesh (``iterations`` levels), keeping one material per face; UVs
        and colours are dropped. For tens of millions of triangles,
        `neuralrt.geometry.subdivision.loop_subdivided` gives the same triangles in less memory."""
        trimesh = import_trimesh()

        tm = trimesh.Trimesh(self.vertices, self.faces, process=False)
        mat = self.face_material_ids
        for _ in range(iterations):
            tm = tm.subdivide_loop(iterations=1)
            mat = np.repeat(mat, 4)
        return Mesh(tm.vertices, tm.faces, face_material_ids=mat, materials=self.materials,
                    name=f"{self.name}-loop{iterations}")


def validate_arrays(vertices: np.ndarray, faces: np.ndarray, name: str) -> None:
    """Raise `MeshError` naming ``name`` for empty, non-finite or badly indexed meshes."""
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"{name}: vertices must have shape [V, 3], got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshError(f"{name}: faces must be triangles with shape [F, 3], got {faces.shape}")
    if len(vertices) == 0 or len(faces) == 0:
        raise MeshError(f"{name}: mesh is empty ({len(vertices)} vertices, {len(faces)} triangles)")
    if not np.isfinite(vertices).all():
        bad = int((~np.isfinite(vertices)).any(1).sum())
        raise MeshError(f"{name}: {bad} vertices have NaN or Inf coordinates (in float32, where beyond 3.4e38 is Inf)")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(
            f"{name}: face indices out of range [0, {len(vertices) - 1}] (found {faces.min()}..{faces.max()})"
        )
    if not any((_cross_lengths(vertices, faces[s:s + _CHUNK]) > 0).any() for s in range(0, len(faces), _CHUNK)):
        raise MeshError(f"{name}: mesh is degenerate (all {len(faces)} triangles have zero area)")


def _as_indices(faces, name: str) -> np.ndarray:
    """Contiguous int32 face indices; whole numbers only, and none that int32 would wrap."""
    try:
        array = np.asarray(faces)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{name}: faces are not an array of vertex indices ({exc})") from None
    if array.size and not np.issubdtype(array.dtype, np.integer):
        if not np.issubdtype(array.dtype, np.floating) or not np.all(np.isfinite(array)) or not np.all(array == np.round(array)):
            raise MeshError(f"{name}: face indices must be whole numbers (got dtype {array.dtype})")
    if array.size and (array.min() < np.iinfo(np.int32).min or array.max() > np.iinfo(np.int32).max):
        raise MeshError(f"{name}: face indices out of range (found {array.min()}..{array.max()})")
    return np.ascontiguousarray(array, dtype=np.int32)


def _per_vertex(values, width: int, what: str, mesh: "Mesh") -> np.ndarray | None:
    """``values`` as contiguous float32 [V, width], or a `MeshError` naming ``what``; None stays None."""
    if values is None:
        return None
    try:
        array = np.ascontiguousarray(values, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{mesh.name}: {what} are not numbers ({exc})") from None
    if array.shape != (len(mesh.vertices), width):
        raise MeshError(f"{mesh.name}: {what} must have shape [{len(mesh.vertices)}, {width}] (one per vertex), got {list(array.shape)}")
    if not np.isfinite(array).all():  # (NaN colours rendered black and stopped training as a "diverged" loss)
        bad = int((~np.isfinite(array)).any(1).sum())
        raise MeshError(f"{mesh.name}: {what} of {bad} vertices are NaN or infinite")
    return array


def _image(values, what: str, mesh: "Mesh") -> np.ndarray | None:
    """``values`` as a float32 [H, W, 3] image, or None; another shape or NaN/Inf is a `MeshError`."""
    if values is None:
        return None
    image = np.asarray(values, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 1 or image.shape[1] < 1:
        raise MeshError(f"{mesh.name}: {what} must be [H, W, 3], got shape {list(image.shape)}")
    if not np.isfinite(image).all():
        raise MeshError(f"{mesh.name}: {what} holds NaN or infinite values")
    return image


def _as_float32(vertices) -> np.ndarray:
    """Contiguous float32 vertices. Coordinates beyond float32's range become Inf, which `validate_arrays`
    reports in one line: numpy's "overflow encountered in cast" warning would only repeat it."""
    with np.errstate(over="ignore"):
        return np.ascontiguousarray(vertices, dtype=np.float32)


# The sizes float32 ray tracing (MeshBLAS, the training rays, the neural models) handles: ray-triangle
# tests multiply up to four lengths (a squared cross product), and 1e±8 keeps those within 1e±32, well
# inside float32's normal range [1.2e-38, 3.4e38]. Measured on a sphere: exact hits and LSNIF/N-BVH
# training unchanged from diagonal 1e-9 to 1e12; exact hits fail at 1e-15 and 1e15.
FLOAT32_DIAGONAL_RANGE = (1e-8, 1e8)
# Rays leaving the surface start this far off it, relative to the diagonal (MeshBLAS's secondary offset,
# the training default): coordinates rounded by more than that put them back on the surface.
SURFACE_OFFSET = 1e-4


def check_float32_extent(mesh: "Mesh", name: str | None = None) -> None:
    """Raise a one-line `MeshError` unless float32 ray tracing keeps ``mesh``'s geometry: its bounding-box
    diagonal within `FLOAT32_DIAGONAL_RANGE`, and its coordinates, rounded to float32, off by less than
    `SURFACE_OFFSET` of the diagonal (a small mesh far from the origin loses its shape). Training checks
    this before any work, and so does `MeshBLAS`; loading does not, so ``neuralrt info`` still reports such meshes."""
    name = name or mesh.name
    lo, hi = (b.astype(np.float64) for b in mesh.bounds)
    diagonal = float(np.linalg.norm(hi - lo))
    low, high = FLOAT32_DIAGONAL_RANGE
    if not low <= diagonal <= high:
        raise MeshError(f"{name}: bounding-box diagonal {diagonal:.3g} is outside [{low:g}, {high:g}], the sizes float32 "
                        "ray tracing keeps precise; scale the mesh")
    farthest = float(np.abs(np.concatenate([lo, hi])).max())
    rounding = float(np.spacing(np.float32(farthest)))
    if rounding > SURFACE_OFFSET * diagonal:
        raise MeshError(f"{name}: coordinates reach {farthest:.3g}, too far from the origin for the mesh's size (diagonal "
                        f"{diagonal:.3g}): float32 rounds them by {rounding:.2g}, more than the {SURFACE_OFFSET:.0e} x diagonal "
                        "offset of rays leaving the surface; move the mesh near the origin")


# Faces per step of the per-face passes: bounds their float64 temporaries (~300 B per face) to ~80 MB
# whatever the mesh size, instead of [F, 3, 3] arrays over the whole mesh.
_CHUNK = 1 << 18


def _cross_lengths(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[F] float64 |(b - a) x (c - a)| (twice the area) of the given faces."""
    tri = vertices[faces].astype(np.float64)
    return np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def unit_face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[F, 3] float32 unit geometric normals (counter-clockwise; zero for degenerate triangles). In
    chunks of faces: the float64 temporaries of the whole mesh at once were ~150 B per triangle
    (row-wise, so the values do not depend on the chunking)."""
    out = np.empty((len(faces), 3), np.float32)
    for s in range(0, len(faces), _CHUNK):
        tri = vertices[faces[s:s + _CHUNK]].astype(np.float64)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        out[s:s + _CHUNK] = n / np.where(length > 0, length, 1)
    return out


def smooth_vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals; vertices of only degenerate faces get +z."""
    vn = np.zeros((len(vertices), 3))
    for s in range(0, len(faces), _CHUNK):
        f = faces[s:s + _CHUNK]
        tri = vertices[f].astype(np.float64)
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
        for k in range(3):
            np.add.at(vn, f[:, k], fn)
    length = np.linalg.norm(vn, axis=1, keepdims=True)
    vn = np.where(length > 0, vn / np.where(length > 0, length, 1), [0.0, 0.0, 1.0])
    return vn.astype(np.float32)


@numba.njit(cache=True)
def _add_weighted_face_normals(summed, faces, weights, face_normals, use):
    """summed[faces[f, k]] += weights[f, k] * face_normals[f] for the faces with ``use``, in face
    order: the order scipy's sparse product sums them in (trimesh), so the results match bitwise."""
    for f in range(faces.shape[0]):
        if use[f]:
            for k in range(3):
                v = faces[f, k]
                for c in range(3):
                    summed[v, c] += weights[f, k] * face_normals[f, c]


SMALL_MESH_DIAGONAL = 2.0 ** -10  # (`angle_weighted_vertex_normals`: meshes smaller are scaled up first)


def angle_weighted_vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V, 3] float32 vertex normals weighted by corner angle, as trimesh's ``vertex_normals``
    computes them for a file without normals (same per-face formulas, same summation order), in
    chunks of faces instead of trimesh's cached [F, 3, 3] float64 arrays and sparse matrix.
    Unreferenced vertices get zero."""
    from trimesh import triangles, util

    # trimesh skips a face whose cross product is below 1e-13 long: every face of a mesh 1e-6 across,
    # whose normals were all zero. A small mesh is scaled up by a power of two first, which leaves
    # each unit normal and angle bitwise as it was.
    diagonal = float(np.linalg.norm(vertices.max(0).astype(np.float64) - vertices.min(0))) if len(vertices) else 0.0
    scale = 2.0 ** -math.floor(math.log2(diagonal)) if 0 < diagonal < SMALL_MESH_DIAGONAL else 1.0
    summed = np.zeros((len(vertices), 3))
    for s in range(0, len(faces), _CHUNK):
        f = faces[s:s + _CHUNK]
        tri = vertices[f].astype(np.float64) * scale
        unit, valid = triangles.normals(crosses=triangles.cross(tri))
        fn = np.zeros((len(f), 3))
        fn[valid] = unit
        use = (fn ** 2).sum(axis=1) > 0.5  # trimesh skips faces without a valid normal
        _add_weighted_face_normals(summed, f, triangles.angles(tri), fn, use)
    unit = np.empty((len(vertices), 3), np.float32)
    for s in range(0, len(summed), _CHUNK):  # row-wise, so chunks give the same values
        unit[s:s + _CHUNK] = util.unitize(summed[s:s + _CHUNK])
    return unit


# --- loading --------------------------------------------------------------------------------


def _material_from_visual(visual, fallback_name: str, where: str, kept_colors=None, linear_colors: bool = False,
                          base_color=None, lit: Container[str] = ()
                          ) -> tuple[MeshMaterial, np.ndarray | None, np.ndarray | None]:
    """(material, per-vertex uv, per-vertex linear colour) from a trimesh visual (``where``: the
    mesh file, for warnings about a texture that cannot be decoded). ``kept_colors``: vertex colours
    beside a material, a glTF primitive's COLOR_0 as trimesh reads it or an OBJ's linear colours
    (`_keep_obj_colours`); ``linear_colors``: vertex colours are
    linear (glTF's), not sRGB (PLY's, OBJ's); ``base_color``: a glTF material's base colour factor
    as the file writes it (trimesh keeps 8 bits); ``lit``: the material names whose emission a scene
    makes a light (not warned as unread)."""
    uv = colors = None
    material = MeshMaterial(name=fallback_name)
    kind = getattr(visual, "kind", None)
    if kind == "texture":
        mat = visual.material
        uv = None if visual.uv is None else np.asarray(visual.uv, np.float32)
        material.name = getattr(mat, "name", None) or fallback_name
        if hasattr(mat, "baseColorFactor"):  # glTF PBR
            colors = None if kept_colors is None else _accessor_colors(kept_colors, where)
            _pbr_colour(material, mat, uv, where, base_color)
            normals = getattr(mat, "normalTexture", None)
            if normals is not None and _has_uvs(uv, "normal map", material.name, where):
                material.normal_map = _normal_map(normals, material.name, where)
            return material, uv, colors
        colors = None if kept_colors is None else _accessor_colors(kept_colors, where)  # (an OBJ's, linear)
        if _is_placeholder(mat):  # UVs but no material (no or a missing MTL): white, as without UVs
            return material, uv, colors
        statements = getattr(mat, "kwargs", None) or {}  # (the MTL's statements trimesh passes on unread)
        exact = statements.get("kd")  # the MTL's Kd as written (diffuse: 8 bits)
        diffuse = getattr(mat, "diffuse", None)
        if isinstance(exact, (list, tuple)) and len(exact) >= 3:
            material.base_color = srgb_to_linear(np.clip(np.asarray(exact[:3], np.float32), 0.0, 1.0))
        elif diffuse is not None:
            material.base_color = srgb_to_linear(np.asarray(diffuse, np.float32)[:3] / 255.0)
        image = getattr(mat, "image", None)
        texture = _texture_pixels(image, material.name, where) \
            if image is not None and _has_uvs(uv, "texture", material.name, where) else None
        if texture is not None:
            material.texture = texture
            material.base_color = np.ones(3, np.float32)  # texture carries the colour (OBJ Kd is usually 1 then)
        material.normal_map = _mtl_normal_map(statements, uv, material.name, where)
        if _positive(statements.get("ke")) and material.name not in lit:
            warnings.warn(f"{where}: the emission of material {material.name!r} (Ke) is not read: give the slot an "
                          f"emissive scene material to make it a light", stacklevel=outside_stacklevel())
    elif kind == "vertex":
        colors = np.asarray(visual.vertex_colors, np.float32)[:, :3] / 255.0
        colors = colors if linear_colors else srgb_to_linear(colors)
    elif kind == "face":
        fc = np.asarray(visual.face_colors, np.float32)[:, :3] / 255.0
        if np.allclose(fc, fc[0]):
            material.base_color = srgb_to_linear(fc[0])
    return material, uv, colors


def _positive(tokens) -> bool:
    """Whether an MTL statement's values (trimesh keeps them as strings) hold a number above 0."""
    for token in tokens if isinstance(tokens, (list, tuple)) else ():
        try:
            if float(token) > 0:
                return True
        except ValueError:
            pass
    return False


def _accessor_colors(values, where: str) -> np.ndarray | None:
    """[V, 3] linear colours of a glTF COLOR_0 accessor as trimesh leaves it beside a material:
    RGB or RGBA, float or normalised unsigned bytes or shorts (trimesh does not scale those)."""
    values = np.asarray(values)
    if values.ndim != 2 or values.shape[1] not in (3, 4):
        warnings.warn(f"{where}: vertex colours of shape {list(values.shape)} are left out",
                      stacklevel=outside_stacklevel())
        return None
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(values.dtype, 1.0)
    return np.clip(values[:, :3].astype(np.float32) / np.float32(scale), 0.0, 1.0)


def _rewritten_gltf(header: dict, path: Path) -> tuple[dict, bytes | None]:
    """(the header trimesh is to read the file under, the file's bytes with it, or None where the
    file is read as it is): unnamed materials that place their maps differently named
    (`named_materials`), GPU instances made nodes (`expanded_instances`). The file is read once."""
    rewritten = named_materials(header)
    if rewritten is None and not instanced_nodes(header):
        return header, None
    data = path.read_bytes()
    try:
        rewritten = expanded_instances(rewritten or header, path) or rewritten
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise MeshError(f"{path}: cannot read mesh: its EXT_mesh_gpu_instancing instances cannot be read "
                        f"({type(exc).__name__}: {exc})") from None
    return rewritten, with_header(data, rewritten)


def _unreadable_why(exc: Exception, suffix: str) -> str:
    """What trimesh's error for a malformed file means, in words (its own text follows in brackets:
    "string or file could not be read to its end due to unmatched data" said little)."""
    text = str(exc)
    if "unmatched data" in text or "invalid literal" in text or "could not convert string" in text:
        why = "text where numbers were expected"
    elif "expected length" in text:  # (PLY, binary STL, GLB chunks)
        why = "its data is shorter or longer than its header says"
    elif "cannot reshape" in text:
        why = "numbers missing or left over"
    elif isinstance(exc, IndexError):
        why = "an index past the end of its data"
    else:
        why = None
    kind = {".gltf": "glTF", ".glb": "glTF"}.get(suffix, suffix[1:].upper() or "mesh")
    return f"not a valid {kind} file: {why}" if why else f"not a valid {kind} file, or damaged"


def _keep_obj_colours(loaded, data: bytes, path: Path) -> None:
    """An OBJ's ``v x y z r g b`` colours (`vertex_colours_of_parts`), which trimesh drops beside a
    material, put where a glTF's are found (`_kept_colours`): the visual's ``vertex_attributes``, linear.
    ``loaded``: trimesh's Scene of the file's parts, or its one part."""
    named = list(loaded.geometry.items()) if hasattr(loaded, "geometry") else [(None, loaded)]
    if not any(getattr(getattr(g, "visual", None), "kind", None) == "texture" for _, g in named):
        return  # (no part has a material: trimesh kept their colours, no second parse)
    with unread_assets():  # (what this second read cannot find, the first has said)
        colours = vertex_colours_of_parts(data, regular_files_resolver(str(path))) or {}
    for name, geometry in named:
        visual = getattr(geometry, "visual", None)
        if name is None:  # (a lone part: the file's one coloured part, if it has one)
            srgb = next(iter(colours.values())) if len(colours) == 1 else None
        else:
            srgb = colours.get(name)
        if srgb is not None and getattr(visual, "kind", None) == "texture" and len(srgb) == len(geometry.vertices):
            visual.vertex_attributes["color"] = srgb_to_linear(srgb)


def _kept_colours(geometry) -> np.ndarray | None:
    """Vertex colours a part keeps beside a material (a texture visual's ``vertex_attributes``: a
    glTF COLOR_0, an OBJ's from `_keep_obj_colours`), or None (none, or one of another length)."""
    visual = getattr(geometry, "visual", None)
    attributes = getattr(visual, "vertex_attributes", None)
    color = attributes.get("color") if getattr(visual, "kind", None) == "texture" and attributes else None
    return color if color is not None and len(color) == len(geometry.vertices) else None


def _scene_parts(scene, position_component: int | None = None) -> tuple[list, list]:
    """A trimesh Scene's triangle meshes moved to their instances' places, as ``Scene.dump`` does,
    keeping what its copies drop: the file's vertex normals (trimesh's cache, which
    ``apply_transform`` turns with the part) and vertex colours beside a material (the visual's
    ``vertex_attributes``: a glTF COLOR_0, an OBJ's from `_keep_obj_colours`; None where there is
    none, or one of another length), one per part."""
    from trimesh import Trimesh

    parts, colors = [], []
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geometry = scene.geometry[name]
        if not isinstance(geometry, Trimesh):
            continue
        part = geometry.copy(include_cache=True)
        if position_component is not None:  # (normalised integers, as trimesh reads them: unscaled; before the node's transform)
            normals = part._cache["vertex_normals"] if "vertex_normals" in part._cache else None
            part.vertices = dequantized_positions(part.vertices, position_component)
            if normals is not None:  # (setting vertices clears the cache: the file's normals stay)
                part.vertex_normals = normals
        part.apply_transform(transform)
        part.metadata["neuralrt_node"] = node  # (what a warning about this part calls it)
        parts.append(part)
        colors.append(_kept_colours(geometry))
    return parts, colors


def _pbr_colour(material: MeshMaterial, pbr, uv: np.ndarray | None, where: str, exact=None) -> None:
    """A glTF material's colour as the glTF spec defines it: ``baseColorFactor`` is linear (trimesh
    keeps it as 0-255) and white when absent; a ``baseColorTexture`` is sRGB and multiplied by it.
    (trimesh's ``to_simple`` reads the factor as sRGB and an absent one as its 0.4 grey.)"""
    factor = pbr.baseColorFactor
    linear = np.ones(3, np.float32) if factor is None else np.asarray(factor, np.float32)[:3] / 255.0
    if exact is not None:  # (the file's own, where `gltf_material_extras` could tell the material by name)
        linear = np.asarray(exact, np.float32)
    image = pbr.baseColorTexture
    texture = _texture_pixels(image, material.name, where) \
        if image is not None and _has_uvs(uv, "texture", material.name, where) else None
    if texture is not None:
        material.texture = texture * linear
    else:
        material.base_color = linear


def _has_uvs(uv: np.ndarray | None, what: str, material: str, where: str) -> bool:
    """Whether an image can be mapped (the part has UVs); else a warning that it is left out."""
    if uv is None:
        warnings.warn(f"{where}: the {what} of material {material!r} is left out: the mesh has no UVs",
                      stacklevel=outside_stacklevel())
    return uv is not None


_GREY_MODES = ("1", "L", "LA", "La", "I", "I;16", "F")  # PIL modes of one channel (with alpha)


def _normal_map(image, material: str, where: str) -> np.ndarray | None:
    """A normal map's image (glTF ``normalTexture``, MTL ``norm``/``map_Bump``) as stored texels,
    or None with a warning where it cannot be a tangent-space normal map: a grey image (a height
    map, most likely; also one stored as RGB), or texels that point into the surface on average
    (blue below 0.5)."""
    why = None
    if image.mode in _GREY_MODES:
        why = f"it is a grey ({image.mode}) image: a tangent-space normal map has three channels (a height map?)"
        texels = None
    else:
        texels = _texture_pixels(image, material, where, data=True)
        blue = None if texels is None else float(texels[..., 2].mean())
        if texels is not None and _is_grey(texels):
            why = "its red, green and blue are equal everywhere: a grey image (a height map?)"
        elif blue is not None and blue <= 0.5:
            why = f"its texels point into the surface on average (mean blue {blue:.3f}, below 0.5)"
    if why is None:
        return texels
    warnings.warn(f"{where}: the normal map of material {material!r} is left out: {why}",
                  stacklevel=outside_stacklevel())
    return None


def _is_grey(texels: np.ndarray) -> bool:
    """Whether every texel's three channels are equal (to 8-bit rounding)."""
    return bool(np.abs(texels[..., 0] - texels[..., 1]).max() <= 0.5 / 255
                and np.abs(texels[..., 1] - texels[..., 2]).max() <= 0.5 / 255)


def _mtl_normal_map(statements: dict, uv: np.ndarray | None, material: str, where: str) -> np.ndarray | None:
    """The normal map an OBJ material's MTL statements name (`neuralrt.geometry.obj_files`), read
    beside the mesh file, or None (with a warning naming the statement where one cannot be used)."""
    from PIL import Image

    from .obj_files import normal_map_statement

    try:
        statement = normal_map_statement(statements)
    except ValueError as exc:
        warnings.warn(f"{where}: the normal map of material {material!r} is left out: {exc}",
                      stacklevel=outside_stacklevel())
        return None
    if statement is None or not _has_uvs(uv, "normal map", material, where):
        return None
    try:
        image = Image.open(io.BytesIO(regular_files_resolver(where).get(statement.file_name)))
    except Exception as exc:  # missing or not a regular file (OSError), not an image, a decompression bomb
        warnings.warn(f"{where}: the normal map of material {material!r} is left out: its file "
                      f"{statement.file_name!r} ({statement.keyword}) could not be read "
                      f"({type(exc).__name__}: {exc})", stacklevel=outside_stacklevel())
        return None
    texels = _normal_map(image, material, where)
    return None if texels is None else scaled_normal_texels(texels, statement.scale)


# Bytes a texture pixel takes while decoded: the float32 result and two float32 temporaries.
_TEXTURE_BYTES_PER_PIXEL = 3 * 4 * 3


def _texture_pixels(image, material: str, where: str, data: bool = False) -> np.ndarray | None:
    """[H, W, 3] linear RGB of a PIL image; 16-bit grey (PIL mode I;16 or I) scaled from 65535, where
    ``convert("RGB")`` would clip every value above 255 to white. ``data``: values as stored in
    [0, 1], not decoded from sRGB (a normal map). trimesh decodes textures lazily, here: one it
    cannot, or one larger than the memory left, is a warning and None (the material keeps its base
    colour, or its interpolated normals), not a traceback."""
    from ..devices import memory_shortfall

    width, height = image.size
    shortfall = memory_shortfall(width * height * _TEXTURE_BYTES_PER_PIXEL, "cpu")
    why = f"decoding it {shortfall}" if shortfall else None
    if why is None:
        try:
            decode = (lambda x: x) if data else srgb_to_linear
            if image.mode.startswith("I"):
                grey = np.clip(np.asarray(image, np.float32) / 65535.0, 0.0, 1.0)
                return decode(np.repeat(grey[..., None], 3, axis=-1))
            return decode(np.asarray(image.convert("RGB"), np.float32) / 255.0)
        except (OSError, ValueError, MemoryError) as exc:  # PIL: truncated data; numpy: allocation
            why = f"{type(exc).__name__}: {exc}"
    _warn_undecodable("normal map" if data else "texture", image.size, material, where, why)
    return None


def _warn_undecodable(what: str, size: tuple[int, int], material: str, where: str, why: str) -> None:
    fallback = "its interpolated normals" if what == "normal map" else "its base colour"
    warnings.warn(f"{where}: the {size[0]}x{size[1]} {what} of material {material!r} could not be decoded ({why}); "
                  f"its material renders with {fallback}", stacklevel=outside_stacklevel())


def _varying_face_colors(visual) -> np.ndarray | None:
    """[F, 3] linear colours of a visual with per-face colours that differ (a PLY's face colours),
    else None (one colour for every face becomes the material's base colour instead)."""
    if getattr(visual, "kind", None) != "face":
        return None
    colors = np.asarray(visual.face_colors, np.float32)[:, :3] / 255.0
    return None if np.allclose(colors, colors[0]) else srgb_to_linear(colors)


def _is_placeholder(mat) -> bool:
    """Whether ``mat`` is trimesh's stand-in for a missing material (`empty_material`: a grey 2x2
    image and diffuse 102/255, which would render 0.13 linear instead of the white of no material)."""
    from trimesh.visual.material import empty_material

    stand_in = empty_material()
    image = getattr(mat, "image", None)
    return (image is not None and image.size == stand_in.image.size
            and np.array_equal(np.asarray(image), np.asarray(stand_in.image))
            and np.array_equal(np.asarray(getattr(mat, "diffuse", None)), np.asarray(stand_in.diffuse)))


def load_mesh(path: str | Path, gltf_mesh: int | str | None = None, lit: Container[str] = ()) -> Mesh:
    """Load a triangle mesh from any format trimesh reads (OBJ+MTL, PLY, OFF, STL, glTF/GLB), or
    build the built-in one that ``procedural:NAME:DETAIL`` names (e.g. ``procedural:statue:2``;
    `neuralrt.geometry.procedural`), so every command that takes a mesh runs without mesh files.

    Multi-part files are merged into one mesh; each part's material becomes one entry of
    ``materials`` and its faces get that ``face_material_ids``. Errors name the file; a texture
    or material file the mesh names but that cannot be read is a warning naming it (the mesh
    loads without it). glTF colours follow the glTF spec (``baseColorFactor`` linear, white when
    absent, times the sRGB ``baseColorTexture``); OBJ/MTL ``Kd`` and textures are sRGB. A glTF
    ``normalTexture``, or an MTL's ``norm``/``map_Bump``/``bump`` (`neuralrt.geometry.obj_files`),
    is the material's tangent-space normal map, kept as stored (not sRGB-decoded); glTF's normal
    map ``scale`` and ``KHR_texture_transform``, which trimesh drops, are applied
    (`neuralrt.geometry.gltf_json`). Vertices are
    kept as the file has them (``process=False``): an STL, which stores each triangle's corners
    apart, stays a triangle soup (3 vertices per triangle in ``mesh_bytes``, flat shading).

    ``gltf_mesh`` (a glTF file's mesh: its index, or its name where one mesh has it) loads that mesh
    alone, in its own space (not placed by the nodes that draw it), named ``FILE-INDEX``. ``lit``: the
    names of the materials a scene makes lights (emissive scene materials): their emission in the
    file (MTL ``Ke``, glTF ``emissiveFactor``) is not warned of as unread.
    """
    from ..devices import check_path

    path = check_path("path", path)  # (None, a number, a trimesh object: one-line ConfigError)
    if str(path).startswith("procedural:"):
        from .procedural import procedural_mesh

        return procedural_mesh(str(path))
    with np.errstate(all="ignore"):  # (NaN in a file: its own error follows, not numpy's "invalid value" warnings)
        return _load_mesh_file(path, gltf_mesh, lit)


def _load_mesh_file(path: Path, gltf_mesh: int | str | None, lit: Container[str]) -> Mesh:
    trimesh = import_trimesh()
    problem = input_file_problem(path, "mesh file")
    if problem:
        raise MeshError(problem)
    suffix = path.suffix.lower()
    if suffix in (".nrt", ".ckpt"):  # (trimesh's answer: "file_type 'nrt' not supported")
        raise MeshError(f"{path}: a neuralrt model file{' (a training checkpoint)' if suffix == '.ckpt' else ''}, not a "
                        f"mesh: load it with neuralrt.load_model")
    gltf = suffix in (".gltf", ".glb")  # (its COLOR_0 is linear, PLY's and OBJ's sRGB; flat normals)
    header = gltf_header(path) if gltf else None
    if gltf and not header:  # (trimesh's word for it: "FileNotFoundError: model.gltf")
        raise MeshError(f"{path}: cannot read mesh: its glTF JSON cannot be read (cut short, or not glTF)")
    if gltf_mesh is not None and not gltf:
        raise MeshError(f"{path}: gltf_mesh: only a glTF file (.gltf, .glb) has meshes to choose from")
    if gltf_mesh is not None:  # (the notes below are then of this mesh and its materials only)
        try:
            gltf_mesh = gltf_mesh_index(header, gltf_mesh)  # (one name whichever way it is chosen)
        except ValueError as exc:
            raise MeshError(f"{path}: gltf_mesh: {exc}") from None
        header = mesh_alone(named_materials(header) or header, gltf_mesh)  # (named as the whole file's are)
    unreadable, notes = gltf_file_notes(header, lit) if header else (None, [])
    if unreadable:
        raise MeshError(f"{path}: cannot read mesh: {unreadable}")
    used_materials: set[str] = set()
    if gltf_mesh is not None:  # (its own bytes only: `packed_alone`)
        try:
            rewritten, file_type = packed_alone(header, path), "glb"
        except (OSError, ValueError) as exc:
            raise MeshError(f"{path}: cannot read glTF mesh {gltf_mesh}: {getattr(exc, 'strerror', None) or exc}") from None
    elif header:
        header, rewritten = _rewritten_gltf(header, path)
        file_type = suffix[1:]
    else:
        rewritten = None
    try:
        with unread_assets() as unread:
            source, obj_bytes = dict(file_obj=str(path)), None
            if rewritten is not None:  # (read under a header of our own: see `_rewritten_gltf`)
                source = dict(file_obj=io.BytesIO(rewritten), file_type=file_type)
            if suffix == ".obj":  # (read once here: trimesh reads the bytes as they are, or as cleaned)
                data = path.read_bytes()
                used_materials = used_material_names(data)
                cleaned = clean_obj_text(data)
                obj_bytes = data if cleaned is None else cleaned
                source = dict(file_obj=io.BytesIO(obj_bytes), file_type="obj")
                data = cleaned = None
            loaded = trimesh.load(**source, process=False, resolver=regular_files_resolver(str(path)))
        if obj_bytes is not None and isinstance(loaded, (trimesh.Scene, trimesh.Trimesh)):
            _keep_obj_colours(loaded, obj_bytes, path)
        source = obj_bytes = rewritten = None
    except Exception as exc:  # trimesh raises many types for malformed files
        if isinstance(exc, OutsideFolderError):  # (ours: it says why, and the file may be fine)
            raise MeshError(f"{path}: cannot read mesh: {exc}") from None
        raise MeshError(f"{path}: cannot read mesh: {_unreadable_why(exc, suffix)} ({type(exc).__name__}: {exc})") from None
    for what in unread:
        warnings.warn(f"{path}: {what}", stacklevel=outside_stacklevel())
    extras_of, extras_notes = gltf_material_extras(header) if header else ({}, [])
    uv_component = uv_dequantization(header) if header else None
    for note in notes + extras_notes:
        warnings.warn(f"{path}: {note}", stacklevel=outside_stacklevel())
    if isinstance(loaded, trimesh.Trimesh) and suffix in (".off", ".ply"):
        _read_what_trimesh_drops(loaded, path)
    if isinstance(loaded, trimesh.Scene):
        _drop_undecodable_images(loaded, str(path))
        parts, kept_colors = _scene_parts(loaded, position_dequantization(header) if header else None)
    elif isinstance(loaded, trimesh.Trimesh):
        parts, kept_colors = [loaded], [_kept_colours(loaded)]
    else:
        parts, kept_colors = [], []
    cut_short = truncation_problem(path, sum(len(p.vertices) for p in parts), sum(len(p.faces) for p in parts))
    if cut_short:
        raise MeshError(f"{path}: {cut_short}")
    kept_colors = [c for p, c in zip(parts, kept_colors) if len(p.faces)]
    parts = [p for p in parts if len(p.faces)]
    if not parts:
        raise MeshError(f"{path}: file contains no triangles")

    loaded = None  # the parts hold what is needed; drop the rest before the per-face passes

    verts, faces, normals, uvs, colors, mat_ids, materials = [], [], [], [], [], [], []
    names: dict[str, int] = {}
    offset = 0
    any_uv = any(getattr(p.visual, "kind", None) == "texture" and getattr(p.visual, "uv", None) is not None for p in parts)
    face_colors_of = [_varying_face_colors(p.visual) for p in parts]  # (None for most parts: small)
    any_color = any(getattr(p.visual, "kind", None) == "vertex" for p in parts) \
        or any(c is not None for c in face_colors_of) or any(c is not None for c in kept_colors)
    for i in range(len(parts)):
        part, parts[i] = parts[i], None  # each part's trimesh arrays go once it is copied
        v = _as_float32(part.vertices)
        f = np.asarray(part.faces).astype(np.int32)
        try:
            validate_arrays(v, f, str(path))
        except MeshError as exc:
            if len(parts) == 1:
                raise
            node = part.metadata.get("neuralrt_node")
            warnings.warn(f"{path}: part {i} of {len(parts)}{f' (node {node!r})' if node is not None else ''} is left "
                          f"out ({str(exc).removeprefix(f'{path}: ')})", stacklevel=outside_stacklevel())
            continue
        part_material = getattr(part.visual, "material", None)  # (glTF: what trimesh drops, by name; None: unnamed)
        extras = extras_of.get(getattr(part_material, "name", None)) if part_material is not None else None
        material, uv, col = _material_from_visual(part.visual, f"material{i}", str(path), kept_colors[i], gltf,
                                                  None if extras is None else extras.base_color, lit)
        kept_colors[i] = None
        if uv_component is not None and uv is not None:  # (before a texture transform, as the glTF spec orders them)
            uv = dequantized_uvs(uv, uv_component)
        if extras is not None:
            uv = None if uv is None else extras.transformed_uvs(uv)
            if material.normal_map is not None:
                material.normal_map = scaled_normal_texels(material.normal_map, extras.normal_scale)
        face_colors, face_colors_of[i] = face_colors_of[i], None
        key = material.name
        known = materials[names[key]] if key in names else None
        # One slot per name only where the parts agree on it: two "paint"s of different colours stay two.
        if known is None or known.texture is not None or material.texture is not None \
                or known.normal_map is not None or material.normal_map is not None \
                or not np.array_equal(known.base_color, material.base_color):
            names[key] = len(materials)
            materials.append(material)
        mat_ids.append(np.full(len(f), names[key], np.int32))
        file_normals = "vertex_normals" in part._cache
        vn = np.asarray(part.vertex_normals, np.float32) if file_normals else None
        vertices64 = np.asarray(part.vertices)
        del part  # frees trimesh's int64 faces before the normals pass
        if file_normals:
            vn = vn if vn.shape == v.shape and np.isfinite(vn).all() else smooth_vertex_normals(v, f)
        elif gltf:  # the glTF spec: flat normals where a primitive has none
            vn = np.repeat(unit_face_normals(v, f), 3, axis=0)
            f, v, uv, col = _per_corner(f, v, uv, col)
        else:  # what trimesh would compute, from its float64 vertices, without its caches
            vn = angle_weighted_vertex_normals(vertices64, f)
        del vertices64
        if face_colors is not None:  # colours per face, exactly (normals kept)
            f, v, vn = _per_corner(f, v, vn)
            uv, col = None, np.repeat(face_colors, 3, axis=0)
        normals.append(vn)
        verts.append(v)
        faces.append(f + np.int32(offset) if offset else f)
        uvs.append(uv if uv is not None and len(uv) == len(v) else np.zeros((len(v), 2), np.float32))
        colors.append(col if col is not None and len(col) == len(v) else np.ones((len(v), 3), np.float32))
        offset += len(v)
    if not verts:
        raise MeshError(f"{path}: no valid triangle part in file")
    unknown = sorted(used_materials - {m.name for m in materials})
    if unknown and not unread:  # (a material file that could not be read is said already)
        warnings.warn(f"{path}: usemtl {', '.join(map(repr, unknown))} names no material of its material file(s): "
                      f"those faces render white", stacklevel=outside_stacklevel())
    return Mesh(
        vertices=_joined(verts),
        faces=_joined(faces),
        vertex_normals=_joined(normals),
        uvs=_joined(uvs) if any_uv else None,
        vertex_colors=_joined(colors) if any_color else None,
        face_material_ids=_joined(mat_ids),
        materials=materials,
        name=path.stem if gltf_mesh is None else f"{path.stem}-{gltf_mesh}",
    )


# PLY vertex properties trimesh does not read, and what they hold (it reads red/green/blue, u/v, s/t, texture_u/v).
_UNREAD_PLY = {"diffuse_red": "colours", "texture_s": "UVs"}


def _read_what_trimesh_drops(mesh, path: Path) -> None:
    """An OFF's colours into ``mesh``'s visual (`neuralrt.geometry.off_colours`); for a PLY whose
    colours or UVs are in properties trimesh does not read, a warning naming them."""
    from trimesh.visual import ColorVisuals

    if path.suffix.lower() == ".off":
        vertex_colours, face_colours, why = off_colours(path)
        if vertex_colours is not None and len(vertex_colours) != len(mesh.vertices):
            vertex_colours, why = None, why or "its colours are not read: trimesh read another number of vertices"
        if face_colours is not None and len(mesh.faces) != len(face_colours):
            face_colours, why = None, why or "its face colours are not read: trimesh read another number of faces"
        if why:
            warnings.warn(f"{path}: {why}", stacklevel=outside_stacklevel())
        if face_colours is not None:
            mesh.visual = ColorVisuals(mesh, face_colors=face_colours)
        elif vertex_colours is not None:
            mesh.visual = ColorVisuals(mesh, vertex_colors=vertex_colours)
        return
    kind = getattr(mesh.visual, "kind", None)
    for name in sorted(set(ply_vertex_properties(path)) & set(_UNREAD_PLY)):
        if (_UNREAD_PLY[name] == "colours" and kind != "vertex") or (_UNREAD_PLY[name] == "UVs" and kind != "texture"):
            warnings.warn(f"{path}: its vertex {_UNREAD_PLY[name]} ({name}, ...) are not read: trimesh reads "
                          f"{'red, green, blue' if name == 'diffuse_red' else 'u, v or s, t'}",
                          stacklevel=outside_stacklevel())


# Where trimesh's materials hold images (OBJ/MTL, glTF PBR), and what neuralrt makes of each (None: unused).
_IMAGE_ROLES = {"image": "texture", "baseColorTexture": "texture", "normalTexture": "normal map",
                "emissiveTexture": None, "occlusionTexture": None, "metallicRoughnessTexture": None}


def _drop_undecodable_images(scene, where: str) -> None:
    """Decode each image a trimesh Scene's materials hold, leaving out one that cannot be (with the
    warning `_texture_pixels` gives, where neuralrt uses that image): PIL decodes lazily, and
    copying a part (`_scene_parts`, as `Scene.dump` did) copies its material, which decoded a
    damaged PNG inside a .glb outside any check (an OSError that named no file). (A lone Trimesh is not dumped: `_texture_pixels` decodes the
    images it uses, after its memory check.)"""
    for geometry in scene.geometry.values():
        material = getattr(getattr(geometry, "visual", None), "material", None)
        for attribute, role in _IMAGE_ROLES.items():
            image = getattr(material, attribute, None)
            if image is None or not hasattr(image, "load"):
                continue
            try:
                image.load()
            except (OSError, ValueError, MemoryError, SyntaxError) as exc:  # PIL: truncated or damaged data
                if role is not None:
                    _warn_undecodable(role, image.size, getattr(material, "name", None) or "unnamed", where,
                                      f"{type(exc).__name__}: {exc}")
                setattr(material, attribute, None)


def _per_corner(faces: np.ndarray, vertices: np.ndarray, *attributes):
    """Each face its own three vertices: (``faces`` renumbered 0..3F-1, ``vertices`` and each
    per-vertex attribute read at the faces' corners; an attribute that is None, or of another
    length, as None)."""
    corners = faces.reshape(-1)
    read = [None if a is None or len(a) != len(vertices) else a[corners] for a in attributes]
    return (np.arange(len(corners), dtype=np.int32).reshape(-1, 3), vertices[corners], *read)


def _joined(arrays: list[np.ndarray]) -> np.ndarray:
    """The arrays concatenated; one array as it is (no copy of a single-part mesh)."""
    return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)

"""OBJ and MTL text, where trimesh misreads it or passes it on unread.

Read before trimesh parses it (`clean_obj_text`, `clean_mtl_text`): a UTF-8 byte-order mark, a
comment after a statement's values (``Kd 0.5 0.5 0.5 # grey`` became trimesh's placeholder grey,
without a word), relative (negative) face indices (trimesh counted them from the end of the file:
objects vanished), one value for a colour (``Kd 0.5``, as the MTL spec allows: the whole file was
dropped), and options before a ``map_Kd`` image (``-s 1 1 1 tex.png`` was looked up as one file
name). Each is rewritten to what trimesh reads as the file means; a map whose options move or
scale its UVs is left out with a reason.

Passed on unread (`normal_map_statement`): the normal map. MTL has no one statement for
tangent-space normal maps: ``norm`` names one, and ``map_Bump`` (or ``bump``), meant for a height
map, is what Blender and most exporters write for a normal map (and what their importers read as
one). So the first of ``norm``, ``map_Bump``, ``bump`` that a material has is its normal map, and
an image that is grey is left out as a height map by the loader, as a glTF ``normalTexture`` that
is grey. ``-bm`` scales it as glTF's ``normalTexture.scale`` does (x and y of each texel, then
normalised); a statement that moves or scales the map's UVs (``-o``, ``-s``, ``-t``) or picks one
channel of it (``-imfchan``: a height map) is left out with a reason, rather than shading with a
map placed wrong.

Read again where trimesh drops it (`vertex_colours_of_parts`): ``v x y z r g b`` colours in a file
with materials (as MeshLab and photogrammetry tools write a coloured scan).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numba
import numpy as np

from ..accel.normal_mapping import usable_texel

__all__ = ["MapStatement", "clean_mtl_text", "clean_obj_text", "normal_map_statement", "scaled_normal_texels",
           "used_material_names"]

_STATEMENTS = ("norm", "map_bump", "bump")  # in order of preference (trimesh lower-cases the keys)
# Options of an MTL map statement and how many values each takes (min, max).
_OPTIONS = {"-bm": (1, 1), "-clamp": (1, 1), "-blendu": (1, 1), "-blendv": (1, 1), "-cc": (1, 1),
            "-texres": (1, 1), "-boost": (1, 1), "-mm": (2, 2), "-imfchan": (1, 1), "-type": (1, 1),
            "-o": (1, 3), "-s": (1, 3), "-t": (1, 3)}
_DEFAULTS = {"-o": 0.0, "-s": 1.0, "-t": 0.0}  # UV offset, scale, turbulence: the map as the UVs place it


@dataclass(frozen=True)
class MapStatement:
    """A material's map statement (its normal map's, or a ``map_Kd`` being cleaned): its keyword as
    trimesh keeps it, the image's file name as written (relative to the OBJ's folder) and the
    ``-bm`` scale."""

    keyword: str
    file_name: str
    scale: float


def normal_map_statement(statements: dict) -> MapStatement | None:
    """The normal map among a trimesh ``SimpleMaterial``'s unread statements (its ``kwargs``:
    lower-cased keyword -> list of tokens), or None where it has none. A ValueError says why a
    statement cannot be used as written."""
    for keyword in _STATEMENTS:
        tokens = statements.get(keyword)
        if isinstance(tokens, (list, tuple)) and tokens:
            return _parsed(keyword, [str(t) for t in tokens])
    return None


def _parsed(keyword: str, tokens: list[str]) -> MapStatement:
    scale, i = 1.0, 0
    while i < len(tokens) and tokens[i].startswith("-") and not _is_number(tokens[i]):
        option = tokens[i].lower()
        if option not in _OPTIONS:
            raise ValueError(f"its statement {keyword} has an option {tokens[i]} that is not an MTL map option")
        least, most = _OPTIONS[option]
        values = tokens[i + 1:i + 1 + most]
        if option in _DEFAULTS or option in ("-bm", "-mm", "-boost"):
            count = 0
            while count < len(values) and _is_number(values[count]):
                count += 1
            if count < least and len(values) > count and not values[count].startswith("-"):
                raise ValueError(f"its statement {keyword} has {tokens[i]} {values[count]}: not a finite number")
            values = values[:count]
        if len(values) < least or i + 1 + len(values) >= len(tokens):
            raise ValueError(f"its statement {keyword} {' '.join(tokens)} has too few values after {tokens[i]}, "
                             f"or no file name")
        if option == "-bm":
            scale = float(values[0])
        elif option == "-imfchan" and keyword != "map_Kd":  # (on a colour map it picks a channel: ignored)
            raise ValueError(f"its statement {keyword} reads one channel (-imfchan {values[0]}): a height map, "
                             f"which is not applied")
        elif option in _DEFAULTS and any(float(v) != _DEFAULTS[option] for v in values):
            raise ValueError(f"its statement {keyword} moves or scales the map's UVs ({tokens[i]} {' '.join(values)}), "
                             f"which is not applied")
        i += 1 + len(values)
    return MapStatement(keyword, " ".join(tokens[i:]), scale)


def _is_number(token: str) -> bool:
    try:
        return np.isfinite(float(token))
    except ValueError:
        return False


def scaled_normal_texels(texels: np.ndarray, scale: float) -> np.ndarray:
    """Texels of a normal map whose directions have x and y scaled by ``scale``, then normalised
    (glTF's ``normalTexture.scale``; MTL's ``-bm``), encoded again in [0, 1]. Texels that encode no
    direction (pointing into the surface, or much shorter than a unit vector) are kept as stored:
    the renderer keeps the interpolated normal there either way."""
    if scale == 1.0:
        return texels
    m = texels * np.float32(2.0) - np.float32(1.0)
    usable = usable_texel(m, np.sum(m * m, axis=-1, keepdims=True))
    m[..., :2] *= np.float32(scale)
    m /= np.sqrt(np.maximum(np.sum(m * m, axis=-1, keepdims=True), np.float32(1e-12)))
    return np.where(usable, (m + np.float32(1.0)) * np.float32(0.5), texels).astype(np.float32)


# --- text trimesh misreads -------------------------------------------------------------------

_BOM = b"\xef\xbb\xbf"
_COLOURS = ("kd", "ka", "ks", "ke", "tf")


def clean_obj_text(data: bytes) -> bytes | None:
    """The OBJ ``data`` rewritten where trimesh would misread it (a BOM, comments after values,
    relative face indices made absolute, polygons of five corners or more split into triangles
    by ear clipping), or None where nothing needs it (the common case: the file is then read as
    it is)."""
    polygons, relative = _face_statements(np.frombuffer(data, np.uint8))
    if not (data.startswith(_BOM) or relative or polygons or _has_comment_after_values(data)):
        return None
    # As trimesh reads it: one statement per line once "\"-newline continuations are joined.
    text = _text(data).replace("\r\n", "\n").replace("\\\n", "")
    counts = {"v": 0, "vt": 0, "vn": 0}
    positions: list[tuple[float, float, float]] = []
    lines = []
    for line in text.splitlines():
        body = _without_comment(line)
        keyword = body.split(None, 1)[0] if body.strip() else ""
        if keyword in counts:
            counts[keyword] += 1
            if keyword == "v" and polygons:
                positions.append(_position(body))
        elif keyword == "f" and (relative or polygons):
            corners = [_absolute_corner(c, counts) for c in body.split()[1:]] if relative else body.split()[1:]
            body = "\n".join("f " + " ".join(t) for t in _triangles(corners, positions)) if polygons and len(corners) > 4 \
                else "f " + " ".join(corners)
        lines.append(body)
    return ("\n".join(lines) + "\n").encode()


@numba.njit(cache=True, nogil=True)
def _face_statements(data: np.ndarray) -> tuple[bool, bool]:
    """(whether a face statement has five corners or more, whether one has a relative index: a
    "-" anywhere in it). trimesh fans polygons (a concave one covered its notch; quads are left to
    it: most files are quads, a concave quad is rare) and counts relative indices from the end of
    the file. One pass over the bytes (regular expressions ran at 60-90 MB/s)."""
    n, at = len(data), 0
    polygons = relative = False
    while at < n and not (polygons and relative):
        while at < n and (data[at] == 32 or data[at] == 9):  # (indentation)
            at += 1
        if at + 1 < n and data[at] == 102 and (data[at + 1] == 32 or data[at + 1] == 9):  # "f "
            tokens, inside = 0, False
            at += 1
            while at < n and data[at] != 10 and data[at] != 35:  # (to the line's end or a comment)
                blank = data[at] == 32 or data[at] == 9 or data[at] == 13 or data[at] == 92  # (a "\" continues)
                if not blank and not inside:
                    tokens += 1
                relative |= data[at] == 45
                inside = not blank
                at += 1
            polygons |= tokens >= 5
        while at < n and data[at] != 10:
            at += 1
        at += 1
    return polygons, relative


def _position(statement: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(w) for w in statement.split()[1:4])
        return x, y, z
    except ValueError:
        return math.nan, math.nan, math.nan  # (trimesh says what is wrong with the statement)


def _triangles(corners: list[str], positions: list) -> list[list[str]]:
    """A polygon's corners as triangles by ear clipping (mapbox-earcut) in the plane its Newell
    normal faces, wound as the polygon is; where that cannot be done (a corner that names no
    vertex read so far, a polygon with no area), the polygon as it is, for trimesh's fan."""
    import mapbox_earcut

    try:
        points = np.array([positions[int(c.split("/", 1)[0]) - 1] for c in corners], np.float64)
    except (ValueError, IndexError):
        return [corners]
    following = np.roll(points, -1, axis=0)
    normal = np.array([np.sum((points[:, j] - following[:, j]) * (points[:, k] + following[:, k]))
                       for j, k in ((1, 2), (2, 0), (0, 1))])  # Newell's method
    if not np.isfinite(normal).all() or not normal.any():
        return [corners]
    drop = int(np.argmax(np.abs(normal)))
    plane = np.delete(points, drop, axis=1)
    found = mapbox_earcut.triangulate_float64(plane, np.array([len(corners)], np.uint32)).reshape(-1, 3)
    if len(found) != len(corners) - 2:
        return [corners]
    triangles = []
    for a, b, c in found.tolist():
        if np.dot(np.cross(points[b] - points[a], points[c] - points[a]), normal) < 0:
            b, c = c, b  # (earcut winds as it likes: keep the polygon's side)
        triangles.append([corners[a], corners[b], corners[c]])
    return triangles


_USEMTL = re.compile(rb"\n[ \t]*usemtl[ \t]+([^\r\n]*)")  # (starts at a line end: a check per line, not per byte)


_FIRST_VERTEX = re.compile(rb"(?m)^[ \t]*v[ \t]+([^\r\n]*)")


def vertex_colours_of_parts(data: bytes, resolver) -> dict[str, np.ndarray] | None:
    """An OBJ's ``v x y z r g b`` colours, which trimesh drops from every part with a material:
    part name (as trimesh names the parts of a Scene from the same bytes) -> [V, 3] sRGB in [0, 1],
    8-bit as trimesh keeps them without a material, aligned with that part's vertices. None where
    the file's vertices hold no colours (trimesh reads them when the first ``v`` has six values)."""
    first = _FIRST_VERTEX.search(data)
    if first is None or len(first.group(1).split()) < 6:
        return None
    import io

    from trimesh.exchange.obj import load_obj
    from trimesh.visual.color import to_rgba

    # (trimesh parses the file again: its parts' vertices are unmerged by UV and normal, so this
    # is how its colours line up with them; only coloured files with materials pay it)
    loaded = load_obj(io.BytesIO(data), resolver=resolver)
    geometry = loaded.get("geometry", {}) if isinstance(loaded, dict) else {}
    return {name: to_rgba(kw["vertex_colors"])[:, :3].astype(np.float32) / np.float32(255.0)
            for name, kw in geometry.items() if isinstance(kw, dict) and kw.get("vertex_colors") is not None}


def used_material_names(data: bytes) -> set[str]:
    """The material names an OBJ's ``usemtl`` statements give, as trimesh reads them."""
    first = re.match(rb"[ \t]*usemtl[ \t]+([^\r\n]*)", data.removeprefix(_BOM))  # (no line end before the first)
    found = _USEMTL.findall(data) + ([first.group(1)] if first else [])
    return {_without_comment(name.decode("utf-8", errors="replace")).strip() for name in found} - {""}


def _has_comment_after_values(data: bytes) -> bool:
    """Whether a statement has a comment after its values: a ``#`` after a space or tab, with
    something before it on a line that is no comment (a ``#`` inside a name, ``tex#1.png``, is
    part of the name). One check per ``#``, skipping the rest of a comment line: comments are few."""
    at = data.find(b"#")
    while at >= 0:
        start = data.rfind(b"\n", 0, at) + 1
        before = data[start:at]
        if before.lstrip().startswith(b"#"):  # a comment line (e.g. "####"): on to the next line
            end = data.find(b"\n", at)
            at = -1 if end < 0 else data.find(b"#", end)
            continue
        if before.strip() and before[-1:] in (b" ", b"\t"):
            return True
        at = data.find(b"#", at + 1)
    return False


_COMMENT = re.compile(r"[ \t]#")


def _without_comment(line: str) -> str:
    """``line`` without a comment after its values (after a space or tab: see above)."""
    if line.lstrip().startswith("#"):
        return line
    found = _COMMENT.search(line)
    return line if found is None else line[:found.start()].rstrip()


def _text(data: bytes) -> str:
    """UTF-8 text without byte-order marks (anywhere: several files may have been joined)."""
    return data.decode("utf-8", errors="replace").replace("\ufeff", "")


def _absolute_corner(corner: str, counts: dict) -> str:
    """One face corner ``v[/vt][/vn]`` with relative indices (-1: the last one read) made absolute."""
    parts = corner.split("/")
    for k, kind in enumerate(("v", "vt", "vn")[:len(parts)]):
        if parts[k].startswith("-") and parts[k][1:].isdigit():
            parts[k] = str(counts[kind] + 1 + int(parts[k]))
    return "/".join(parts)


def clean_mtl_text(data: bytes, warn) -> bytes:
    """The MTL ``data`` as trimesh reads it as meant: no BOM, no comments after values, one-value
    colours as three, ``map_Kd`` options dropped (``warn(material, why)`` where they move its UVs:
    the texture is left out)."""
    lines, material = [], None
    for line in _text(data).splitlines():
        line = _without_comment(line)
        tokens = line.split()
        keyword = tokens[0].lower() if tokens else ""
        if keyword == "newmtl":
            material = " ".join(tokens[1:])
        elif keyword in _COLOURS and len(tokens) == 2 and _is_number(tokens[1]):
            line = f"{tokens[0]} {tokens[1]} {tokens[1]} {tokens[1]}"
        elif keyword == "map_kd" and len(tokens) > 2 and tokens[1].startswith("-"):
            try:
                line = f"{tokens[0]} {_parsed('map_Kd', tokens[1:]).file_name}"
            except ValueError as exc:
                warn(material, str(exc))
                continue
        lines.append(line)
    return ("\n".join(lines) + "\n").encode()

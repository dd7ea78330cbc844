"""The colours of an OFF file, which trimesh's OFF reader drops.

An OFF vertex record may carry a colour after its position (``COFF``: ``x y z r g b [a]``) and a
face record one after its corner indices (``3 i j k r g b [a]``): 0-255 integers or 0-1 floats, in
the file's colour space (taken as sRGB, as PLY colours are). trimesh reads positions and faces
only, so a coloured OFF rendered white without a word. `off_colours` reads them from the records,
where the file has them; face colours only where every face is a triangle (trimesh splits a
polygon into several, and the colours would then need its split).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .declared_counts import off_header

__all__ = ["off_colours"]


def off_colours(path: str | Path) -> tuple[np.ndarray | None, np.ndarray | None, str | None]:
    """(per-vertex, per-face colours as [N, 3] uint8 sRGB, or None each; why colours the file has
    are not read, or None) of the ASCII OFF at ``path``, in its records' order. The records are
    read only where the first vertex or the last face record holds a colour."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            declared = off_header(f.read(1 << 16))
            if declared is None:
                return None, None, None
            vertices, faces, start = declared
            f.seek(start)
            head = f.read(1 << 12)
            f.seek(max(path.stat().st_size - 4096, start))
            if not _may_hold_colours(head, f.read()):
                return None, None, None
            f.seek(start)
            records = [words for words in (raw.split(b"#", 1)[0].split() for raw in f) if words]
    except OSError:
        return None, None, None
    if vertices == 0 or len(records) < vertices + faces:
        return None, None, None
    vertex_records, face_records = records[:vertices], records[vertices:vertices + faces]
    has_vertex = len(vertex_records[0]) > 3
    has_face = bool(face_records) and face_records[0][0].isdigit() and len(face_records[0]) > 1 + int(face_records[0][0])
    vertex_colours = _colours([r[3:] for r in vertex_records]) if has_vertex else None
    face_colours = why = None
    if has_face:
        if all(r[0] == b"3" for r in face_records):
            face_colours = _colours([r[4:] for r in face_records])
        else:
            why = "its face colours are not read: some faces are polygons (trimesh splits them into triangles)"
    if (has_vertex and vertex_colours is None) or (has_face and face_colours is None and why is None):
        why = "its colours are not read: their records do not all hold three or four numbers"
    return vertex_colours, face_colours, why


def _may_hold_colours(records: bytes, tail: bytes) -> bool:
    """Whether the first vertex record (in ``records``, the bytes after the header) or the last
    face record (the last line of ``tail``, the file's last bytes: faces come last) holds more than
    a position or a corner list. O(1): a file without colours is not read again."""
    first = next((w for w in (raw.split(b"#", 1)[0].split() for raw in records.splitlines()) if w), [])
    last = next((w for w in (raw.split(b"#", 1)[0].split() for raw in reversed(tail.splitlines())) if w), [])
    return len(first) > 3 or (bool(last) and last[0].isdigit() and len(last) > 1 + int(last[0]))


def _colours(values: list[list[bytes]]) -> np.ndarray | None:
    """[N, 3] uint8 from records of 3 or 4 numbers each (0-255 integers, or 0-1 floats), or None."""
    if not values or any(len(v) not in (3, 4) for v in values):
        return None
    try:
        numbers = np.array([[float(x) for x in v[:3]] for v in values])
    except ValueError:
        return None
    integers = all(b"." not in x and b"e" not in x.lower() for v in values[:64] for x in v[:3])
    scaled = numbers if integers else numbers * 255.0
    return np.clip(np.round(scaled), 0, 255).astype(np.uint8)

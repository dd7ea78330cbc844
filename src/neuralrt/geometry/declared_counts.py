"""What a mesh file's header says it holds, to tell a truncated file from a small one.

trimesh reads what is there: an ASCII PLY or an OFF cut short (an interrupted download or copy)
loads as the triangles before the cut, with no word, and a binary STL cut short loads as nothing.
The headers of these formats say how many vertices and faces follow; `declared_counts` reads them
(a few KiB of the file), and `truncation_problem` compares them with what was read.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["declared_counts", "truncation_problem"]

_HEADER_BYTES = 1 << 16  # PLY and OFF headers are a few lines; a longer one is not checked
_STL_HEADER = 80  # binary STL: an 80-byte header, then the uint32 triangle count


def declared_counts(path: str | Path) -> tuple[int, int] | None:
    """(vertices, faces) that the header of the PLY, OFF or binary STL at ``path`` declares, or
    None (another format, or a header not read as one). An STL's vertices are 3 a triangle."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(_HEADER_BYTES)
    except OSError:
        return None
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return _ply(head)
    if suffix == ".off":
        return _off(head)
    if suffix == ".stl":
        return _binary_stl(head)
    return None


def truncation_problem(path: str | Path, vertices_read: int, faces_read: int) -> str | None:
    """Why the file at ``path`` looks cut short, or None: fewer vertices or faces read than its header
    declares. (A polygon face is read as one triangle or more, so more faces than declared is fine.)"""
    declared = declared_counts(path)
    if declared is None:
        return None
    vertices, faces = declared
    if vertices_read >= vertices and faces_read >= faces:
        return None
    return (f"file is truncated or malformed: its header declares {vertices} vertices and {faces} faces, "
            f"{vertices_read} and {faces_read} were read")


def _ply(head: bytes) -> tuple[int, int] | None:
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return None
    counts = {}
    for line in head[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == "element" and words[2].isdigit():
            counts[words[1]] = int(words[2])
    if "vertex" not in counts:
        return None
    return counts["vertex"], counts.get("face", 0)


_OFF_COUNTS = re.compile(rb"^\s*[A-Z]*OFF\s+(\d+)\s+(\d+)")


def _off(head: bytes) -> tuple[int, int] | None:
    text = re.sub(rb"#[^\n]*", b"", head)  # comments, as trimesh strips them
    match = _OFF_COUNTS.match(text)
    return (int(match[1]), int(match[2])) if match else None


def _binary_stl(head: bytes) -> tuple[int, int] | None:
    if len(head) < _STL_HEADER + 4 or head.lstrip()[:5].lower() == b"solid" and b"facet" in head:
        return None  # ASCII STL (which has no count), or too short to hold one
    triangles = int.from_bytes(head[_STL_HEADER:_STL_HEADER + 4], "little")
    return 3 * triangles, triangles  # a triangle soup: each triangle its own 3 vertices

"""What a mesh file's header says it holds, to tell a truncated file from a small one.

trimesh reads what is there: an ASCII PLY or an OFF cut short (an interrupted download or copy)
loads as the triangles before the cut, with no word, and a binary STL cut short loads as nothing.
The headers of these formats say how many vertices and faces follow. `truncation_problem`
compares them with what was read, and where fewer were read, whether the file holds fewer
records than declared: a reader also leaves out records that are not triangles (a PLY face of
two corners), and a whole file that has some is not a truncated one.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["off_header", "ply_vertex_properties", "truncation_problem"]

_HEADER_BYTES = 1 << 16  # PLY and OFF headers are a few lines; a longer one is not checked
_STL_HEADER, _STL_TRIANGLE = 80, 50  # binary STL: an 80-byte header, a uint32 count, 50 bytes a triangle


def truncation_problem(path: str | Path, vertices_read: int, faces_read: int) -> str | None:
    """Why the PLY, OFF or binary STL file at ``path`` looks cut short, or None: fewer vertices or
    faces read than its header declares, and fewer records in the file than that (a polygon is
    read as one triangle or more, so more faces than declared is fine)."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(_HEADER_BYTES)
        size = path.stat().st_size
    except OSError:
        return None
    suffix = path.suffix.lower()
    if suffix == ".stl":  # (a triangle read: not a binary STL cut short, or an ASCII one)
        return _binary_stl(head, size) if faces_read == 0 else None
    declared = _ply(head) if suffix == ".ply" else off_header(head) if suffix == ".off" else None
    if declared is None:
        return None
    vertices, faces, ascii_data_at = declared
    if vertices_read >= vertices and faces_read >= faces:
        return None
    if ascii_data_at is not None and _records_at_least(path, ascii_data_at, vertices + faces):
        return None  # all there: the reader left some records out as not triangles
    return (f"file is truncated or malformed: its header declares {vertices} vertices and {faces} faces, "
            f"{vertices_read} and {faces_read} were read")


def _ply(head: bytes) -> tuple[int, int, int | None] | None:
    """(vertices, faces, where ASCII records start or None for a binary PLY)."""
    header = _ply_header(head)
    if header is None or "vertex" not in header[0]:
        return None
    counts, ascii_data, data_at, _ = header
    return counts["vertex"], counts.get("face", 0), data_at if ascii_data and data_at > 0 else None


def ply_vertex_properties(path: str | Path) -> list[str]:
    """The names of the vertex properties a PLY header declares (``[]`` where it declares none)."""
    try:
        with Path(path).open("rb") as f:
            head = f.read(_HEADER_BYTES)
    except OSError:
        return []
    header = _ply_header(head)
    return [] if header is None else header[3]


def _ply_header(head: bytes) -> tuple[dict[str, int], bool, int, list[str]] | None:
    """(element counts, whether the data are ASCII, where the data start (0: not found), the vertex
    properties' names) of the PLY header at the start of ``head``, or None where it holds none."""
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return None
    counts, ascii_data, element, properties = {}, False, None, []
    for line in head[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) >= 2 and words[0] == "element":
            element = words[1]
            if len(words) == 3 and words[2].isdigit():
                counts[words[1]] = int(words[2])
        elif len(words) >= 2 and words[0] == "format":
            ascii_data = words[1] == "ascii"
        elif len(words) >= 3 and words[0] == "property" and element == "vertex":
            properties.append(words[-1])
    return counts, ascii_data, head.find(b"\n", end) + 1, properties


def off_header(head: bytes) -> tuple[int, int, int] | None:
    """(vertices, faces, where the records start): the counts follow the ``OFF`` keyword (``COFF``,
    ``NOFF``, ...), on its line or a later one, past comments."""
    numbers: list[int] = []
    at, keyword = 0, False
    for line in head.splitlines(keepends=True):
        at += len(line)
        words = line.split(b"#", 1)[0].split()
        if not keyword:
            if not words:
                continue
            if not words[0].endswith(b"OFF"):
                return None
            keyword, words = True, words[1:]
        numbers += [int(w) for w in words if w.isdigit()]
        if len(numbers) >= 2:
            return numbers[0], numbers[1], at
    return None


def _records_at_least(path: Path, start: int, wanted: int) -> bool:
    """Whether the file holds ``wanted`` non-empty, non-comment lines from byte ``start`` (read until
    it does); a last line without its line end counts only if the file ends there anyway after the
    records (a cut inside the last record leaves one without it, and so does an editor's last line)."""
    found = 0
    with path.open("rb") as f:
        f.seek(start)
        for line in f:
            stripped = line.strip()
            if stripped and not stripped.startswith(b"#"):
                found += 1
                if found >= wanted:
                    return line.endswith(b"\n") or found > wanted or _whole_last_record(line)
    return False


def _whole_last_record(line: bytes) -> bool:
    # Without a line end, the last record may be cut: whole only if it has as many numbers as the
    # record before would say. Cheap stand-in: a face record's first number is its corner count.
    words = line.split()
    return len(words) >= 2 and words[0].isdigit() and len(words) >= 1 + int(words[0])


def _binary_stl(head: bytes, size: int) -> str | None:
    text = head.removeprefix(b"\xef\xbb\xbf").lstrip().lower()  # (a UTF-8 byte order mark, any case)
    if len(head) < _STL_HEADER + 4 or text.startswith(b"solid") and b"facet" in text:
        return None  # ASCII STL (which has no count), or too short to hold one
    triangles = int.from_bytes(head[_STL_HEADER:_STL_HEADER + 4], "little")
    needed = _STL_HEADER + 4 + _STL_TRIANGLE * triangles
    if size >= needed:
        return None
    return (f"file is truncated or malformed: its header declares {triangles} triangles "
            f"({needed} bytes), the file has {size} bytes")

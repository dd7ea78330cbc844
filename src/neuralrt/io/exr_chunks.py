"""An OpenEXR file's chunk table checked against the file, before any pixel is decoded.

OpenEXR reports a truncated file or a broken chunk only by printing (its C core to file
descriptor 2, its Python binding to stdout) and may still hand back partial pixels. Catching that
text meant redirecting the process's output while decoding, which swallowed other threads' output
and let their text fail a sound file. Checked here instead, from the header and the chunk leaders
(the EXR file layout, openexr.com "OpenEXR File Layout"): every chunk the header implies is
listed, lies inside the file, and says it belongs where it is; ZIP-compressed chunks (how
`write_exr` writes, and the most common) must also inflate to their pixels' size. Single-part
scanline images and single-level tiled ones are checked; multi-part, deep and mip-mapped files go
to the library as they are.
"""

from __future__ import annotations

import struct
import zlib

__all__ = ["exr_chunk_problem"]

_TILED, _LONG_NAMES, _DEEP, _MULTIPART = 0x200, 0x400, 0x800, 0x1000
# Scanlines per chunk by compression id (NO, RLE, ZIPS, ZIP, PIZ, PXR24, B44, B44A, DWAA, DWAB).
_LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256}
_ONE_LEVEL = 0
_ZIP_COMPRESSIONS = (2, 3)  # ZIPS, ZIP: zlib streams
_SAMPLE_BYTES = {0: 4, 1: 2, 2: 4}  # UINT, HALF, FLOAT


def exr_chunk_problem(data: bytes) -> str | None:
    """What is wrong with the chunk table of the EXR file ``data`` (a phrase), or None if nothing
    (or not checked)."""
    try:
        return _problem(data)
    except (struct.error, IndexError, ValueError):
        return "its header ends before it is complete"


def _problem(data: bytes) -> str | None:
    flags = struct.unpack_from("<I", data, 4)[0]
    if flags & (_DEEP | _MULTIPART):
        return None
    attributes, end = _header(data, 8, 255 if flags & _LONG_NAMES else 31)
    if "dataWindow" not in attributes or "compression" not in attributes:
        return "its header lacks a data window or compression"
    xmin, ymin, xmax, ymax = struct.unpack("<4i", attributes["dataWindow"][:16])
    if xmax < xmin or ymax < ymin:
        return f"its data window is empty ({xmin}, {ymin}) - ({xmax}, {ymax})"
    width, height = xmax - xmin + 1, ymax - ymin + 1
    if flags & _TILED:
        tile_width, tile_height, mode = struct.unpack("<IIB", attributes["tiles"][:9])
        if mode & 0xF != _ONE_LEVEL or tile_width == 0 or tile_height == 0:
            return None
        count, leader = -(-width // tile_width) * -(-height // tile_height), "<4ii"
    else:
        lines = _LINES_PER_CHUNK.get(attributes["compression"][0])
        if lines is None:
            return None
        count, leader = -(-height // lines), "<ii"
    if "chunkCount" in attributes and struct.unpack("<i", attributes["chunkCount"][:4])[0] != count:
        return f"its header's chunkCount is not the {count} chunks its data window needs"
    table_end = end + 8 * count
    if table_end > len(data):
        return f"it ends inside its table of {count} chunk offsets"
    leader_size = struct.calcsize(leader)
    zipped = attributes["compression"][0] in _ZIP_COMPRESSIONS
    row_bytes = _row_bytes(attributes["channels"]) if zipped else 0
    for k, offset in enumerate(struct.unpack_from(f"<{count}Q", data, end)):
        if offset < table_end or offset + leader_size > len(data):
            return f"chunk {k} of {count} starts outside the file (offset {offset}, file size {len(data)})"
        fields = struct.unpack_from(leader, data, offset)
        size = fields[-1]
        if size < 0 or offset + leader_size + size > len(data):
            return f"chunk {k} of {count} ends past the end of the file"
        if not flags & _TILED and not ymin <= fields[0] <= ymax:
            return f"chunk {k} of {count} names scanline {fields[0]}, outside {ymin}..{ymax}"
        if zipped:
            if flags & _TILED:
                tx, ty = fields[0], fields[1]
                pixels = min(tile_width, width - tx * tile_width) * min(tile_height, height - ty * tile_height)
                expected = pixels * row_bytes
            else:
                expected = min(lines, ymax + 1 - fields[0]) * width * row_bytes
            if size < expected and not _inflates_to(data[offset + leader_size:offset + leader_size + size], expected):
                return f"chunk {k} of {count} does not decompress to its {expected} bytes"
    return None


def _row_bytes(channels: bytes) -> int:
    """Bytes of one pixel over all channels of a ``chlist`` attribute (full-resolution channels)."""
    total, at = 0, 0
    while channels[at] != 0:
        at = channels.index(b"\0", at) + 1
        pixel_type = struct.unpack_from("<i", channels, at)[0]
        total += _SAMPLE_BYTES.get(pixel_type, 4)
        at += 16  # type, pLinear + 3 reserved bytes, x and y sampling
    return total


def _inflates_to(packed: bytes, expected: int) -> bool:
    try:
        inflater = zlib.decompressobj()
        return len(inflater.decompress(packed, expected + 1)) == expected and inflater.eof
    except zlib.error:
        return False


def _header(data: bytes, at: int, name_limit: int) -> tuple[dict[str, bytes], int]:
    """({attribute name: value bytes}, offset after the header) of the header starting at ``at``."""
    attributes = {}
    while True:
        name, at = _string(data, at, name_limit)
        if not name:
            return attributes, at
        _, at = _string(data, at, name_limit)  # the attribute's type
        size = struct.unpack_from("<i", data, at)[0]
        at += 4
        if size < 0 or at + size > len(data):
            raise ValueError("attribute past the end")
        attributes[name] = data[at:at + size]
        at += size


def _string(data: bytes, at: int, limit: int) -> tuple[str, int]:
    end = data.index(b"\0", at, at + limit + 1)
    return data[at:end].decode("latin-1"), end + 1

"""Byte ranges of a glTF file's buffers, as its buffer views name them: the .glb's own binary
chunk and the .bin files beside a .gltf read by seeking (a view is read, not the file), data URIs
decoded once. `gltf_pack` packs one mesh's views from them, `gltf_json.expanded_instances` reads
GPU instances' accessors.
"""

from __future__ import annotations

import base64
import os
import struct
import urllib.parse
from pathlib import Path

from ..io.files import resolved
from .unread_assets import regular_files_resolver

__all__ = ["GltfBuffers", "GLB_MAGIC", "JSON_CHUNK", "BIN_CHUNK"]

GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = b"glTF", 0x4E4F534A, 0x004E4942  # (a .glb: its magic, its chunks' types)


class GltfBuffers:
    """The buffers of the glTF file at ``path`` whose JSON is ``header``; `read` gives a view's bytes."""

    def __init__(self, header: dict, path: str | Path):
        buffers = header.get("buffers")
        self.buffers, self.path, self.decoded = buffers if isinstance(buffers, list) else [], Path(path), {}

    def read(self, index, offset, length, view: int) -> bytes:
        """``length`` bytes at ``offset`` of buffer ``index`` (buffer view ``view``'s, named in errors): a
        ValueError for a bad index or range, a FileNotFoundError for a .bin that is not there."""
        if not (isinstance(index, int) and 0 <= index < len(self.buffers) and isinstance(self.buffers[index], dict)):
            raise ValueError(f"buffer view {view} names buffer {index!r}, which the file does not have")
        if not (isinstance(offset, int) and isinstance(length, int) and offset >= 0 and length >= 0):
            raise ValueError(f"buffer view {view}'s byteOffset and byteLength must be non-negative integers")
        uri = self.buffers[index].get("uri")
        if uri is None:  # (the .glb's own binary chunk)
            data = self._from_file(self.path, self._binary_chunk_start() + offset, length)
        elif not isinstance(uri, str):
            raise ValueError(f"buffer {index}'s uri must be a string")
        elif uri.startswith("data:"):
            if index not in self.decoded:
                self.decoded[index] = base64.b64decode(uri.partition(",")[2])
            data = self.decoded[index][offset:offset + length]
        else:
            file = self._inside_folder(urllib.parse.unquote(uri), index)
            data = self._from_file(file, offset, length) if file.is_file() else self._other_spelling(uri, index)[offset:offset + length]
        if len(data) != length:
            raise ValueError(f"buffer view {view} reaches past the end of buffer {index} (cut short?)")
        return data

    def _inside_folder(self, name: str, index: int) -> Path:
        """The file ``name`` beside the glTF, or a ValueError where it leads out of that folder (an
        absolute path, ``..``, a link elsewhere): a file's data is read only from its own folder, as
        trimesh reads a whole file's buffers."""
        folder = resolved(self.path.parent)
        file = resolved(folder / name)
        if not file.is_relative_to(folder):
            raise ValueError(f"buffer {index}'s uri {name[:200]!r} leads out of the file's folder; buffers are read "
                             f"only beside it")
        return file

    def _binary_chunk_start(self) -> int:
        with self.path.open("rb") as f:
            start = f.read(20)
            if start[:4] != GLB_MAGIC:
                raise ValueError("a buffer without a uri, in a file that is no .glb")
            json_length = struct.unpack_from("<I", start, 12)[0]
            f.seek(20 + json_length)
            chunk = f.read(8)
        if len(chunk) < 8 or struct.unpack_from("<I", chunk, 4)[0] != BIN_CHUNK:
            raise ValueError("the .glb has no binary chunk after its JSON (cut short?)")
        return 20 + json_length + 8

    def _other_spelling(self, uri: str, index: int) -> bytes:
        """The whole file ``uri`` names as the mesh's other files are found (backslashes, letter case:
        `regular_files_resolver`), or a FileNotFoundError naming where it was looked for."""
        if index not in self.decoded:
            try:
                self.decoded[index] = regular_files_resolver(str(self.path)).get(uri)
            except (OSError, ValueError):
                raise FileNotFoundError(2, f"buffer {index}'s file {uri} is not in {self.path.parent}") from None
        return self.decoded[index]

    @staticmethod
    def _from_file(file: Path, offset: int, length: int) -> bytes:
        """At most what the file holds there (a view declaring 2**40 bytes was a MemoryError): a range
        past the end comes back short, which `read` names."""
        with file.open("rb") as f:
            f.seek(offset)
            return f.read(max(0, min(length, os.fstat(f.fileno()).st_size - offset)))

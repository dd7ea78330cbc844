"""glTF test files: a .glb written by trimesh, then its JSON edited (what trimesh does not write)."""

import json
import struct


def edited_glb(path, edit):
    """The .glb at ``path`` with ``edit(header)`` applied to its JSON chunk."""
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    header = json.loads(data[20:20 + length])
    edit(header)
    chunk = json.dumps(header).encode()
    chunk += b" " * (-len(chunk) % 4)
    rest = data[20 + length:]
    body = struct.pack("<II", len(chunk), 0x4E4F534A) + chunk + rest
    path.write_bytes(data[:8] + struct.pack("<I", 12 + len(body)) + body)
    return path

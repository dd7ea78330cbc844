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


_QUANTIZED = {5121: ("<u1", 255, False), 5123: ("<u2", 65535, False), 5120: ("<i1", 127, True), 5122: ("<i2", 32767, True)}


def quantized_uvs_glb(path, component):
    """The .glb at ``path`` with every TEXCOORD_0 stored as normalised integers of ``component``
    type (as gltfpack / KHR_mesh_quantization write them): the float UVs rounded into new buffer
    views appended to the binary chunk."""
    import numpy as np

    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    header = json.loads(data[20:20 + length])
    binary = bytearray(data[20 + length + 8:])
    dtype, largest, signed = _QUANTIZED[component]
    for mesh in header["meshes"]:
        for primitive in mesh["primitives"]:
            accessor = header["accessors"][primitive["attributes"]["TEXCOORD_0"]]
            view = header["bufferViews"][accessor["bufferView"]]
            start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
            uv = np.frombuffer(bytes(binary[start:start + 8 * accessor["count"]]), "<f4").reshape(-1, 2)
            stored = np.round(np.clip(uv, -1.0 if signed else 0.0, 1.0) * largest).astype(dtype)
            row = stored.itemsize * 2
            padded = np.zeros((len(stored), (row + 3) // 4 * 4), np.uint8)  # (rows aligned to 4 bytes, as the spec asks)
            padded[:, :row] = stored.view(np.uint8).reshape(len(stored), row)
            binary += b"\0" * (-len(binary) % 4)
            header["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": padded.size,
                                          "byteStride": padded.shape[1]})
            binary += padded.tobytes()
            accessor.update(bufferView=len(header["bufferViews"]) - 1, byteOffset=0, componentType=component, normalized=True)
            accessor.pop("min", None), accessor.pop("max", None)
    binary += b"\0" * (-len(binary) % 4)
    header["buffers"][0]["byteLength"] = len(binary)
    if signed:
        header.setdefault("extensionsUsed", []).append("KHR_mesh_quantization")
        header.setdefault("extensionsRequired", []).append("KHR_mesh_quantization")
    chunk = json.dumps(header).encode()
    chunk += b" " * (-len(chunk) % 4)
    body = struct.pack("<II", len(chunk), 0x4E4F534A) + chunk + struct.pack("<II", len(binary), 0x004E4942) + bytes(binary)
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    return path


def glb_as_gltf(glb_path, gltf_path):
    """The .glb at ``glb_path`` written as a .gltf (its JSON) and a .bin beside it (its binary chunk)."""
    data = glb_path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    header = json.loads(data[20:20 + length])
    binary = data[20 + length + 8:]
    bin_path = gltf_path.with_suffix(".bin")
    bin_path.write_bytes(binary)
    header["buffers"][0]["uri"] = bin_path.name
    gltf_path.write_text(json.dumps(header))
    return gltf_path

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


def street_glb(path, lights=True):
    """A small glTF scene: a ground, one house mesh drawn by three nodes, a metal ball, an emissive
    lamp; with ``lights``, a perspective camera, a point light and a directional light
    (KHR_lights_punctual). trimesh writes a mesh per node, so the JSON is edited to share one."""
    import numpy as np
    import trimesh
    from trimesh.transformations import translation_matrix
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    def part(mesh, **material):
        mesh.visual = TextureVisuals(material=PBRMaterial(**material))
        return mesh

    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box((10, 0.1, 10)), node_name="ground", geom_name="ground",
                       transform=translation_matrix([0, -0.05, 0]))
    house = part(trimesh.creation.box((1, 2, 1)), name="brick", baseColorFactor=[200, 80, 60, 255], metallicFactor=0.0,
                 roughnessFactor=0.7)
    for k, x in enumerate((-2.0, 0.0, 2.0)):
        scene.add_geometry(house, node_name=f"house{k}", geom_name="house", transform=translation_matrix([x, 1, -1]))
    ball = part(trimesh.creation.icosphere(2, 0.5), name="chrome", baseColorFactor=[230, 230, 230, 255],
                metallicFactor=1.0, roughnessFactor=0.2)
    scene.add_geometry(ball, node_name="ball", geom_name="ball", transform=translation_matrix([0, 0.5, 1]))
    lamp = part(trimesh.creation.box((0.4, 0.05, 0.4)), name="lamp", baseColorFactor=[255, 255, 255, 255],
                emissiveFactor=[1.0, 0.9, 0.7])
    scene.add_geometry(lamp, node_name="lamp", geom_name="lamp", transform=translation_matrix([0, 3, 0]))
    scene.export(path)

    def edit(header):
        header["nodes"][2]["mesh"] = header["nodes"][3]["mesh"] = header["nodes"][1]["mesh"]
        if not lights:
            return
        header["cameras"] = [{"type": "perspective", "perspective": {"yfov": 0.8, "aspectRatio": 1.5, "znear": 0.1}}]
        header.setdefault("extensions", {})["KHR_lights_punctual"] = {"lights": [
            {"type": "point", "color": [1, 1, 1], "intensity": 30000.0, "name": "bulb"},
            {"type": "directional", "color": [1, 0.95, 0.9], "intensity": 1500.0, "name": "sun"}]}
        header.setdefault("extensionsUsed", []).append("KHR_lights_punctual")
        n, half = len(header["nodes"]), float(np.sqrt(0.5))
        header["nodes"] += [{"name": "cam", "camera": 0, "translation": [0, 2, 8], "rotation": [-0.0998, 0, 0, 0.995]},
                            {"name": "bulb", "translation": [2, 4, 2], "extensions": {"KHR_lights_punctual": {"light": 0}}},
                            {"name": "sun", "rotation": [-half, 0, 0, half], "extensions": {"KHR_lights_punctual": {"light": 1}}}]
        header["scenes"][header.get("scene", 0)]["nodes"] += [n, n + 1, n + 2]

    return edited_glb(path, edit)

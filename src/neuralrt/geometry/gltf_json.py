"""What a glTF file's JSON says that trimesh does not pass on.

`gltf_file_notes`: what trimesh cannot read at all, said before it misleads (a required
compression extension decoded as nothing gave "mesh is degenerate"; sparse accessors, triangle
fans, normalised integer UVs, skins, morph weights and emission were dropped without a word).

`gltf_material_extras`: what trimesh drops of a material. It loads a material's
``baseColorTexture`` and ``normalTexture`` but drops the normal map's ``scale``, the
``KHR_texture_transform`` that moves, turns or tiles an image on the UVs, and the ``texCoord``
that picks a UV set, and keeps ``baseColorFactor`` in 8 bits (a linear 0.0015 became 0). This
reads them from the file's JSON so that `load_mesh` applies the scale, the transform and the exact
factor, and says what it cannot apply: a second UV set (trimesh reads only the first), two images
of one material placed differently (they share one UV set here), and a material that trimesh's
parts cannot be told apart from another (they keep its name, not its index, so the extras of a
name two materials share apply only where those materials place their maps alike; unnamed
materials, which trimesh names None, are matched as one where they place their maps alike, as
gltfpack's one material, and else the file is read under names of its own, `named_materials`).

`uv_dequantization` / `dequantized_uvs` (and the same for positions): UVs and positions stored as
normalised integers (gltfpack's output, KHR_mesh_quantization), which trimesh reads unscaled,
scaled as the file means them where every primitive stores them one way (else a note: trimesh's
parts cannot be matched to primitives).

`gltf_mesh_index` / `mesh_alone`: one of the file's meshes read alone, in its own space (a scene
object's ``gltf_mesh``: `neuralrt.scene.gltf_import` places each node's mesh as an instance).
"""

from __future__ import annotations

import functools
import json
import math
import struct
from collections.abc import Container
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .gltf_buffers import GLB_MAGIC, JSON_CHUNK, GltfBuffers

__all__ = ["MaterialExtras", "dequantized_positions", "dequantized_uvs", "expanded_instances", "gltf_file_notes",
           "gltf_header", "gltf_material_extras", "gltf_mesh_index", "instanced_nodes", "mesh_alone", "named_materials",
           "position_dequantization", "uv_dequantization", "with_header"]

_SLOTS = ("baseColorTexture", "normalTexture")  # the images neuralrt uses
_FLIP_V = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 1.0], [0.0, 0.0, 1.0]])  # glTF's v down <-> trimesh's v up


@dataclass(frozen=True)
class MaterialExtras:
    """What trimesh drops of a glTF material: its normal map's ``scale``, a 3x3 affine transform
    of its UVs (trimesh's convention, v up; None: as they are) and its ``baseColorFactor``'s RGB
    as written (linear; None where absent)."""

    normal_scale: float = 1.0
    uv_transform: np.ndarray | None = None
    base_color: tuple[float, float, float] | None = None

    def transformed_uvs(self, uv: np.ndarray) -> np.ndarray:
        if self.uv_transform is None:
            return uv
        m = self.uv_transform
        return (uv.astype(np.float64) @ m[:2, :2].T + m[:2, 2]).astype(np.float32)


# Required extensions without which trimesh reads no geometry, or only part of it.
_UNREADABLE_EXTENSIONS = {"KHR_draco_mesh_compression": "Draco-compressed geometry",
                          "EXT_meshopt_compression": "meshoptimizer-compressed buffers"}
_INSTANCING = "EXT_mesh_gpu_instancing"
_TRIANGLE_FAN, _COMPONENT_BYTES = 6, {5121: "unsigned bytes", 5123: "unsigned shorts"}
_POINTS_AND_LINES, _TRIANGLES_AND_STRIPS = (0, 1, 2, 3), (4, 5)  # (primitive modes; 4 when none is given)
# Normalised integer components (the glTF spec's "accessor.normalized"; signed ones from
# KHR_mesh_quantization): (bits, signed); 1.0 is stored as the largest value, -1.0 as minus it.
_NORMALISED = {5121: (8, False), 5123: (16, False), 5120: (8, True), 5122: (16, True)}


def uv_dequantization(header: dict) -> int | None:
    """The component type (5121, 5123; 5120, 5122 signed) of normalised integer UVs, which trimesh
    reads unscaled, where every primitive's TEXCOORD_0 is stored so (as gltfpack and
    KHR_mesh_quantization write them); None where none is, or where they are stored in more than
    one way (the parts trimesh makes cannot be told apart: `gltf_file_notes` warns)."""
    return _normalised_throughout(header, "TEXCOORD_0")


def position_dequantization(header: dict) -> int | None:
    """As `uv_dequantization`, for positions (gltfpack ``-vpn``: normalised, placed by their node)."""
    return _normalised_throughout(header, "POSITION")


def _normalised_throughout(header: dict, attribute: str) -> int | None:
    accessors = json_list(header.get("accessors"))
    kinds = set()
    for mesh in json_list(header.get("meshes")):
        for primitive in json_list(mesh.get("primitives")) if isinstance(mesh, dict) else []:
            attributes = primitive.get("attributes") if isinstance(primitive, dict) else None
            index = attributes.get(attribute) if isinstance(attributes, dict) else None
            accessor = accessors[index] if isinstance(index, int) and 0 <= index < len(accessors) else None
            if isinstance(accessor, dict):
                kinds.add((accessor.get("componentType"), bool(accessor.get("normalized"))))
    if len(kinds) != 1:
        return None
    component, normalised = kinds.pop()
    return component if normalised and component in _NORMALISED else None


def _unit(stored: np.ndarray, component: int) -> np.ndarray:
    """Normalised integers of ``component`` type as the values they stand for (glTF's formulas)."""
    bits, signed = _NORMALISED[component]
    largest = float(2 ** (bits - 1) - 1 if signed else 2**bits - 1)
    return np.maximum(stored / largest, -1.0)


def dequantized_positions(vertices: np.ndarray, component: int) -> np.ndarray:
    """Positions as trimesh reads normalised integers of ``component`` type (unscaled, before their
    node's transform) as the file means them."""
    return _unit(np.asarray(vertices, np.float64), component)


def dequantized_uvs(uv: np.ndarray, component: int) -> np.ndarray:
    """UVs as trimesh reads normalised integers of ``component`` type (unscaled; v turned to 1 - v
    in the integer type, so it wraps around) as the file means them, in trimesh's v-up convention."""
    bits, signed = _NORMALISED[component]

    def stored(x):  # the integer the file holds, from what trimesh kept (wrapped or not)
        x = np.mod(np.rint(x).astype(np.int64), 2**bits)
        return x - 2**bits * (x >= 2 ** (bits - 1)) if signed else x

    uv = np.asarray(uv, np.float64)
    return np.stack([_unit(stored(uv[:, 0]), component), 1.0 - _unit(stored(1.0 - uv[:, 1]), component)],
                    axis=1).astype(np.float32)


_NAMED = {"meshes": "mesh", "materials": "material", "nodes": "node", "images": "image", "textures": "texture",
          "scenes": "scene"}


def gltf_file_notes(header: dict, lit: Container[str] = ()) -> tuple[str | None, list[str]]:
    """(why trimesh cannot read this glTF's geometry, or None; one line per thing it leaves out, but
    for the emission of the materials named in ``lit``, which a scene makes lights)."""
    required = [e for e in json_list(header.get("extensionsRequired")) if e in _UNREADABLE_EXTENSIONS]
    if required:
        return (f"it needs the glTF extension {required[0]} ({_UNREADABLE_EXTENSIONS[required[0]]}), which trimesh "
                f"does not read"), []
    for kind, one in _NAMED.items():  # (trimesh hashes names: a list was "TypeError: unhashable type")
        for i, item in enumerate(json_list(header.get(kind))):
            if isinstance(item, dict) and "name" in item and not isinstance(item["name"], str):
                return f"{one} {i}'s name must be text, not {type(item['name']).__name__}", []
    accessors = json_list(header.get("accessors"))
    notes: list[str] = []
    fans = morphs = strokes = 0
    integer_uvs: dict[int, str] = {}  # mesh -> how its UVs are stored
    scaled_positions: list[int] = []  # meshes whose positions are normalised integers
    short_colours: list[int] = []
    for m, mesh in enumerate(json_list(header.get("meshes"))):
        primitives = json_list(mesh.get("primitives")) if isinstance(mesh, dict) else []
        for primitive in primitives:
            if not isinstance(primitive, dict):
                continue
            fans += primitive.get("mode") == _TRIANGLE_FAN
            strokes += primitive.get("mode") in _POINTS_AND_LINES
            attributes = primitive.get("attributes") if isinstance(primitive.get("attributes"), dict) else {}
            used = {**{name: attributes.get(name) for name in ("POSITION", "NORMAL", "TEXCOORD_0", "COLOR_0")},
                    "indices": primitive.get("indices")}
            for role, index in used.items():
                accessor = accessors[index] if isinstance(index, int) and 0 <= index < len(accessors) else None
                if isinstance(accessor, dict) and "sparse" in accessor:
                    return (f"the {role} of mesh {m} is a sparse accessor (values stored as changes to a base), "
                            f"which trimesh does not read"), notes
                if role == "COLOR_0" and isinstance(accessor, dict) and accessor.get("componentType") == 5123 \
                        and "material" not in primitive:
                    short_colours.append(m)
                if role == "POSITION" and isinstance(accessor, dict) and accessor.get("normalized"):
                    scaled_positions.append(m)
                if role == "TEXCOORD_0" and isinstance(accessor, dict) and accessor.get("normalized") \
                        and accessor.get("componentType") in _COMPONENT_BYTES:
                    integer_uvs[m] = _COMPONENT_BYTES[accessor["componentType"]]
        weights = mesh.get("weights") if isinstance(mesh, dict) else None
        morphs += isinstance(weights, list) and any(isinstance(w, (int, float)) and w != 0 for w in weights)
    if integer_uvs and uv_dequantization(header) is None:  # (stored one way throughout: the loader scales them)
        notes.append(f"the UVs of {_meshes(integer_uvs)} are normalised {' or '.join(sorted(set(integer_uvs.values())))}, "
                     f"which trimesh reads unscaled: their textures and normal maps are placed wrong")
    if scaled_positions and position_dequantization(header) is None:  # (stored one way throughout: scaled)
        notes.append(f"the positions of {_meshes(scaled_positions)} are normalised integers, which trimesh reads "
                     f"unscaled: the mesh is read at the wrong size and place")
    if short_colours:
        notes.append(f"the vertex colours of {_meshes(short_colours)} are unsigned shorts on a primitive without a "
                     f"material, which trimesh reads as their low byte: right only for 8-bit colours stored as 257 times "
                     f"their value (as gltfpack writes them)")
    if fans:
        notes.append(f"{fans} primitive(s) drawn as triangle fans are left out (trimesh reads triangles and strips)")
    if strokes:
        notes.append(f"{strokes} primitive(s) of points or lines are left out (rays hit triangles only)")
    if morphs:
        notes.append(f"the morph target weights of {morphs} mesh(es) are not applied: each is read in its base shape")
    if json_list(header.get("skins")):
        notes.append("skins are not applied: skinned meshes are read in their bind pose, placed by their nodes")
    glowing = [_label(material, i) for i, material in enumerate(json_list(header.get("materials")))
               if isinstance(material, dict) and _emits(material)
               and not (isinstance(material.get("name"), str) and material["name"] in lit)]
    if glowing:
        notes.append(f"the emission of {', '.join(glowing)} is not read: give the slot an emissive scene material to "
                     f"make it a light")
    return None, notes


def _meshes(indices) -> str:
    """"mesh 3" or "meshes 0, 1, 2, ... (12)": a note per file, not per primitive."""
    found = sorted(set(indices))
    if len(found) == 1:
        return f"mesh {found[0]}"
    shown = ", ".join(map(str, found[:3]))
    return f"meshes {shown}" + (f", ... ({len(found)})" if len(found) > 3 else "")


def _emits(material: dict) -> bool:
    factor = material.get("emissiveFactor")
    return isinstance(factor, list) and any(isinstance(x, (int, float)) and x > 0 for x in factor)


def _label(material: dict, index: int) -> str:
    name = material.get("name")
    return f"material {name!r}" if isinstance(name, str) else f"unnamed material {index}"


def draws_triangles(mesh) -> bool:
    """Whether a glTF mesh has a primitive that trimesh reads as triangles (mode 4 or 5; not fans,
    points or lines)."""
    primitives = json_list(mesh.get("primitives")) if isinstance(mesh, dict) else []
    return any(isinstance(p, dict) and p.get("mode", 4) in _TRIANGLES_AND_STRIPS for p in primitives)


def json_extension(owner, name: str) -> dict:
    """``owner["extensions"][name]`` where both are JSON objects, else {} (a wrong type is read as absent)."""
    extensions = owner.get("extensions") if isinstance(owner, dict) else None
    found = extensions.get(name) if isinstance(extensions, dict) else None
    return found if isinstance(found, dict) else {}


def json_list(value) -> list:
    """`value` if the JSON gave a list there, else [] (a file's wrong type is read as absent)."""
    return value if isinstance(value, list) else []


def gltf_material_extras(header: dict) -> tuple[dict[str, MaterialExtras], list[str]]:
    """(extras per material name, None for the unnamed ones (one material, as gltfpack writes, or
    several placing their maps alike); one line per thing in the file that is not applied), from the
    file's JSON (`gltf_header`)."""
    materials = json_list(header.get("materials"))
    found: dict[str | None, list[MaterialExtras]] = {}  # (None: the unnamed ones, which trimesh names None)
    notes: list[str] = []
    for index, material in enumerate(materials):
        if not isinstance(material, dict):
            continue
        name, label = material.get("name"), _label(material, index)
        extras = _extras(material, label, notes)
        found.setdefault(name if isinstance(name, str) else None, []).append(extras)
    by_name = {}
    for name, each in found.items():
        first, placed_alike = each[0], all(_placed_alike(p, each[0]) for p in each)
        if not placed_alike and name is None:
            notes.append(f"how the maps of the {len(each)} unnamed materials are placed (normal map scale, "
                         f"KHR_texture_transform) is not applied: they place them differently, and trimesh keeps "
                         f"materials by name")
        elif not placed_alike:
            notes.append(f"how the maps of material {name!r} are placed is not applied: {len(each)} materials share "
                         f"that name and place their maps differently")
        colour = first.base_color if all(p.base_color == first.base_color for p in each) else None
        by_name[name] = MaterialExtras(first.normal_scale, first.uv_transform, colour) if placed_alike \
            else MaterialExtras(base_color=colour)
    return by_name, notes


def named_materials(header: dict) -> dict | None:
    """A copy of ``header`` whose unnamed materials are named ``material<index>`` (another name where
    that one is taken), where two or more of them place their maps differently: trimesh names every
    unnamed material None, so their parts could not be told apart (`gltf_material_extras`), and the
    file is read again under this header (`with_header`). None where no such renaming is needed."""
    materials = json_list(header.get("materials"))
    unnamed = [i for i, m in enumerate(materials) if isinstance(m, dict) and not isinstance(m.get("name"), str)]
    if len(unnamed) < 2:
        return None
    quiet: list[str] = []  # (the notes come from the header as it is read)
    extras = [_extras(materials[i], _label(materials[i], i), quiet) for i in unnamed]
    if all(_placed_alike(e, extras[0]) for e in extras):
        return None
    taken = {m.get("name") for m in materials if isinstance(m, dict)}
    renamed = json.loads(json.dumps(header))
    for i in unnamed:
        name = f"material{i}"
        while name in taken:
            name += "'"
        taken.add(name)
        renamed["materials"][i]["name"] = name
    return renamed


def gltf_mesh_index(header: dict, mesh: int | str) -> int:
    """The index in ``meshes`` of the mesh that ``mesh`` names: an index, or the name of exactly one
    mesh. A ValueError says why none is."""
    meshes = json_list(header.get("meshes"))
    if isinstance(mesh, bool) or not isinstance(mesh, (int, str)):
        raise ValueError(f"a glTF mesh is named by its index or its name, not {type(mesh).__name__} {mesh!r}")
    if isinstance(mesh, int):
        if not 0 <= mesh < len(meshes):
            raise ValueError(f"the file has no mesh {mesh} (it has {len(meshes)}: 0 to {len(meshes) - 1})"
                             if meshes else f"the file has no mesh {mesh} (it has none)")
        return mesh
    named = [i for i, m in enumerate(meshes) if isinstance(m, dict) and m.get("name") == mesh]
    if len(named) != 1:
        raise ValueError(f"{len(named)} of the file's meshes are named {mesh!r} (name one by its index instead)"
                         if named else f"no mesh of the file is named {mesh!r}")
    return named[0]


def mesh_alone(header: dict, index: int) -> dict:
    """A copy of ``header`` whose scene is the one mesh ``index`` in its own space: one node, no
    transform. The other meshes and the materials this one does not use become empty (a stub keeping
    a material's name), and indices stay as they were (`gltf_pack.packed_alone` then keeps only the
    bytes it reads). Skins and animations, which name nodes, are dropped. (A shallow copy: the
    entries it keeps are ``header``'s own, which neither changes.)"""
    alone = dict(header)
    meshes = json_list(alone.get("meshes"))
    chosen = meshes[index] if isinstance(meshes[index], dict) else {}
    used = {p.get("material") for p in json_list(chosen.get("primitives")) if isinstance(p, dict)}
    alone["meshes"] = [m if i == index else {"primitives": []} for i, m in enumerate(meshes)]
    materials = json_list(alone.get("materials"))
    if materials:
        alone["materials"] = [m if i in used or not isinstance(m, dict) else
                              {"name": m["name"] if isinstance(m.get("name"), str) else f"unused material {i}"}
                              for i, m in enumerate(materials)]
    alone["nodes"] = [{"mesh": index}]
    alone["scenes"], alone["scene"] = [{"nodes": [0]}], 0
    for key in ("skins", "animations"):
        alone.pop(key, None)
    return alone


def instanced_nodes(header: dict) -> list[int]:
    """The nodes that ``EXT_mesh_gpu_instancing`` draws several times (gltfpack ``-mi``)."""
    return [i for i, n in enumerate(json_list(header.get("nodes"))) if json_extension(n, _INSTANCING)]


def expanded_instances(header: dict, path: str | Path) -> dict | None:
    """A copy of ``header`` (the JSON of the file at ``path``) whose `instanced_nodes` (trimesh
    reads no instances) hold one child node per instance, placed by the instance's TRANSLATION,
    ROTATION and SCALE, and the extension gone; the file is read again under it (`with_header`).
    None where no node uses the extension. A ValueError names an instance accessor that cannot be read."""
    instanced = instanced_nodes(header)
    if not instanced:
        return None
    expanded = json.loads(json.dumps(header))
    buffers = GltfBuffers(header, path)
    for i in instanced:
        node = expanded["nodes"][i]
        attributes = node["extensions"].pop(_INSTANCING).get("attributes") or {}
        columns = {name: _accessor_values(expanded, attributes[name], buffers)
                   for name in ("TRANSLATION", "ROTATION", "SCALE") if name in attributes}
        counts = {len(c) for c in columns.values()}
        if len(counts) != 1:
            raise ValueError(f"node {i}'s {_INSTANCING} attributes are of different lengths (or none)")
        children = []
        for k in range(counts.pop()):
            child = {"mesh": node["mesh"]} if "mesh" in node else {}
            for name, key in (("TRANSLATION", "translation"), ("ROTATION", "rotation"), ("SCALE", "scale")):
                if name in columns:
                    child[key] = [float(x) for x in columns[name][k]]
            children.append(len(expanded["nodes"]))
            expanded["nodes"].append(child)
        node.pop("mesh", None)
        node["children"] = json_list(node.get("children")) + children
    for key in ("extensionsUsed", "extensionsRequired"):
        if key in expanded:
            expanded[key] = [e for e in json_list(expanded[key]) if e != _INSTANCING]
    return expanded


_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _accessor_values(header: dict, index, buffers: GltfBuffers) -> np.ndarray:
    """An accessor's values, [count, width] float64 (normalised integers scaled as the spec says),
    read from its buffer view's bytes."""
    accessors = json_list(header.get("accessors"))
    if not (isinstance(index, int) and 0 <= index < len(accessors)):
        raise ValueError(f"instance accessor {index!r} does not exist")
    accessor = accessors[index]
    view = json_list(header.get("bufferViews"))[accessor["bufferView"]]
    data = buffers.read(view.get("buffer", 0), view.get("byteOffset", 0), view.get("byteLength"), accessor["bufferView"])
    dtype = np.dtype(_COMPONENTS[accessor["componentType"]]).newbyteorder("<")
    width, count = _WIDTHS[accessor["type"]], int(accessor["count"])
    stride = view.get("byteStride") or dtype.itemsize * width
    start = accessor.get("byteOffset", 0)  # (within the view's bytes)
    if count < 0 or (count and start + (count - 1) * stride + width * dtype.itemsize > len(data)):
        # (checked before the index table is made: a count of 10^10 in a 1 KB file asked for gigabytes)
        raise ValueError(f"instance accessor {index} declares {count:,} values, more than its buffer view's "
                         f"{len(data):,} bytes hold (cut short?)")
    at = start + np.arange(count)[:, None] * stride + np.arange(width * dtype.itemsize)[None, :]
    values = np.frombuffer(data, np.uint8)[at].view(dtype).reshape(count, width).astype(np.float64)  # (IndexError: cut short)
    if accessor.get("normalized") and accessor["componentType"] in _NORMALISED:
        values = _unit(values, accessor["componentType"])
    return values


def with_header(data: bytes, header: dict) -> bytes:
    """A glTF file's bytes (``data``) with its JSON replaced by ``header``: a .glb's chunk rewritten
    (its binary chunk kept), or a .gltf's text."""
    chunk = json.dumps(header).encode()
    if data[:4] != GLB_MAGIC:
        return chunk
    chunk += b" " * (-len(chunk) % 4)
    body = struct.pack("<II", len(chunk), JSON_CHUNK) + chunk + data[_after_json_chunk(data):]
    return data[:8] + struct.pack("<I", 12 + len(body)) + body


def _after_json_chunk(data: bytes) -> int:
    """Where a .glb's JSON chunk ends: a 12-byte header, then the chunk's length, type and bytes."""
    return 20 + struct.unpack_from("<I", data, 12)[0]


def _placed_alike(a: MaterialExtras, b: MaterialExtras) -> bool:
    if a.normal_scale != b.normal_scale or (a.uv_transform is None) != (b.uv_transform is None):
        return False
    return a.uv_transform is None or bool(np.array_equal(a.uv_transform, b.uv_transform))


def _extras(material: dict, label: str, notes: list[str]) -> MaterialExtras:
    slots = {"normalTexture": material.get("normalTexture"),
             "baseColorTexture": (material.get("pbrMetallicRoughness") or {}).get("baseColorTexture")}
    transforms = {}
    for slot in _SLOTS:
        info = slots[slot]
        if not isinstance(info, dict):
            continue
        extension = json_extension(info, "KHR_texture_transform")
        extension = extension if isinstance(extension, dict) else {}
        uv_set = extension.get("texCoord", info.get("texCoord", 0))
        if uv_set not in (0, None):
            notes.append(f"the {slot} of {label} maps UV set {uv_set}: trimesh reads only the first, which maps it here")
        try:
            transforms[slot] = _uv_transform(extension)
        except (TypeError, ValueError) as exc:
            notes.append(f"the KHR_texture_transform of the {slot} of {label} is not applied ({exc})")
            transforms[slot] = None
    uv_transform = None
    distinct = {None if t is None else t.tobytes() for t in transforms.values()}
    if len(distinct) > 1:  # (the colour is what shows: it is placed right, and the normal map with it)
        uv_transform = transforms["baseColorTexture"]
        notes.append(f"the normalTexture of {label} is placed by its baseColorTexture's KHR_texture_transform: the "
                     f"two are placed differently and share one UV set here, so the normal map is misplaced")
    elif transforms:
        uv_transform = next(iter(transforms.values()))
    scale = slots["normalTexture"].get("scale", 1.0) if isinstance(slots["normalTexture"], dict) else 1.0
    if not isinstance(scale, (int, float)) or isinstance(scale, bool) or not math.isfinite(scale):
        notes.append(f"the normalTexture scale of {label} ({scale!r}) is not a finite number: not applied")
        scale = 1.0
    factor = (material.get("pbrMetallicRoughness") or {}).get("baseColorFactor")
    base_color = None
    if isinstance(factor, list) and len(factor) >= 3 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in factor[:3]):
        base_color = tuple(min(max(float(x), 0.0), 1.0) for x in factor[:3])
    return MaterialExtras(float(scale), uv_transform, base_color)


def _uv_transform(extension: dict) -> np.ndarray | None:
    """KHR_texture_transform's matrix (translation x rotation x scale, in glTF's UVs: v down) in
    trimesh's UVs, or None for the identity."""
    offset = [float(x) for x in extension.get("offset", (0.0, 0.0))]
    rotation = float(extension.get("rotation", 0.0))
    scale = [float(x) for x in extension.get("scale", (1.0, 1.0))]
    if len(offset) != 2 or len(scale) != 2 or not all(map(math.isfinite, [*offset, rotation, *scale])):
        raise ValueError("offset and scale must be two finite numbers each, rotation one")
    if offset == [0.0, 0.0] and rotation == 0.0 and scale == [1.0, 1.0]:
        return None
    c, s = math.cos(rotation), math.sin(rotation)
    translation = np.array([[1.0, 0.0, offset[0]], [0.0, 1.0, offset[1]], [0.0, 0.0, 1.0]])
    turn = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    stretch = np.diag([scale[0], scale[1], 1.0])
    return _FLIP_V @ translation @ turn @ stretch @ _FLIP_V


def gltf_header(path: str | Path) -> dict:
    """The JSON of a .gltf or .glb file; {} where it cannot be read here (trimesh reads the file
    too, and says what is wrong with it). Read once per version of the file (its size, time and
    inode) for the last few files: a scene reads each of a file's meshes alone, one header each
    time. The dict is shared: a caller that changes it changes a copy (`mesh_alone`, `named_materials`)."""
    try:
        stat = Path(path).stat()
    except OSError:
        return {}
    return _read_header(str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns, stat.st_ino)


@functools.lru_cache(maxsize=4)
def _read_header(path: str, size: int, mtime_ns: int, inode: int) -> dict:
    """`gltf_header`, read (the file's version is the cache key)."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            start = f.read(20)
            if start[:4] == GLB_MAGIC:  # binary: a 12-byte header, then the JSON chunk (length, type, bytes)
                length, kind = struct.unpack_from("<II", start, 12)  # (only the chunk is read: not the buffers)
                if kind != JSON_CHUNK:
                    return {}
                header = json.loads(f.read(length))
            else:
                header = json.loads(start + f.read())
    except (OSError, ValueError, struct.error, UnicodeDecodeError, RecursionError):
        return {}
    return header if isinstance(header, dict) else {}

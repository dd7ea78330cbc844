"""One mesh of a glTF file as a .glb of its own, holding only the bytes that mesh reads.

A scene `neuralrt import` writes names each mesh of a glTF file alone (``gltf_mesh``), and each is
read on its own. Read under a `mesh_alone` header, trimesh still loads every buffer of the file,
slices every buffer view and opens every image: a file of many meshes was read whole once per mesh
(a 1.6 MB file of 200 meshes: 17 ms a mesh), and a missing .bin that only another mesh uses failed
them all, in the name of the first mesh read. `packed_alone` reads the buffer views the mesh's
accessors and its materials' images use (seeking to them in the .glb's binary chunk or the .bin
files beside a .gltf) into one binary chunk; the other views and accessors are left out and the
other images a one-pixel stand-in; the accessors and views kept are renumbered (trimesh then parses
and slices those alone).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

from .gltf_buffers import BIN_CHUNK, GLB_MAGIC, JSON_CHUNK, GltfBuffers
from .gltf_json import json_list

__all__ = ["packed_alone"]

# What trimesh opens for an image the mesh does not use (it opens each image of the file): 1 x 1 grey.
_STAND_IN_IMAGE = ("data:image/png;base64,iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAAAAAA6fptVAAAACklEQVR4nGNgAAAAAgAB"
                   "SK+kcQAAAABJRU5ErkJggg==")
_ALIGN = 16  # each view's bytes start at a multiple of this (glTF asks 4; a component is at most 4 bytes)


def packed_alone(header: dict, path: Path) -> bytes:
    """The .glb bytes of ``header`` (a `mesh_alone` header: one mesh, the others and the materials
    it does not use empty) with only the accessors its mesh reads and the buffer views they and its
    materials' images use (renumbered), read from ``path``'s buffers. An OSError names a buffer
    file the mesh needs that cannot be read; a ValueError a view the file's buffers do not hold."""
    accessors, views = json_list(header.get("accessors")), json_list(header.get("bufferViews"))
    images = json_list(header.get("images"))
    used_images = _material_images(header)
    kept_accessors = sorted(a for a in _mesh_accessors(header) if 0 <= a < len(accessors) and isinstance(accessors[a], dict))
    kept_views = sorted({v for a in kept_accessors for v in _accessor_views(accessors[a]) if 0 <= v < len(views)}
                        | {images[i]["bufferView"] for i in used_images if 0 <= i < len(images) and isinstance(images[i], dict)
                           and isinstance(images[i].get("bufferView"), int) and 0 <= images[i]["bufferView"] < len(views)})
    new_accessor, new_view = {a: k for k, a in enumerate(kept_accessors)}, {v: k for k, v in enumerate(kept_views)}

    reader = GltfBuffers(header, path)
    chunk, packed_views = bytearray(), []
    for v in kept_views:
        view = views[v] if isinstance(views[v], dict) else {}
        data = reader.read(view.get("buffer"), view.get("byteOffset", 0), view.get("byteLength"), v)
        chunk += b"\0" * (-len(chunk) % _ALIGN)
        packed_views.append({**view, "buffer": 0, "byteOffset": len(chunk), "byteLength": len(data)})
        chunk += data
    chunk += b"\0" * (-len(chunk) % 4)

    packed = dict(header)
    packed["accessors"] = [_renumbered_accessor(accessors[a], a, new_view) for a in kept_accessors]
    packed["bufferViews"] = packed_views
    packed["buffers"] = [{"byteLength": len(chunk)}]
    packed["meshes"] = [_renumbered_mesh(m, new_accessor) for m in json_list(header.get("meshes"))]
    if images:
        packed["images"] = [_renumbered_image(image, new_view) if i in used_images else {"uri": _STAND_IN_IMAGE}
                            for i, image in enumerate(images)]
    return _glb(packed, bytes(chunk))


def _renumbered_accessor(accessor: dict, index: int, new_view: dict) -> dict:
    """``accessor`` (the file's ``index``) with its buffer views renumbered; a ValueError for a view the
    file does not have (`bufferView: -1` was a KeyError)."""

    def renumber(view: int) -> int:
        if view not in new_view:
            raise ValueError(f"accessor {index} names buffer view {view}, which the file does not have")
        return new_view[view]

    out = {**accessor}
    if isinstance(out.get("bufferView"), int):
        out["bufferView"] = renumber(out["bufferView"])
    sparse = out.get("sparse")
    if isinstance(sparse, dict):
        out["sparse"] = {**sparse, **{part: {**sparse[part], "bufferView": renumber(sparse[part]["bufferView"])}
                                      for part in ("indices", "values") if isinstance(sparse.get(part), dict)
                                      and isinstance(sparse[part].get("bufferView"), int)}}
    return out


def _renumbered_mesh(mesh, new_accessor: dict):
    """``mesh`` with its primitives' accessor indices renumbered (an index it does not keep: the
    mesh's own error, left for trimesh to say: -1)."""
    if not isinstance(mesh, dict):
        return mesh

    def renumber(index):
        return new_accessor.get(index, -1) if isinstance(index, int) else index

    primitives = []
    for primitive in json_list(mesh.get("primitives")):
        if isinstance(primitive, dict):
            primitive = dict(primitive)
            if isinstance(primitive.get("attributes"), dict):
                primitive["attributes"] = {k: renumber(v) for k, v in primitive["attributes"].items()}
            if "indices" in primitive:
                primitive["indices"] = renumber(primitive["indices"])
            if isinstance(primitive.get("targets"), list):
                primitive["targets"] = [{k: renumber(v) for k, v in t.items()} if isinstance(t, dict) else t
                                        for t in primitive["targets"]]
        primitives.append(primitive)
    return {**mesh, "primitives": primitives}


def _renumbered_image(image, new_view: dict):
    if isinstance(image, dict) and isinstance(image.get("bufferView"), int):
        return {**image, "bufferView": new_view[image["bufferView"]]}
    return image


def _mesh_accessors(header: dict) -> set[int]:
    """The accessors the header's meshes read: attributes, indices and morph targets."""
    used = set()
    for mesh in json_list(header.get("meshes")):
        for primitive in json_list(mesh.get("primitives")) if isinstance(mesh, dict) else []:
            if not isinstance(primitive, dict):
                continue
            maps = [primitive.get("attributes"), *json_list(primitive.get("targets"))]
            used.update(a for m in maps if isinstance(m, dict) for a in m.values() if isinstance(a, int))
            if isinstance(primitive.get("indices"), int):
                used.add(primitive["indices"])
    return used


def _accessor_views(accessor: dict) -> list[int]:
    """The buffer views an accessor reads: its own, and a sparse one's indices and values."""
    sparse = accessor.get("sparse") if isinstance(accessor.get("sparse"), dict) else {}
    owners = [accessor, sparse.get("indices"), sparse.get("values")]
    return [o["bufferView"] for o in owners if isinstance(o, dict) and isinstance(o.get("bufferView"), int)]


def _material_images(header: dict) -> set[int]:
    """The images the header's materials use: each ``...Texture`` slot's texture's sources (its own,
    and those of its extensions, such as EXT_texture_webp)."""
    textures, used = json_list(header.get("textures")), set()

    def walk(value, key=""):
        if isinstance(value, dict):
            index = value.get("index")
            if key.endswith("Texture") and isinstance(index, int) and 0 <= index < len(textures):
                used.update(_sources(textures[index]))
            for k, v in value.items():
                walk(v, k)
        elif isinstance(value, list):
            for v in value:
                walk(v, key)

    for material in json_list(header.get("materials")):
        walk(material)
    return used


def _sources(texture) -> list[int]:
    if not isinstance(texture, dict):
        return []
    found = [texture["source"]] if isinstance(texture.get("source"), int) else []
    extensions = texture.get("extensions") if isinstance(texture.get("extensions"), dict) else {}
    return found + [e["source"] for e in extensions.values() if isinstance(e, dict) and isinstance(e.get("source"), int)]


def _glb(header: dict, binary: bytes) -> bytes:
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), JSON_CHUNK) + text + struct.pack("<II", len(binary), BIN_CHUNK) + binary
    return GLB_MAGIC + struct.pack("<II", 2, 12 + len(body)) + body

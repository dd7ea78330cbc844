"""How a glTF file places its materials' images, which trimesh reads but does not pass on.

trimesh loads a material's ``baseColorTexture`` and ``normalTexture`` but drops the normal map's
``scale``, the ``KHR_texture_transform`` that moves, turns or tiles an image on the UVs, and the
``texCoord`` that picks a UV set. `gltf_map_placements` reads them from the file's JSON so that
`load_mesh` applies the first two, and says what it cannot apply: a second UV set (trimesh reads
only the first), two images of one material placed differently (they share one UV set here), and
a material that trimesh's parts cannot be told apart from another (they keep its name, not its
index, so an unnamed or twice-named material's placement is not applied).
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["MapPlacement", "gltf_map_placements"]

_SLOTS = ("baseColorTexture", "normalTexture")  # the images neuralrt uses
_FLIP_V = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 1.0], [0.0, 0.0, 1.0]])  # glTF's v down <-> trimesh's v up


@dataclass(frozen=True)
class MapPlacement:
    """What to do to a material's maps: its normal map's ``scale`` and a 3x3 affine transform of
    its UVs (trimesh's convention, v up; None: as they are)."""

    normal_scale: float = 1.0
    uv_transform: np.ndarray | None = None

    @property
    def is_default(self) -> bool:
        return self.normal_scale == 1.0 and self.uv_transform is None

    def transformed_uvs(self, uv: np.ndarray) -> np.ndarray:
        if self.uv_transform is None:
            return uv
        m = self.uv_transform
        return (uv.astype(np.float64) @ m[:2, :2].T + m[:2, 2]).astype(np.float32)


def gltf_map_placements(path: str | Path) -> tuple[dict[str, MapPlacement], list[str]]:
    """(placement per material name, where one differs from the default; one line per thing in the
    file that is not applied). A file whose JSON cannot be read here (trimesh loaded it, so this
    is unlikely) gives nothing."""
    materials = _materials(Path(path))
    found: dict[str, list[MapPlacement]] = {}
    notes: list[str] = []
    for index, material in enumerate(materials):
        if not isinstance(material, dict):
            continue
        name = material.get("name")
        label = f"material {name!r}" if isinstance(name, str) else f"unnamed material {index}"
        placement = _placement(material, label, notes)
        if isinstance(name, str):
            found.setdefault(name, []).append(placement)
        elif not placement.is_default:
            notes.append(f"how the maps of {label} are placed (normal map scale, KHR_texture_transform) is not "
                         f"applied: trimesh keeps materials by name")
    placements = {}
    for name, each in found.items():
        if all(_same(p, each[0]) for p in each):
            if not each[0].is_default:
                placements[name] = each[0]
        else:
            notes.append(f"how the maps of material {name!r} are placed is not applied: {len(each)} materials share "
                         f"that name and place their maps differently")
    return placements, notes


def _same(a: MapPlacement, b: MapPlacement) -> bool:
    if a.normal_scale != b.normal_scale or (a.uv_transform is None) != (b.uv_transform is None):
        return False
    return a.uv_transform is None or bool(np.array_equal(a.uv_transform, b.uv_transform))


def _placement(material: dict, label: str, notes: list[str]) -> MapPlacement:
    slots = {"normalTexture": material.get("normalTexture"),
             "baseColorTexture": (material.get("pbrMetallicRoughness") or {}).get("baseColorTexture")}
    transforms = {}
    for slot in _SLOTS:
        info = slots[slot]
        if not isinstance(info, dict):
            continue
        extension = (info.get("extensions") or {}).get("KHR_texture_transform")
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
    if len(distinct) > 1:
        notes.append(f"the KHR_texture_transforms of {label} are not applied: its baseColorTexture and normalTexture "
                     f"are placed differently, and share one UV set here")
    elif transforms:
        uv_transform = next(iter(transforms.values()))
    scale = slots["normalTexture"].get("scale", 1.0) if isinstance(slots["normalTexture"], dict) else 1.0
    if not isinstance(scale, (int, float)) or isinstance(scale, bool) or not math.isfinite(scale):
        notes.append(f"the normalTexture scale of {label} ({scale!r}) is not a finite number: not applied")
        scale = 1.0
    return MapPlacement(float(scale), uv_transform)


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


def _materials(path: Path) -> list:
    try:
        data = path.read_bytes()
        if data[:4] == b"glTF":  # binary: a 12-byte header, then the JSON chunk (length, type, bytes)
            length, kind = struct.unpack_from("<II", data, 12)
            if kind != 0x4E4F534A:  # "JSON"
                return []
            header = json.loads(data[20:20 + length])
        else:
            header = json.loads(data)
    except (OSError, ValueError, struct.error, UnicodeDecodeError, RecursionError):
        return []
    materials = header.get("materials") if isinstance(header, dict) else None
    return materials if isinstance(materials, list) else []

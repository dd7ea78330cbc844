"""A scene for one mesh or one model on its own: ``neuralrt render bunny.obj`` or ``bunny.nrt``.

The object stays where its file puts it, in the scene's default material (diffuse 0.8, times the
mesh's own colours), under a soft sky (a constant environment) and a key light above the camera's
left shoulder, seen in a three-quarter view (from +x, +y, +z: the scenes' +y is up) that frames
its bounding sphere. A model file renders alone, with no mesh: every ray, camera rays too, is
answered by the model, so the image shows what it learned.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["MESH_SUFFIXES", "MODEL_SUFFIX", "is_lone_object", "studio_dict"]

MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".gltf", ".glb")
MODEL_SUFFIX = ".nrt"
PROCEDURAL_PREFIX = "procedural:"

_FOV = 30.0  # degrees, vertical
_VIEW = np.array([0.55, 0.45, 1.0])  # towards the camera from the object's centre
_KEY = np.array([-0.6, 1.0, 0.7])  # towards the key light
_SKY = 0.3  # constant environment radiance
_KEY_IRRADIANCE = 1.5  # at the object's centre, from the key light (the sky gives ~0.94: lit and shadowed sides apart)


def is_lone_object(name: str) -> bool:
    """Whether a scene argument names one mesh (a mesh file trimesh reads, ``procedural:NAME:DETAIL``)
    or one model file rather than a scene."""
    suffix = Path(name).suffix.lower()
    if name.startswith(PROCEDURAL_PREFIX) or suffix in MESH_SUFFIXES + (MODEL_SUFFIX,):
        return True
    if suffix in ("", ".toml", ".json"):
        return False
    from ..geometry.mesh import import_trimesh

    return suffix[1:] in import_trimesh().available_formats()  # (.dae, .3mf, ... where their readers are installed)


def studio_dict(key: str, value, lo, hi, resolution: tuple[int, int] | None = None) -> dict:
    """A scene dict (`neuralrt.scene.load_dict`) holding ``value`` (a `Mesh` or a BLAS) as its one
    object's ``key`` (``"mesh"`` or ``"model"``), framed from its bounds ``lo``, ``hi``."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-30)  # (a mesh is never a point: loading refuses one)
    distance = radius / math.sin(math.radians(_FOV / 2)) * 1.05
    view, key_dir = _VIEW / np.linalg.norm(_VIEW), _KEY / np.linalg.norm(_KEY)
    light_distance = 4.0 * radius
    camera = {"position": (centre + view * distance).tolist(), "look_at": centre.tolist(), "fov": _FOV}
    if resolution is not None:
        camera["resolution"] = list(resolution)
    return {
        "camera": camera,
        # (named as its mesh is, so that `--nif bunny` names a lone bunny)
        "objects": [{"name": getattr(value, "name", None) or getattr(value, "mesh_name", None) or "object", key: value}],
        "lights": [{"position": (centre + key_dir * light_distance).tolist(),
                    "intensity": [_KEY_IRRADIANCE * light_distance ** 2] * 3}],
        "environment": {"color": [_SKY] * 3},
    }

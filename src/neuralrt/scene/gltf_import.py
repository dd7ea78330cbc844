"""A glTF scene as a scene file: ``neuralrt import city.glb -o city.toml``.

`load_mesh` merges a glTF file into one mesh, so a mesh that many nodes draw becomes as many
copies. Here each node that draws a mesh becomes a scene object naming that mesh of the file
(``gltf_mesh``: the mesh alone, in its own space) and placed by the node's world matrix, so a
mesh drawn many times is one accelerator (one model once converted) and many instances, as
LSNIF's instancing means. GPU instances (``EXT_mesh_gpu_instancing``) become objects too, and
meshes whose primitives name the same accessors and materials (trimesh writes one per node) are
one mesh.

What else the file says is read where the scene format has it:
- The first perspective camera the scene's nodes reach (``yfov``, ``aspectRatio`` as the
  resolution's shape, 256 pixels high); without one, the scene is framed as a lone mesh is.
- ``KHR_lights_punctual``: a point light as a point light, its candela over 683 lm/W as W/sr
  (as Blender's importer reads it); a spot light as a point light (its cone is dropped: a note
  says so); a directional light as a point light 100 scene radii away, giving the same irradiance
  at the scene's centre (within 2% across the scene).
- Materials, by name (the scene gives each mesh slot the scene material of its name): a material
  that emits (``emissiveFactor`` times ``KHR_materials_emissive_strength``) becomes an emissive
  scene material, one with ``metallicFactor`` >= 0.5 a conductor, any other a plastic (glTF's
  dielectric: a diffuse base under a coat of index 1.5), the GGX alpha being the square of
  ``roughnessFactor``; each albedo is white, so the mesh's base colour (factor and texture) is
  the colour. Unnamed materials and slots without a material take ``default``: white diffuse.
- A scene without lights gets the lone-mesh key light and sky.
What is not read (an orthographic camera, unnamed emissive materials, a node whose matrix cannot
place a mesh) is a warning naming it.
"""

from __future__ import annotations

import json
import math
import shlex
import warnings
from pathlib import Path

import numpy as np

from ..errors import SceneError, outside_stacklevel
from ..geometry.gltf_json import (draws_triangles, expanded_instances, gltf_file_notes, gltf_header, instanced_nodes,
                                  json_extension, json_list)
from .schema import DEFAULT_MATERIAL_NAME, MAX_LIGHT_COORDINATE, MAX_RADIANCE

__all__ = ["gltf_scene_dict", "import_gltf_scene", "unused_scene_note"]

CANDELA_PER_WATT_SR = 683.0  # lm/W at 555 nm: glTF lights are photometric, the scene's radiometric
DISTANT = 100.0  # a directional light's distance, in scene radii
IMAGE_HEIGHT = 256  # pixels; the width follows the camera's aspect ratio
_LIGHTS = "KHR_lights_punctual"


def import_gltf_scene(path: str | Path, output: str | Path) -> dict:
    """Write the scene file ``output`` (.toml or .json) for the glTF scene ``path``: its paths
    relative to the new file's folder, atomically. Returns what it holds."""
    from .loader import validate_spec
    from .scene import save_scene

    path, output = Path(path), Path(output)
    if output.suffix.lower() not in (".toml", ".json"):
        raise SceneError(f"{output}: scene files must end in .toml or .json")
    scene, facts = gltf_scene_dict(path)
    spec = validate_spec(scene, str(path))
    output.parent.mkdir(parents=True, exist_ok=True)
    save_scene(spec, output)
    return {"scene": str(output), **facts}


def gltf_scene_dict(path: str | Path) -> tuple[dict, dict]:
    """(a scene dict for `neuralrt.scene.loader.validate_spec`, its mesh paths absolute; facts about
    it: objects, distinct meshes, camera, lights, materials)."""
    path = Path(path).absolute()
    if path.suffix.lower() not in (".gltf", ".glb"):
        raise SceneError(f"{path}: a glTF file (.gltf, .glb) holds a scene to import; other mesh files are one "
                         "object (name them as an object's mesh)")
    from ..io.files import input_file_problem

    problem = input_file_problem(path, "glTF file")
    if problem:
        raise SceneError(problem)
    header = gltf_header(path)
    if not header:
        raise SceneError(f"{path}: cannot read its glTF JSON")
    unreadable, _ = gltf_file_notes(header)
    if unreadable:
        raise SceneError(f"{path}: cannot read mesh: {unreadable}")
    if instanced_nodes(header):
        try:
            header = expanded_instances(header, path)
        except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
            raise SceneError(f"{path}: its EXT_mesh_gpu_instancing instances cannot be read "
                             f"({type(exc).__name__}: {exc})") from None
    placed = _placed_nodes(header, path)
    materials, emissive = _materials(header, path)
    lit = {m["name"] for m in materials if m["type"] == "emissive"}
    objects, bounds = _objects(header, placed, path, lit)
    if not objects:
        raise SceneError(f"{path}: no node of its scene draws a mesh")
    lo, hi = bounds
    reach = float(np.max(np.abs([lo, hi])))
    if not reach < MAX_LIGHT_COORDINATE / DISTANT:  # (its lights, or the ones a scene without lights gets, go further)
        raise SceneError(f"{path}: its meshes reach {reach:.3g} from the origin: a scene holds lights within "
                         f"{MAX_LIGHT_COORDINATE:g}, and this one's would be further (move or scale the file's nodes)")
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-30)
    lights = _lights(header, placed, (lo + hi) / 2, radius, path)
    camera = _camera(header, placed, radius, path)
    from .studio import studio_dict

    studio = studio_dict("mesh", None, lo, hi, (IMAGE_HEIGHT, IMAGE_HEIGHT))
    scene = {"camera": camera or studio["camera"], "materials": materials, "objects": objects, "lights": lights}
    if not lights and not emissive:  # (a file with no light of its own would render black)
        scene["lights"], scene["environment"] = studio["lights"], studio["environment"]
    facts = {"objects": len(objects), "meshes": len({o["gltf_mesh"] for o in objects}),
             "camera": "the file's" if camera else "framed", "lights": len(scene["lights"]),
             "emissive_materials": emissive, "lit_as_a_lone_mesh": "environment" in scene}
    return scene, facts


def unused_scene_note(path: str | Path) -> str | None:
    """What a glTF file holds as a scene that rendering it as one merged mesh leaves unused (meshes
    drawn more than once, which become copies; cameras; lights), with the command that keeps it;
    None where there is nothing of the kind (or the file is no glTF)."""
    header = gltf_header(path) if Path(path).suffix.lower() in (".gltf", ".glb") else {}
    nodes = [n for n in json_list(header.get("nodes")) if isinstance(n, dict)]
    meshes = json_list(header.get("meshes"))
    drawn: dict[str, int] = {}
    for node in nodes:
        mesh = node.get("mesh")
        if isinstance(mesh, int) and 0 <= mesh < len(meshes):
            key = _geometry_key(meshes[mesh])
            drawn[key] = drawn.get(key, 0) + (2 if json_extension(node, "EXT_mesh_gpu_instancing") else 1)
    repeated = sum(count > 1 for count in drawn.values())
    cameras = sum(isinstance(node.get("camera"), int) for node in nodes)
    lights = sum(isinstance(json_extension(node, _LIGHTS).get("light"), int) for node in nodes)
    lost = [f"{repeated} {_plural(repeated, 'mesh', 'meshes')} drawn by several nodes "
            f"{_plural(repeated, 'is', 'are')} copied"] if repeated else []
    unused = [f"{n} {_plural(n, what, what + 's')}" for n, what in ((cameras, "camera"), (lights, "light")) if n]
    if unused:
        lost.append(f"{' and '.join(unused)} {_plural(cameras + lights, 'is', 'are')} not used")
    if not lost:
        return None
    command = f"neuralrt import {shlex.quote(str(path))} -o {shlex.quote(str(Path(path).with_suffix('.toml')))}"
    return (f"{path}: rendered as one merged mesh, framed and lit ({'; '.join(lost)}): `{command}` writes a scene that "
            f"keeps them")


def _plural(count: int, one: str, more: str) -> str:
    return one if count == 1 else more


def _placed_nodes(header: dict, path: Path) -> list[tuple[int, np.ndarray]]:
    """(node index, world matrix) of every node the scene reaches, parents before children."""
    nodes = json_list(header.get("nodes"))
    scenes = json_list(header.get("scenes"))
    chosen = header.get("scene", 0)
    if "scene" in header and not (isinstance(chosen, int) and 0 <= chosen < len(scenes)):
        raise SceneError(f"{path}: the default scene is {chosen!r}, but the file has {len(scenes)} "
                         f"{_plural(len(scenes), 'scene', 'scenes')}")
    if scenes and isinstance(scenes[chosen], dict):
        roots = _indices(scenes[chosen], "nodes", path, f"scene {chosen}")
    else:  # (no scene: every node that is no node's child, as viewers show such a file)
        children = {c for n in nodes if isinstance(n, dict) for c in json_list(n.get("children")) if isinstance(c, int)}
        roots = [i for i in range(len(nodes)) if i not in children]
    placed, stack = [], [(r, np.eye(4), ()) for r in reversed(roots)]
    while stack:
        index, parent, above = stack.pop()
        if not isinstance(index, int) or not 0 <= index < len(nodes) or not isinstance(nodes[index], dict):
            raise SceneError(f"{path}: a scene or node names node {index!r}, which the file does not have")
        if index in above:
            raise SceneError(f"{path}: node {index} is its own ancestor (its children lead back to it)")
        try:
            world = parent @ _local_matrix(nodes[index])
        except (TypeError, ValueError) as exc:
            raise SceneError(f"{path}: node {index}'s transform cannot be read ({exc})") from None
        placed.append((index, world))
        for child in reversed(_indices(nodes[index], "children", path, f"node {index}")):
            stack.append((child, world, above + (index,)))
    return placed


def _indices(owner: dict, key: str, path: Path, label: str) -> list:
    """``owner[key]``, a list of node indices ([] if absent; ``label`` names the owner): an error if it is no list."""
    found = owner.get(key, [])
    if not isinstance(found, list):
        raise SceneError(f"{path}: {label}'s {key} must be a list of node indices, not {type(found).__name__}")
    return found


def _local_matrix(node: dict) -> np.ndarray:
    """A node's matrix (glTF stores it column by column), or its translation, rotation and scale."""
    if "matrix" in node:
        values = np.array(node["matrix"], np.float64)
        if values.shape != (16,):
            raise ValueError("a matrix is 16 numbers")
        return values.reshape(4, 4).T
    t = np.array(node.get("translation", (0.0, 0.0, 0.0)), np.float64)
    q = np.array(node.get("rotation", (0.0, 0.0, 0.0, 1.0)), np.float64)
    s = np.array(node.get("scale", (1.0, 1.0, 1.0)), np.float64)
    if t.shape != (3,) or s.shape != (3,) or q.shape != (4,) or not np.linalg.norm(q) > 0:
        raise ValueError("translation and scale are 3 numbers, rotation 4 (a unit quaternion)")
    from ..geometry.mesh import import_trimesh  # (trimesh's first import holds Ctrl-C: see there)

    x, y, z, w = q
    matrix = import_trimesh().transformations.quaternion_matrix([w, x, y, z])  # (normalised: exporters round them)
    matrix[:3, :3] *= s[None, :]
    matrix[:3, 3] = t
    return matrix


def _objects(header: dict, placed: list, path: Path, lit) -> tuple[list[dict], tuple[np.ndarray, np.ndarray]]:
    """One object per node that draws a mesh, and the world bounds of them all; each mesh is read
    once (``lit``: the material names the scene makes lights)."""
    nodes, meshes = json_list(header.get("nodes")), json_list(header.get("meshes"))  # (both optional in glTF)
    objects, corners, taken, first_alike, bounds_of = [], [], {}, {}, {}
    for index, world in placed:
        mesh = nodes[index].get("mesh")
        if mesh is None:
            continue
        if not isinstance(mesh, int) or not 0 <= mesh < len(meshes):
            raise SceneError(f"{path}: node {index} draws mesh {mesh!r}, which the file does not have")
        name = _name(nodes[index]) or _name(meshes[mesh]) or f"node{index}"
        mesh = first_alike.setdefault(_geometry_key(meshes[mesh]), mesh)
        taken[name] = taken.get(name, 0) + 1
        name = name if taken[name] == 1 else f"{name}.{taken[name] - 1}"
        matrix = [[float(x) for x in row] for row in world]
        reason = _placing_problem(world, matrix)
        if reason:
            warnings.warn(f"{path}: node {index} ({name!r}) is left out: its world matrix cannot place a mesh ({reason})",
                          stacklevel=outside_stacklevel())
            continue
        if not draws_triangles(meshes[mesh]):
            warnings.warn(f"{path}: node {index} ({name!r}) is left out: mesh {mesh} draws no triangles (points, lines "
                          "or fans)", stacklevel=outside_stacklevel())
            continue
        if mesh not in bounds_of:  # (read here, so that a mesh the scene could not load fails the import)
            bounds_of[mesh] = _mesh_bounds(path, mesh, lit)
        objects.append({"name": name, "mesh": str(path), "gltf_mesh": mesh, "transform": {"matrix": matrix}})
        corners.append(_world_corners(bounds_of[mesh], world))
    every = np.concatenate(corners) if corners else np.zeros((1, 3))
    return objects, (every.min(axis=0), every.max(axis=0))


def _placing_problem(world: np.ndarray, matrix: list) -> str | None:
    """Why a node's world matrix cannot place a mesh (not finite; singular: a scale of 0), or None."""
    from pydantic import ValidationError

    from ..errors import validation_message
    from .schema import TransformSpec

    if not np.isfinite(world).all():  # (one reason, not pydantic's line per entry)
        return "it holds numbers that are not finite"
    try:
        TransformSpec(matrix=matrix)
    except ValidationError as exc:
        return validation_message(exc, TransformSpec)
    return None


def _geometry_key(mesh) -> str:
    """What a glTF mesh draws, as one key: its primitives (accessors and materials) and morph weights.
    Exporters such as trimesh write a mesh per node, each naming the same accessors: one mesh."""
    drawn = mesh if isinstance(mesh, dict) else {}
    return json.dumps([drawn.get("primitives"), drawn.get("weights")], sort_keys=True)


def _mesh_bounds(path: Path, mesh: int, lit) -> tuple[np.ndarray, np.ndarray]:
    from ..errors import NeuralRTError
    from ..geometry.mesh import load_mesh

    try:
        return load_mesh(path, mesh, lit=lit).bounds
    except NeuralRTError as exc:
        said = str(exc)
        raise SceneError(said if f"glTF mesh {mesh}:" in said else f"{said} (glTF mesh {mesh})") from None


def _name(entry) -> str | None:
    name = entry.get("name") if isinstance(entry, dict) else None
    return name if isinstance(name, str) and name.strip() else None


def _world_corners(bounds: tuple[np.ndarray, np.ndarray], world: np.ndarray) -> np.ndarray:
    """The corners of a mesh's box, ``bounds`` in its own space, in world space (float64: the
    import's reach check sees the file's numbers, not float32's)."""
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    box = np.array([[(lo, hi)[i >> k & 1][k] for k in range(3)] for i in range(8)])
    return box @ world[:3, :3].T + world[:3, 3]


def _materials(header: dict, path: Path) -> tuple[list[dict], int]:
    """(the scene materials of the file's named materials; how many emit). The rest take the scene's
    ``default`` (diffuse 0.8, as `neuralrt render mesh.glb` gives them)."""
    found, emissive, unnamed = [], 0, []
    seen = {DEFAULT_MATERIAL_NAME}
    for i, material in enumerate(header.get("materials") or []):
        if not isinstance(material, dict):
            continue
        name, glow = _name(material), _emission(material)
        if name is None or name in seen:
            if glow is not None:
                unnamed.append(f"material {i}")
            continue
        seen.add(name)
        pbr = material.get("pbrMetallicRoughness") if isinstance(material.get("pbrMetallicRoughness"), dict) else {}
        metallic, roughness = _unit_number(pbr.get("metallicFactor", 1.0)), _unit_number(pbr.get("roughnessFactor", 1.0))
        if glow is not None:
            emissive += 1
            found.append({"name": name, "type": "emissive", "emission": glow})
        else:
            alpha = max(float(f"{roughness**2:.6g}"), 1e-3)  # (GGX alpha: perceptual roughness squared)
            found.append({"name": name, "type": "conductor" if metallic >= 0.5 else "plastic", "albedo": [1.0, 1.0, 1.0],
                          "roughness": alpha})
    if unnamed:
        warnings.warn(f"{path}: the emission of {', '.join(unnamed)} is not read: a scene material takes a slot by "
                      f"name, and these have none (or another material's)", stacklevel=outside_stacklevel())
    note = unread_alpha_note(path, header)
    if note:
        warnings.warn(note, stacklevel=outside_stacklevel())
    return found, emissive


def unread_alpha_note(path: str | Path, header: dict | None = None) -> str | None:
    """That the file's materials cut surfaces out by alpha (``alphaMode`` MASK or BLEND: leaves,
    fences, decals), which nothing reads: they render opaque. None where none does."""
    if header is None:
        header = gltf_header(path) if Path(path).suffix.lower() in (".gltf", ".glb") else {}
    cut = [_name(m) or f"material {i}" for i, m in enumerate(json_list(header.get("materials")))
           if isinstance(m, dict) and m.get("alphaMode") in ("MASK", "BLEND")]
    if not cut:
        return None
    shown = ", ".join(map(repr, cut[:4])) + (f" and {len(cut) - 4} more" if len(cut) > 4 else "")
    return (f"{path}: the alpha of {shown} (alphaMode MASK or BLEND) is not read: {_plural(len(cut), 'its', 'their')} "
            f"surfaces render opaque, cut-out leaves as whole quads")


def _unit_number(value) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    return min(max(float(value), 0.0), 1.0) if ok else 1.0


def _emission(material: dict) -> list[float] | None:
    factor = material.get("emissiveFactor")
    strength = json_extension(material, "KHR_materials_emissive_strength").get("emissiveStrength", 1.0)
    try:
        emission = [float(x) * float(strength) for x in factor]
    except (TypeError, ValueError):
        return None
    if len(emission) != 3 or not all(math.isfinite(x) and x >= 0 for x in emission) or max(emission) <= 0:
        return None
    return emission


def _lights(header: dict, placed: list, centre: np.ndarray, radius: float, path: Path) -> list[dict]:
    table = json_extension(header, _LIGHTS).get("lights", [])
    if not isinstance(table, list):
        raise SceneError(f"{path}: {_LIGHTS}'s lights must be a list, not {type(table).__name__}")
    lights = []
    for index, world in placed:
        used = json_extension(header["nodes"][index], _LIGHTS).get("light")
        if used is None:
            continue
        light = table[used] if isinstance(used, int) and 0 <= used < len(table) and isinstance(table[used], dict) else None
        if light is None:
            raise SceneError(f"{path}: node {index} uses light {used!r}, which {_LIGHTS} does not define")
        try:
            colour = np.array(light.get("color", (1.0, 1.0, 1.0)), np.float64) * float(light.get("intensity", 1.0))
            if colour.shape != (3,) or not np.isfinite(colour).all() or (colour < 0).any():
                raise ValueError
        except (TypeError, ValueError):
            raise SceneError(f"{path}: light {used}'s color and intensity must be finite, non-negative numbers") from None
        kind, label = light.get("type"), f"{light.get('type')} light {_name(light) or used!r}"
        position = world[:3, 3]
        if kind == "directional":  # (lux at the centre from far away: the same irradiance)
            facing = -world[:3, 2] / max(np.linalg.norm(world[:3, 2]), 1e-30)
            distance = DISTANT * radius
            position, colour = centre - facing * distance, colour * distance**2
        elif kind == "spot":
            warnings.warn(f"{path}: {label} is read as a point light (its cone is not)",
                          stacklevel=outside_stacklevel())
        elif kind != "point":
            warnings.warn(f"{path}: {label} is left out (point, spot and directional lights are read)",
                          stacklevel=outside_stacklevel())
            continue
        intensity = colour / CANDELA_PER_WATT_SR
        if not (np.abs(position) <= MAX_LIGHT_COORDINATE).all() or not (intensity <= MAX_RADIANCE).all():
            raise SceneError(f"{path}: {label} at node {index}: its position must lie within {MAX_LIGHT_COORDINATE:g} "
                             f"and its intensity within {MAX_RADIANCE:g} W/sr (got {position.tolist()} and "
                             f"{intensity.tolist()})")
        lights.append({"position": [float(x) for x in position], "intensity": [float(x) for x in intensity]})
    return lights


def _camera(header: dict, placed: list, radius: float, path: Path) -> dict | None:
    """The first perspective camera the nodes reach, as the scene's camera; None where there is none."""
    cameras = json_list(header.get("cameras"))
    for index, world in placed:
        used = header["nodes"][index].get("camera")
        if used is None:
            continue
        camera = cameras[used] if isinstance(used, int) and 0 <= used < len(cameras) else None
        if not isinstance(camera, dict):
            raise SceneError(f"{path}: node {index} uses camera {used!r}, which the file does not have")
        lens = camera.get("perspective")
        if camera.get("type") != "perspective" or not isinstance(lens, dict):
            warnings.warn(f"{path}: camera {_name(camera) or used!r} is left out: only perspective cameras are read",
                          stacklevel=outside_stacklevel())
            continue
        fov = math.degrees(float(lens.get("yfov", 0.0))) if isinstance(lens.get("yfov"), (int, float)) else 0.0
        aspect = lens.get("aspectRatio", 1.0)
        if not 0 < fov < 180 or not isinstance(aspect, (int, float)) or not 0 < aspect < 64:
            raise SceneError(f"{path}: camera {used}: yfov must be in (0, pi) and aspectRatio positive, got "
                             f"{json.dumps(lens.get('yfov'))} and {json.dumps(aspect)}")
        forward, up = -world[:3, 2], world[:3, 1]
        if not np.isfinite(world).all() or np.linalg.norm(forward) == 0 or np.linalg.norm(np.cross(forward, up)) == 0:
            warnings.warn(f"{path}: camera {_name(camera) or used!r} at node {index} is left out: the node's matrix "
                          "gives it no view direction (a scale of 0, or not finite)", stacklevel=outside_stacklevel())
            continue
        position = world[:3, 3]
        look_at = position + forward / np.linalg.norm(forward) * radius
        width = max(1, round(IMAGE_HEIGHT * float(aspect)))
        return {"position": [float(x) for x in position], "look_at": [float(x) for x in look_at],
                "up": [float(x) for x in up / np.linalg.norm(up)], "fov": fov, "resolution": [width, IMAGE_HEIGHT]}
    return None

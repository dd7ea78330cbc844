"""Notes on a camera or point light placed inside an object, said before a render.

A camera inside a mesh (a scene's units off by 100, a mistyped position) renders that mesh's
inside: black when no light is in there, with nothing to say why. A point light inside one lights
only its inside. Both are told as warnings; neither is an error, as a room seen from inside is a
scene too.

"Inside" is judged by rays, not by the mesh's topology (a neural object has none): a point is
enclosed by an instance when each of `ENCLOSURE_DIRECTIONS` from it first meets that instance. An
opening those rays miss lets light through; the notes say how they judged.
"""

from __future__ import annotations

import itertools

import torch
from torch import Tensor

from ..rays import Rays

__all__ = ["ENCLOSURE_DIRECTIONS", "enclosing_instance", "enclosing_instances", "enclosure_notes"]

# The 26 directions to a cube's faces, edges and corners from its centre.
ENCLOSURE_DIRECTIONS = torch.nn.functional.normalize(
    torch.tensor([d for d in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(d)]), dim=-1)


def enclosing_instance(accel, point: Tensor, camera_rays: bool = False) -> int | None:
    """The instance that each of `ENCLOSURE_DIRECTIONS` from ``point`` (world space) first meets,
    or None (one ray escapes, or two meet different instances). ``camera_rays``: ask whoever
    answers camera rays (a hybrid scene's exact view of a neural object)."""
    return enclosing_instances(accel, torch.as_tensor(point, dtype=torch.float32).reshape(1, 3), camera_rays)[0]


def enclosing_instances(accel, points, camera_rays: bool = False) -> list[int | None]:
    """`enclosing_instance` of each of ``points`` ([P, 3]), in one query."""
    directions = ENCLOSURE_DIRECTIONS.to(accel.device)
    points = torch.as_tensor(points, dtype=torch.float32, device=accel.device).reshape(-1, 3)
    if len(points) == 0:
        return []
    origins = points[:, None, :].expand(-1, len(directions), 3)
    hits = accel.intersect(Rays(origins, directions.expand_as(origins)), camera_rays=camera_rays)
    met = hits.instance_id.reshape(len(points), len(directions))
    alike = hits.hit.reshape(met.shape).all(1) & (met == met[:, :1]).all(1)
    return [int(first) if ok else None for first, ok in zip(met[:, 0].tolist(), alike.tolist())]


def enclosure_notes(scene) -> list[str]:
    """What to tell about ``scene`` (a `neuralrt.scene.Scene`) before it renders: a camera inside a
    non-emitting object with no light within its bounds, and each point light inside an object
    whose bounds the camera is outside of. (Enclosure is judged strictly, by rays; a light or the
    camera "within bounds" loosely, by the object's world box, so that a room with a ball in it,
    whose rays meet the ball, still counts as lit from inside.)"""
    accel, lights = scene.accel, scene.lights
    label = scene.name or "scene"
    judged = f"each of {len(ENCLOSURE_DIRECTIONS)} rays from it, in all directions, meets it first"
    emitters = [] if lights.area is None else lights.area.instance_ids.tolist()
    points = lights.points
    # (index in the scene's list, position) of each point light that shines: a dark one lights nothing
    lit = [] if points is None else [(k, p) for k, (p, on) in enumerate(zip(points.positions.tolist(),
                                                                          (points.intensities > 0).any(1).tolist())) if on]
    positions = [p for _, p in lit]
    camera_at = scene.camera.position.tolist()
    boxes = [inst.world_bounds for inst in accel.instances]
    notes = []
    inside = enclosing_instance(accel, camera_at, camera_rays=True)
    if (inside is not None and inside not in emitters and not any(_holds(boxes[inside], p, p) for p in positions)
            and not any(_holds(boxes[inside], boxes[e].lo.tolist(), boxes[e].hi.tolist()) for e in emitters)):
        notes.append(f"{label}: the camera at {_point(camera_at)} seems to be inside object {_name(accel, inside)} "
                     f"({judged}) and no light is inside it: the image shows its inside, unlit")
    for (k, position), around in zip(lit, enclosing_instances(accel, positions)):
        if around is not None and not _holds(boxes[around], camera_at, camera_at):
            notes.append(f"{label}: point light {k} at {_point(position)} seems to be inside object "
                         f"{_name(accel, around)} ({judged}): little or none of its light leaves it")
    return notes


def _holds(box, lo, hi) -> bool:
    """Does ``box`` (world bounds) hold the box ``lo``..``hi`` (a point where they are equal)?"""
    return all(a <= b for a, b in zip(box.lo.tolist(), lo)) and all(b <= a for a, b in zip(box.hi.tolist(), hi))


def _name(accel, index: int) -> str:
    return repr(accel.instances[index].name or f"instance {index}")


def _point(xyz) -> str:
    return "(" + ", ".join(f"{v:.4g}" for v in xyz) + ")"

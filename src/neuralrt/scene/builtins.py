"""Built-in scenes that need no files: ``builtin:<name>`` or ``builtin:<name>?detail=N``.

``detail`` is the procedural meshes' detail level (`neuralrt.geometry.procedural`): the default
renders quickly on 2 CPU cores; each step multiplies the triangle count by about 2-4, reaching
millions of triangles at detail 4-5. `list_builtins` names them all.
"""

from __future__ import annotations

from ..arguments import check_count, given
import math
from dataclasses import dataclass
from typing import Callable
from urllib.parse import parse_qs

from ..errors import SceneError
from ..geometry.procedural import MAX_DETAIL
from .schema import (
    CameraSpec,
    ConductorMaterialSpec,
    DiffuseMaterialSpec,
    EmissiveMaterialSpec,
    EnvironmentSpec,
    GeneratorSpec,
    ObjectSpec,
    PlasticMaterialSpec,
    PointLightSpec,
    SceneSpec,
    TransformSpec,
)

__all__ = ["BUILTIN_SCENES", "BuiltinScene", "list_builtins", "builtin_spec"]


@dataclass(frozen=True)
class BuiltinScene:
    description: str
    build: Callable[[int], SceneSpec]  # detail -> spec
    default_detail: int
    max_detail: int  # the finest level every generator of the scene takes (`neuralrt.geometry.procedural`)


def _gen(name: str, **params) -> GeneratorSpec:
    return GeneratorSpec(name=name, params=params)


def _ceiling_light(size: float, height: float, emission) -> tuple[EmissiveMaterialSpec, ObjectSpec]:
    """A square emitter of side ``size`` at ``height`` facing down (the plane faces +y; turned over)."""
    return (EmissiveMaterialSpec(name="light", emission=emission),
            ObjectSpec(name="light", generator=_gen("plane", size=size), material="light",
                       transform=TransformSpec(translate=(0.0, height, 0.0), rotate=(180.0, 0.0, 0.0))))


def cornell_statue(detail: int) -> SceneSpec:
    """Cornell box (area light in the ceiling) with the procedural statue on the floor."""
    return SceneSpec(
        camera=CameraSpec(position=(0.0, 0.0, 3.9), look_at=(0.0, 0.0, 0.0), fov=39.0),
        materials=[
            DiffuseMaterialSpec(name="white", albedo=(0.73, 0.73, 0.73)),
            DiffuseMaterialSpec(name="red", albedo=(0.63, 0.065, 0.05)),
            DiffuseMaterialSpec(name="green", albedo=(0.14, 0.45, 0.091)),
            EmissiveMaterialSpec(name="light", emission=(17.0, 12.0, 4.0), albedo=(0.78, 0.78, 0.78)),
            PlasticMaterialSpec(name="statue", albedo=(0.75, 0.6, 0.4), roughness=0.25),
        ],
        objects=[
            ObjectSpec(name="box", generator=_gen("cornell_box")),
            ObjectSpec(name="statue", generator=_gen("statue", detail=detail), material="statue",
                       transform=TransformSpec(translate=(0.0, -0.4, 0.0), rotate=(0.0, 25.0, 0.0), scale=0.6)),
        ],
    )


def hairball(detail: int) -> SceneSpec:
    """A hairball of thin tubes on a floor, lit by a sky environment and an overhead area light."""
    light_mat, light = _ceiling_light(1.5, 2.5, (6.0, 6.0, 6.0))
    return SceneSpec(
        camera=CameraSpec(position=(0.0, 0.4, 3.3), look_at=(0.0, -0.05, 0.0), fov=40.0),
        materials=[
            PlasticMaterialSpec(name="hair", albedo=(0.55, 0.3, 0.12), roughness=0.3),
            DiffuseMaterialSpec(name="floor", albedo=(0.5, 0.5, 0.5)),
            light_mat,
        ],
        objects=[
            ObjectSpec(name="hairball", generator=_gen("hairball", detail=detail), material="hair"),
            ObjectSpec(name="floor", generator=_gen("plane", size=8.0), material="floor",
                       transform=TransformSpec(translate=(0.0, -1.0, 0.0))),
            light,
        ],
        environment=EnvironmentSpec(color=(0.35, 0.42, 0.55)),
    )


def foliage(detail: int) -> SceneSpec:
    """A tree with thousands of leaves on a ground plane, sky environment plus a sun-like point light."""
    return SceneSpec(
        camera=CameraSpec(position=(0.0, 0.2, 3.6), look_at=(0.0, 0.0, 0.0), fov=40.0),
        materials=[
            DiffuseMaterialSpec(name="bark", albedo=(0.3, 0.2, 0.12)),
            DiffuseMaterialSpec(name="leaf", albedo=(0.18, 0.42, 0.1)),
            DiffuseMaterialSpec(name="ground", albedo=(0.45, 0.42, 0.38)),
        ],
        objects=[
            ObjectSpec(name="tree", generator=_gen("foliage", detail=detail)),
            ObjectSpec(name="ground", generator=_gen("plane", size=10.0), material="ground",
                       transform=TransformSpec(translate=(0.0, -1.0, 0.0))),
        ],
        lights=[PointLightSpec(position=(3.0, 6.0, 4.0), intensity=(60.0, 55.0, 45.0))],
        environment=EnvironmentSpec(color=(0.4, 0.5, 0.7)),
    )


def instances(detail: int) -> SceneSpec:
    """A 6 x 6 grid of rotated and scaled copies of three meshes (statue at detail - 1, sphere, box) on a floor, under an
    area light: 36 instances of 3 meshes, 38 instances and 5 BLASes in all."""
    light_mat, light = _ceiling_light(2.0, 3.0, (8.0, 8.0, 8.0))
    materials = [
        PlasticMaterialSpec(name="plastic", albedo=(0.7, 0.2, 0.15), roughness=0.2),
        ConductorMaterialSpec(name="gold", albedo=(1.0, 0.78, 0.34), roughness=0.2),
        DiffuseMaterialSpec(name="chalk", albedo=(0.8, 0.8, 0.75)),
        DiffuseMaterialSpec(name="floor", albedo=(0.4, 0.4, 0.42)),
        light_mat,
    ]
    shapes = [_gen("statue", detail=max(detail - 1, 0)), _gen("sphere", subdivisions=2 + detail), _gen("box", size=(1.0, 1.0, 1.0))]
    mats = ["plastic", "gold", "chalk"]
    objects = []
    n = 6
    for i in range(n):
        for j in range(n):
            k = (i * n + j) % 3
            # Deterministic variety: a golden-angle rotation and a scale that wobbles across the grid.
            s = 0.22 * (1.0 + 0.25 * math.sin(1.7 * i + 0.9 * j))
            x, z = -2.0 + 4.0 * i / (n - 1), -2.0 + 4.0 * j / (n - 1)
            objects.append(ObjectSpec(
                name=f"copy{i}_{j}", generator=shapes[k], material=mats[k],
                transform=TransformSpec(translate=(x, -1.0 + s, z), rotate=(0.0, (137.5 * (i * n + j)) % 360.0, 0.0), scale=s),
            ))
    objects.append(ObjectSpec(name="floor", generator=_gen("plane", size=12.0), material="floor",
                              transform=TransformSpec(translate=(0.0, -1.0, 0.0))))
    objects.append(light)
    return SceneSpec(
        camera=CameraSpec(position=(0.0, 1.8, 5.2), look_at=(0.0, -0.8, 0.0), fov=45.0),
        materials=materials,
        objects=objects,
        environment=EnvironmentSpec(color=(0.25, 0.28, 0.35)),
    )


BUILTIN_SCENES: dict[str, BuiltinScene] = {
    "cornell-statue": BuiltinScene(cornell_statue.__doc__, cornell_statue, 2, MAX_DETAIL["statue"]),
    "hairball": BuiltinScene(hairball.__doc__, hairball, 2, MAX_DETAIL["hairball"]),
    "foliage": BuiltinScene(foliage.__doc__, foliage, 2, MAX_DETAIL["foliage"]),
    # Its statue is at detail - 1 (its sphere, subdivisions 2 + detail <= 9, allows more).
    "instances": BuiltinScene(instances.__doc__, instances, 2, MAX_DETAIL["statue"] + 1),
}


def list_builtins() -> list[tuple[str, str]]:
    """(name, one-line description) of every built-in scene."""
    return [(name, " ".join(b.description.split())) for name, b in BUILTIN_SCENES.items()]


def builtin_spec(query: str, detail: int | None = None) -> SceneSpec:
    """Spec of builtin ``name[?detail=N]``; a ``detail`` argument that differs from the query
    string's is an error (which one was meant?)."""
    name, _, params = query.partition("?")
    builtin = BUILTIN_SCENES.get(name)
    if builtin is None:
        raise SceneError(f"builtin:{name}: unknown built-in scene (known: {', '.join(BUILTIN_SCENES)})")
    options = parse_qs(params, keep_blank_values=True, strict_parsing=False) if params else {}
    unknown = sorted(set(options) - {"detail"})
    if unknown:
        raise SceneError(f"builtin:{query}: unknown option(s) {', '.join(unknown)} (accepted: detail)")
    level = builtin.default_detail
    if len(options.get("detail", ())) > 1:
        raise SceneError(f"builtin:{query}: detail given {len(options['detail'])} times: give it once")
    if "detail" in options:
        try:
            level = int(options["detail"][-1])
        except ValueError:
            raise SceneError(f"builtin:{query}: detail must be an integer") from None
    if detail is not None:
        detail = check_count(given("detail"), detail, minimum=0)
        if "detail" in options and detail != level:
            raise SceneError(f"builtin:{query}: detail given twice ({level} in the name, {detail} as {given('detail')}): give it once")
        level = detail
    if not 0 <= level <= builtin.max_detail:
        raise SceneError(f"builtin:{name}: detail must be in 0..{builtin.max_detail}, got {level}")
    return builtin.build(level)

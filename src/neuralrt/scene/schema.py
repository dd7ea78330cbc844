"""The scene file schema (TOML or JSON), validated by pydantic: every key, its meaning and default.

A scene file has these sections (unknown keys are errors)::

    [camera]                      # perspective pinhole camera
    position = [0, 0, 3.9]        # eye point (world units)
    look_at = [0, 0, 0]           # point the camera looks at
    up = [0, 1, 0]                # up direction (+y up, right-handed)
    fov = 40.0                    # vertical field of view, degrees
    resolution = [256, 256]       # image width, height in pixels

    [[materials]]                 # type picks the kind; each kind accepts only its own keys
    name = "white"                # referenced by objects
    type = "diffuse"              # diffuse | conductor | plastic | emissive
    albedo = [0.8, 0.8, 0.8]      # linear RGB, or an image path (textured; relative to this file)

    [[objects]]
    name = "statue"
    mesh = "meshes/statue.obj"    # a mesh file (relative to this file) ...
    generator = { name = "statue", params = { detail = 2 } }   # ... or a procedural mesh
    model = "statue.nrt"          # optional trained neural model of this object (see ObjectSpec)
    material = "white"            # one scene material for all faces, or per mesh material:
    materials = { body = "white" }  # mesh material name -> scene material name
    transform = { translate = [0, -0.5, 0], rotate = [0, 30, 0], scale = 0.5 }

    [[lights]]                    # point lights
    position = [0, 2, 0]
    intensity = [5, 5, 5]         # radiant intensity, W/sr

    [environment]                 # distant light: a constant colour or a lat-long HDR image
    color = [0.1, 0.1, 0.1]       # or: image = "sky.hdr" (EXR, HDR, PNG, JPG)
    scale = 1.0

    [render]                      # defaults for `render` when the caller gives none
    spp = 16
    max_depth = 5

Emissive objects (materials of type "emissive") are the area lights. Every number must be
finite: ``nan`` and ``inf`` (which TOML and JSON readers accept) are errors naming the key.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, Union

from pydantic import (BaseModel, BeforeValidator, ConfigDict, Field, StrictBool, StrictFloat, StrictInt, StrictStr, field_validator,
                      model_validator)

from ..arguments import given
from ..errors import ConfigError
from ..rays import MAX_CONDITION, MAX_SCALE, MIN_SCALE, Transform

__all__ = [
    "CameraSpec",
    "TransformSpec",
    "DiffuseMaterialSpec",
    "ConductorMaterialSpec",
    "PlasticMaterialSpec",
    "EmissiveMaterialSpec",
    "MaterialSpec",
    "GeneratorSpec",
    "ObjectSpec",
    "PointLightSpec",
    "EnvironmentSpec",
    "RenderSettings",
    "SceneSpec",
    "MAX_RESOLUTION",
    "MAX_RADIANCE",
    "DEFAULT_MATERIAL_NAME",
    "check_resolution",
]

# Every number in a scene is finite: TOML and JSON readers accept nan / inf, and a NaN in a transform
# or camera would only surface deep inside rendering. Text and booleans are not numbers ("40" and true
# would be read as 40.0 and 1); numpy numbers are (pydantic's strict mode would refuse np.int64).
def _not_text_or_bool(value):
    if isinstance(value, (str, bytes, bool)):
        raise ValueError(f"expected a number, got {value!r}")
    return value


NumberOnly = BeforeValidator(_not_text_or_bool)
Real = Annotated[float, NumberOnly]
Count = Annotated[int, NumberOnly]
Finite = Annotated[float, NumberOnly, Field(allow_inf_nan=False)]
NonNegFinite = Annotated[float, NumberOnly, Field(ge=0, allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]
NonNegVec3 = tuple[NonNegFinite, NonNegFinite, NonNegFinite]
# The material every scene has: added (diffuse 0.8, `material_rules.DEFAULT_MATERIAL`) unless the file
# defines one of that name; slots nothing else names get it.
DEFAULT_MATERIAL_NAME = "default"
# Radiance and intensity are rendered in float32: a value near its 3.4e38 limit overflows once scaled by
# a pdf or summed into a light-sampling table (a traceback, or silently black pixels). 1e20 leaves room.
MAX_RADIANCE = 1e20
Radiance = Annotated[float, NumberOnly, Field(ge=0, le=MAX_RADIANCE, allow_inf_nan=False)]
RadianceVec3 = tuple[Radiance, Radiance, Radiance]
# A point light's squared distance to a shading point is computed in float32 (3.4e38): 1e18 per
# coordinate keeps it finite (a light at 1e39 contributed nothing, silently).
MAX_LIGHT_COORDINATE = 1e18
LightCoordinate = Annotated[float, NumberOnly, Field(ge=-MAX_LIGHT_COORDINATE, le=MAX_LIGHT_COORDINATE, allow_inf_nan=False)]


class _Strict(BaseModel):
    # allow_inf_nan=False for every float (bounded ones too): pydantic then reports NaN as
    # "Input should be a finite number" before a bound check could say "less than 180".
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


MAX_RESOLUTION = 16384  # pixels per side
Pixels = Annotated[int, NumberOnly, Field(gt=0, le=MAX_RESOLUTION)]


def check_resolution(resolution) -> tuple[int, int]:
    """A caller's (width, height) override, checked like ``camera.resolution``; a one-line
    `ConfigError` (``resolution: 100000x100000 is over the largest allowed 16384x16384``; ``--res``
    on the command line) if bad."""
    name = given("resolution", flag="--res")
    try:
        w, h = (int(v) if int(v) == v and not isinstance(v, bool) else None for v in resolution)
    except (TypeError, ValueError, OverflowError):
        w = h = None
    if w is None or h is None:
        raise ConfigError(f"{name}: expected two whole numbers (width, height), got {resolution!r}")
    if w < 1 or h < 1:
        raise ConfigError(f"{name}: {w}x{h} must be at least 1x1")
    if max(w, h) > MAX_RESOLUTION:
        raise ConfigError(f"{name}: {w}x{h} is over the largest allowed {MAX_RESOLUTION}x{MAX_RESOLUTION}")
    return w, h


class CameraSpec(_Strict):
    """Perspective camera (looks from ``position`` to ``look_at``)."""

    position: Vec3 = Field((0.0, 0.0, 3.9), description="eye point, world units")
    look_at: Vec3 = Field((0.0, 0.0, 0.0), description="point the camera looks at")
    up: Vec3 = Field((0.0, 1.0, 0.0), description="up direction (must not be parallel to the view direction)")
    fov: Real = Field(40.0, gt=0.0, lt=180.0, description="vertical field of view, degrees")
    resolution: tuple[Pixels, Pixels] = Field((256, 256), description=f"image width, height in pixels (at most {MAX_RESOLUTION} each)")

    @model_validator(mode="after")
    def _not_degenerate(self) -> "CameraSpec":
        fwd = [b - a for a, b in zip(self.position, self.look_at)]
        if math.hypot(*fwd) == 0:
            raise ValueError("camera position and look_at coincide")
        if math.hypot(*self.up) == 0:
            raise ValueError("camera up is zero: give a direction, e.g. [0, 1, 0]")
        cross = (fwd[1] * self.up[2] - fwd[2] * self.up[1], fwd[2] * self.up[0] - fwd[0] * self.up[2], fwd[0] * self.up[1] - fwd[1] * self.up[0])
        if math.hypot(*cross) < 1e-9 * max(math.hypot(*fwd), 1e-30):
            raise ValueError("camera up is parallel to the view direction")
        try:
            Transform.look_at(self.position, self.look_at, self.up)  # its float32 copy must stay finite
        except ConfigError as exc:  # look_at's own checks (above, in other words) or a matrix float32 cannot hold
            message = str(exc)
            raise ValueError(message.removeprefix("look_at: ") if message.startswith("look_at:")
                             else "camera position is beyond the float32 range") from None
        return self


class TransformSpec(_Strict):
    """Object-to-world transform: ``translate @ rotate @ scale`` (scale first), or a full affine ``matrix``.

    ``rotate`` holds Euler angles in degrees about the world x, then y, then z axis. For float32, the
    scale factors must lie within [1e-12, 1e12] and differ at most 8.4e6-fold.
    """

    translate: Vec3 = Field((0.0, 0.0, 0.0), description="offset, world units (applied last)")
    rotate: Vec3 = Field((0.0, 0.0, 0.0), description="Euler angles in degrees about the world x, then y, then z axis")
    scale: Real | tuple[Real, Real, Real] = Field(1.0, description="uniform factor or per-axis [x, y, z] (applied first); "
                                                      f"magnitudes {MIN_SCALE:g} to {MAX_SCALE:g}, per-axis factors at most {MAX_CONDITION:.2g}-fold apart")
    matrix: list[list[Finite]] | None = Field(None, description="4x4 row-major object-to-world matrix: bottom row [0, 0, 0, 1], invertible; "
                                              "replaces translate/rotate/scale")

    @field_validator("scale")
    @classmethod
    def _nonzero_scale(cls, v):
        values = (v,) if isinstance(v, (int, float)) else v
        if any(x == 0 or not math.isfinite(x) for x in values):
            raise ValueError("scale must be finite and non-zero")
        if any(not MIN_SCALE <= abs(x) <= MAX_SCALE for x in values):
            raise ValueError(f"scale must be within {MIN_SCALE:g} to {MAX_SCALE:g} in magnitude, so float32 does not overflow")
        return v

    @field_validator("matrix")
    @classmethod
    def _matrix_shape(cls, m):
        if m is not None and (len(m) != 4 or any(len(r) != 4 for r in m)):
            raise ValueError("matrix must be 4x4 (a list of 4 rows of 4 numbers)")
        return m

    @model_validator(mode="after")
    def _matrix_alone(self) -> "TransformSpec":
        scaled = any(x != 1.0 for x in ((self.scale,) if isinstance(self.scale, (int, float)) else self.scale))
        if self.matrix is not None and (self.translate != (0, 0, 0) or self.rotate != (0, 0, 0) or scaled):  # (scale [1, 1, 1] as 1)
            raise ValueError("give either matrix or translate/rotate/scale, not both")
        return self

    @model_validator(mode="after")
    def _usable(self) -> "TransformSpec":
        # Singular or float32-overflowing matrices fail here, at load time, naming the key, not mid-render.
        try:
            self.to_transform()
        except ConfigError as exc:
            raise ValueError(str(exc).removeprefix("transform: ")) from None
        return self

    def to_transform(self) -> Transform:
        if self.matrix is not None:
            return Transform(self.matrix)
        return Transform.translate_rotate_scale(self.translate, self.rotate, self.scale)


Albedo = Union[NonNegVec3, str]  # linear RGB, or a texture image path


class DiffuseMaterialSpec(_Strict):
    """Lambertian reflector."""

    type: Literal["diffuse"] = Field("diffuse", description="material kind (the default when `type` is omitted)")
    name: str = Field(description="referenced by objects' material / materials")
    albedo: Albedo = Field((0.8, 0.8, 0.8), description="linear RGB reflectance, or a texture image path")


class ConductorMaterialSpec(_Strict):
    """Rough metal (GGX); ``albedo`` is the reflectance at normal incidence (Schlick F0)."""

    type: Literal["conductor"] = Field("conductor", description="material kind")
    name: str = Field(description="referenced by objects' material / materials")
    albedo: Albedo = Field((0.9, 0.9, 0.9), description="reflectance at normal incidence (Schlick F0), RGB or texture path")
    roughness: Real = Field(0.1, gt=0.0, le=1.0, description="GGX alpha (values below 1e-3 act as 1e-3)")


class PlasticMaterialSpec(_Strict):
    """Diffuse base (``albedo``) under a rough dielectric coat (GGX alpha ``roughness``, index ``ior``)."""

    type: Literal["plastic"] = Field("plastic", description="material kind")
    name: str = Field(description="referenced by objects' material / materials")
    albedo: Albedo = Field((0.5, 0.5, 0.5), description="diffuse base colour, RGB or texture path")
    roughness: Real = Field(0.1, gt=0.0, le=1.0, description="GGX alpha of the coat (values below 1e-3 act as 1e-3)")
    ior: Real = Field(1.5, gt=1.0, le=4.0, description="index of refraction of the coat")


class EmissiveMaterialSpec(_Strict):
    """Area light: emits ``emission`` (radiance) from its front face; reflects diffusely with ``albedo``."""

    type: Literal["emissive"] = Field("emissive", description="material kind")
    name: str = Field(description="referenced by objects' material / materials")
    emission: RadianceVec3 = Field(description="emitted radiance (linear RGB), from the front face only")
    albedo: Albedo = Field((0.0, 0.0, 0.0), description="diffuse reflectance of the emitter's surface")


def _default_material_type(value):
    """A material table without ``type`` is diffuse (the discriminator alone would reject it)."""
    if isinstance(value, dict) and "type" not in value:
        return {"type": "diffuse", **value}
    return value


MaterialSpec = Annotated[
    Union[DiffuseMaterialSpec, ConductorMaterialSpec, PlasticMaterialSpec, EmissiveMaterialSpec],
    Field(discriminator="type"),
    BeforeValidator(_default_material_type),
]


class GeneratorSpec(_Strict):
    """A procedural mesh: ``neuralrt.geometry.procedural.make_procedural(name, **params)``."""

    name: str = Field(description="statue, hairball, foliage, box, plane, sphere or cornell_box")
    params: dict[str, Union[bool, int, float, str, list[float]]] = Field(
        default_factory=dict, description="keyword arguments of the generator, e.g. { detail = 3 }")


class ObjectSpec(_Strict):
    """One placed object. Meshes (file or generator) used by several objects are loaded and built once.

    ``model``: path of a trained neural model (.nrt) of this object; when set, the object's rays
    are answered by the model, and if the mesh is also given the exact mesh still answers camera
    rays (hybrid rendering).
    """

    name: str = Field("", description="label (used by conversion to select objects)")
    mesh: str | None = Field(None, description="mesh file (OBJ, PLY, OFF, STL, glTF), relative to the scene file")
    gltf_mesh: Annotated[StrictInt, Field(ge=0)] | Annotated[str, Field(min_length=1)] | None = Field(
        None, description="one mesh of the glTF `mesh` file (its index, or its name where one mesh has it), in its own "
        "space; none: the whole file, placed by its nodes (`neuralrt import` writes these)")
    generator: GeneratorSpec | None = Field(None, description="procedural mesh instead of a file")
    model: str | None = Field(None, description="trained neural model (.nrt) answering this object's rays (objects naming one file, or byte-identical copies of it, share one model)")
    transform: TransformSpec = Field(default_factory=TransformSpec, description="object-to-world transform")
    material: str | None = Field(None, description="scene material for every face")
    materials: dict[str, str] = Field(default_factory=dict, description="mesh material name -> scene material name "
                                      "(unmapped slots use the scene material of the same name, else 'default')")
    inference: dict[str, StrictBool | StrictInt | StrictFloat | StrictStr | None] = Field(
        default_factory=dict, description="the model's inference settings changed for this object, e.g. N-BVH's "
        "{ lod = 2 } (keys of its method's inference section, docs/config.md, but storage_precision; the trained "
        "parameters are the same: instances share them)")

    @field_validator("transform", mode="before")
    @classmethod
    def _transform_object(cls, v):
        from ..rays import Transform  # (from Python, load_dict takes the API's Transform too)

        return {"matrix": v.tolist()} if isinstance(v, Transform) else v

    @model_validator(mode="after")
    def _one_source(self) -> "ObjectSpec":
        if self.mesh is not None and self.generator is not None:
            raise ValueError("give either mesh or generator, not both")
        if self.mesh is None and self.generator is None and self.model is None:
            raise ValueError("an object needs a mesh, a generator or a model")
        if self.gltf_mesh is not None and self.mesh is None:
            raise ValueError("gltf_mesh chooses a mesh of the glTF file that mesh names: give mesh too")
        if self.material is not None and self.materials:
            raise ValueError("give either material or materials, not both")
        if self.inference and self.model is None:
            raise ValueError("inference changes how a model answers: give model too")
        return self


class PointLightSpec(_Strict):
    """Isotropic point light of radiant intensity ``intensity`` (W/sr)."""

    type: Literal["point"] = Field("point", description="light kind")
    position: tuple[LightCoordinate, LightCoordinate, LightCoordinate] = Field(
        description=f"world position (each coordinate within +-{MAX_LIGHT_COORDINATE:g})")
    intensity: RadianceVec3 = Field(description="radiant intensity, W/sr (linear RGB)")


class EnvironmentSpec(_Strict):
    """Distant lighting: constant ``color`` or a lat-long ``image`` (importance sampled), times ``scale``."""

    color: RadianceVec3 | None = Field(None, description="constant radiance (linear RGB)")
    image: str | None = Field(None, description="lat-long image (EXR, HDR, PNG, JPG), relative to the scene file; "
                              "its centre is seen looking down -z, row 0 is straight up")
    scale: Radiance = Field(1.0, description="multiplies the colour or image")
    rotate_y: Finite = Field(0.0, description="turns the image about +y, degrees (right-handed)")

    @model_validator(mode="after")
    def _one_source(self) -> "EnvironmentSpec":
        if (self.color is None) == (self.image is None):
            raise ValueError("give exactly one of color or image")
        if self.color is not None and max(self.color) * self.scale > MAX_RADIANCE:
            raise ValueError(f"color times scale is above {MAX_RADIANCE:g} (rendering in float32 would overflow)")
        return self


MAX_SPP = 1 << 20  # a scene's, a render call's and the CLI's bound on samples per pixel
MAX_DEPTH = 256  # ... and on bounces


class RenderSettings(_Strict):
    """Render defaults stored with the scene (callers may override)."""

    spp: Count = Field(16, gt=0, le=MAX_SPP, description="samples per pixel")
    max_depth: Count = Field(5, ge=1, le=MAX_DEPTH, description="maximum number of bounces (1 = direct lighting)")


class SceneSpec(_Strict):
    """A whole scene file."""

    camera: CameraSpec = Field(default_factory=CameraSpec, description="the camera")
    materials: list[MaterialSpec] = Field(default_factory=list, description="scene materials ('default', diffuse 0.8, is added if absent)")
    objects: list[ObjectSpec] = Field(min_length=1, description="placed objects (at least one)")
    lights: list[PointLightSpec] = Field(default_factory=list, description="point lights (area lights are emissive objects)")
    environment: EnvironmentSpec | None = Field(None, description="distant light; none = black")
    render: RenderSettings = Field(default_factory=RenderSettings, description="render defaults")

    def with_paths(self, fn) -> "SceneSpec":
        """A copy (sharing nothing with ``self``) with every file path (textures, meshes, models,
        environment image) mapped by ``fn``."""
        spec = self.model_copy(deep=True)
        spec.map_paths_in_place(fn)
        return spec

    def map_paths_in_place(self, fn) -> None:
        """`with_paths` on this spec itself (for a spec no one else holds: no copy)."""
        for m in self.materials:
            if isinstance(m.albedo, str):
                m.albedo = fn(m.albedo)
        for obj in self.objects:
            if obj.mesh is not None:  # (an assignment re-validates the object: only where there is a path)
                obj.mesh = fn(obj.mesh)
            if obj.model is not None:
                obj.model = fn(obj.model)
        if self.environment is not None and self.environment.image is not None:
            self.environment.image = fn(self.environment.image)

    def reference_errors(self) -> list[tuple[str, str]]:
        """(key path, problem) for duplicate material names and references to unknown materials."""
        errors: list[tuple[str, str]] = []
        names: dict[str, int] = {}
        for i, m in enumerate(self.materials):
            if m.name in names:
                errors.append((f"materials.{i}.name", f"duplicate material name {m.name!r} (also materials.{names[m.name]})"))
            names.setdefault(m.name, i)
        known = set(names) | {DEFAULT_MATERIAL_NAME}  # the implicit diffuse material is always there
        listed = [*names, *([DEFAULT_MATERIAL_NAME] if DEFAULT_MATERIAL_NAME not in names else [])]
        choices = ", ".join(map(repr, listed[:12])) + (f", ... ({len(listed)})" if len(listed) > 12 else "")
        for i, obj in enumerate(self.objects):
            if obj.material is not None and obj.material not in known:
                errors.append((f"objects.{i}.material", f"unknown material {obj.material!r} (the scene's: {choices})"))
            for slot, target in obj.materials.items():
                if target not in known:
                    errors.append((f"objects.{i}.materials.{slot}", f"unknown material {target!r} (the scene's: {choices})"))
        return errors

"""Generates docs/scenes.md, the scene-file reference, from the pydantic schema and the built-ins.

    python -m neuralrt.scene.schemadoc [path]      # default: docs/scenes.md of the source tree
                                                   # (an installed copy, with none: printed)

A test compares the committed file with `scene_reference()`, so the page stays true to the code.
"""

from __future__ import annotations

import inspect
import json
from pathlib import Path

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from ..geometry.procedural import GENERATORS
from .builtins import BUILTIN_SCENES
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
    RenderSettings,
    SceneSpec,
    TransformSpec,
)

__all__ = ["scene_reference", "main"]

_SECTIONS: list[tuple[str, type[BaseModel]]] = [
    ("top level", SceneSpec),
    ("`[camera]`", CameraSpec),
    ("`[[materials]]` with `type = \"diffuse\"`", DiffuseMaterialSpec),
    ("`[[materials]]` with `type = \"conductor\"`", ConductorMaterialSpec),
    ("`[[materials]]` with `type = \"plastic\"`", PlasticMaterialSpec),
    ("`[[materials]]` with `type = \"emissive\"`", EmissiveMaterialSpec),
    ("`[[objects]]`", ObjectSpec),
    ("`objects.transform`", TransformSpec),
    ("`objects.generator`", GeneratorSpec),
    ("`[[lights]]`", PointLightSpec),
    ("`[environment]`", EnvironmentSpec),
    ("`[render]`", RenderSettings),
]

_INTRO = """# Scene file reference

Generated from `neuralrt/scene/schema.py` by `python -m neuralrt.scene.schemadoc` (a test keeps it
current). Scene files are TOML or JSON with these keys; an unknown key or a bad value is an error
naming the file and the key path (`scene.toml: objects.2.transform.scale: scale must be finite and
non-zero`). Paths (meshes, models, textures, environment images) resolve relative to the scene file.
Objects that use the same mesh file, or the same generator with the same parameters, share one
accelerator (instancing). `neuralrt.scene.scene.save_scene(spec, path)` writes a spec back (`spec`:
a `SceneSpec`, e.g. `neuralrt.scene.loader.load_scene_spec(path)[0]`).
Every number must be finite (`nan` / `inf` are errors naming the key).

From Python, `neuralrt.scene.loader.load_dict(d)` builds a scene from a dict with these same keys,
validated at once; there an object's `mesh` may also be a `neuralrt.Mesh`, its `model` a
loaded model (any BLAS with `material_names`) and its `transform` a `neuralrt.Transform`. A
model's material slots map to scene materials like a mesh's: the object's `material`, else its `materials` map, else the scene material of the
same name, else `default`. `load_scene(..., primary="neural")` / `render --primary neural`
builds no mesh BVH for objects with a model (camera rays go to the model too).

Conventions: right-handed, +y up; the camera looks down its -z axis. Colours are linear RGB.
Images (textures, environment maps) in PNG or JPEG are sRGB, decoded to linear (a texel of 128 is
albedo 0.216); EXR and HDR are linear. Textures repeat outside [0, 1] and are filtered bilinearly,
so an edge texel blends with the opposite edge's; an image's alpha is not read. A colour PNG is read
at 8 bits per channel (a 16-bit one with a warning: save it as EXR), a grey one at its depth; a
JPEG's EXIF orientation is not applied; an EXR is read as its display window (outside its data
window: black).
A surface's colour is its scene material's `albedo` times the mesh's own colour at the hit (MTL
`Kd` and `map_Kd`, glTF base colour, vertex colours; white where the mesh has none, as the
generators' meshes): give one or the other. A neural object's own colour is what its model
learned; it carries no UVs, so a texture `albedo` on it shows one texel (a warning says so).
Shading normals are the mesh's vertex normals, turned by a tangent-space normal map (green up):
a glTF material's `normalTexture`, or the one an OBJ's MTL names (`norm`, else `map_Bump` or
`bump`, which Blender and most exporters write for a normal map; `-bm` scales it as glTF's `scale`
does; a statement with `-o`, `-s`, `-t` or `-imfchan` is left out with a warning). Tangents are
built from the UVs as `neuralrt.geometry.tangents` says, since trimesh reads no `TANGENT`
attribute. glTF's normal-map `scale` and `KHR_texture_transform` (offset, rotation, scale of a
base-colour or normal map's UVs), which trimesh drops, are read from the file and applied, per
material name; a `texCoord` other than 0 is a warning (the first UV set maps every image). A texel
that points into the surface or is far from unit length (a neutral grey) keeps the interpolated
normal; a grey image (most likely a height map: bump mapping is not done), or a map pointing into
the surface on average, is left out with a warning, as is an image on a mesh without UVs. A model
of such a mesh learns the turned normals; `neuralrt info MESH` lists the normal-mapped materials.
Mesh files are whatever trimesh reads (OBJ + MTL, glTF / GLB, PLY, OFF, STL), merged into one
mesh in the file's world space (glTF node transforms applied). A file's own normals are kept, in
every part (else smooth angle-weighted ones are computed; flat ones for glTF, as its spec says). MTL `Kd` / `map_Kd` and PLY or OBJ
vertex colours are sRGB; glTF's `baseColorFactor` (as written, where trimesh keeps 8 bits) and
`COLOR_0` are linear, its texture sRGB. OFF colours (`COFF` vertex colours, colours after a
triangle's corners; 0-255 or 0-1) are read as sRGB, which trimesh's OFF reader leaves out, as are
OBJ `v x y z r g b` colours in a file with materials, which trimesh drops.
OBJ and MTL text is read as the file means where trimesh would misread it (relative face indices,
comments after values, a byte-order mark, one-value colours, `map_Kd` options, several files on
one `mtllib` line; faces of five corners or more split by ear clipping, where trimesh's fan
covered a concave one's notches), and a texture or buffer not found as named is looked for percent-decoded (glTF
URIs), with `/` for `\\`, by its last part beside the mesh, and in another letter case.
What a file holds but is not read is a warning naming it: emission (MTL `Ke`, glTF
`emissiveFactor`; give the slot an emissive scene material to make it a light, and the warning
goes), glTF skins, morph
weights, triangle fans, and positions or UVs stored as normalised integers in more than one way
(stored so throughout, as gltfpack and KHR_mesh_quantization write them, they are read as meant,
and unnamed materials' texture transforms are applied: a gltfpack file reads as its source);
so is an OBJ `usemtl` naming no material (its
faces render white), and PLY colours or UVs in properties trimesh does not read (`diffuse_red`,
`texture_s`). A glTF that needs Draco or meshopt compression (gltfpack `-c`, `-cc`), or whose
primitives use sparse accessors, is an error. GPU instances (`EXT_mesh_gpu_instancing`, gltfpack
`-mi`) are read as nodes: each instance a copy in the merged mesh. A material's base-colour and normal maps placed by different texture transforms share
one UV set here: the base colour's places both (a warning says the normal map is misplaced).

**A glTF scene** (`neuralrt import city.glb -o city.toml`, `neuralrt.api.import_scene`) becomes a
scene file instead of one merged mesh: an object per node that draws a mesh (GPU instances too),
naming that mesh of the file (`gltf_mesh`: the mesh alone, in its own space) and placed by the
node's world `matrix`, so a mesh many nodes draw is one accelerator, and one model once
converted (meshes naming the same accessors, as trimesh writes one per node, are one). The scene
also gets the file's first perspective camera (256 pixels high, its aspect ratio), its `KHR_lights_punctual` lights (candela / 683 lm/W as W/sr; a spot light without its
cone; a directional light as a point light 100 scene radii away giving the same irradiance), and
a scene material per named glTF material: emissive where it emits (`emissiveFactor` x
`KHR_materials_emissive_strength`), else a conductor (`metallicFactor` >= 0.5) or a plastic
(glTF's dielectric), GGX alpha = `roughnessFactor`^2, albedo white (the mesh's base colour is the
colour); the other meshes take the scene's `default`, diffuse 0.8. A file without lights is lit
and framed as a lone mesh is (`neuralrt render mesh.glb`), so a file without materials renders as
it does alone; a file with named materials renders as they say, where alone every mesh is diffuse
0.8 times its colours. What is not read (orthographic cameras, unnamed emissive materials,
a node whose matrix cannot place a mesh, cut-outs by alpha: `alphaMode` MASK or BLEND surfaces
render opaque, a leaf as its whole quad, also when the file renders alone) is a warning naming it (`neuralrt.scene.gltf_import`).
Rendering a glTF alone warns of what it leaves unused (copies of meshes several nodes draw,
cameras, lights) and names the `neuralrt import` command that keeps them. A `gltf_mesh` is read
from its own bytes (`neuralrt.geometry.gltf_pack`: its accessors, views and images only): in a
.glb of 200 distinct meshes (1.6 MB) a mesh reads in 1.8 ms, all 200 in 1.7x the time of one read
of the whole file, the file imports in 0.55 s and its scene loads in 0.86 s, against 15.6 ms,
13.4x, 3.24 s and 3.51 s when each mesh read the whole file (`benchmarks/bench_gltf_mesh_reads.py`;
`results/gltf_mesh_reads.json`, `gltf_mesh_reads_before.json`); a buffer file that only some
meshes use fails those alone, by name.
Emissive objects are the area lights (sampled by area x luminance); they emit from the side their
triangles' normals face, and cannot be neural models.

```toml
[camera]
position = [0, 0, 3.9]
look_at = [0, 0, 0]
fov = 40
resolution = [256, 256]

[[materials]]
name = "white"
type = "diffuse"
albedo = [0.73, 0.73, 0.73]

[[materials]]
name = "light"
type = "emissive"
emission = [17, 12, 4]

[[objects]]
generator = { name = "cornell_box" }        # its mesh materials "white", "red", "green", "light"
materials = { red = "white", green = "white" }

[[objects]]
name = "statue"
mesh = "meshes/statue.ply"
material = "white"
transform = { translate = [0, -0.4, 0], rotate = [0, 25, 0], scale = 0.6 }

[environment]
image = "sky.hdr"
scale = 0.5
```
"""


def _default(field) -> str:
    if field.default is PydanticUndefined and field.default_factory is None:
        return "required"
    if field.default_factory is not None:
        value = field.default_factory()
        if isinstance(value, BaseModel):
            return "(section)"
        return f"`{json.dumps(value)}`"
    value = field.default
    if value is None:
        return "none"
    if isinstance(value, tuple):
        value = list(value)
    return f"`{json.dumps(value)}`"


_BOUNDS = (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))


def _bounds(metadata) -> list[str]:
    """``["> 0", "< 180"]`` from a field's or an element type's annotated constraints."""
    return [f"{sign} {getattr(m, attr):g}" for m in metadata for attr, sign in _BOUNDS if getattr(m, attr, None) is not None]


def _range(field) -> str:
    """The allowed values the schema enforces on a key (its own bounds, or each element's), derived,
    so the page cannot drift from the checks."""
    from types import UnionType
    from typing import Annotated, Union, get_args, get_origin

    own = _bounds(field.metadata)
    if own:
        return ", ".join(own)
    elements, alone = set(), set()
    for arg in get_args(field.annotation):  # a tuple or list of bounded numbers (Vec3 of NonNegFinite, ...)
        for inner in (arg, *get_args(arg)):
            if get_origin(inner) is Annotated:  # (pydantic's Field(...) there holds its bounds in .metadata)
                constraints = [m for a in get_args(inner)[1:] for m in getattr(a, "metadata", [a])]
                # (a bounded value that is one of a union's kinds, as gltf_mesh's index, is no element)
                (alone if inner is arg and get_origin(field.annotation) in (Union, UnionType) else elements).add(
                    ", ".join(_bounds(constraints)))
    elements.discard("")
    alone.discard("")
    return " or ".join(sorted(alone) + ([f"each {' or '.join(sorted(elements))}"] if elements else []))


def scene_reference() -> str:
    """The reference page as Markdown."""
    lines = [_INTRO]
    for title, model in _SECTIONS:
        lines.append(f"## {title}\n")
        doc = (model.__doc__ or "").strip().split("\n\n")[0].replace("\n", " ")
        lines.append(f"{doc}\n")
        lines.append("| key | default | allowed | meaning |")
        lines.append("|---|---|---|---|")
        for name, field in model.model_fields.items():
            lines.append(f"| `{name}` | {_default(field)} | {_range(field)} | {field.description or ''} |")
        lines.append("")
    lines.append("## Generators\n")
    lines.append("`generator = { name = NAME, params = { ... } }`: a procedural mesh, built in object space "
                 "(`neuralrt.geometry.procedural`; the CLI's `procedural:NAME[:DETAIL]`).\n")
    lines.append("| name | params (defaults) | mesh |")
    lines.append("|---|---|---|")
    for name, make in GENERATORS.items():
        params = ", ".join(f"`{p.name} = {p.default!r}`" for p in inspect.signature(make).parameters.values()
                           if p.default is not inspect.Parameter.empty)
        what = " ".join((make.__doc__ or "").strip().split("\n\n")[0].split())
        lines.append(f"| `{name}` | {params or 'none'} | {what} |")
    lines.append("")
    lines.append("## Built-in scenes\n")
    lines.append("`builtin:<name>` or `builtin:<name>?detail=N` (or `load_scene(..., detail=N)`) needs no files; "
                 "`detail` is the procedural meshes' detail level (triangle counts: `neuralrt.geometry.procedural`).\n")
    lines.append("| name | default detail | scene |")
    lines.append("|---|---|---|")
    for name, b in BUILTIN_SCENES.items():
        lines.append(f"| `{name}` | {b.default_detail} | {' '.join(b.description.split())} |")
    lines.append("")
    return "\n".join(lines)


def default_path() -> Path:
    return Path(__file__).resolve().parents[3] / "docs" / "scenes.md"


def _in_source_tree() -> bool:
    """Is this module in a checkout's ``src/neuralrt/scene`` (so `default_path` is our docs page),
    not in an install whose third parent is some other folder (``pip install --target ~/libs``)?"""
    here = Path(__file__).resolve()
    return here.parents[2].name == "src" and (here.parents[3] / "pyproject.toml").is_file() and default_path().parent.is_dir()


def main(argv: list[str] | None = None) -> None:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m neuralrt.scene.schemadoc",
                                     description="write the scene file reference (docs/scenes.md)")
    parser.add_argument("output", nargs="?", type=Path, help=f"default: {default_path()} in a source tree; "
                        "printed where there is none (an installed copy)")
    path = parser.parse_args(argv).output
    if path is None and not _in_source_tree():  # (site-packages: no docs folder of ours beside it)
        print(scene_reference(), end="")
        return
    path = path or default_path()
    path.write_text(scene_reference(), encoding="utf-8")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

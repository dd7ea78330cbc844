"""The same scene rendered by Mitsuba 3's path tracer, as an independent check of our integrator.

`reference_render(scene, spp)` hands a runtime `Scene` (exact meshes) to Mitsuba's ``scalar_rgb``
variant: the same camera (vertical field of view, box-filtered pixels), triangles in world space
with their vertex normals, one mesh per (object, scene material), two-sided diffuse BSDFs, area
lights on emissive faces (front side only), point lights and a constant environment. Mitsuba's
``max_depth`` counts the camera segment, ours the bounces, so it gets ours + 1. Emitters go
without vertex normals (ours emit and are sampled by the triangle's normal, Mitsuba's by the
interpolated one), wound so that their face normal is ours under mirroring transforms; so an
emitter's own reflection is flat-shaded there.

Where the two renderers' conventions differ, scenes should not go (measured by a trial: the
differences are large and local, not noise): a light inside a closed mesh of few triangles with
smooth normals (Mitsuba takes light samples above the shading hemisphere though below the
surface, and lets them through: ours gives 0), and surfaces seen from behind their shading normal
while in front of the triangle (ours shades with the triangle's normal there, Mitsuba's two-sided
BSDF with the reversed shading normal: darker).

Only what both renderers define the same way is exported: diffuse and emissive materials with
constant colours. Conductor and plastic (ours: Schlick F0 and a GGX coat over a diffuse base;
Mitsuba's roughconductor and roughplastic are other models), textures, normal maps, vertex
colours, neural objects and environment images are refused with one line naming what
(`SceneError`).
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import SceneError

__all__ = ["reference_render", "mitsuba_reference_available"]

_VARIANT = "scalar_rgb"  # runs on every CPU (the LLVM variant needs a matching LLVM build)


def mitsuba_reference_available() -> bool:
    """Whether Mitsuba 3 with its ``scalar_rgb`` variant can be imported (the ``[gpu]`` extra)."""
    try:
        import mitsuba as mi
    except ImportError:
        return False
    return _VARIANT in mi.variants()


def reference_render(scene, spp: int, max_depth: int | None = None, seed: int = 0) -> np.ndarray:
    """Mitsuba 3's render of ``scene`` ([H, W, 3] float32 linear RGB, row 0 at the top), at ``spp``
    samples per pixel and ``max_depth`` bounces (default: the scene's)."""
    import mitsuba as mi

    if not mitsuba_reference_available():
        raise SceneError("a Mitsuba reference render needs mitsuba 3 with its scalar_rgb variant (pip install mitsuba: the gpu extra)")
    mi.set_variant(_VARIANT)
    depth = scene.settings.max_depth if max_depth is None else int(max_depth)
    description = {"type": "scene", "integrator": {"type": "path", "max_depth": depth + 1, "hide_emitters": False},
                   "sensor": _sensor(mi, scene.camera, spp, seed)}
    description.update(_shapes(mi, scene))
    description.update(_lights(scene))
    image = mi.render(mi.load_dict(description), spp=int(spp), seed=int(seed))
    return np.array(image, dtype=np.float32)[..., :3]


def _sensor(mi, camera, spp: int, seed: int) -> dict:
    m = camera.camera_to_world.tolist()
    eye = np.array([row[3] for row in m[:3]])
    forward = -np.array([row[2] for row in m[:3]])  # our camera looks down its -z
    up = np.array([row[1] for row in m[:3]])
    return {
        "type": "perspective", "fov": camera.fov_y_degrees, "fov_axis": "y",
        "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=(eye + forward).tolist(), up=up.tolist()),
        "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
        "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},  # ours: each sample counts for the pixel it falls in
    }


def _shapes(mi, scene) -> dict:
    from ..accel.mesh_blas import MeshBLAS
    from ..render.materials import MaterialKind

    table = scene.materials
    out = {}
    for k, inst in enumerate(scene.accel.instances):
        if not isinstance(inst.blas, MeshBLAS):
            raise SceneError(f"instance {k} ({inst.name}): a neural object has no mesh for Mitsuba; render it exactly")
        mesh = inst.blas.mesh
        if mesh.vertex_colors is not None:
            raise SceneError(f"instance {k} ({inst.name}): vertex colours are not exported to Mitsuba")
        vertices = inst.transform.apply_points(torch.from_numpy(mesh.vertices)).numpy()
        mirrored = np.linalg.det(np.asarray(inst.transform.tolist())[:3, :3]) < 0
        normals = inst.transform.apply_normals(torch.from_numpy(mesh.vertex_normals)).numpy()
        for slot, material in enumerate(inst.material_map.tolist()):
            faces = mesh.faces[mesh.face_material_ids == slot]
            if not len(faces):
                continue
            slot_material = mesh.materials[slot]
            if slot_material.texture is not None or table.textures[material] is not None:
                raise SceneError(f"instance {k} ({inst.name}): textures are not exported to Mitsuba")
            if slot_material.normal_map is not None:
                raise SceneError(f"instance {k} ({inst.name}): normal maps are not exported to Mitsuba")
            kind = MaterialKind(int(table.kind[material]))
            if kind not in (MaterialKind.DIFFUSE, MaterialKind.EMISSIVE):
                raise SceneError(f"material {table.names[material]!r}: {kind.name.lower()} is not the same model in "
                                 "Mitsuba; the reference takes diffuse and emissive materials")
            albedo = table.albedo[material].cpu().numpy() * np.asarray(slot_material.base_color, np.float32).reshape(-1)[:3]
            props = mi.Properties()
            props["bsdf"] = mi.load_dict({"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": _rgb(albedo)}})
            emitter = kind == MaterialKind.EMISSIVE
            if emitter:
                props["emitter"] = mi.load_dict({"type": "area", "radiance": _rgb(table.emission[material].cpu().numpy())})
            # An emitter goes without vertex normals: Mitsuba's area light faces (and weights its
            # samples by) the interpolated normal, ours the triangle's. Its triangles' winding must
            # then give our face normal, which a mirroring transform reverses.
            if emitter and mirrored:
                faces = faces[:, ::-1]
            out[f"instance{k}_slot{slot}"] = _mesh(mi, f"instance{k}_slot{slot}", vertices, None if emitter else normals,
                                                   faces, props)
    return out


def _mesh(mi, name: str, vertices: np.ndarray, normals: np.ndarray | None, faces: np.ndarray, props):
    used, local = np.unique(faces, return_inverse=True)  # only this slot's vertices
    mesh = mi.Mesh(name, len(used), len(faces), props=props, has_vertex_normals=normals is not None)
    params = mi.traverse(mesh)
    params["vertex_positions"] = np.ascontiguousarray(vertices[used], np.float32).ravel()
    if normals is not None:
        params["vertex_normals"] = np.ascontiguousarray(normals[used], np.float32).ravel()
    params["faces"] = local.astype(np.uint32).ravel()
    params.update()
    return mesh


def _lights(scene) -> dict:
    out = {}
    points = scene.lights.points
    if points is not None:
        for i, (position, intensity) in enumerate(zip(points.positions.tolist(), points.intensities.tolist())):
            out[f"point{i}"] = {"type": "point", "position": position, "intensity": _rgb(intensity)}
    env = scene.lights.environment
    if env is not None:
        if not env.is_constant:
            raise SceneError("an environment image is not exported to Mitsuba; the reference takes a constant colour")
        out["environment"] = {"type": "constant", "radiance": _rgb(env.color.cpu().numpy())}
    return out


def _rgb(values) -> dict:
    return {"type": "rgb", "value": [float(v) for v in np.asarray(values).reshape(-1)[:3]]}


def agreement(ours: list[np.ndarray], reference: list[np.ndarray], block: int = 4) -> dict:
    """How two renderers' images of one scene agree, given each renderer's images at several seeds
    ([H, W, 3] each, at least 2 a side): differences in units of their seed-to-seed standard error.

    - ``mean_relative_difference``: (ours - reference) / reference over the whole image's mean;
      ``mean_z``: that difference over its standard error.
    - ``block_chi2``: the mean over ``block`` x ``block`` pixel blocks and channels of z squared
      (each block's error from its own seed spread): near 1 when the two differ by noise alone, a
      little above with few seeds (with 8 a side, ~1.4: Student's t with 7 degrees of freedom).
    """
    ours, reference = np.stack(ours).astype(np.float64), np.stack(reference).astype(np.float64)
    if len(ours) < 2 or len(reference) < 2:
        raise ValueError("agreement needs at least 2 images (seeds) from each renderer")
    n, h, w, _ = ours.shape
    hb, wb = h // block, w // block
    if hb == 0 or wb == 0:  # (no whole block: the statistics would be NaN)
        raise ValueError(f"agreement needs images of at least {block}x{block} pixels (block), got {w}x{h}")

    def blocks(images):
        return images[:, :hb * block, :wb * block].reshape(len(images), hb, block, wb, block, 3).mean(axis=(2, 4))

    def standard_error(values):  # of the mean over seeds
        return values.var(axis=0, ddof=1) / len(values)

    image_o, image_r = ours.mean(axis=(1, 2, 3)), reference.mean(axis=(1, 2, 3))
    diff = image_o.mean() - image_r.mean()
    mean_se = np.sqrt(standard_error(image_o) + standard_error(image_r))
    bo, br = blocks(ours), blocks(reference)
    # Where neither varies (sky seen directly, a light's face) the two differ by float32 rounding
    # in their sums: an error floor of 1e-5 of the block's level stands for it.
    rounding = (1e-5 * np.maximum(np.abs(bo.mean(0)), np.abs(br.mean(0)))) ** 2
    block_var = np.maximum(standard_error(bo) + standard_error(br), np.maximum(rounding, 1e-30))
    z2 = (bo.mean(0) - br.mean(0)) ** 2 / block_var
    return {
        "ours_mean": float(image_o.mean()), "reference_mean": float(image_r.mean()),
        "mean_relative_difference": float(diff / image_r.mean()), "mean_z": float(diff / mean_se) if mean_se > 0 else 0.0,
        "block_chi2": float(z2.mean()), "blocks": int(hb * wb * 3), "seeds": [len(ours), len(reference)],
    }

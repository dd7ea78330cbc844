"""How a scene object's material slots become scene materials: the one place for these rules.

- The scene's material table is the spec's ``materials`` in order, plus an implicit ``default``
  (diffuse, albedo 0.8) appended when none is named so (`scene_materials`, `material_index`).
- Each object has material *slots*: its mesh's materials, or a model's `material_names` (what
  ``Hits.material_id`` indexes). A slot gets the object's ``material`` when set; else its entry in
  the object's ``materials`` map; else the scene material of the same name; else ``default``
  (`scene_material_for`, `material_map`).
- An object is an area light when any slot gets a material that emits: type ``emissive`` with
  a non-zero emission (`emits`, `is_emissive`). Area lights stay exact meshes. The slot names an
  object makes lights (`lit_slots`) are the ones whose emission in the mesh file is not "unread".
"""

from __future__ import annotations

from .schema import DEFAULT_MATERIAL_NAME, DiffuseMaterialSpec, EmissiveMaterialSpec, ObjectSpec, SceneSpec

__all__ = ["DEFAULT_MATERIAL", "scene_materials", "material_index", "scene_material_for", "material_map", "emits", "is_emissive",
           "lit_slots"]

DEFAULT_MATERIAL = DiffuseMaterialSpec(name=DEFAULT_MATERIAL_NAME, albedo=(0.8, 0.8, 0.8))  # for slots nothing else names


def scene_materials(spec: SceneSpec) -> list:
    """The scene's material specs in table order (``default`` appended when absent)."""
    specs = list(spec.materials)
    if all(m.name != DEFAULT_MATERIAL_NAME for m in specs):
        specs.append(DEFAULT_MATERIAL)
    return specs


def material_index(spec: SceneSpec) -> dict[str, int]:
    """Scene material name -> index in `scene_materials`."""
    return {m.name: i for i, m in enumerate(scene_materials(spec))}


def scene_material_for(obj: ObjectSpec, slot: str, index: dict[str, int]) -> str:
    """The scene material name a slot named ``slot`` of ``obj`` gets (``index``: `material_index`)."""
    if obj.material is not None:
        return obj.material
    if slot in obj.materials:
        return obj.materials[slot]
    return slot if slot in index else DEFAULT_MATERIAL_NAME


def material_map(obj: ObjectSpec, slot_names: list[str], index: dict[str, int]) -> list[int]:
    """Scene material index of each slot, in slot order (the object's instance material map)."""
    return [index[scene_material_for(obj, slot, index)] for slot in slot_names]


def emits(material) -> bool:
    """Whether a material spec is a light: type emissive with some non-zero emission."""
    return isinstance(material, EmissiveMaterialSpec) and max(material.emission) > 0


def is_emissive(spec: SceneSpec, obj: ObjectSpec, slot_names: list[str]) -> bool:
    """Whether any of ``obj``'s slots (named ``slot_names``) gets a material that emits."""
    specs = scene_materials(spec)
    return any(emits(specs[i]) for i in material_map(obj, slot_names, material_index(spec)))


class _EverySlot:
    def __contains__(self, slot) -> bool:
        return True


def lit_slots(spec: SceneSpec, obj: ObjectSpec):
    """The slot names ``obj`` gives a material that emits, as a container (before its slots are
    known: every name, where the object's ``material`` emits)."""
    specs = {m.name: m for m in scene_materials(spec)}
    if obj.material is not None:
        return _EverySlot() if emits(specs.get(obj.material)) else frozenset()
    mapped = {slot for slot, name in obj.materials.items() if emits(specs.get(name))}
    same_name = {name for name, m in specs.items() if emits(m) and name not in obj.materials}
    return frozenset(mapped | same_name)

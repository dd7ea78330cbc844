"""What a loaded scene's accelerators cost at run time, split so a converted scene is reported honestly.

Objects with a model ("neural objects") cost their model. When the scene was loaded with
``primary="exact"``, each also keeps its mesh and BVH to answer camera rays, so converting adds
memory instead of saving it; with ``primary="neural"`` no BVH is built for them. `scene_memory`
states all of it, each BLAS counted once (instancing).
"""

from __future__ import annotations

from dataclasses import dataclass

from ..methods.base import is_neural, memory_owner

__all__ = ["SceneMemory", "scene_memory"]


@dataclass
class SceneMemory:
    """Run-time bytes of a scene's accelerators; ``total`` equals ``scene.accel.memory_bytes().total``."""

    exact_bytes: int  # meshes + BVHs of the exact objects (answer every ray)
    neural_bytes: int  # models of the neural objects
    camera_bytes: int  # meshes + BVHs kept only for camera rays of neural objects (0 with primary="neural")
    instances_bytes: int  # per-instance matrices and boxes
    replaced_bytes: int | None  # meshes + BVHs the neural objects would need as exact objects (None: meshes not loaded)
    neural_objects: int  # instances answered by a model
    primary: str  # who answers camera rays of neural objects

    @property
    def total(self) -> int:
        return self.exact_bytes + self.neural_bytes + self.camera_bytes + self.instances_bytes

    @property
    def saved_bytes(self) -> int | None:
        """What converting saved against the all-exact scene (negative: it costs more)."""
        return None if self.replaced_bytes is None else self.replaced_bytes - self.neural_bytes - self.camera_bytes

    @property
    def saved_bytes_primary_neural(self) -> int | None:
        """What converting saves when the models answer camera rays too (``primary="neural"``: no
        mesh kept), against the all-exact scene: the methods' memory claim. Known from a hybrid
        load (``primary="exact"``), which builds the meshes' BVHs that a neural load skips."""
        return None if self.replaced_bytes is None else self.replaced_bytes - self.neural_bytes

    def as_dict(self) -> dict:
        return {
            "total_bytes": self.total,
            "exact_bytes": self.exact_bytes,
            "neural_bytes": self.neural_bytes,
            "camera_bytes": self.camera_bytes,
            "instances_bytes": self.instances_bytes,
            "replaced_bytes": self.replaced_bytes,
            "saved_bytes": self.saved_bytes,
            "saved_bytes_primary_neural": self.saved_bytes_primary_neural,
            "neural_objects": self.neural_objects,
            "primary": self.primary,
        }


def scene_memory(scene) -> SceneMemory:
    """The memory of ``scene`` (a `neuralrt.scene.Scene`) by role. An object is neural when its
    spec gives a model (`ObjectSpec.model`), which is what made the loader build it from one.

    ``replaced_bytes`` is the mesh + BVH of the neural objects' meshes (those not also placed as
    exact objects): known when every neural object kept its mesh for camera rays.
    """
    instances = scene.accel.instances
    if scene.spec is not None:
        has_model = [obj.model is not None for obj in scene.spec.objects]
    else:  # a scene assembled by hand: hybrid instances are the ones we can tell
        has_model = [inst.camera_blas is not None for inst in instances]
    exact = {id(i.blas): i.blas for i, m in zip(instances, has_model) if not m}
    # (views of one model, e.g. objects at other N-BVH LoDs, count its bytes once: `memory_owner`)
    neural = {id(memory_owner(i.blas)): memory_owner(i.blas) for i, m in zip(instances, has_model) if m and id(i.blas) not in exact}
    # A neural camera BLAS is a view of the object's model (e.g. N-BVH's finest LoD), counted in `neural`.
    kept = [i.camera_blas is not None and not is_neural(i.camera_blas) for i in instances]
    camera = {id(i.camera_blas): i.camera_blas for i, m, k in zip(instances, has_model, kept) if m and k and id(i.camera_blas) not in exact}
    every_mesh_kept = all(k for k, m in zip(kept, has_model) if m)

    def total(blases: dict) -> int:
        return int(sum(b.memory_bytes().total for b in blases.values()))

    camera_bytes = total(camera)
    return SceneMemory(
        exact_bytes=total(exact),
        neural_bytes=total(neural),
        camera_bytes=camera_bytes,
        instances_bytes=int(scene.accel.memory_bytes().parts.get("instances", 0)),
        replaced_bytes=camera_bytes if every_mesh_kept else None,
        neural_objects=sum(has_model),
        primary=scene.primary,
    )

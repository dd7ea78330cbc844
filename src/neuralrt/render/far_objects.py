"""Notes on objects placed so far from the origin, for their size, that float32 shading loses them.

Secondary rays leave a hit at least `shading_kernels.POSITION_OFFSET` of the point's largest
coordinate off the surface (float32 rounds positions there by a few ulps; less and surfaces shadow
themselves). A unit sphere moved to x = 1e6 is then left 0.48 units away: shadow rays start past
the geometry they should meet, and its shadows and contact details go, silently (a trial: a black
crescent at 1e6, no shadow at all at 1e7). Mesh files are refused by the same reasoning
(`geometry.mesh.check_float32_extent`); a scene's transform is told as a warning, since where the
loss starts to show depends on what is looked at.
"""

from __future__ import annotations

import torch

from .shading_kernels import POSITION_OFFSET

__all__ = ["FAR_OFFSET_FRACTION", "far_object_notes"]

FAR_OFFSET_FRACTION = 0.01  # told above this share of an object's size (a unit sphere from x ~ 7e4 on)


def far_object_notes(scene) -> list[str]:
    """What to tell about ``scene`` (a `neuralrt.scene.Scene`) before it renders: the objects whose
    rays leave their surfaces more than `FAR_OFFSET_FRACTION` of their size away, because they are
    far from the origin (one note: the worst object, and how many others)."""
    instances = scene.accel.instances
    if not instances:
        return []
    lo = torch.stack([i.world_bounds.lo for i in instances]).double().cpu()
    hi = torch.stack([i.world_bounds.hi for i in instances]).double().cpu()
    size = (hi - lo).norm(dim=-1)
    farthest = torch.maximum(lo.abs(), hi.abs()).amax(-1)
    share = POSITION_OFFSET * farthest / size.clamp_min(1e-30)
    far = ((share > FAR_OFFSET_FRACTION) & (size > 0)).nonzero().flatten().tolist()  # (a point has no shadow to lose)
    if not far:
        return []
    worst = max(far, key=lambda k: float(share[k]))
    name = repr(instances[worst].name or f"instance {worst}")
    others = f" (and {len(far) - 1} other{'s' if len(far) > 2 else ''})" if len(far) > 1 else ""
    at = float(farthest[worst])
    return [f"{scene.name or 'scene'}: object {name}{others} is {at:.3g} from the origin, far for its size "
            f"({float(size[worst]):.3g}): rays leave its surfaces {POSITION_OFFSET * at:.2g} away there (float32 "
            f"rounding; {100 * float(share[worst]):.2g}% of its size), so its shadows and fine details are lost; "
            "move the scene near the origin"]

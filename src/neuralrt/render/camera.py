"""Perspective pinhole camera: pixel-jittered primary rays, batched."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..rays import Rays, Transform

__all__ = ["Camera"]


@dataclass
class Camera:
    """A pinhole camera looking down its -z axis (+y up, +x right; `Transform.look_at`).

    Pixel (0, 0) is the top-left of the image; a pixel's footprint is ``[x, x+1) x [y, y+1)``.
    Primary rays have unit directions, so a hit's ``t`` is its distance from the camera.
    """

    camera_to_world: Transform
    fov_y_degrees: float  # vertical field of view
    width: int
    height: int

    @staticmethod
    def look_at(position, target, up=(0.0, 1.0, 0.0), fov_y_degrees: float = 40.0, resolution=(256, 256)) -> "Camera":
        w, h = (int(v) for v in resolution)
        return Camera(Transform.look_at(position, target, up), float(fov_y_degrees), w, h)

    @property
    def num_pixels(self) -> int:
        return self.width * self.height

    @property
    def position(self) -> Tensor:
        return self.camera_to_world.matrix[:3, 3]

    def with_resolution(self, resolution) -> "Camera":
        w, h = (int(v) for v in resolution)
        return Camera(self.camera_to_world, self.fov_y_degrees, w, h)

    def generate_rays(self, pixel_index: Tensor, jitter: Tensor) -> Rays:
        """Rays through pixels ``pixel_index`` [N] (row-major, y * width + x) at offsets ``jitter`` [N, 2] in [0, 1)."""
        dev = pixel_index.device
        px = (pixel_index % self.width).float() + jitter[:, 0]
        py = torch.div(pixel_index, self.width, rounding_mode="floor").float() + jitter[:, 1]
        tan_half = math.tan(math.radians(self.fov_y_degrees) * 0.5)
        aspect = self.width / self.height
        x = (2.0 * px / self.width - 1.0) * tan_half * aspect
        y = (1.0 - 2.0 * py / self.height) * tan_half
        d_cam = torch.nn.functional.normalize(torch.stack([x, y, -torch.ones_like(x)], -1), dim=-1)
        m = self.camera_to_world.matrix.to(dev)
        directions = torch.nn.functional.normalize(d_cam @ m[:3, :3].T, dim=-1)
        origins = m[:3, 3].expand_as(directions).contiguous()
        return Rays(origins, directions)

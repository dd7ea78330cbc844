"""LSNIF configuration: one typed section per component, defaults from the paper (Sec. 5-6).

Every value is validated on construction (pydantic), so a wrong key or value names itself, and
the whole config round-trips through the model file's JSON header. Derived sizes (network input
width, number of outputs) are computed, never stored.
"""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, model_validator

from .config import ConfigSection as _Section
from .config import InferenceConfig, MethodConfig, TrainingConfig

__all__ = [
    "VoxelConfig", "FeatureConfig", "EncodingConfig", "NetworkConfig", "LossConfig",
    "TrainingConfig", "InferenceConfig", "LSNIFConfig", "PRESETS",
]


class VoxelConfig(_Section):
    resolution: int = Field(
        32, ge=1, le=256,
        description="V: occupancy grid is V^3 over the inflated box (paper: 32; powers of two walk faster on AVX-512 CPUs)",
    )  # fmt: skip
    box_inflation: float = Field(
        0.005, ge=0.0, le=0.5,
        description="padding of the object's AABB on each side, relative to its diagonal, so no triangle lies on the box faces",
    )


class FeatureConfig(_Section):
    max_points: int = Field(18, ge=1, le=256, description="H: voxel-boundary points kept per ray, in ray order (paper: 18)")
    origin_point: bool = Field(
        True, description="a ray starting in an occupied voxel gets its origin as first point (trilinear); else only the exit point"
    )
    point_distances: bool = Field(
        True, description="also give the MLP each point's position along the ray's box interval (H extra inputs; not in the paper)"
    )
    share_boundary_points: bool = Field(
        True, description="a face between two consecutive occupied voxels gives one point, not two (more voxels fit in H)"
    )


class EncodingConfig(_Section):
    type: Literal["sparse_hash_grid"] = Field(
        "sparse_hash_grid", description="multiresolution hash grid over the occupied voxels only (paper Sec. 3.2; its parameters Sec. 5.1)")
    resolutions: tuple[int, ...] = Field((64, 128), min_length=1, description="grid resolution per level (paper: 64^3, 128^3)")
    features_per_level: int = Field(3, ge=1, le=16, description="features per hash-table entry (paper: 3)")
    log2_table_size: int = Field(17, ge=4, le=24, description="log2 of hash-table entries per level (paper: 2^17)")
    init_scale: float = Field(1e-4, gt=0.0, le=1.0, description="features start U(-s, s) (paper: 1e-4)")


class NetworkConfig(_Section):
    type: Literal["mlp"] = Field("mlp", description="fully connected layers with leaky ReLUs")
    hidden_width: int = Field(128, ge=1, le=4096, description="neurons per hidden layer (paper: 128; preset lq: 64)")
    hidden_layers: int = Field(2, ge=1, le=16, description="hidden layers (paper: 2)")
    leaky_relu_slope: float = Field(0.01, ge=0.0, lt=1.0, description="negative slope of the leaky ReLUs")


class LossConfig(_Section):
    """Weights of the five losses (paper: occlusion BCE, distance L1, normal cosine, albedo relative L2, material CE)."""

    occlusion: float = Field(1.0, ge=0.0, description="BCE on hit / no hit, over the rays that reach the network")
    distance: float = Field(1.0, ge=0.0, description="L1 on the hit's fraction of the ray's box interval, hits only")
    normal: float = Field(1.0, ge=0.0, description="1 - cos against the exact normal turned towards the ray, hits only")
    albedo: float = Field(1.0, ge=0.0, description="relative L2 on the albedo, hits only")
    material: float = Field(1.0, ge=0.0,
                            description="cross-entropy on the material slot, hits only, meshes with several materials")


class LSNIFConfig(MethodConfig):
    """The whole LSNIF config. Presets: ``hq`` (the paper's network; CPU training scale), ``lq``
    (64-wide MLP, H = 10), ``gpu`` (``hq`` at the paper's training scale, 2,000 steps of 2^18 rays;
    the default when training on CUDA). ``LSNIFConfig.preset(name, **overrides)`` merges overrides
    key by key into the preset's sections."""

    method: Literal["lsnif"] = Field("lsnif", description="the intersection method this config belongs to")
    voxel: VoxelConfig = Field(default_factory=VoxelConfig)
    features: FeatureConfig = Field(default_factory=FeatureConfig)
    encoding: EncodingConfig = Field(default_factory=EncodingConfig)
    network: NetworkConfig = Field(default_factory=NetworkConfig)
    loss: LossConfig = Field(default_factory=LossConfig)
    training: TrainingConfig = Field(default_factory=TrainingConfig)
    inference: InferenceConfig = Field(default_factory=InferenceConfig)

    PRESETS: ClassVar[dict] = {}  # filled below

    @model_validator(mode="after")
    def _grid_planes_hold_voxel_faces(self) -> "LSNIFConfig":
        from ..neural.sparse_hash_grid import check_resolutions

        check_resolutions(self.encoding.resolutions, self.voxel.resolution)
        return self


def _hq() -> LSNIFConfig:
    return LSNIFConfig()


def _lq() -> LSNIFConfig:
    return LSNIFConfig(network=NetworkConfig(hidden_width=64), features=FeatureConfig(max_points=10))


def _gpu() -> LSNIFConfig:
    # The paper's scale (Sec. 6: 2,000 steps of 2^18 rays); a pool as large as a batch's surface
    # half, and inference chunks large enough to fill a GPU.
    return LSNIFConfig(
        training=TrainingConfig(steps=2000, batch_size=1 << 18, surface_pool_size=1 << 18),
        inference=InferenceConfig(chunk_size=1 << 20),
    )


PRESETS = {"hq": _hq, "lq": _lq, "gpu": _gpu}
LSNIFConfig.PRESETS = PRESETS

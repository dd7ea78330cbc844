"""LSNIF configuration: one typed section per component, defaults from the paper (Sec. 5-6).

Every value is validated on construction (pydantic), so a wrong key or value names itself, and
the whole config round-trips through the model file's JSON header. Derived sizes (network input
width, number of outputs) are computed, never stored.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = [
    "VoxelConfig", "FeatureConfig", "EncodingConfig", "NetworkConfig", "LossConfig",
    "TrainingConfig", "InferenceConfig", "LSNIFConfig", "PRESETS",
]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class VoxelConfig(_Section):
    resolution: int = Field(32, ge=1, le=256, description="V: occupancy grid is V^3 over the inflated box (paper: 32)")
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
    type: Literal["sparse_hash_grid"] = "sparse_hash_grid"
    resolutions: tuple[int, ...] = Field((64, 128), min_length=1, description="grid resolution per level (paper: 64^3, 128^3)")
    features_per_level: int = Field(3, ge=1, le=16, description="features per hash-table entry (paper: 3)")
    log2_table_size: int = Field(17, ge=4, le=24, description="log2 of hash-table entries per level (paper: 2^17)")
    init_scale: float = Field(1e-4, gt=0.0, description="features start U(-s, s) (paper: 1e-4)")


class NetworkConfig(_Section):
    type: Literal["mlp"] = "mlp"
    hidden_width: int = Field(128, ge=1, le=4096, description="neurons per hidden layer (paper: 128; preset lq: 64)")
    hidden_layers: int = Field(2, ge=1, le=16, description="hidden layers (paper: 2)")
    leaky_relu_slope: float = Field(0.01, ge=0.0, lt=1.0, description="negative slope of the leaky ReLUs")


class LossConfig(_Section):
    """Weights of the five losses (paper: occlusion BCE, distance L1, normal cosine, albedo relative L2, material CE)."""

    occlusion: float = Field(1.0, ge=0.0)
    distance: float = Field(1.0, ge=0.0)
    normal: float = Field(1.0, ge=0.0)
    albedo: float = Field(1.0, ge=0.0)
    material: float = Field(1.0, ge=0.0)


class TrainingConfig(_Section):
    steps: int = Field(4000, ge=1, description="optimizer steps (paper: 2,000 of 2^18 rays; CPU default: 4,000 of 2^13, see docs/lsnif.md)")
    batch_size: int = Field(1 << 13, ge=16, description="rays drawn per step (paper: 2^18 on a GPU; CPU default measured, see docs/lsnif.md)")
    learning_rate: float = Field(0.01, gt=0.0, description="Adam learning rate (paper: 0.01)")
    adam_betas: tuple[float, float] = Field((0.9, 0.99), description="Adam betas (instant-ngp's hash-grid setting)")
    adam_eps: float = Field(1e-15, gt=0.0, description="Adam epsilon (instant-ngp's: tiny, so rarely-hit table entries still move)")
    lr_decay_final: float = Field(
        0.1, gt=0.0, le=1.0,
        description="learning rate at the last step, relative to the first, exponential decay (1 = constant, as in the paper; "
        "0.1 measured better on the bunny: t error 0.37% -> 0.29%, normals 5.8 -> 5.0 deg)",
    )
    surface_fraction: float = Field(0.5, ge=0.0, le=1.0, description="share of rays starting on the surface (paper: 0.5)")
    surface_pool_size: int = Field(1 << 16, ge=1, description="surface points kept for surface-ray origins")
    surface_offset: float = Field(1e-4, ge=0.0, description="origin offset of surface rays along the normal, relative to the diagonal")
    compute_precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto", description="hidden-layer arithmetic in training (weights stay fp32): auto = bf16 where the CPU has native bf16"
    )
    seed: int = Field(0, description="seeds the weights, the hash-table init and the ray sampler")
    checkpoint_every: int = Field(200, ge=1, description="steps between checkpoints when a checkpoint path is given")


class InferenceConfig(_Section):
    occlusion_threshold: float = Field(0.5, gt=0.0, lt=1.0, description="hit if the occlusion probability exceeds this (paper: 0.5)")
    secondary_offset: float = Field(
        1e-2, ge=0.0,
        description="how far a ray leaving a neural hit starts along the normal, relative to the box diagonal "
        "(measured on the bunny: self-hits 0.9% of bounces at 1e-3, 0.13% at 1e-2; about 1/3 voxel at V=32)",
    )
    storage_precision: Literal["fp16", "fp32"] = Field("fp16", description="precision of the stored parameters (paper: fp16)")
    compute_precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto", description="MLP arithmetic at inference: auto = bf16 where the CPU has native bf16 (or on CUDA), else fp32"
    )
    chunk_size: int = Field(1 << 16, ge=1, description="rays per inference chunk (bounds temporary memory)")


class LSNIFConfig(_Section):
    voxel: VoxelConfig = Field(default_factory=VoxelConfig)
    features: FeatureConfig = Field(default_factory=FeatureConfig)
    encoding: EncodingConfig = Field(default_factory=EncodingConfig)
    network: NetworkConfig = Field(default_factory=NetworkConfig)
    loss: LossConfig = Field(default_factory=LossConfig)
    training: TrainingConfig = Field(default_factory=TrainingConfig)
    inference: InferenceConfig = Field(default_factory=InferenceConfig)

    @model_validator(mode="after")
    def _grid_planes_hold_voxel_faces(self) -> "LSNIFConfig":
        from ..neural.sparse_hash_grid import check_resolutions

        check_resolutions(self.encoding.resolutions, self.voxel.resolution)
        return self

    @staticmethod
    def preset(name: str, **overrides) -> "LSNIFConfig":
        """``hq`` (paper defaults) or ``lq`` (64-wide MLP, H = 10); ``overrides`` replace whole sections."""
        if name not in PRESETS:
            raise ValueError(f"unknown LSNIF preset {name!r} (choose from {', '.join(PRESETS)})")
        data = PRESETS[name]().model_dump()
        for section, values in overrides.items():
            data[section] = {**data[section], **(values.model_dump() if isinstance(values, BaseModel) else values)}
        return LSNIFConfig.model_validate(data)

    def with_training(self, **changes) -> "LSNIFConfig":
        """A copy with some training keys changed (e.g. ``steps=100, batch_size=4096``)."""
        data = self.model_dump()
        data["training"].update({k: v for k, v in changes.items() if v is not None})
        return LSNIFConfig.model_validate(data)


def _hq() -> LSNIFConfig:
    return LSNIFConfig()


def _lq() -> LSNIFConfig:
    return LSNIFConfig(network=NetworkConfig(hidden_width=64), features=FeatureConfig(max_points=10))


PRESETS = {"hq": _hq, "lq": _lq}

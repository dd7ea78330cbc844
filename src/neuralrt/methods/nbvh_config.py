"""N-BVH configuration (Weier et al. 2024; numbers from ../shared/METHODS-SPEC.md section A).

Typed sections, validated on construction, round-tripping through the model file's JSON header.
Where the paper and the authors' code differ, one is the default and the other an option: the
code's chord points ({0, 1/2, 1}; the paper's stratified ones as an option), the paper's loss
weights (the code's 1:1:3:3 as an option); see docs/nbvh.md, "Choices".
"""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, field_validator, model_validator

from .config import MAX_STEPS, AdamBeta, ConfigSection as _Section
from .config import InferenceConfig, MethodConfig, TrainingConfig

__all__ = ["NBVHEncodingConfig", "NBVHNetworkConfig", "QueryConfig", "CutConfig", "NBVHLossConfig",
           "NBVHTrainingConfig", "NBVHInferenceConfig", "NBVHConfig", "PRESETS"]


class NBVHEncodingConfig(_Section):
    type: Literal["hash_grid"] = Field(
        "hash_grid", description="one multiresolution hash grid over the whole object, queried at points in each BVH-cut leaf")
    levels: int = Field(8, ge=1, le=12, description="grid levels (paper: 8)")
    base_resolution: int = Field(8, ge=2, le=64, description="vertices per axis of the coarsest level; each level doubles it (paper: 8 .. 1024)")
    features_per_level: int = Field(4, ge=1, le=8, description="features per table row (paper: 4)")
    log2_table_size: int = Field(18, ge=14, le=22, description="log2 of the rows of a hashed level (paper: 2^18; the authors' configs 14..22)")
    init_scale: float = Field(1e-4, gt=0.0, le=1.0, description="features start U(-s, s) (the authors' code, tiny-cuda-nn's: 1e-4; the paper names none)")


class NBVHNetworkConfig(_Section):
    type: Literal["mlp"] = Field("mlp", description="fully connected layers with ReLUs")
    hidden_width: int = Field(64, ge=1, le=1024, description="neurons per hidden layer (paper: 64)")
    hidden_layers: int = Field(4, ge=1, le=16, description="hidden ReLU layers (paper: 4)")


class QueryConfig(_Section):
    """How a ray's chord through a leaf becomes the network input."""

    chord_points: Literal["equidistant", "stratified"] = Field(
        "equidistant",
        description="3 points at t in {0, 1/2, 1} of the chord (the code) or one random point per third in training and "
        "the thirds' centres at inference (the paper's 'stratified')",
    )
    scene_box_dilation: float = Field(1.1e-4, ge=0.0, le=0.1, description="the grid's unit cube is the object's box grown by this (relative to its largest extent) on each side")


class CutConfig(_Section):
    """The BVH cut grown during training (paper Sec. 5.1, 5.3; the code's split scheduler)."""

    max_leaf_size: int = Field(4, ge=1, le=64, description="triangles per leaf of the binary SAH base BVH (its leaves never split)")
    splitting_interval: int = Field(40, ge=1, description="steps between splits, constant (the authors' scheduler; the paper has the interval grow too): only the number split at once grows, after steps 0, 2, 4, 8, ... intervals")
    split_scaling: float = Field(2.5, ge=1.0, le=16.0, description="factor by which the number of leaves split at once grows")
    last_split_step: int = Field(3000, ge=0, description="no splits after this step (the authors' configs: 3000 of 10,000)")
    target_nodes: int | None = Field(
        None, ge=1, description="stop splitting at this many nodes (interior included: 2 * leaves - 1); None: as the schedule gives"
    )
    lods: int = Field(7, ge=1, le=7, description="levels of detail registered during training (paper: up to 7; 0 finest)")


class NBVHLossConfig(_Section):
    """Loss weights. Paper: 2 Lv + 2 Ld + Ln + La (default); the code's effective weights are 1:1:3:3."""

    visibility: float = Field(2.0, ge=0.0, description="BCE on hit / no hit")
    depth: float = Field(2.0, ge=0.0, description="L1 on the LocalT depth, hits only")
    normal: float = Field(1.0, ge=0.0, description="L1 on the normal in [-1, 1], hits only")
    albedo: float = Field(1.0, ge=0.0, description="relative L2 on the albedo, hits only")
    material: float = Field(1.0, ge=0.0, description="cross-entropy on the material slot, hits only, meshes with several materials (not in the paper)")


class NBVHTrainingConfig(TrainingConfig):
    steps: int = Field(4000, ge=1, le=MAX_STEPS, description="optimizer steps (the authors' configs: 10,000 of 2^18 rays; the paper gives the batch, its Fig. 9 1,000 + 5,000 steps)")
    batch_size: int = Field(1 << 13, ge=16, description="leaf samples per step (paper: 2^18)")
    adam_betas: tuple[AdamBeta, AdamBeta] = Field((0.9, 0.999), description="Adam betas (the code's)")
    adam_eps: float = Field(1e-8, gt=0.0, description="Adam epsilon (the code's)")
    adam_l2: float = Field(1e-8, ge=0.0, le=1.0, description="L2 regularisation added to the gradients (the code's Adam l2_reg)")
    lr_decay_final: float = Field(1.0, gt=0.0, le=1.0, description="learning rate at the last step relative to the first (1 = constant; the paper names no schedule)")
    surface_fraction: float = Field(0.0, ge=0.0, le=1.0, description="unused by N-BVH (its rays start in the scaled box): only 0")
    surface_pool_size: int = Field(1 << 16, ge=1, le=1 << 24, description="unused by N-BVH (its rays start in the scaled box): only the default")
    surface_offset: float = Field(1e-4, ge=0.0, description="unused by N-BVH (its rays start in the scaled box): only the default")
    origin_box_scale: float = Field(1.5, ge=1.0, le=4.0, description="ray origins are uniform in the object box scaled by this about its centre (paper: 1.5)")
    dilation: float = Field(1e-5, ge=0.0, le=0.1, description="leaf boxes grow by this (unit cube) in training, plus U(0, dilation_jitter) per sample")
    dilation_jitter: float = Field(1e-4, ge=0.0, le=0.1, description="random extra leaf-box growth per training sample (against thin leaves)")
    min_acceptance: float = Field(0.005, ge=0.0, le=1.0, description="samples are kept with p = max(h / h_max, this) (paper: 0.005)")

    @field_validator("surface_fraction", "surface_pool_size", "surface_offset")
    @classmethod
    def _unused(cls, value, info):
        # Shared training keys N-BVH's ray distribution never reads: a changed value would be silently ignored.
        default = cls.model_fields[info.field_name].default
        if value != default:
            raise ValueError(f"unused by N-BVH (its rays start in the scaled box); leave it at {default}")
        return value


class NBVHInferenceConfig(InferenceConfig):
    lod: int = Field(0, ge=0, le=6, description="level of detail of the cut that answers rays (0: finest)")
    secondary_lod: int | None = Field(1, ge=0, le=6, description="in a scene, the level of detail that answers every ray but camera rays (paper Sec. 7.1: a coarser cut after the first bounce); the coarsest registered LoD up to it, never finer than `lod`; None: `lod` for every ray")
    box_dilation: float = Field(1e-5, ge=0.0, le=0.1, description="leaf boxes grow by this (unit cube) at inference")
    max_steps: int = Field(1000, ge=1, description="wavefront steps (leaves per ray) at most")


class NBVHConfig(MethodConfig):
    """The whole N-BVH config. Presets: ``cpu`` and ``cpu_long`` (measured on 2 CPU cores, see
    docs/nbvh.md), ``paper`` (2^18 rays x 10,000 steps, splits until 3,000, 2^18 table; the default on CUDA)."""

    method: Literal["nbvh"] = Field("nbvh", description="the intersection method this config belongs to")
    encoding: NBVHEncodingConfig = Field(default_factory=NBVHEncodingConfig)
    network: NBVHNetworkConfig = Field(default_factory=NBVHNetworkConfig)
    query: QueryConfig = Field(default_factory=QueryConfig)
    cut: CutConfig = Field(default_factory=CutConfig)
    loss: NBVHLossConfig = Field(default_factory=NBVHLossConfig)
    training: NBVHTrainingConfig = Field(default_factory=NBVHTrainingConfig)
    inference: NBVHInferenceConfig = Field(default_factory=NBVHInferenceConfig)

    PRESETS: ClassVar[dict] = {}  # filled below
    SCHEDULE_SPANS_THE_STEPS: ClassVar[bool] = True  # (the cut's splits and LoDs: `nbvh_cut.effective_last_split`)

    @model_validator(mode="after")
    def _lod_registered(self):
        if self.inference.lod >= self.cut.lods:
            raise ValueError(f"inference.lod: {self.inference.lod} is coarser than every level of detail "
                             f"cut.lods = {self.cut.lods} registers (0..{self.cut.lods - 1})")
        return self


def _paper() -> NBVHConfig:
    # The shipped CHESS config: (interval 40, scaling 2.5) until step 3000 of 10,000, 2^18 rays.
    return NBVHConfig(
        training=NBVHTrainingConfig(steps=10_000, batch_size=1 << 18),
        inference=NBVHInferenceConfig(chunk_size=1 << 20),
    )


def _cpu() -> NBVHConfig:
    # Measured on the 2-core machine (docs/nbvh.md): 1,000 steps of 2^13 samples, 2,395 nodes
    # (interval 15, scaling 2, splits until step 600), a 2^16 table.
    return NBVHConfig(
        encoding=NBVHEncodingConfig(log2_table_size=16),
        cut=CutConfig(splitting_interval=15, split_scaling=2.0, last_split_step=600),
        training=NBVHTrainingConfig(steps=1000, batch_size=1 << 13),
    )


def _cpu_long() -> NBVHConfig:
    # Twice the training of ``cpu`` (2,000 steps, splits until 1,200 every 30 steps: 2,395 nodes too).
    return NBVHConfig(
        encoding=NBVHEncodingConfig(log2_table_size=16),
        cut=CutConfig(splitting_interval=30, split_scaling=2.0, last_split_step=1200),
        training=NBVHTrainingConfig(steps=2000, batch_size=1 << 13),
    )


PRESETS = {"cpu": _cpu, "cpu_long": _cpu_long, "paper": _paper}
NBVHConfig.PRESETS = PRESETS

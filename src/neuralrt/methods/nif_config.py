"""NIF configuration (Fujieda et al., HPG 2023): networks as in the paper's Table 1 and Sec. 5, online
training as in Sec. 4.2, and the choices the paper leaves open (docs/nif.md).

Typed and validated (pydantic): an unknown key or a bad value is an error naming the key.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from .config import AdamBeta, ConfigSection

__all__ = ["NIFGridConfig", "NIFNetworkConfig", "NIFTrainingConfig", "NIFConfig"]


class NIFGridConfig(ConfigSection):
    resolution: int = Field(ge=2, le=4096, description="R: vertices per axis")
    features: int = Field(ge=1, le=64, description="N: features per vertex")


class NIFNetworkConfig(ConfigSection):
    """One network kind (outer or inner): its grids and its MLP (shared by every NIF object of a scene)."""

    position_grid: NIFGridConfig = Field(description="2D grid at the spherical coordinates of the box entry point (outer) "
                                         "or of the origin (inner), about the box centre")
    direction_grid: NIFGridConfig = Field(description="2D grid at the ray direction's spherical coordinates")
    distance_grid: NIFGridConfig | None = Field(None, description="1D grid at |origin - centre| / half diagonal (inner only)")
    hidden_width: int = Field(ge=1, le=1024, description="neurons per hidden layer")
    hidden_layers: int = Field(ge=1, le=16, description="hidden layers")

    @property
    def input_width(self) -> int:
        return self.position_grid.features + self.direction_grid.features + (self.distance_grid.features if self.distance_grid else 0)


def _outer() -> NIFNetworkConfig:
    return NIFNetworkConfig(position_grid=NIFGridConfig(resolution=256, features=3), direction_grid=NIFGridConfig(resolution=256, features=3),
                            hidden_width=64, hidden_layers=2)


def _inner() -> NIFNetworkConfig:
    return NIFNetworkConfig(position_grid=NIFGridConfig(resolution=128, features=5), direction_grid=NIFGridConfig(resolution=128, features=5),
                            distance_grid=NIFGridConfig(resolution=128, features=3), hidden_width=48, hidden_layers=3)


class NIFTrainingConfig(ConfigSection):
    train_spp: int = Field(32, ge=1, description="samples per pixel rendered with exact shadow rays while collecting training pairs "
                           "(the paper's figures: 32-128)")
    passes_per_spp: int = Field(1, ge=1, le=64, description="passes (epochs) over each collected pair; the paper leaves it open "
                                "(measured in docs/nif.md)")
    pair_fraction: float = Field(0.5, gt=0.0, le=1.0, description="share of each round's collected pairs a pass trains on "
                                 "(a fresh random subset per pass): 0.5 halves the training time for a little accuracy, "
                                 "keeping the PSNR target (measured in docs/nif.md); 1 trains on every pair")
    outer_batch: int = Field(1 << 11, ge=16, description="pairs per outer training step (paper: 2^11)")
    inner_batch: int = Field(1 << 12, ge=16, description="pairs per inner training step (paper: 2^12)")
    round_pairs: int = Field(1 << 16, ge=1, description="collected pairs buffered before a training round (shuffled within it)")
    learning_rate: float = Field(0.005, gt=0.0, description="Adam learning rate (paper: 0.005)")
    adam_betas: tuple[AdamBeta, AdamBeta] = Field((0.9, 0.999), description="Adam betas (paper: 0.9, 0.999)")
    adam_eps: float = Field(1e-15, gt=0.0, description="Adam epsilon (paper: 1e-15)")
    init_scale: float = Field(1e-4, gt=0.0, le=1.0, description="grid features start U(-s, s)")
    seed: int = Field(0, ge=0, lt=1 << 63, description="seeds grids, MLP weights and the batch order; 0 <= seed < 2^63, as `training.seed`")


class NIFConfig(ConfigSection):
    """The whole NIF config: outer and inner networks, training, and which objects ``auto`` picks."""

    outer: NIFNetworkConfig = Field(default_factory=_outer, description="network for shadow rays starting outside the object's box")
    inner: NIFNetworkConfig = Field(default_factory=_inner, description="network for shadow rays starting inside the object's box")
    leaky_relu_slope: float = Field(0.01, ge=0.0, lt=1.0, description="negative slope of the hidden layers' leaky ReLUs")
    compute_precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto", description="MLP hidden layers when answering (training is fp32): auto = bf16 on CUDA or where the CPU has "
        "native bf16 (decided once per process, neuralrt.neural.precision)")
    box_inflation: float = Field(1e-4, ge=0.0, le=0.1, description="object box padding per side, relative to its diagonal "
                                 "(no triangle lies on a box face)")
    training: NIFTrainingConfig = Field(default_factory=NIFTrainingConfig)
    shadow_rays: Literal["first_hit", "every_hit"] = Field(
        "first_hit", description="the shadow rays NIF trains on and answers: those of direct light at the camera rays' hits "
        "(paper Sec. 4; deeper paths are its future work, Sec. 8), or those of every bounce; the others are traced exactly")
    auto_min_triangles: int = Field(100_000, ge=1, description="--nif auto: objects with more triangles than this "
                                    "(the paper's Bistro: 100K)")

    @classmethod
    def _label(cls) -> str:
        return "nif config"  # (as the scene's and render_nif's messages name it)

    @model_validator(mode="after")
    def _distance_grid_only_inner(self) -> "NIFConfig":
        if self.outer.distance_grid is not None:
            raise ValueError("outer.distance_grid: the outer network has no distance input")
        if self.inner.distance_grid is None:
            raise ValueError("inner.distance_grid: the inner network needs its distance grid")
        return self

"""Config pieces every method shares: the section base class, the training and inference sections,
and `MethodConfig`, the base of each method's whole config (its ``method`` field names it).

A method's config subclasses `MethodConfig`, sets ``method: Literal["name"] = "name"``, adds its
own sections (encoding, network, ...), has a ``training`` section that is (a subclass of)
`TrainingConfig` and an ``inference`` section that is (a subclass of) `InferenceConfig`, and lists
its presets in ``PRESETS`` (name -> function returning the config).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..arguments import given
from ..errors import ConfigError, validation_message

AdamBeta = Annotated[float, Field(ge=0.0, lt=1.0)]  # (torch's Adam refuses others, after set-up)
MAX_STEPS = 10**9  # (a typo of 1e20 steps would run forever; the papers train 2,000-10,000)

__all__ = ["ConfigSection", "TrainingConfig", "InferenceConfig", "MethodConfig", "parse_settings", "merged_settings",
           "differing_keys", "ABSENT"]


def merged_settings(base: dict, changes: dict) -> dict:
    """``base`` (a config's ``model_dump``) with ``changes`` merged in key by key, at every depth:
    ``{"outer": {"position_grid": {"resolution": 64}}}`` changes that one key and keeps the rest of
    the section and its subsections. A config section among the changes counts by the keys set in it."""
    merged = dict(base)
    for key, value in changes.items():
        if isinstance(value, BaseModel):
            value = value.model_dump(exclude_unset=True)
        merged[key] = merged_settings(merged[key], value) if isinstance(merged.get(key), dict) and isinstance(value, dict) \
            else value
    return merged


ABSENT = object()  # (`differing_keys`: a key one side has and the other lacks)


def differing_keys(saved: dict, now: dict, prefix: str = ""):
    """(dotted key, (``saved``'s value, ``now``'s)) for each leaf of two nested dicts (configs'
    ``model_dump``, run identities) that differs, in ``now``'s key order; `ABSENT` where one side
    lacks the key."""
    for key in dict.fromkeys([*now, *saved]):
        a, b = saved.get(key, ABSENT), now.get(key, ABSENT)
        if isinstance(a, dict) and isinstance(b, dict):
            yield from differing_keys(a, b, f"{prefix}{key}.")
        elif a != b:
            yield f"{prefix}{key}", (a, b)


class ConfigSection(BaseModel):
    """A typed, validated config section: unknown keys and bad values are errors naming the key."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)  # NaN: "finite number", not "less than 1"

    # Built or changed in code (``NBVHConfig(cut={"lods": 0})``, ``config.training.steps = -1``), a bad
    # value is one `ConfigError` line, as from a file or ``--set``, not pydantic's multi-line dump.
    def __init__(self, /, **data):
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise ConfigError(f"{self._label()}: {validation_message(exc, type(self))}") from None

    # Nested sections are then validated as plain models (one error path, ``training.steps``), not
    # through this __init__ (pydantic's own mark, as its RootModel uses).
    __init__.__pydantic_base_init__ = True

    def __setattr__(self, name: str, value) -> None:
        try:
            super().__setattr__(name, value)
        except ValidationError as exc:
            raise ConfigError(f"{self._label()}: {validation_message(exc, type(self))}") from None

    @classmethod
    def _label(cls) -> str:
        return cls.__name__

    def __str__(self) -> str:
        """``print(config)``, IPython and Jupyter show a config one field per line where its repr
        (one line, ~900 characters for a whole method's) would not fit; sections that fit keep one."""
        return self._laid_out("")

    def _repr_pretty_(self, printer, cycle: bool) -> None:
        printer.text(str(self))

    def _laid_out(self, indent: str, used: int = 0, width: int = 100) -> str:
        """(``used``: columns the line holds before this section)"""
        one_line = repr(self)
        if max(used, len(indent)) + len(one_line) + (used > 0) <= width:  # (a field's line ends in a comma)
            return one_line
        inner = indent + "    "
        fields = [f"{inner}{name}=" + (value._laid_out(inner, len(inner) + len(name) + 1, width)
                                       if isinstance(value, ConfigSection) else repr(value)) for name, value in self]
        return f"{type(self).__name__}(\n" + ",\n".join(fields) + f",\n{indent})"


class TrainingConfig(ConfigSection):
    """What the shared training loop and the training ray distribution read."""

    steps: int = Field(4000, ge=1, le=MAX_STEPS, description="optimizer steps (paper: 2,000 of 2^18 rays; CPU default: 4,000 of 2^13, see docs/lsnif.md)")
    batch_size: int = Field(
        1 << 13, ge=16, le=1 << 22,
        description="rays drawn per step (paper: 2^18 on a GPU; CPU default measured, see docs/lsnif.md; at most 2^22: "
        "LSNIF `hq` holds ~1.8 KB per ray in a step, so 2^22 rays take ~7.5 GB)",
    )
    learning_rate: float = Field(0.01, gt=0.0, description="Adam learning rate (paper: 0.01)")
    adam_betas: tuple[AdamBeta, AdamBeta] = Field((0.9, 0.99), description="Adam betas (instant-ngp's hash-grid setting)")
    adam_eps: float = Field(1e-15, gt=0.0, description="Adam epsilon (instant-ngp's: tiny, so rarely-hit table entries still move)")
    adam_l2: float = Field(0.0, ge=0.0, le=1.0, description="L2 regularisation: this times each parameter added to its gradient "
                           "(tiny-cuda-nn's Adam l2_reg; LSNIF's paper names none)")
    lr_decay_final: float = Field(
        0.1, gt=0.0, le=1.0,
        description="learning rate at the last step, relative to the first, exponential decay (1 = constant; the paper names no schedule; "
        "0.1 measured better on the bunny: t error 0.37% -> 0.29%, normals 5.8 -> 5.0 deg)",
    )
    surface_fraction: float = Field(0.5, ge=0.0, le=1.0, description="share of rays starting on the surface (paper: 0.5)")
    surface_pool_size: int = Field(1 << 16, ge=1, le=1 << 24, description="surface points kept for surface-ray origins")
    surface_offset: float = Field(1e-4, ge=0.0, description="origin offset of surface rays along the normal, relative to the diagonal")
    compute_precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto", description="hidden-layer arithmetic in training (weights stay fp32): auto = bf16 on CUDA or where the CPU "
        "has native bf16 (decided once per process; the training record stores the choice)"
    )
    seed: int = Field(
        0, ge=0, lt=1 << 63,
        description="seeds the weights, the hash-table init and the training rays; 0 <= seed < 2^63 (numba kernels take "
        "it as an int64; torch generators take 64 bits, so derived seeds such as seed + 1 fit too)",
    )
    checkpoint_every: int = Field(200, ge=1, description="steps between checkpoints when a checkpoint path is given")


class InferenceConfig(ConfigSection):
    """How a trained model answers rays."""

    # Keys that describe the stored model, not how it answers: no view of a trained model changes
    # them (`NeuralBLAS.with_inference`), and a cached model is reused only under the same ones.
    STORED_KEYS: ClassVar[tuple[str, ...]] = ("storage_precision",)

    @classmethod
    def changeable_keys(cls) -> list[str]:
        """The keys a trained model may answer with other values of: all but `STORED_KEYS`."""
        return [k for k in cls.model_fields if k not in cls.STORED_KEYS]

    occlusion_threshold: float = Field(0.5, gt=0.0, lt=1.0, description="hit if the occlusion probability exceeds this (paper: 0.5)")
    secondary_offset: float = Field(
        1e-2, ge=0.0,
        description="how far a ray leaving a neural hit starts along the normal, relative to the box diagonal "
        "(measured on the bunny: self-hits 0.9% of bounces at 1e-3, 0.13% at 1e-2; about 1/3 voxel at V=32)",
    )
    storage_precision: Literal["fp16", "fp32"] = Field("fp16", description="precision of the stored parameters (paper: fp16)")
    compute_precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto", description="MLP arithmetic at inference: auto = bf16 on CUDA or where the CPU has native bf16, else fp32 "
        "(answers differ slightly between the two: see neuralrt.neural.precision)"
    )
    chunk_size: int = Field(
        1 << 16, ge=1, description="rays per inference chunk (bounds temporary memory; LSNIF's fused CPU pass takes at least "
        "2^17 rays per thread, up to 2^18: lsnif_fused_cpu.rays_per_chunk)"
    )


class MethodConfig(ConfigSection):
    """Base of a method's whole config. Subclasses narrow ``method`` to a literal and fill ``PRESETS``."""

    method: str = Field(description="the intersection method this config belongs to")

    PRESETS: ClassVar[dict[str, Callable[[], "MethodConfig"]]] = {}
    # Keys added after models and checkpoints existed, with the value that trains as before them:
    # left out of `model_defining` while they hold it, so a new key does not retrain every cached
    # model or orphan every checkpoint (section -> key -> value).
    ADDED_KEYS: ClassVar[dict[str, dict[str, object]]] = {"training": {"adam_l2": 0.0}}
    # Whether a run's schedule is laid over its ``training.steps`` (N-BVH's cut: splits and LoDs at
    # fractions of the run), so that a checkpoint resumes only under the same count; else a run may
    # be resumed to train longer.
    SCHEDULE_SPANS_THE_STEPS: ClassVar[bool] = False

    @classmethod
    def preset(cls, name: str, **overrides) -> "MethodConfig":
        """The preset ``name``, with ``overrides`` merged in key by key (`merged_settings`):
        ``preset("hq", training={"steps": 100})`` changes only ``training.steps`` and keeps every
        other training key of the preset. Values may
        be dicts or config sections. An unknown preset or a bad override is a one-line `ConfigError`
        (a ``ValueError``) naming the known presets or the key."""
        if not isinstance(name, str) or name not in cls.PRESETS:
            raise ConfigError(f"{given('preset')}: unknown {cls._method_name()} preset {name!r} (choose from "
                              f"{', '.join(cls.PRESETS)})")
        return cls.validated(merged_settings(cls.PRESETS[name]().model_dump(), overrides))

    def with_training(self, **changes) -> "MethodConfig":
        """A copy with some training keys changed (``None`` values are ignored): ``with_training(steps=100, batch_size=4096)``.
        A bad value or unknown key is a one-line `ConfigError` naming ``training.<key>``."""
        data = self.model_dump()
        data["training"].update({k: v for k, v in changes.items() if v is not None})
        return type(self).validated(data)

    def model_defining(self) -> dict:
        """The JSON form of the keys that make the trained model: all but ``training.checkpoint_every``
        (how often a run saves; the model is the same bit for bit) and `ADDED_KEYS` at their old
        behaviour's value. The converter's cache and a checkpoint's identity compare these."""
        data = self.model_dump(mode="json")
        data["training"].pop("checkpoint_every")
        for section, keys in self.ADDED_KEYS.items():
            for key, neutral in keys.items():
                if key in data.get(section, {}) and data[section][key] == neutral:
                    del data[section][key]
        return data

    @classmethod
    def validated(cls, data: dict) -> "MethodConfig":
        """``data`` as a config; pydantic's multi-line errors become one `ConfigError` line (``lsnif config: training.steps: ...``)."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise ConfigError(f"{cls._label()}: {validation_message(exc, cls)}") from None

    @classmethod
    def _label(cls) -> str:
        return f"{cls._method_name()} config"

    @classmethod
    def _method_name(cls) -> str:
        return cls.model_fields["method"].default


def parse_settings(items: list[str] | None) -> dict:
    """``["training.steps=100", "voxel.resolution=64"]`` (the CLI's ``--set``) as the nested overrides
    `MethodConfig.preset` takes: ``{"training": {"steps": 100}, "voxel": {"resolution": 64}}``. Values
    are JSON (``64``, ``0.5``, ``true``, ``null``, ``[64, 128]``) or Python's ``None``/``True``/``False``
    (docs/config.md shows defaults that way), else plain words (``stratified``)."""
    import json

    python_words = {"None": None, "True": True, "False": False}

    overrides: dict = {}
    for item in items or []:
        key, eq, value = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not eq or not dot or not section or not name:
            raise ConfigError(f"--set {item}: expected SECTION.KEY=VALUE, e.g. training.steps=100 (keys: python -m neuralrt.configdoc)")
        try:
            parsed = python_words[value.strip()] if value.strip() in python_words else json.loads(value)
        except json.JSONDecodeError:
            parsed = value  # a plain word
        overrides.setdefault(section, {})[name] = parsed
    return overrides

"""The method registry: every neural intersection method, by name.

One `register_method` call (in `neuralrt.methods`) makes a method known to everything that deals
with methods by name: ``neuralrt train/convert/eval --method NAME --preset NAME``, `load_model`,
the scene converter, the config reference page and the benchmarks. A method provides its config
class (a `MethodConfig` with ``PRESETS``) and its model class (a `NeuralBLAS`), imported only when
first used, so listing methods and presets never loads numba kernels.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field

from pydantic import ValidationError

from ..devices import check_device_name
from ..errors import ConfigError, validation_message
from .config import MethodConfig

__all__ = ["MethodSpec", "register_method", "get_method", "method_names", "config_from_dict", "DEFAULT_METHOD"]

DEFAULT_METHOD = "lsnif"


@dataclass(frozen=True)
class MethodSpec:
    """A registered method.

    Attributes:
        name: the name in configs, model files and ``--method``.
        config_class: its `MethodConfig` subclass (``PRESETS`` lists its presets).
        model: ``"module:Class"`` of its `NeuralBLAS` subclass (imported on first use).
        summary: one line for listings.
        default_presets: device type -> preset used when none is named (``"*"``: any other device).
    """

    name: str
    config_class: type[MethodConfig]
    model: str
    summary: str
    default_presets: dict[str, str] = field(default_factory=dict)

    @property
    def presets(self) -> dict:
        """Preset name -> function returning the config."""
        return self.config_class.PRESETS

    @property
    def model_class(self):
        module, name = self.model.split(":")
        return getattr(importlib.import_module(module), name)

    def default_preset(self, device: str = "cpu") -> str:
        kind = check_device_name(device).type  # a bad name is one line, not torch's RuntimeError
        return self.default_presets.get(kind) or self.default_presets.get("*") or next(iter(self.presets))

    def config(self, preset: str | None = None, device: str = "cpu", settings: dict | None = None, **training) -> MethodConfig:
        """The preset's config (default: the device's default preset) with ``settings`` merged in
        (``{"voxel": {"resolution": 64}}``, `parse_settings` of the CLI's ``--set``), then training keys
        changed (``steps=..., batch_size=..., seed=...``; ``None`` keeps the preset's). Errors are one-line `ConfigError`s."""
        if settings is not None and not isinstance(settings, dict):
            raise ConfigError(f"settings: expected a dict of config sections, got {type(settings).__name__}")
        return self.config_class.preset(preset or self.default_preset(device), **(settings or {})).with_training(**training)


_METHODS: dict[str, MethodSpec] = {}


def register_method(spec: MethodSpec) -> MethodSpec:
    """Make ``spec`` known by its name; a second, different method under the same name is an error."""
    known = _METHODS.get(spec.name)
    if known is not None and known != spec:
        raise ValueError(f"method {spec.name!r} is already registered ({known.model})")
    if spec.config_class.model_fields["method"].default != spec.name:
        raise ValueError(f"{spec.config_class.__name__}.method must default to {spec.name!r}")
    _METHODS[spec.name] = spec
    return spec


def method_names() -> list[str]:
    """Registered method names, in registration order."""
    return list(_METHODS)


def get_method(name: str) -> MethodSpec:
    """The registered method ``name``; an unknown name is a `ConfigError` listing the known ones."""
    if name not in _METHODS:
        raise ConfigError(f"unknown method {name!r} (registered: {', '.join(_METHODS) or 'none'})")
    return _METHODS[name]


def config_from_dict(data: dict) -> MethodConfig:
    """A config from its JSON form (e.g. a model file's header), dispatched on its ``method`` key
    (configs written before the key existed are LSNIF's)."""
    spec = get_method(data.get("method", DEFAULT_METHOD))
    try:
        return spec.config_class.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{spec.name} config: {validation_message(exc, spec.config_class)}") from None

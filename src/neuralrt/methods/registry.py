"""The method registry: every neural intersection method, by name.

One `register_method` call makes a method known to everything that deals with methods by name:
``neuralrt train/convert/demo --method NAME --preset NAME``, `load_model` (and so ``eval``,
``info``, ``render`` of its model files and scenes), the scene converter, the config reference
and the benchmarks. A method provides its config class (a `MethodConfig` with ``PRESETS``) and its
model class (a `NeuralBLAS`), imported only when first used, so listing methods and presets never
loads numba kernels.

The built-in methods register in `neuralrt.methods`. A method of your own (a plugin module that
calls `register_method` when imported) is loaded the first time methods are listed or looked up
by name (so before the CLI parses its arguments), from either of (docs/methods.md, "A method of
your own"):

- the entry point group ``neuralrt.methods`` of an installed package
  (``[project.entry-points."neuralrt.methods"] NAME = "your_module"``);
- ``NEURALRT_PLUGINS``: module names separated by commas, importable from ``sys.path``.

A model file never names code to import: a file of an unregistered method is an error that says
how to register it.
"""

from __future__ import annotations

import importlib
import os
import warnings
from dataclasses import dataclass, field

from pydantic import ValidationError

from ..arguments import given
from ..devices import check_device_name
from ..errors import ConfigError, outside_stacklevel, validation_message
from .config import ABSENT, MethodConfig, differing_keys

__all__ = ["MethodSpec", "register_method", "get_method", "method_names", "config_from_dict", "DEFAULT_METHOD",
           "load_plugins", "PLUGIN_GROUP", "PLUGIN_VARIABLE", "HOW_TO_REGISTER"]

DEFAULT_METHOD = "lsnif"
PLUGIN_GROUP = "neuralrt.methods"  # entry point group of installed plugin packages
PLUGIN_VARIABLE = "NEURALRT_PLUGINS"  # comma-separated plugin modules
HOW_TO_REGISTER = (f"a plugin registers it: install its package (entry point group {PLUGIN_GROUP!r}) or name its "
                   f"module in {PLUGIN_VARIABLE}")


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
        """The `NeuralBLAS` subclass ``model`` names, imported; one that cannot be imported, or that
        does not declare this method's name and config, is a one-line `ConfigError`."""
        from .base import NeuralBLAS

        module, _, name = self.model.partition(":")
        try:
            cls = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError, ValueError) as exc:
            raise ConfigError(f"method {self.name!r}: cannot import its model class {self.model!r} "
                              f"({type(exc).__name__}: {exc})") from None
        if not (isinstance(cls, type) and issubclass(cls, NeuralBLAS)):
            raise ConfigError(f"method {self.name!r}: {self.model} is not a NeuralBLAS subclass")
        if getattr(cls, "METHOD", None) != self.name or getattr(cls, "CONFIG", None) is not self.config_class:
            raise ConfigError(f"method {self.name!r}: {self.model} must declare METHOD = {self.name!r} and "
                              f"CONFIG = {self.config_class.__name__} (has {getattr(cls, 'METHOD', None)!r}, "
                              f"{getattr(getattr(cls, 'CONFIG', None), '__name__', None)})")
        return cls

    def default_preset(self, device: str = "cpu") -> str:
        kind = check_device_name(device).type  # a bad name is one line, not torch's RuntimeError
        return self.default_presets.get(kind) or self.default_presets.get("*") or next(iter(self.presets))

    def config(self, preset: str | None = None, device: str = "cpu", settings: dict | None = None, **training) -> MethodConfig:
        """The preset's config (default: the device's default preset) with ``settings`` merged in
        (``{"voxel": {"resolution": 64}}``, `parse_settings` of the CLI's ``--set``), then training keys
        changed (``steps=..., batch_size=..., seed=...``; ``None`` keeps the preset's). Errors are one-line `ConfigError`s."""
        if settings is not None and not isinstance(settings, dict):
            raise ConfigError(f"settings: expected a dict of config sections, got {type(settings).__name__}")
        self._check_sections(settings or {})
        named = (settings or {}).get("training")
        for key, value in training.items():  # (one would silently win over the other)
            if value is not None and isinstance(named, dict) and key in named and named[key] != value:
                argument = {"batch_size": "batch"}.get(key, key)
                raise ConfigError(f"{given(argument, value)} and training.{key}={named[key]!r} in "
                                  f"{given('settings', flag='--set')} disagree: give one of them")
        return self.config_class.preset(preset or self.default_preset(device), **(settings or {})).with_training(**training)

    def _check_sections(self, settings: dict) -> None:
        """A one-line `ConfigError` for a dotted key (the CLI's spelling; a dict nests) or a section
        this method lacks, naming the methods that have it."""
        own = self.config_class.model_fields
        for key in settings:
            head, dot, rest = str(key).partition(".")
            if dot and head in own:
                raise ConfigError(f"{given('settings', flag='--set')}: {key!r}: sections nest as dicts here, "
                                  f"{{{head!r}: {{{rest!r}: ...}}}} (the CLI's --set takes {key}=VALUE)")
            if key not in own:
                others = [name for name in method_names() if name != self.name and key in get_method(name).config_class.model_fields]
                if others:
                    raise ConfigError(f"{self.name} config: {key}: not a section of {self.name}'s config (it is of "
                                      f"{', '.join(others)}'s: {given('method', others[0])})")

    def nearest_preset(self, config: MethodConfig) -> tuple[str, dict]:
        """(the preset ``config`` differs from in the fewest keys, those keys as ``--set`` spells them
        with ``config``'s values), up to the training keys `config` sets, as `preset_of` compares."""
        t, mine = config.training, config.model_defining()
        best = None
        for name in self.presets:
            theirs = self.config(name, steps=t.steps, batch_size=t.batch_size, seed=t.seed).model_defining()
            changed = {key: None if value is ABSENT else value for key, (_, value) in differing_keys(theirs, mine)}
            if best is None or len(changed) < len(best[1]):
                best = (name, changed)
        return best

    def preset_of(self, config: MethodConfig) -> str | None:
        """The preset ``config`` was made from, up to the training keys `config` sets (steps, batch
        size, seed) and what makes no other model (`model_defining`); None where other keys differ."""
        t = config.training
        for name in self.presets:
            made = self.config(name, steps=t.steps, batch_size=t.batch_size, seed=t.seed)
            if made.model_defining() == config.model_defining():
                return name
        return None


_METHODS: dict[str, MethodSpec] = {}


def register_method(spec: MethodSpec) -> MethodSpec:
    """Make ``spec`` known by its name. A second, different method under the same name is an error;
    the same one registered again (its module imported again, e.g. reloaded in a notebook) replaces
    the first. A spec whose config class is not a `MethodConfig` with presets and its name is a
    `ValueError` here, not a failure at first use."""
    config_class = spec.config_class
    if not (isinstance(config_class, type) and issubclass(config_class, MethodConfig)):
        raise ValueError(f"method {spec.name!r}: config_class must be a MethodConfig subclass, got {config_class!r}")
    if config_class.model_fields["method"].default != spec.name:
        raise ValueError(f"{config_class.__name__}.method must default to {spec.name!r}")
    if not config_class.PRESETS:
        raise ValueError(f"method {spec.name!r}: {config_class.__name__}.PRESETS names no preset (at least one)")
    unknown = sorted(p for p in spec.default_presets.values() if p not in config_class.PRESETS)
    if unknown:
        raise ValueError(f"method {spec.name!r}: default_presets name no preset of {config_class.__name__}: {', '.join(unknown)}")
    if ":" not in spec.model:
        raise ValueError(f"method {spec.name!r}: model must be 'module:Class', got {spec.model!r}")
    known = _METHODS.get(spec.name)
    if known is not None and _identity(known) != _identity(spec):
        raise ValueError(f"method {spec.name!r} is already registered ({known.model})")
    _METHODS[spec.name] = spec
    return spec


def _identity(spec: MethodSpec) -> tuple:
    """What makes two registrations the same method: names, not class objects (a reload makes new ones)."""
    return spec.name, spec.model, spec.config_class.__module__, spec.config_class.__qualname__


def load_plugins() -> list[str]:
    """Import the plugin modules of the ``neuralrt.methods`` entry points and of ``NEURALRT_PLUGINS``
    (each registers its methods when imported); return their names. A plugin that fails to import
    is a warning naming it and the error: the built-in methods stay usable."""
    from importlib.metadata import entry_points

    modules = [(ep.value.partition(":")[0].strip(), f"entry point {ep.name!r}") for ep in entry_points(group=PLUGIN_GROUP)]
    modules += [(m.strip(), PLUGIN_VARIABLE) for m in os.environ.get(PLUGIN_VARIABLE, "").split(",") if m.strip()]
    loaded = []
    for module, source in modules:
        try:
            importlib.import_module(module)
        except Exception as exc:  # a plugin's own bug must not stop the built-in methods
            warnings.warn(f"method plugin {module!r} ({source}) not loaded: {type(exc).__name__}: {exc}",
                          stacklevel=outside_stacklevel())
        else:
            loaded.append(module)
    return loaded


_plugins_loaded = False


def _with_plugins() -> dict[str, MethodSpec]:
    """The registry, after the plugins are loaded (once: on the first lookup, not on import, so a
    plugin can import neuralrt freely and a command shows its warnings in its own format)."""
    global _plugins_loaded
    if not _plugins_loaded:
        _plugins_loaded = True
        load_plugins()
    return _METHODS


def method_names() -> list[str]:
    """Registered method names, in registration order (the built-ins, then plugins')."""
    return list(_with_plugins())


def get_method(name: str) -> MethodSpec:
    """The registered method ``name``; an unknown name is a `ConfigError` listing the known ones."""
    if not isinstance(name, str) or name not in _with_plugins():
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


def changeable_inference_keys() -> list[str]:
    """The ``inference`` settings a registered method's models may change when answering (not how
    the parameters were stored), in the methods' order."""
    keys: dict[str, None] = {}
    for name in method_names():
        keys.update((k, None) for k in get_method(name).config_class.model_fields["inference"].annotation.changeable_keys())
    return list(keys)


def methods_answering_with(key: str) -> list[str]:
    """The registered methods whose ``inference`` section has ``key`` (for errors that name them)."""
    return [name for name in method_names()
            if key in get_method(name).config_class.model_fields["inference"].annotation.model_fields]

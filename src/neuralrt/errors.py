"""Errors neuralrt raises for bad input. The CLI prints them as one line, never a traceback."""


class NeuralRTError(Exception):
    """Base class: a problem with the user's input, stated in one line."""


class MeshError(NeuralRTError):
    """A mesh file is missing, unreadable, empty or malformed."""


class SceneError(NeuralRTError):
    """A scene file is missing or invalid."""


class ModelFileError(NeuralRTError):
    """A model file is missing, truncated, corrupted, of another method or a newer version."""


class ImageError(NeuralRTError):
    """An image file is missing or unreadable, or two images do not match."""


class ConfigError(NeuralRTError, ValueError):
    """An argument or config value is invalid: unknown method or preset, a value out of range."""


class MeshMismatchError(NeuralRTError):
    """A model is used with a mesh it was not trained on."""


class DeviceError(NeuralRTError, ValueError):
    """A device is unavailable (``cuda`` on a CPU-only torch), or rays and model sit on different devices."""


def validation_message(exc) -> str:
    """One line from a pydantic ``ValidationError``: ``training.steps: Input should be greater than or
    equal to 1 (got -3)``, errors joined by ``; ``."""
    parts = []
    for err in exc.errors():
        where = ".".join(str(x) for x in err.get("loc", ())) or "value"
        got = f" (got {err['input']!r})" if "input" in err and not isinstance(err["input"], dict) else ""
        parts.append(f"{where}: {err.get('msg', 'invalid')}{got}")
    return "; ".join(parts)

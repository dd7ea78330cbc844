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

"""Exceptions of stablecues: one base class, one subclass per area.

Every message says what was expected and what was found, and names the file when one is
involved, so that the CLI can print it as one line.
"""

from __future__ import annotations


class StableCuesError(Exception):
    """Base class of every error that stablecues raises on purpose."""


class InputError(StableCuesError, ValueError):
    """Bad input handed to a public function: wrong shape, dtype, range or a corrupt image."""


class ConfigError(StableCuesError, ValueError):
    """Unknown or invalid setting, or an unknown preset name."""


class VocabularyError(StableCuesError):
    """A vocabulary file that is missing, truncated, corrupt or of an unknown format."""


class DatabaseError(StableCuesError):
    """A database file that is missing, corrupt, or made with a different vocabulary."""


class DatasetError(StableCuesError):
    """A dataset, ground-truth or calibration file that is missing or malformed."""


class ImageError(DatasetError, InputError):
    """An image file that is missing, empty, undecodable or of an unexpected form.

    A :class:`DatasetError` (it comes from a file) and an :class:`InputError` (it is bad input),
    so code catching either keeps working.
    """


class CalibrationError(DatasetError):
    """A calibration file that is missing a field or holds an invalid value."""


class ModelError(StableCuesError):
    """A network weights file that is missing or unreadable."""


class OutputError(StableCuesError):
    """A path the project cannot write a file to (a link, a folder, a device, a missing or
    read-only folder, a full disk)."""


class ClusterError(StableCuesError):
    """A Dask cluster that cannot be reached or started, or a task lost with its worker."""


class MissingDependencyError(StableCuesError, ImportError):
    """An optional dependency that a chosen feature needs is not installed; the message says
    how to install it. An :class:`ImportError` too, so code catching that keeps working."""


def check_array(
    name: str,
    array: object,
    *,
    dtype: object | None = None,
    ndim: int | None = None,
    shape: tuple[int | None, ...] | None = None,
) -> None:
    """Raise :class:`InputError` unless ``array`` is a NumPy array of the expected form.

    Args:
        name: what the array is, for the message ("descriptors").
        array: the value to check.
        dtype: expected NumPy dtype, if any.
        ndim: expected number of dimensions, if any.
        shape: expected shape; ``None`` entries match any size.
    """
    import numpy as np

    if not isinstance(array, np.ndarray):
        raise InputError(f"{name}: expected a numpy array, got {type(array).__name__}")
    if dtype is not None and array.dtype != np.dtype(dtype):  # type: ignore[call-overload]
        raise InputError(f"{name}: expected dtype {np.dtype(dtype)}, got {array.dtype}")  # type: ignore[call-overload]
    if shape is not None:
        ok = array.ndim == len(shape) and all(
            want is None or want == got for want, got in zip(shape, array.shape, strict=False)
        )
        if not ok:
            want_s = "x".join("N" if s is None else str(s) for s in shape)
            raise InputError(f"{name}: expected shape {want_s}, got {array.shape}")
    elif ndim is not None and array.ndim != ndim:
        raise InputError(f"{name}: expected {ndim} dimensions, got shape {array.shape}")


def reason(exc: BaseException) -> str:
    """A third-party exception as a short phrase for a one-line message: its type and the first
    line of its text (at most 120 characters)."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0][:120]}" if text else type(exc).__name__

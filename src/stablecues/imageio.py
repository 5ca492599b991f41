"""Reading images with clear errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .errors import InputError


def read_image(path: str | Path, *, grey: bool = False, unchanged: bool = False) -> np.ndarray:
    """Read an image file.

    Args:
        path: image file (PNG, JPEG, BMP, PGM, ...).
        grey: return a single-channel (H, W) uint8 image.
        unchanged: keep the file's depth and channels (16-bit depth images).

    Returns:
        (H, W) or (H, W, 3) array; uint8 unless ``unchanged`` keeps a 16-bit file.

    Raises:
        InputError: the file is missing or is not a readable image.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: image file not found")
    flags = cv2.IMREAD_UNCHANGED if unchanged else (cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
    data = np.fromfile(str(p), dtype=np.uint8)
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise InputError(f"{p}: not a readable image (corrupt or unknown format)")
    return image


def to_grey(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Convert a uint8 image (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA to (H, W) grey."""
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name}: expected a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise InputError(f"{name}: expected dtype uint8, got {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise InputError(f"{name}: expected shape HxW or HxWxC with C in 1, 3, 4; got {image.shape}")

"""Images on disk: one reader with a mode, one error type, one suffix list, one lister.

Every stage that reads an image file goes through :func:`read_image`; a missing, empty or
undecodable file raises :class:`~stablecues.errors.ImageError` naming the file.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from .errors import ImageError, InputError

__all__ = [
    "IMAGE_SUFFIXES",
    "ImageMode",
    "is_image_file",
    "list_images",
    "match_by_stem",
    "natural_key",
    "read_depth",
    "read_image",
    "read_labels",
    "to_grey",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")

ImageMode = Literal["bgr", "grey", "unchanged", "8bit", "8bit-grey", "rgb"]
"""How :func:`read_image` returns the pixels:

``bgr``        (H, W, 3) uint8 BGR, whatever the file holds (OpenCV's ``IMREAD_COLOR``)
``rgb``        (H, W, 3) uint8 RGB (the same, channels swapped)
``grey``       (H, W) uint8, decoded to grey by the codec (``IMREAD_GRAYSCALE``)
``unchanged``  the file's own depth and channels (16-bit depth images, label PNGs)
``8bit``       as stored but 8-bit: grey stays (H, W), colour is (H, W, 3) BGR, alpha is
               dropped, 16-bit values are scaled down (``>> 8``); what datasets hand over
``8bit-grey``  ``8bit``, then colour converted to grey with ``cv2.cvtColor``
"""

_FLAGS = {
    "bgr": cv2.IMREAD_COLOR,
    "rgb": cv2.IMREAD_COLOR,
    "grey": cv2.IMREAD_GRAYSCALE,
    "unchanged": cv2.IMREAD_UNCHANGED,
    "8bit": cv2.IMREAD_UNCHANGED,
    "8bit-grey": cv2.IMREAD_UNCHANGED,
}


def read_image(path: str | Path, mode: ImageMode = "bgr") -> np.ndarray:
    """Read an image file.

    Args:
        path: image file (PNG, JPEG, BMP, PGM, TIFF, ...).
        mode: the form of the result, see :data:`ImageMode`.

    Returns:
        (H, W) or (H, W, C) array, uint8 unless ``unchanged`` keeps a 16-bit or float file.

    Raises:
        ImageError: the file is missing, empty or not a decodable image, or (``8bit``) holds
            neither 8- nor 16-bit pixels.
        InputError: an unknown mode.
    """
    flags = _FLAGS.get(mode)
    if flags is None:
        raise InputError(f"image mode {mode!r}: expected one of {', '.join(_FLAGS)}")
    p = Path(path)
    if not p.is_file():
        raise ImageError(f"{p}: image file not found")
    data = np.fromfile(str(p), dtype=np.uint8)
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise ImageError(f"{p}: not a readable image (corrupt or unknown format)")
    if mode == "rgb":
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if mode in ("8bit", "8bit-grey"):
        return _as_8bit(image, p, grey=mode == "8bit-grey")
    return image


def _as_8bit(raw: np.ndarray, path: Path, *, grey: bool) -> np.ndarray:
    if raw.dtype == np.uint16:
        raw = (raw >> 8).astype(np.uint8)
    elif raw.dtype != np.uint8:
        raise ImageError(f"{path}: expected an 8-bit image, found dtype {raw.dtype}")
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[:, :, 0]
    elif raw.ndim == 3 and raw.shape[2] == 4:
        raw = cv2.cvtColor(raw, cv2.COLOR_BGRA2BGR)
    if grey and raw.ndim == 3:
        raw = cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY)
    return raw


def read_depth(path: str | Path, factor: float) -> np.ndarray:
    """Read a depth image: (H, W) float32 metres = value / ``factor``; zeros become NaN.

    Float files (already metres) are not divided.

    Raises:
        ImageError: missing, unreadable or multi-channel file.
    """
    raw = read_image(path, "unchanged")
    if raw.ndim != 2:
        raise ImageError(f"{path}: expected a single-channel depth image, found shape {raw.shape}")
    depth = raw.astype(np.float32)
    if np.issubdtype(raw.dtype, np.integer):
        depth /= np.float32(factor)
    depth[(raw == 0) | ~np.isfinite(depth)] = np.nan
    return depth


def read_labels(path: str | Path) -> np.ndarray:
    """Read a label image: (H, W) uint8 class ids.

    Raises:
        ImageError: missing file, or not a single-channel 8-bit image.
    """
    raw = read_image(path, "unchanged")
    if raw.ndim != 2 or raw.dtype != np.uint8:
        raise ImageError(
            f"{path}: expected a single-channel uint8 label image, found shape {raw.shape} {raw.dtype}"
        )
    return raw


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


# ----------------------------------------------------------------------------------------------
# listing


def natural_key(name: str) -> tuple[tuple[tuple[int, int | str], ...], str]:
    """Sort key comparing digit runs as numbers and letters without case: ``2.png`` before
    ``10.png``, ``img1`` before ``Img2``.

    Names equal under that comparison (``a01`` and ``a1``, ``A.png`` and ``a.png``) are ordered
    by their raw text, so the order is total and the same on every file system.
    """
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p)) if p.isdigit() else (1, p.lower()) for p in parts), name


def is_image_file(path: Path) -> bool:
    """True for a regular file with one of :data:`IMAGE_SUFFIXES` (any case)."""
    return path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES


def list_images(
    folder: str | Path,
    what: str = "images",
    *,
    recursive: bool = False,
    suffixes: Sequence[str] = IMAGE_SUFFIXES,
    allow_empty: bool = False,
) -> list[Path]:
    """Image files in ``folder``, in natural name order (of the path below ``folder``).

    Args:
        folder: the folder.
        what: what the images are, for messages ("left images").
        recursive: include sub-folders.
        suffixes: accepted file suffixes (lower case).
        allow_empty: return an empty list instead of raising when there is no image.

    Raises:
        ImageError: the folder is missing, or (unless ``allow_empty``) holds no image file.
    """
    root = Path(folder)
    if not root.is_dir():
        raise ImageError(f"{root}: {what} folder not found")
    candidates = root.rglob("*") if recursive else root.iterdir()
    files = [p for p in candidates if p.is_file() and p.suffix.lower() in suffixes]
    if not files and not allow_empty:
        raise ImageError(f"{root}: expected image files ({', '.join(suffixes)}), found none")
    return sorted(files, key=lambda p: natural_key(p.relative_to(root).as_posix()))


def match_by_stem(images: Sequence[Path], folder: Path, what: str) -> list[Path]:
    """The file in ``folder`` with the same stem as each of ``images`` (any image suffix).

    Raises:
        ImageError: some image has no counterpart in ``folder``.
    """
    by_stem = {p.stem: p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
    out = []
    for img in images:
        other = by_stem.get(img.stem)
        if other is None:
            raise ImageError(f"{folder}: expected a {what} image named {img.stem}.*, found none")
        out.append(other)
    return out

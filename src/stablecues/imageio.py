"""Images on disk: one reader with a mode, one error type, one suffix list, one lister.

Every stage that reads an image file goes through :func:`read_image`; a missing, empty or
undecodable file raises :class:`~stablecues.errors.ImageError` naming the file.
"""

from __future__ import annotations

import logging
import re
import struct
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from .errors import ImageError, InputError
from .fileio import captured_stderr
from .limits import MAX_IMAGE_BYTES, MAX_IMAGE_PIXELS

logger = logging.getLogger(__name__)

__all__ = [
    "IMAGE_SUFFIXES",
    "ImageMode",
    "check_decoded_bytes",
    "header_size",
    "image_format",
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


def read_image(
    path: str | Path, mode: ImageMode = "bgr", *, max_pixels: int = MAX_IMAGE_PIXELS
) -> np.ndarray:
    """Read an image file: PNG, JPEG, BMP, PNM (PBM, PGM, PPM), TIFF or WebP.

    The format is told from the file's first bytes and its size read from its header before
    anything is decoded: a damaged header, or an image of more than ``max_pixels`` pixels, is
    refused with one error naming the file (a decoder would allocate what the header claims).
    What the codec libraries print while decoding goes into the error (or, for a file that
    still decodes, into a logged warning), not onto the terminal.

    Args:
        path: image file.
        mode: the form of the result, see :data:`ImageMode`.
        max_pixels: the largest width x height accepted (:data:`stablecues.limits.MAX_IMAGE_PIXELS`).

    Returns:
        (H, W) or (H, W, C) array, uint8 unless ``unchanged`` keeps a 16-bit or float file.

    Raises:
        ImageError: the file is missing, empty, of another format, larger than ``max_pixels``
            or not decodable, or (``8bit``) holds neither 8- nor 16-bit pixels.
        InputError: an unknown mode.
    """
    flags = _FLAGS.get(mode)
    if flags is None:
        raise InputError(f"image mode {mode!r}: expected one of {', '.join(_FLAGS)}")
    p = Path(path)
    if not p.is_file():
        raise ImageError(f"{p}: image file not found")
    data = np.fromfile(str(p), dtype=np.uint8)
    if not data.size:
        raise ImageError(f"{p}: not a readable image (the file is empty)")
    buf = data.tobytes()
    kind = image_format(buf)
    if kind is None:
        raise ImageError(f"{p}: not a readable image (expected a PNG, JPEG, BMP, PNM, TIFF or WebP file)")
    size = header_size(buf)
    if size is None:
        raise ImageError(f"{p}: not a readable image (a damaged {kind} header)")
    _check_pixels(p, size, max_pixels)
    check_decoded_bytes(p, buf, size)
    image = _decode(data, flags, p, kind)
    _check_pixels(p, (image.shape[1], image.shape[0]), max_pixels)
    if mode == "rgb":
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if mode in ("8bit", "8bit-grey"):
        return _as_8bit(image, p, grey=mode == "8bit-grey")
    return image


def _decode(data: np.ndarray, flags: int, path: Path, kind: str) -> np.ndarray:
    """``cv2.imdecode``, what the codec prints turned into the error or a logged warning."""
    with captured_stderr() as printed:
        try:
            image = cv2.imdecode(data, flags)
            failure = ""
        except cv2.error as exc:
            image, failure = None, str(exc).strip().splitlines()[-1]
    messages = [failure] if failure else []
    messages += printed.lines
    if image is None:
        why = f"; {messages[0][:120]}" if messages else ""
        raise ImageError(f"{path}: not a readable image (a corrupt {kind} file{why})")
    if messages:
        logger.warning("%s: %s", path, messages[0][:200])
    return image


# channels a PNG colour type decodes to (OpenCV expands a palette to BGR)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}


def check_decoded_bytes(where: object, data: bytes, size: tuple[int, int]) -> None:
    """Refuse a PNG whose header says it decodes to more than :data:`MAX_IMAGE_BYTES` (its
    channels and 16-bit depth count: under the pixel limit a 16-bit RGBA image is 8 bytes a
    pixel); other formats decode to at most 3 bytes a pixel and the pixel limit bounds them."""
    if image_format(data) != "PNG" or len(data) < 26:
        return
    depth, colour = data[24], data[25]
    per_pixel = _PNG_CHANNELS.get(colour, 4) * (2 if depth == 16 else 1)
    need = size[0] * size[1] * per_pixel
    if need > MAX_IMAGE_BYTES:
        raise ImageError(f"{where}: a {size[0]} x {size[1]} PNG of {per_pixel} bytes a pixel decodes to "
                         f"{need >> 20} MiB, more than the {MAX_IMAGE_BYTES >> 20} MiB accepted "
                         "(stablecues.limits)")


def _check_pixels(path: Path, size: tuple[int, int], max_pixels: int) -> None:
    width, height = size
    if width * height > max_pixels:
        raise ImageError(
            f"{path}: a {width} x {height} image is larger than the {max_pixels} pixels accepted "
            "(stablecues.limits)"
        )


_MAGIC = (
    (b"\x89PNG\r\n\x1a\n", "PNG"),
    (b"\xff\xd8\xff", "JPEG"),
    (b"BM", "BMP"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
)


def image_format(data: bytes) -> str | None:
    """The format a file's first bytes announce: "PNG", "JPEG", "BMP", "PNM", "TIFF", "WebP",
    or None for anything else."""
    for magic, name in _MAGIC:
        if data.startswith(magic):
            return name
    if len(data) >= 3 and data[0:1] == b"P" and data[1:2] in (b"1", b"2", b"3", b"4", b"5", b"6"):
        return "PNM"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "WebP"
    return None


def header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the header of a PNG, JPEG, BMP, PNM, TIFF or WebP file, without
    decoding it; None for another format or a damaged header (a PNG's IHDR is checked field by
    field and against its CRC). Give the whole file: a JPEG's size may follow 64 kB of
    metadata, a TIFF's directory may sit at its end."""
    sniffers = {"PNG": _png_size, "JPEG": _jpeg_size, "BMP": _bmp_size, "PNM": _pnm_size,
                "TIFF": _tiff_size, "WebP": _webp_size}  # fmt: skip
    sniff = sniffers.get(image_format(data) or "")
    if sniff is None:
        return None
    try:
        size = sniff(data)
    except (IndexError, ValueError, struct.error):
        return None
    if size is None or size[0] <= 0 or size[1] <= 0:
        return None
    return int(size[0]), int(size[1])


# bit depths each PNG colour type allows
_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}


def _png_size(b: bytes) -> tuple[int, int] | None:
    if b[12:16] != b"IHDR" or struct.unpack(">I", b[8:12])[0] != 13:
        return None
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", b[16:29])
    if struct.unpack(">I", b[29:33])[0] != zlib.crc32(b[12:29]):
        return None
    if depth not in _PNG_DEPTHS.get(colour, ()) or compression or filtering or interlace not in (0, 1):
        return None
    if not _png_chunks_fit(b):
        return None
    return (width, height) if width < 2**31 and height < 2**31 else None


def _png_chunks_fit(b: bytes) -> bool:
    """Whether every chunk up to IEND lies within the file (a decoder allocates a chunk's
    declared length before reading it)."""
    at = 8
    while at + 8 <= len(b):
        (length,) = struct.unpack(">I", b[at : at + 4])
        if length >= 2**31 or at + 12 + length > len(b):
            return False
        if b[at + 4 : at + 8] == b"IEND":
            return True
        at += 12 + length
    return at == len(b)


def _jpeg_size(b: bytes) -> tuple[int, int] | None:
    if not b.startswith(b"\xff\xd8"):
        return None
    i = 2
    while i + 9 < len(b):
        if b[i] != 0xFF:
            return None
        marker = b[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            height, width = struct.unpack(">HH", b[i + 5 : i + 9])
            return width, height
        if marker in (0x01, *range(0xD0, 0xDA)):
            i += 2
            continue
        i += 2 + struct.unpack(">H", b[i + 2 : i + 4])[0]
    return None


def _bmp_size(b: bytes) -> tuple[int, int] | None:
    if not b.startswith(b"BM") or len(b) < 26:
        return None
    if struct.unpack("<I", b[14:18])[0] == 12:  # BITMAPCOREHEADER
        return struct.unpack("<HH", b[18:22])
    width, height = struct.unpack("<ii", b[18:26])
    return abs(width), abs(height)


def _pnm_size(b: bytes) -> tuple[int, int] | None:
    if len(b) < 3 or b[0:1] != b"P" or b[1:2] not in b"123456" or not b[2:3].isspace():
        return None
    text = re.sub(rb"#[^\n]*", b" ", b[2:512])
    parts = text.split()
    return (int(parts[0]), int(parts[1])) if len(parts) >= 2 else None


def _tiff_size(b: bytes) -> tuple[int, int] | None:
    if b[:4] not in (b"II*\x00", b"MM\x00*"):
        return None
    e = "<" if b[:2] == b"II" else ">"
    ifd = struct.unpack(e + "I", b[4:8])[0]
    count = struct.unpack(e + "H", b[ifd : ifd + 2])[0]
    found: dict[int, int] = {}
    for k in range(count):
        at = ifd + 2 + 12 * k
        tag, kind = struct.unpack(e + "HH", b[at : at + 4])
        if tag in (256, 257):
            fmt = e + ("H" if kind == 3 else "I")
            found[tag] = struct.unpack(fmt, b[at + 8 : at + 8 + struct.calcsize(fmt)])[0]
    return (found[256], found[257]) if len(found) == 2 else None


def _webp_size(b: bytes) -> tuple[int, int] | None:
    if b[:4] != b"RIFF" or b[8:12] != b"WEBP":
        return None
    chunk = b[12:16]
    if chunk == b"VP8X":
        return 1 + int.from_bytes(b[24:27], "little"), 1 + int.from_bytes(b[27:30], "little")
    if chunk == b"VP8L":
        bits = int.from_bytes(b[21:25], "little")
        return 1 + (bits & 0x3FFF), 1 + ((bits >> 14) & 0x3FFF)
    if chunk == b"VP8 ":
        width, height = struct.unpack("<HH", b[26:30])
        return width & 0x3FFF, height & 0x3FFF
    return None


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

"""CamVid (SegNet 11-class release) on disk, a cached in-memory copy, and training augmentation.

Layout expected under ``DIR``: ``train/``, ``val/``, ``test/`` with the RGB frames and
``trainannot/``, ``valannot/``, ``testannot/`` with single-channel PNG labels of the same stem
(ids 0..10, 11 = void). Only NumPy and OpenCV are used here, so evaluation needs no torch.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import DatasetError
from ..imageio import list_images, read_image
from .classes import NUM_CLASSES, VOID_ID

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class CamVidSplit:
    """One split held in memory.

    Attributes:
        images: (N, H, W, 3) uint8 RGB frames.
        labels: (N, H, W) uint8 class ids (11 = void).
        names: the N file stems, sorted.
    """

    images: np.ndarray
    labels: np.ndarray
    names: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.images.shape[0])


def read_rgb(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB.

    Raises:
        ImageError: a missing or corrupt file (an InputError and a DatasetError).
    """
    return read_image(path, "rgb")


def read_label(path: str | Path) -> np.ndarray:
    """Read a CamVid label PNG as (H, W) uint8 ids (the first channel of a colour file).

    Raises:
        ImageError: a missing or unreadable file (a DatasetError).
        DatasetError: not uint8, or values above 11.
    """
    label = read_image(path, "unchanged")
    if label.ndim == 3:
        label = label[..., 0]
    if label.dtype != np.uint8 or int(label.max(initial=0)) > VOID_ID:
        raise DatasetError(f"{path}: expected uint8 class ids 0..{VOID_ID}, found max {int(label.max())}")
    return label


def list_split(root: str | Path, split: str) -> list[tuple[Path, Path]]:
    """(image, label) path pairs of one split, sorted by name."""
    if split not in SPLITS:
        raise DatasetError(f"unknown CamVid split {split!r}; expected one of {', '.join(SPLITS)}")
    root = Path(root)
    image_dir, label_dir = root / split, root / f"{split}annot"
    if not image_dir.is_dir() or not label_dir.is_dir():
        raise DatasetError(f"{root}: expected folders {split}/ and {split}annot/ (CamVid SegNet layout)")
    pairs = []
    # natural order; CamVid's names are zero-padded, so it is also their sorted order
    for image in list_images(image_dir, f"CamVid {split}", allow_empty=True):
        label = label_dir / f"{image.stem}.png"
        if not label.is_file():
            raise DatasetError(f"{image}: no label {label.name} in {label_dir}")
        pairs.append((image, label))
    if not pairs:
        raise DatasetError(f"{image_dir}: no images found")
    return pairs


def load_split(
    root: str | Path, split: str, *, cache_dir: str | Path | None = None, limit: int | None = None
) -> CamVidSplit:
    """Load a split into memory, through an ``.npz`` cache in ``cache_dir`` when given.

    Args:
        root: the CamVid folder.
        split: "train", "val" or "test".
        cache_dir: folder for ``camvid_<split>.npz`` (decoded once, reused while the names match).
        limit: keep only the first ``limit`` frames (for smoke tests; never cached).
    """
    pairs = list_split(root, split)
    if limit is not None:
        pairs = pairs[:limit]
    names = tuple(p.stem for p, _ in pairs)
    cache = Path(cache_dir) / f"camvid_{split}.npz" if cache_dir is not None and limit is None else None
    if cache is not None and cache.is_file():
        with np.load(cache) as z:
            if tuple(z["names"].tolist()) == names:
                return CamVidSplit(z["images"], z["labels"], names)
        log.info("cache %s is stale, rebuilding", cache)
    images, labels = [], []
    for image_path, label_path in pairs:
        image, label = read_rgb(image_path), read_label(label_path)
        if image.shape[:2] != label.shape:
            raise DatasetError(f"{label_path}: label is {label.shape}, image is {image.shape[:2]}")
        images.append(image)
        labels.append(label)
    if len({im.shape for im in images}) != 1:
        raise DatasetError(f"{root}/{split}: frames of different sizes; expected one size")
    out = CamVidSplit(np.stack(images), np.stack(labels), names)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_suffix(".tmp.npz")
        np.savez(tmp, images=out.images, labels=out.labels, names=np.array(names))
        tmp.replace(cache)
    return out


def class_frequencies(labels: np.ndarray) -> np.ndarray:
    """(11,) float64 median-frequency statistics: pixels of c / pixels of images containing c."""
    counts = np.zeros(NUM_CLASSES, np.float64)
    present = np.zeros(NUM_CLASSES, np.float64)
    for label in labels:
        hist = np.bincount(label.ravel(), minlength=VOID_ID + 1)[:NUM_CLASSES].astype(np.float64)
        counts += hist
        present += (hist > 0) * float(label.size)
    return counts / np.maximum(present, 1.0)


def median_frequency_weights(labels: np.ndarray) -> np.ndarray:
    """(11,) float32 median-frequency-balancing weights (Eigen & Fergus), as SegNet trains with."""
    freq = class_frequencies(labels)
    valid = freq > 0
    weights = np.ones(NUM_CLASSES, np.float64)
    weights[valid] = np.median(freq[valid]) / freq[valid]
    return weights.astype(np.float32)


@dataclass(frozen=True)
class AugmentConfig:
    """Training augmentation.

    Attributes:
        crop: (height, width) of the training crops.
        scale: range of the random resize factor applied to the full-size frame first.
        flip: probability of a horizontal flip.
        brightness, contrast, saturation: maximum relative colour jitter.
    """

    crop: tuple[int, int] = (224, 288)
    scale: tuple[float, float] = (0.55, 1.1)
    flip: float = 0.5
    brightness: float = 0.25
    contrast: float = 0.25
    saturation: float = 0.25


def augment(
    image: np.ndarray, label: np.ndarray, rng: np.random.Generator, config: AugmentConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Random scale, crop, flip and colour jitter of one frame.

    Args:
        image: (H, W, 3) uint8 RGB.
        label: (H, W) uint8 ids.
        rng: the random generator (seeded by the caller).
        config: augmentation settings.

    Returns:
        ((3, ch, cw) float32 RGB in [0, 1], (ch, cw) int64 ids with padding as void).
    """
    ch, cw = config.crop
    s = rng.uniform(*config.scale)
    h, w = max(1, round(image.shape[0] * s)), max(1, round(image.shape[1] * s))
    img = cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR if s > 1 else cv2.INTER_AREA)
    lab = cv2.resize(label, (w, h), interpolation=cv2.INTER_NEAREST)
    if h < ch or w < cw:
        ph, pw = max(0, ch - h), max(0, cw - w)
        img = cv2.copyMakeBorder(img, 0, ph, 0, pw, cv2.BORDER_CONSTANT, value=(124, 116, 104))
        lab = cv2.copyMakeBorder(lab, 0, ph, 0, pw, cv2.BORDER_CONSTANT, value=VOID_ID)
        h, w = lab.shape
    y0 = int(rng.integers(0, h - ch + 1))
    x0 = int(rng.integers(0, w - cw + 1))
    img = img[y0 : y0 + ch, x0 : x0 + cw]
    lab = lab[y0 : y0 + ch, x0 : x0 + cw]
    if rng.random() < config.flip:
        img, lab = img[:, ::-1], lab[:, ::-1]
    x = img.astype(np.float32) * (1.0 / 255.0)
    b = 1.0 + rng.uniform(-config.brightness, config.brightness)
    c = 1.0 + rng.uniform(-config.contrast, config.contrast)
    sat = 1.0 + rng.uniform(-config.saturation, config.saturation)
    grey = x @ np.array([0.299, 0.587, 0.114], np.float32)
    x = grey[..., None] + sat * (x - grey[..., None])
    x = (x - grey.mean()) * c + grey.mean()
    x = np.clip(x * b, 0.0, 1.0)
    return np.ascontiguousarray(x.transpose(2, 0, 1)), lab.astype(np.int64)


def to_input(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a (H, W, 3) uint8 RGB frame to ``size`` = (height, width) and make a (1, 3, h, w)
    float32 [0, 1] network input."""
    h, w = size
    interp = cv2.INTER_AREA if image.shape[0] > h else cv2.INTER_LINEAR
    x = cv2.resize(image, (w, h), interpolation=interp).astype(np.float32) * (1.0 / 255.0)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])

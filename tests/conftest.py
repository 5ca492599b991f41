"""Shared fixtures: where the real data lives, and skipping cleanly when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from dbkit import make_images
from stablecues.vocabulary import Vocabulary, train_vocabulary

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("STABLECUES_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_path(*parts: str) -> Path:
    """Path under ``../shared/data``; skips the calling test when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not available: {path} is absent")
    return path


@pytest.fixture
def shared_data() -> Path:
    return shared_path()


def textured(h: int = 240, w: int = 320, seed: int = 0, blur: bool = True) -> np.ndarray:
    """A grey (h, w) uint8 image of 150 random filled rectangles on mid grey (corners and blobs
    for any extractor), lightly blurred unless ``blur`` is False."""
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 128, np.uint8)
    for _ in range(150):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        cv2.rectangle(img, (x, y), (x + int(rng.integers(4, 30)), y + int(rng.integers(4, 30))),
                      int(rng.integers(0, 256)), -1)
    return cv2.GaussianBlur(img, (3, 3), 0) if blur else img


# Fixtures of the database tests: descriptor sets of fake images and a small vocabulary.
@pytest.fixture(scope="session")
def images() -> list[np.ndarray]:
    return make_images()


@pytest.fixture(scope="session")
def voc(images: list[np.ndarray]) -> Vocabulary:
    return train_vocabulary(images, k=6, levels=4, seed=0, levels_up=2, progress=False)


@pytest.fixture(scope="session")
def many_images() -> list[np.ndarray]:
    """300 images: enough for many segments with a small tail."""
    return make_images(300, seed=1)


def write_wall_drive(root: Path, frames: int = 16) -> Path:
    """``frames`` grey 320x240 PNGs driving along a textured wall, the frames from the 10th on
    revisiting the first ones (5 px off); returns ``root``."""
    rng = np.random.default_rng(3)
    pano = np.full((260, 1400), 110, np.uint8)
    for _ in range(1600):
        x, y = int(rng.integers(0, 1400)), int(rng.integers(0, 260))
        w, h = int(rng.integers(3, 25)), int(rng.integers(3, 25))
        cv2.rectangle(pano, (x, y), (x + w, y + h), int(rng.integers(0, 256)), -1)
    pano = cv2.GaussianBlur(pano, (3, 3), 0)
    for i in range(frames):
        x = 60 * i if i < 9 else 60 * (i - 9) + 5
        cv2.imwrite(str(root / f"{i:03d}.png"), pano[10:250, x : x + 320])
    return root

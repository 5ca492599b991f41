"""Shared fixtures: where the real data lives, and skipping cleanly when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

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

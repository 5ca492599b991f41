"""Helpers shared by the database tests (and by the subprocesses the crash tests start)."""

from __future__ import annotations

import numpy as np

from stablecues.database import Database
from stablecues.types import Features
from stablecues.vocabulary import Vocabulary

N_IMAGES = 30


def fake_features(desc: np.ndarray) -> Features:
    n = desc.shape[0]
    rng = np.random.default_rng(n)
    return Features(
        keypoints=rng.random((n, 2)).astype(np.float32) * 100,
        descriptors=desc,
        octaves=np.zeros(n, np.int16),
        angles=np.zeros(n, np.float32),
        responses=np.ones(n, np.float32),
        sizes=np.full(n, 31, np.float32),
        image_size=(100, 100),
    )


def make_images(n: int = N_IMAGES, seed: int = 0) -> list[np.ndarray]:
    """Descriptor sets of 'images': each mixes its own descriptors with some shared ones."""
    rng = np.random.default_rng(seed)
    common = rng.integers(0, 256, (60, 32), dtype=np.uint8)
    return [
        np.concatenate([rng.integers(0, 256, (80, 32), dtype=np.uint8), common[rng.choice(60, 20)]])
        for _ in range(n)
    ]


def fill(
    db: Database, voc: Vocabulary, images: list[np.ndarray], with_3d: bool = False, start: int = 0,
    session: int | None = None,
) -> list[int]:
    ids = []
    for k, d in enumerate(images):
        i = start + k
        bow, fvec = voc.transform(d)
        pts = np.random.default_rng(i).random((d.shape[0], 3)).astype(np.float32) if with_3d else None
        ids.append(db.add(bow, fvec, fake_features(d), points3d=pts, timestamp=float(i), meta={"i": i},
                          session=session))
    return ids


def brute_scores(db: Database, voc: Vocabulary, query: np.ndarray) -> dict[int, float]:
    """Score of a query against every live entry, pairwise (no inverse index)."""
    from stablecues.vocabulary import score

    bow, _ = voc.transform(query)
    out = {}
    for i in db.ids().tolist():
        other = db.entry(i).bow
        if np.intersect1d(bow.words, other.words).size:
            out[i] = score(bow, other, voc.scoring)
    return out

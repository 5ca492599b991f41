"""Semantic weighting in the preparation path: the BoW vector re-weighted, every feature kept."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from stablecues.detection import FramePreparer, LoopDetector, preset
from stablecues.errors import InputError
from stablecues.types import Frame
from stablecues.vocabulary import default_vocabulary


def textured(seed: int = 0, shape: tuple[int, int] = (240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (shape[0] // 8, shape[1] // 8), dtype=np.uint8)
    return np.kron(small, np.ones((8, 8), np.uint8))


def frame(image: np.ndarray, **kwargs: object) -> Frame:
    return Frame(index=3, name="f3", timestamp=0.0, image=image, **kwargs)  # type: ignore[arg-type]


def test_semantic_weighting_reweights_the_bow_and_keeps_every_feature() -> None:
    vocab = default_vocabulary()
    img = textured(4)
    labels = np.full(img.shape, 1, np.uint8)  # Building on the left ...
    labels[:, img.shape[1] // 2:] = 8  # ... Car on the right
    weighted_cfg = dataclasses.replace(preset("weighted"), semantic_source="labels")
    weighted = FramePreparer(weighted_cfg, vocab).prepare(frame(img, labels=labels))
    plain = FramePreparer(preset("default"), vocab).prepare(frame(img))
    assert len(weighted.features) == len(plain.features) and not weighted.mask_fallback
    np.testing.assert_array_equal(weighted.fvec.nodes, plain.fvec.nodes)
    assert set(weighted.bow.words.tolist()) == set(plain.bow.words.tolist())
    right = weighted.features.keypoints[:, 0] >= img.shape[1] // 2
    words_right = set(vocab.transform(weighted.features.descriptors[right])[0].words.tolist())
    words_left = set(vocab.transform(weighted.features.descriptors[~right])[0].words.tolist())
    only_right = np.isin(weighted.bow.words, sorted(words_right - words_left))
    only_left = np.isin(weighted.bow.words, sorted(words_left - words_right))
    ratio = weighted.bow.weights / plain.bow.weights
    assert ratio[only_right].mean() < 0.6 * ratio[only_left].mean()  # cars count less than buildings
    assert "segment" in weighted.timings


def test_feature_weights_travel_with_the_view_and_the_entry(tmp_path: Path) -> None:
    """The weights that weight the BoW vector also order the matches for triangles: the prepared
    frame hands them to the verifier and the map keeps them with the entry, in the same float32
    a reopened map gives back."""
    img = textured(4)
    labels = np.full(img.shape, 1, np.uint8)
    labels[:, img.shape[1] // 2:] = 8  # Car on the right
    cfg = dataclasses.replace(preset("weighted"), semantic_source="labels")
    prep = FramePreparer(cfg, default_vocabulary()).prepare(frame(img, labels=labels))
    assert prep.weights is not None and prep.weights.dtype == np.float32
    assert prep.weights.shape == (len(prep.features),) and prep.view.weights is prep.weights
    right = prep.features.keypoints[:, 0] >= img.shape[1] // 2
    assert prep.weights[right].mean() < 0.6 * prep.weights[~right].mean()
    assert FramePreparer(preset("fast"), default_vocabulary()).prepare(frame(img)).weights is None

    det = LoopDetector(cfg, database=tmp_path / "map.sqlite")
    det.process(frame(img, labels=labels))
    det.close()
    reopened = LoopDetector(cfg, database=tmp_path / "map.sqlite")
    stored = reopened.db.entry(0).arrays["weights"]
    np.testing.assert_array_equal(stored, prep.weights)
    reopened.close()


def test_malformed_stored_weights_name_the_map(tmp_path: Path) -> None:
    """A map entry whose stored weights do not fit its features: a one-line error naming the file."""
    cfg = dataclasses.replace(preset("weighted"), semantic_source="labels")
    det = LoopDetector(cfg, database=tmp_path / "map.sqlite")
    prep = det.preparer.prepare(frame(textured(4), labels=np.full((240, 320), 1, np.uint8)))
    det.db.add(prep.bow, prep.fvec, prep.features, arrays={"weights": np.ones(5, np.float32)})
    with pytest.raises(InputError, match=r"map\.sqlite: database entry 0: view: feature weights") as info:
        det._candidate(det.preparer.verifier(None), 0)
    assert "\n" not in str(info.value)
    det.close()

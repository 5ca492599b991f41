"""Semantic weighting: stable classes count more, dynamic ones less, unsure pixels not at all."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import ConfigError
from stablecues.semantics.classes import CLASS_NAMES, NUM_CLASSES
from stablecues.semantics.inference import SegmentationResult
from stablecues.semantics.weighting import WeightingConfig, feature_weights, shipped_stability
from stablecues.types import Features

BUILDING, CAR = CLASS_NAMES.index("Building"), CLASS_NAMES.index("Car")


def _features(xy: list[tuple[float, float]]) -> Features:
    n = len(xy)
    return Features(np.array(xy, np.float32), np.zeros((n, 32), np.uint8), np.zeros(n, np.int16),
                    np.zeros(n, np.float32), np.ones(n, np.float32), np.full(n, 31.0, np.float32), (80, 40))


def _seg(prob: np.ndarray) -> SegmentationResult:
    """A segmentation of an 80x40 frame from a (C, 10, 20) posterior."""
    labels = np.zeros((40, 80), np.uint8)
    return SegmentationResult(labels, np.ones((40, 80), np.float32), np.zeros((40, 80), np.float32), 1,
                              prob.astype(np.float32))


def test_sure_classes_take_their_stability_and_flat_posteriors_fade_out() -> None:
    prob = np.full((NUM_CLASSES, 10, 20), 1.0 / NUM_CLASSES)  # unsure everywhere ...
    prob[:, :, :5] = 0.0
    prob[BUILDING, :, :5] = 1.0  # ... but sure of a building on the left
    prob[:, :, 15:] = 0.0
    prob[CAR, :, 15:] = 1.0  # and of a car on the right
    cfg = WeightingConfig(stability={"Building": 1.5, "Car": 0.2}, domain=None)
    w = feature_weights(_features([(2.0, 20.0), (40.0, 20.0), (78.0, 20.0)]), _seg(prob), cfg)
    np.testing.assert_allclose(w, [1.5, 1.0, 0.2])
    assert feature_weights(_features([(78.0, 20.0)]), _seg(prob), WeightingConfig(
        stability={"Car": 0.0}, min_weight=0.05, domain=None))[0] == pytest.approx(0.05)  # suppressed
    assert feature_weights(_features([(2.0, 20.0)]), _seg(prob), WeightingConfig(
        stability={"Building": 1.5}, strength=0.0))[0] == pytest.approx(1.0)


def test_frames_the_network_is_unsure_of_fade_to_plain_bow() -> None:
    """The frame as a whole gates the weighting: a frame whose mean certainty is below
    domain[0] is weighted 1 everywhere, above domain[1] fully, linearly between."""
    def frame(sure: float) -> SegmentationResult:
        # a posterior sure of a car on the right, and equally sure of something everywhere
        prob = np.full((NUM_CLASSES, 10, 20), (1.0 - sure) / (NUM_CLASSES - 1))
        prob[BUILDING] = sure
        prob[:, :, 15:] = (1.0 - sure) / (NUM_CLASSES - 1)
        prob[CAR, :, 15:] = sure
        return _seg(prob)

    lam = lambda sure: (sure - 1 / NUM_CLASSES) / (1 - 1 / NUM_CLASSES)  # noqa: E731
    cfg = WeightingConfig(stability={"Car": 0.2}, domain=(0.75, 0.85))
    car = _features([(78.0, 20.0)])
    for sure in (0.6, 0.76, 0.8, 0.84, 0.95, 1.0):
        seg = frame(sure)
        assert seg.frame_certainty() == pytest.approx(lam(sure))
        gate = float(np.clip((lam(sure) - 0.75) / 0.10, 0.0, 1.0))
        stability = sure * 0.2 + (1.0 - sure) * 1.0  # the posterior's expected stability
        expected = 1.0 + gate * lam(sure) * (stability - 1.0)
        assert feature_weights(car, seg, cfg)[0] == pytest.approx(expected)
    assert feature_weights(car, frame(0.6), cfg)[0] == 1.0  # out of domain: plain BoW
    assert feature_weights(car, frame(1.0), cfg)[0] == pytest.approx(0.2)  # in domain: full
    with pytest.raises(ConfigError, match="domain"):
        WeightingConfig(domain=(0.9, 0.8))


def test_oracle_labels_are_certain() -> None:
    labels = np.full((40, 80), BUILDING, np.uint8)
    labels[:, 40:] = CAR
    seg = SegmentationResult(labels, np.ones((40, 80), np.float32), np.zeros((40, 80), np.float32), 0,
                             np.zeros((NUM_CLASSES, 1, 1), np.float32))
    w = feature_weights(_features([(10.0, 10.0), (70.0, 10.0)]), seg, WeightingConfig())
    table = shipped_stability()
    np.testing.assert_allclose(w, [table["Building"], table["Car"]])


def test_shipped_stabilities_follow_the_measurement() -> None:
    """Measured on real CamVid revisits (scripts/estimate_class_stability.py): buildings come back
    more often than the average feature, cars, people and road texture much less."""
    s = shipped_stability()
    assert set(CLASS_NAMES) <= set(s)
    assert s["Building"] > 1.0 > s["Car"] and s["Pedestrian"] < 0.5 and s["Road"] < 0.5


def test_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match="unknown class"):
        WeightingConfig(stability={"Cow": 2.0})
    with pytest.raises(ConfigError):
        WeightingConfig(min_weight=0.0)
    empty = Features.empty((80, 40))
    assert len(feature_weights(empty, _seg(np.ones((NUM_CLASSES, 10, 20))), WeightingConfig())) == 0

"""Stable cues by weight, not deletion: each feature counts as much as its class comes back.

The paper deletes features off static classes; METHOD.md measured that deletion loses places
(skyline and road-marking corners identify them). Here every feature keeps a place in the
bag-of-words vector, weighted by the *stability* of its class: how often features of that class
were found again when a place was revisited (``scripts/estimate_class_stability.py`` measures it
on real CamVid revisits; ``data/class_stability.json`` ships the result). Cars, people and road
texture come back about a third as often as the average feature, building corners and skylines
more often.

The network's certainty decides how far a feature's weight moves from 1: with the mean softmax
``p`` at the keypoint, the expected stability is ``s = sum_c p_c stability_c`` and the certainty
``lam = (max_c p_c - 1/C) / (1 - 1/C)`` (0 for a flat posterior, 1 for a sure one); the weight is
``1 + lam * (s - 1)`` (raised to ``strength``, floored at ``min_weight``). Where the network is
unsure (indoors, out of its domain) the weights fade to 1 by themselves: the plain BoW vector.
"""

from __future__ import annotations

import functools
import importlib.resources
import json
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, ModelError
from ..types import Features
from .classes import CLASS_NAMES, NUM_CLASSES
from .inference import SegmentationResult

__all__ = ["WeightingConfig", "feature_weights", "shipped_stability", "STABILITY_FILE"]

STABILITY_FILE = "class_stability.json"


@functools.cache
def shipped_stability() -> dict[str, float]:
    """The per-class stabilities shipped with the package (``data/class_stability.json``)."""
    path = importlib.resources.files("stablecues") / "data" / STABILITY_FILE
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        table = {str(k): float(v) for k, v in doc["stability"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ModelError(f"{path}: expected the class-stability table, could not read it ({exc})") from None
    return table


@dataclass(frozen=True)
class WeightingConfig:
    """Semantic weighting of features.

    Attributes:
        stability: class name -> stability (1: average); None takes the shipped estimates.
            Classes left out count 1.
        strength: exponent on the weights (0: no weighting, 1: the stabilities as measured).
        min_weight: the smallest weight a feature gets (dynamic objects are suppressed, not
            removed: a parked car may still help when nothing else is there).
    """

    stability: Mapping[str, float] | None = None
    strength: float = 1.0
    min_weight: float = 0.05

    def __post_init__(self) -> None:
        if not (self.strength >= 0 and 0 < self.min_weight <= 1):
            raise ConfigError(
                f"semantic weighting: strength >= 0 and min_weight in (0, 1] needed, got {self}"
            )
        if self.stability is not None:
            unknown = sorted(set(self.stability) - set(CLASS_NAMES) - {"Unlabelled"})
            if unknown:
                raise ConfigError(f"semantic weighting: unknown class {unknown[0]!r}; known: "
                                  f"{', '.join(CLASS_NAMES)}")

    def class_weights(self) -> np.ndarray:
        """(C,) float64 stability of each network class, in class-id order."""
        table = shipped_stability() if self.stability is None else dict(self.stability)
        return np.array([float(table.get(name, 1.0)) for name in CLASS_NAMES[:NUM_CLASSES]])


def _posterior(features: Features, seg: SegmentationResult) -> np.ndarray:
    """(N, C) class posterior at each keypoint: the network's mean softmax, or one-hot labels."""
    kp = features.keypoints
    w, h = seg.image_size
    prob = seg.prob
    if prob.ndim == 3 and prob.shape[0] == NUM_CLASSES and prob.shape[1] > 1 and prob.shape[2] > 1:
        ph, pw = prob.shape[1:]
        x = np.clip((kp[:, 0] * pw / w).astype(np.int64), 0, pw - 1)
        y = np.clip((kp[:, 1] * ph / h).astype(np.int64), 0, ph - 1)
        return np.asarray(prob[:, y, x].T, np.float64)
    # labels given (semantic_source="labels"): certain, one class per pixel
    x = np.clip(kp[:, 0].astype(np.int64), 0, w - 1)
    y = np.clip(kp[:, 1].astype(np.int64), 0, h - 1)
    lab = seg.labels[y, x].astype(np.int64)
    out = np.zeros((len(kp), NUM_CLASSES))
    known = lab < NUM_CLASSES
    out[np.flatnonzero(known), lab[known]] = 1.0
    out[~known] = 1.0 / NUM_CLASSES  # void: no information
    return out


def feature_weights(features: Features, seg: SegmentationResult, config: WeightingConfig) -> np.ndarray:
    """(N,) float64 weight of each feature (see the module docstring)."""
    if not len(features):
        return np.zeros(0)
    p = _posterior(features, seg)
    expected = p @ config.class_weights()
    certainty = np.clip((p.max(axis=1) - 1.0 / NUM_CLASSES) / (1.0 - 1.0 / NUM_CLASSES), 0.0, 1.0)
    weight = 1.0 + certainty * (expected - 1.0)
    return np.maximum(np.power(np.maximum(weight, 0.0), config.strength), config.min_weight)

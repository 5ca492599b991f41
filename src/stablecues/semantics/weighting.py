"""Stable cues by weight, not deletion: each feature counts as much as its class comes back.

The paper deletes features off static classes; docs/presets.md shows that deletion loses places
(skyline and road-marking corners identify them). Here every feature keeps a place in the
bag-of-words vector, weighted by the *stability* of its class: how often features of that class
were found again when a place was revisited (``scripts/estimate_class_stability.py`` measures it
on real CamVid revisits; ``data/class_stability.json`` ships the result). Cars, people and road
texture come back about a third as often as the average feature, building corners and skylines
more often.

The network's certainty decides how far a feature's weight moves from 1: with the mean softmax
``p`` at the keypoint, the expected stability is ``s = sum_c p_c stability_c`` and the certainty
``lam = (max_c p_c - 1/C) / (1 - 1/C)`` (0 for a flat posterior, 1 for a sure one); the weight is
``1 + g * lam * (s - 1)`` (raised to ``strength``, floored at ``min_weight``).

The softmax alone is over-confident out of its domain (a corridor's ceiling is "Sky" at 0.9), so
the frame as a whole gates it too: ``g`` rises linearly from 0 to 1 as the frame's mean
certainty (:meth:`SegmentationResult.frame_certainty`) goes from ``domain[0]`` to ``domain[1]``.
The defaults (0.75, 0.85) sit between the medians measured on eight sets with the shipped
network at T = 1: CamVid train and val drives 0.86-0.87 (10th percentile 0.76-0.79), indoor
corridor, TUM desk and Kinect 0.72-0.77, KITTI 0.81 and EuRoC 0.79. Where the network is unsure
(indoors, out of its domain) the weights thus fade to 1 by themselves: the plain BoW vector.
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
        domain: (lo, hi) frame certainties between which the weighting fades in (below lo: no
            weighting; above hi: full); None weighs every frame fully.
    """

    stability: Mapping[str, float] | None = None
    strength: float = 1.0
    min_weight: float = 0.05
    domain: tuple[float, float] | None = (0.75, 0.85)

    def __post_init__(self) -> None:
        if not (self.strength >= 0 and 0 < self.min_weight <= 1):
            raise ConfigError(
                f"semantic weighting: strength >= 0 and min_weight in (0, 1] needed, got {self}"
            )
        if self.domain is not None and not (
            len(self.domain) == 2 and 0.0 <= self.domain[0] < self.domain[1] <= 1.0
        ):
            raise ConfigError(f"semantic weighting: domain must be (lo, hi) with 0 <= lo < hi <= 1, "
                              f"got {self.domain}")
        if self.stability is not None:
            unknown = sorted(set(self.stability) - set(CLASS_NAMES) - {"Unlabelled"})
            if unknown:
                raise ConfigError(f"semantic weighting: unknown class {unknown[0]!r}; known: "
                                  f"{', '.join(CLASS_NAMES)}")

    def frame_gate(self, certainty: float) -> float:
        """How much of the weighting applies at this frame certainty, in [0, 1] (module docstring)."""
        if self.domain is None:
            return 1.0
        lo, hi = self.domain
        return float(np.clip((certainty - lo) / (hi - lo), 0.0, 1.0))

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


def feature_weights(
    features: Features, seg: SegmentationResult, config: WeightingConfig, certainty: float | None = None
) -> np.ndarray:
    """(N,) float64 weight of each feature (see the module docstring).

    ``certainty`` is the certainty that places the frame in or out of the network's domain: the
    detector hands in the median over the recent frames of the stream (one unsure frame of a
    street drive stays in the domain); None takes this frame's own.
    """
    if not len(features):
        return np.zeros(0)
    gate = config.frame_gate(seg.frame_certainty() if certainty is None else certainty)
    if gate <= 0.0:
        return np.ones(len(features))
    p = _posterior(features, seg)
    expected = p @ config.class_weights()
    certainty = np.clip((p.max(axis=1) - 1.0 / NUM_CLASSES) / (1.0 - 1.0 / NUM_CLASSES), 0.0, 1.0)
    weight = 1.0 + gate * certainty * (expected - 1.0)
    return np.maximum(np.power(np.maximum(weight, 0.0), config.strength), config.min_weight)

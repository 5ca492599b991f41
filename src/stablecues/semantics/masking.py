"""Meaningful feature selection: keep keypoints on static, confidently segmented structure.

Modes (``MaskingConfig.mode``):

- ``"hard"`` (the paper): keep a keypoint when the class at its pixel is in the static set and
  the uncertainty there is at most ``max_uncertainty``.
- ``"dilate"``: as ``hard``, with the static mask dilated by ``dilation`` pixels first, so corners
  on a static/non-static boundary (skylines, kerbs) survive.
- ``"patch"``: the class is looked up over the keypoint's patch (a square of half-side
  ``patch_radius``, or half the keypoint's size when None): keep when at least ``patch_fraction``
  of the patch is static and the patch's mean uncertainty is at most ``max_uncertainty``.
- ``"dynamic"``: drop only keypoints whose pixel is confidently (uncertainty at most
  ``max_uncertainty``) a dynamic class (Car, Pedestrian, Bicyclist); keep everything else.
  This is the default: the ablation in docs/presets.md measured hard static masking losing place
  recognition (skyline and road-marking corners identify places) and dynamic-only masking
  gaining it; the paper's rule is the ``"paper"`` preset. The project's ablation decides.
- ``"none"``: keep everything (the baseline).

Fallback: when fewer than ``min_kept`` keypoints, or fewer than ``min_kept_fraction`` of them,
survive (a frame outside the network's domain, e.g. indoors), all keypoints are kept and the
report says ``fallback=True``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError, InputError
from ..types import Features
from .classes import DYNAMIC_CLASSES, STATIC_CLASSES, class_lookup
from .inference import SegmentationResult
from .modes import MODES

PixelRule = Callable[[SegmentationResult, "MaskingConfig"], np.ndarray]
"""``(segmentation, settings) -> (H, W) bool``: the pixels where a keypoint is kept."""

KeypointRule = Callable[
    [Features, SegmentationResult, "MaskingConfig", np.ndarray, np.ndarray, float], np.ndarray
]
"""``(features, segmentation, settings, x, y, x scale) -> (N,) bool``: the keypoints kept, with
``x``, ``y`` the (N,) int64 pixel of each keypoint in the segmentation."""


def _trusted(seg: SegmentationResult, config: MaskingConfig) -> np.ndarray:
    trusted = seg.uncertainty <= config.max_uncertainty
    if config.min_confidence > 0:
        trusted &= seg.confidence >= config.min_confidence
    return trusted


def _static(seg: SegmentationResult, config: MaskingConfig) -> np.ndarray:
    """hard: a static class, confidently."""
    return class_lookup(config.static_classes)[seg.labels] & _trusted(seg, config)


def _dilated_static(seg: SegmentationResult, config: MaskingConfig) -> np.ndarray:
    """dilate: the hard map dilated by ``dilation`` pixels."""
    static = _static(seg, config)
    if config.dilation > 0:
        k = 2 * config.dilation + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        static = cv2.dilate(static.astype(np.uint8), kernel).astype(bool)
    return static


def _not_dynamic(seg: SegmentationResult, config: MaskingConfig) -> np.ndarray:
    """dynamic: everywhere but confidently dynamic classes."""
    dynamic = class_lookup(config.dynamic_classes)[seg.labels]
    return ~(dynamic & _trusted(seg, config))


def _everywhere(seg: SegmentationResult, config: MaskingConfig) -> np.ndarray:
    """none: every pixel."""
    return np.ones(seg.labels.shape, bool)


def _at_pixel(
    features: Features, seg: SegmentationResult, config: MaskingConfig, x: np.ndarray, y: np.ndarray,
    sx: float,
) -> np.ndarray:
    """The mode's pixel map looked up at each keypoint."""
    return pixel_mask(seg, config)[y, x]


def _static_patch(
    features: Features, seg: SegmentationResult, config: MaskingConfig, x: np.ndarray, y: np.ndarray,
    sx: float,
) -> np.ndarray:
    """patch: static fraction and mean uncertainty over each keypoint's square patch."""
    h, w = seg.labels.shape
    static = class_lookup(config.static_classes)[seg.labels].astype(np.float64)
    if config.patch_radius is None:
        r = np.maximum(np.round(features.sizes.astype(np.float64) * sx / 2.0), 1).astype(np.int64)
    else:
        r = np.full(len(features), config.patch_radius, np.int64)
    frac = _box_mean(cv2.integral(static), x, y, r, w, h)
    unc = _box_mean(cv2.integral(seg.uncertainty.astype(np.float64)), x, y, r, w, h)
    return (frac >= config.patch_fraction) & (unc <= config.max_uncertainty)


#: mode -> its pixel map (the patch mode depends on each keypoint's size and has no pixel map;
#: it gets the hard mode's)
PIXEL_RULES: dict[str, PixelRule] = {
    "hard": _static,
    "dilate": _dilated_static,
    "patch": _static,
    "dynamic": _not_dynamic,
    "none": _everywhere,
}

#: mode -> how its keypoints are decided, for modes that do more than look up their pixel
KEYPOINT_RULES: dict[str, KeypointRule] = {
    "patch": _static_patch,
}

if tuple(PIXEL_RULES) != MODES:  # one name list for the command line (.modes) and the rules here
    raise ImportError(f"masking modes {tuple(PIXEL_RULES)} differ from stablecues.semantics.modes {MODES}")


@dataclass(frozen=True)
class MaskingConfig:
    """Settings of the feature selection (see the module docstring for the modes).

    Attributes:
        mode: "hard", "dilate", "patch", "dynamic" or "none".
        static_classes: class names whose features are kept (hard / dilate / patch).
        dynamic_classes: class names whose features are dropped (dynamic).
        max_uncertainty: highest uncertainty at which a pixel's class is trusted (the uncertainty
            is the variance of the winning class's softmax, in [0, 0.25]; always 0 with T = 1).
            0.01 is chosen from the shipped weights' calibration on CamVid val (T = 6): pixels
            below it (92 %) are 95 % correct, those above it 64 %.
        min_confidence: lowest mean softmax of the winning class at which a pixel's class is
            trusted (0: any). With T = 1 the uncertainty is always 0, so this is the certainty
            gate that still works; it keeps unsure pixels (indoors) from being dropped.
        dilation: radius in pixels of the static mask's dilation (dilate).
        patch_radius: half-side of the square patch in pixels; None = half the keypoint's size.
        patch_fraction: static fraction of the patch needed to keep a keypoint (patch).
        min_kept: fewer survivors than this keeps every keypoint (fallback); 0 disables it.
        min_frame_certainty: frames whose mean certainty
            (:meth:`SegmentationResult.frame_certainty`) is below this are outside the network's
            domain: every keypoint is kept and the report says ``out_of_domain`` (0 disables it;
            the default preset uses 0.8, between the medians of CamVid drives, 0.86-0.87, and of
            indoor sets, 0.72-0.77).
        min_kept_fraction: fewer survivors than this fraction of the keypoints also triggers the
            fallback (0 disables it). With the shipped weights and the paper's hard mask, 10 % of
            ORB features survive on indoor EuRoC frames, 24 % on TUM desk, 44 % on KITTI, 70 %
            on CamVid test, so 0.2 catches the frames the network does not understand.
    """

    mode: str = "dynamic"
    static_classes: frozenset[str] = STATIC_CLASSES
    dynamic_classes: frozenset[str] = DYNAMIC_CLASSES
    max_uncertainty: float = 0.01
    min_confidence: float = 0.0
    dilation: int = 8
    patch_radius: int | None = None
    patch_fraction: float = 0.5
    min_kept: int = 50
    min_kept_fraction: float = 0.2
    min_frame_certainty: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_frame_certainty <= 1.0:
            raise ConfigError(
                f"min_frame_certainty: expected a value in [0, 1], got {self.min_frame_certainty}"
            )
        if self.mode not in MODES:
            raise ConfigError(f"masking mode: expected one of {', '.join(MODES)}, got {self.mode!r}")
        if not 0.0 <= self.min_kept_fraction <= 1.0:
            raise ConfigError(f"min_kept_fraction: expected a value in [0, 1], got {self.min_kept_fraction}")
        if self.dilation < 0 or self.min_kept < 0:
            raise ConfigError(f"dilation and min_kept must be >= 0, got {self.dilation}, {self.min_kept}")
        if not 0.0 <= self.patch_fraction <= 1.0:
            raise ConfigError(f"patch_fraction: expected a value in [0, 1], got {self.patch_fraction}")
        if self.patch_radius is not None and self.patch_radius < 0:
            raise ConfigError(f"patch_radius: expected >= 0 or None, got {self.patch_radius}")
        class_lookup(self.static_classes)  # rejects unknown names
        class_lookup(self.dynamic_classes)


#: Named settings: the paper's hard mask and the soft forms measured against it (docs/presets.md).
MASKING_PRESETS: dict[str, MaskingConfig] = {
    "paper": MaskingConfig(mode="hard"),
    "dilate": MaskingConfig(mode="dilate"),
    "patch": MaskingConfig(mode="patch"),
    "dynamic": MaskingConfig(mode="dynamic"),
    "none": MaskingConfig(mode="none"),
}


@dataclass(frozen=True)
class MaskReport:
    """What the selection did to one frame.

    Attributes:
        total: keypoints handed in.
        kept: keypoints handed out.
        passed: (N,) bool, the masking decision per keypoint before any fallback.
        fallback: True when too few passed and every keypoint was kept instead.
        classes: (N,) uint8 class id at each keypoint's pixel.
        out_of_domain: the frame's certainty was below ``min_frame_certainty``: nothing dropped.
    """

    total: int
    kept: int
    passed: np.ndarray
    fallback: bool
    classes: np.ndarray
    out_of_domain: bool = False

    @property
    def dropped(self) -> int:
        """Keypoints removed."""
        return self.total - self.kept


def _pixels(features: Features, seg: SegmentationResult) -> tuple[np.ndarray, np.ndarray, float]:
    """Integer pixel (x, y) of each keypoint in the segmentation's frame, and the x scale."""
    seg_w, seg_h = seg.image_size
    feat_w, feat_h = features.image_size
    sx = seg_w / feat_w if feat_w > 0 else 1.0
    sy = seg_h / feat_h if feat_h > 0 else 1.0
    xy = features.keypoints.astype(np.float64)
    if not np.isfinite(xy).all():
        raise InputError("features: keypoints must be finite (NaN or inf found)")
    x = np.clip(np.floor(xy[:, 0] * sx), 0, seg_w - 1).astype(np.int64)
    y = np.clip(np.floor(xy[:, 1] * sy), 0, seg_h - 1).astype(np.int64)
    return x, y, sx


def pixel_mask(seg: SegmentationResult, config: MaskingConfig) -> np.ndarray:
    """(H, W) bool map of the pixels where a keypoint would be kept (hard, dilate, dynamic, none).

    Usable as the extractor's detection mask. The patch mode depends on each keypoint's size and
    has no pixel map; it gets the hard mode's map here.
    """
    return PIXEL_RULES[config.mode](seg, config)


def _box_mean(
    integral: np.ndarray, x: np.ndarray, y: np.ndarray, r: np.ndarray, w: int, h: int
) -> np.ndarray:
    x0, x1 = np.clip(x - r, 0, w), np.clip(x + r + 1, 0, w)
    y0, y1 = np.clip(y - r, 0, h), np.clip(y + r + 1, 0, h)
    total = integral[y1, x1] - integral[y0, x1] - integral[y1, x0] + integral[y0, x0]
    area = np.maximum((x1 - x0) * (y1 - y0), 1)
    return total / area


def select_features(
    features: Features,
    seg: SegmentationResult,
    config: MaskingConfig | None = None,
    certainty: float | None = None,
) -> tuple[Features, MaskReport]:
    """Keep the features on meaningful structure.

    Args:
        features: keypoints of a frame (coordinates in the frame whose size is
            ``features.image_size``; they are scaled if the segmentation has another size).
        seg: the frame's segmentation.
        config: the selection settings (default: ``MaskingConfig()``).
        certainty: the certainty compared with ``min_frame_certainty`` (the detector hands in the
            median over the stream's recent frames); None takes this frame's own.

    Returns:
        (the kept features, the report). Zero features give zero features and no fallback.
    """
    config = MaskingConfig() if config is None else config
    if not isinstance(features, Features):
        raise InputError(f"features: expected Features, got {type(features).__name__}")
    n = len(features)
    if n == 0:
        empty = np.zeros(0, bool)
        return features, MaskReport(0, 0, empty, False, np.zeros(0, np.uint8))
    x, y, sx = _pixels(features, seg)
    classes = seg.labels[y, x]
    if config.min_frame_certainty > 0 and (
        seg.frame_certainty() if certainty is None else certainty
    ) < config.min_frame_certainty:
        return features, MaskReport(n, n, np.ones(n, bool), False, classes.astype(np.uint8), True)
    rule = KEYPOINT_RULES.get(config.mode, _at_pixel)
    passed = rule(features, seg, config, x, y, sx)
    n_passed = int(passed.sum())
    needed = max(config.min_kept, math.ceil(config.min_kept_fraction * n))
    fallback = n_passed < needed and n_passed < n
    kept = features if fallback else features.subset(passed)
    return kept, MaskReport(n, len(kept), passed, fallback, classes.astype(np.uint8))

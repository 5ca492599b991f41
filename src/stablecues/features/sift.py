"""SIFT features through OpenCV (``cv2.SIFT``, in the main package since OpenCV 4.4).

Descriptors are (N, 128) float32, as OpenCV computes them (each a unit vector scaled by 512
and clipped to 0..255). Keypoints keep OpenCV's order; when OpenCV keeps more than
``n_features`` (keypoints with several orientations share a response, so its cut can let ties
through) the strongest ``n_features`` are kept.

OpenCV packs a SIFT keypoint's octave, layer and sub-layer offset into ``KeyPoint.octave``;
:attr:`Features.octaves` holds the octave alone as a signed level: 0 is the input image, 1 the
image halved, and -1 the image doubled that SIFT starts from. The scale between levels
(``level_scale``) is 2.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError
from ..imageio import to_grey
from ..types import DescriptorKind, Features
from .base import ExtractorConfig, check_mask

SIFT_DESCRIPTOR = DescriptorKind("float", 128)
"""The descriptors of SIFT: 128 float32 values."""


@dataclass(frozen=True)
class SiftConfig(ExtractorConfig):
    """SIFT settings (OpenCV's parameters, with its defaults except ``n_features``).

    Attributes:
        name: "sift", the registry name (see :mod:`stablecues.features.registry`).
        n_features: how many features to keep at most (the strongest); None keeps all that
            pass the thresholds; 0 gives none.
        n_octave_layers: layers per octave (Lowe's 3).
        contrast_threshold: filters weak features in low-contrast regions (divided by
            ``n_octave_layers`` by OpenCV); larger gives fewer features.
        edge_threshold: filters edge-like features; larger keeps more.
        sigma: Gaussian blur of the first octave's image.
    """

    name: str = "sift"
    n_features: int | None = 1000
    n_octave_layers: int = 3
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    sigma: float = 1.6

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_features is not None and self.n_features < 0:
            raise ConfigError(f"n_features must be >= 0 or None, got {self.n_features}")
        if self.n_octave_layers < 1:
            raise ConfigError(f"n_octave_layers must be >= 1, got {self.n_octave_layers}")
        if self.contrast_threshold < 0 or self.edge_threshold <= 0 or self.sigma <= 0:
            raise ConfigError(
                "need contrast_threshold >= 0, edge_threshold > 0 and sigma > 0, got "
                f"{self.contrast_threshold}, {self.edge_threshold}, {self.sigma}"
            )


def unpack_sift_octave(packed: np.ndarray) -> np.ndarray:
    """The signed octave of OpenCV's packed SIFT ``KeyPoint.octave`` values.

    OpenCV stores ``octave & 0xFF | layer << 8 | offset << 16``, the octave as a signed byte
    (-1, the doubled image, is 255).

    Args:
        packed: (N,) integer ``KeyPoint.octave`` values.

    Returns:
        (N,) int16 octaves: -1, 0, 1, ...
    """
    low = np.asarray(packed, np.int64) & 0xFF
    return np.where(low >= 128, low - 256, low).astype(np.int16)


class SiftExtractor:
    """SIFT keypoints and 128-dim float32 descriptors (see the module docstring)."""

    def __init__(self, config: SiftConfig | None = None) -> None:
        self.config = config or SiftConfig()

    @property
    def descriptor_kind(self) -> DescriptorKind:
        """128-dim float32."""
        return SIFT_DESCRIPTOR

    @property
    def level_scale(self) -> float:
        """2: each octave halves the image."""
        return 2.0

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        """Detect and describe SIFT features.

        Args:
            image: (H, W) grey or (H, W, 3) BGR uint8 image, any size.
            mask: optional (H, W) uint8 mask; keypoints only where it is nonzero.

        Returns:
            Features with (N, 128) float32 descriptors, at most ``n_features``, possibly none.
        """
        grey = to_grey(image)
        h, w = grey.shape
        size = (int(w), int(h))
        mask = check_mask(mask, grey.shape)
        c = self.config
        if c.n_features == 0 or grey.size == 0:
            return Features.empty(size, SIFT_DESCRIPTOR)
        sift = cv2.SIFT.create(
            nfeatures=c.n_features or 0,
            nOctaveLayers=c.n_octave_layers,
            contrastThreshold=c.contrast_threshold,
            edgeThreshold=c.edge_threshold,
            sigma=c.sigma,
        )
        kps, desc = sift.detectAndCompute(grey, mask)
        if desc is None or len(kps) == 0:
            return Features.empty(size, SIFT_DESCRIPTOR)
        features = _to_features(kps, desc, size)
        if c.n_features is not None and len(features) > c.n_features:
            strongest = np.argsort(-features.responses, kind="stable")[: c.n_features]
            features = features.subset(np.sort(strongest))
        return features


def _to_features(kps: Sequence[cv2.KeyPoint], desc: np.ndarray, size: tuple[int, int]) -> Features:
    return Features(
        keypoints=np.array([k.pt for k in kps], np.float32).reshape(-1, 2),
        descriptors=np.ascontiguousarray(desc, dtype=np.float32).reshape(-1, SIFT_DESCRIPTOR.size),
        octaves=unpack_sift_octave(np.array([k.octave for k in kps], np.int64)),
        angles=np.array([k.angle for k in kps], np.float32),
        responses=np.array([k.response for k in kps], np.float32),
        sizes=np.array([k.size for k in kps], np.float32),
        image_size=size,
    )

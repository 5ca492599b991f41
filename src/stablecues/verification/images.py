"""Verification of two images end to end: features, direct index, 3D lifting, the verifier.

This is what ``stablecues verify`` runs; the loop detector instead keeps features, feature
vectors and 3D points per database entry and calls :class:`~.verifier.Verifier` directly.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import CalibrationError, InputError
from ..geometry.camera import Calibration
from ..geometry.depth import DepthConfig, lift_depth
from ..geometry.points import NoiseModel, Points3D
from ..geometry.rectify import StereoRectifier
from ..geometry.stereo import StereoConfig, StereoLifter
from ..imageio import read_image
from ..types import Features, FeatureVector
from .config import VerificationConfig
from .result import Verification
from .verifier import Verifier, View

if TYPE_CHECKING:
    from ..vocabulary import Vocabulary

__all__ = ["Frame", "PairVerification", "ImagePairVerifier"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Frame:
    """One prepared frame.

    Attributes:
        image: the image the keypoints refer to (the rectified left image for stereo).
        view: features, direct index and 3D points.
    """

    image: np.ndarray
    view: View


@dataclass(frozen=True, eq=False)
class PairVerification:
    """Outcome of :meth:`ImagePairVerifier.verify`: the decision and both prepared frames."""

    verification: Verification
    query: Frame
    candidate: Frame
    calibration: Calibration


def _load(image: np.ndarray | str | Path, *, unchanged: bool = False) -> np.ndarray:
    if isinstance(image, np.ndarray):
        return image
    return read_image(image, "unchanged" if unchanged else "bgr")


class ImagePairVerifier:
    """Prepares frames from images and verifies pairs of them.

    Args:
        calib: calibration of the camera (raw or rectified stereo, RGB-D, or monocular).
        config: verification settings.
        n_features: ORB features per image.
        use_vocabulary: match through the shipped vocabulary's direct index (else brute force).
        stereo: sparse stereo settings.
        depth: depth-image lifting settings.
    """

    def __init__(
        self,
        calib: Calibration,
        config: VerificationConfig | None = None,
        *,
        n_features: int = 2000,
        use_vocabulary: bool = True,
        stereo: StereoConfig | None = None,
        depth: DepthConfig | None = None,
    ) -> None:
        self.raw_calibration = calib
        self.rectifier = StereoRectifier(calib) if calib.is_stereo and not calib.rectified else None
        self.calibration = self.rectifier.rectified if self.rectifier is not None else calib
        self.lifter = (
            StereoLifter(self.calibration, stereo or StereoConfig()) if self.calibration.is_stereo else None
        )
        self.depth_config = depth or DepthConfig()
        self._extractor = _make_extractor(n_features)
        self._vocabulary = _default_vocabulary() if use_vocabulary else None
        # ORB-SLAM's direct index sits at depth 2 of the tree (levels_up 4 of L = 6): ~k^2 groups,
        # fine enough to make matching cheap, coarse enough to keep correct matches together.
        self._levels_up = max(0, self._vocabulary.levels - 2) if self._vocabulary is not None else 0
        noise: NoiseModel | None
        if self.calibration.depth_scale is not None:
            noise = NoiseModel.kinect(self.calibration.left.fx)
        elif self.lifter is not None:
            noise = self.lifter.noise
        else:
            noise = None
        self.verifier = Verifier(config or VerificationConfig(), self.calibration.left, noise)

    def extract(self, image: np.ndarray) -> tuple[Features, FeatureVector | None]:
        """ORB features of an image and their direct index (None without vocabulary)."""
        feats = self._extractor(image)
        if self._vocabulary is None:
            return feats, None
        return feats, self._vocabulary.transform(feats.descriptors, levels_up=self._levels_up)[1]

    def frame(
        self,
        image: np.ndarray | str | Path,
        *,
        right: np.ndarray | str | Path | None = None,
        depth: np.ndarray | str | Path | None = None,
    ) -> Frame:
        """Prepare one frame: rectify (raw stereo), extract, index, lift to 3D.

        Args:
            image: the (left) image or its path.
            right: the right image of a stereo pair (needs a stereo calibration).
            depth: a depth image registered to ``image`` (raw units, needs a depth scale).
        """
        left = _load(image)
        if right is not None and depth is not None:
            raise InputError("give a right image or a depth image, not both")
        points: Points3D | None = None
        if right is not None:
            if self.lifter is None:
                raise CalibrationError(
                    f"{self.raw_calibration.source}: a right image needs a stereo calibration"
                )
            right_img = _load(right)
            if self.rectifier is not None:
                left, right_img = self.rectifier.rectify(left, right_img)
            feats, fvec = self.extract(left)
            points = self.lifter.lift(feats, left, right_img)
        elif depth is not None:
            scale = self.calibration.depth_scale
            if scale is None:
                raise CalibrationError(
                    f"{self.raw_calibration.source}: a depth image needs a depth scale (DepthMapFactor)"
                )
            depth_img = _load(depth, unchanged=True)
            if depth_img.ndim != 2:
                raise InputError(f"depth image: expected one channel, got shape {depth_img.shape}")
            feats, fvec = self.extract(left)
            points = lift_depth(
                feats,
                depth_img,
                self.calibration.left,
                depth_scale=scale,
                noise=self.verifier.noise,
                config=self.depth_config,
            )
        else:
            if self.rectifier is not None:  # keypoints refer to the rectified camera in every case
                left = self.rectifier.rectify_left(left)
            feats, fvec = self.extract(left)
        return Frame(image=left, view=View(feats, fvec, points))

    def verify_frames(self, query: Frame, candidate: Frame) -> PairVerification:
        """Verify two prepared frames (query = the current one, candidate = the earlier one)."""
        result = self.verifier.verify(query.view, candidate.view)
        return PairVerification(result, query, candidate, self.calibration)

    def verify(
        self,
        image_a: np.ndarray | str | Path,
        image_b: np.ndarray | str | Path,
        *,
        right_a: np.ndarray | str | Path | None = None,
        right_b: np.ndarray | str | Path | None = None,
        depth_a: np.ndarray | str | Path | None = None,
        depth_b: np.ndarray | str | Path | None = None,
    ) -> PairVerification:
        """Verify image A (query) against image B (candidate).

        The relative pose in the result takes points from B's camera to A's camera.
        """
        if (right_a is None) != (right_b is None) or (depth_a is None) != (depth_b is None):
            raise InputError("give right images (or depth images) for both frames or for neither")
        qa = self.frame(image_a, right=right_a, depth=depth_a)
        qb = self.frame(image_b, right=right_b, depth=depth_b)
        return self.verify_frames(qa, qb)


def _make_extractor(n_features: int) -> Callable[[np.ndarray], Features]:
    """``image -> Features`` with stablecues' ORB extractor (ORB-SLAM's spread)."""
    from ..features import OrbConfig, OrbExtractor

    return OrbExtractor(OrbConfig(n_features=n_features)).extract


def _default_vocabulary() -> Vocabulary:
    from ..vocabulary import default_vocabulary

    return default_vocabulary()

"""Verification of two images end to end, exactly as the loop detector would verify them.

This is what ``stablecues verify`` runs. Frames are prepared by the detector's own
:class:`~.prepare.FramePreparer` (features on the image as stored, the vocabulary's direct index,
3D points from a stereo pair or a depth image), and checked by the same
:class:`~stablecues.verification.Verifier` the detector builds for that calibration.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import types
from ..errors import CalibrationError, InputError
from ..features import ExtractorConfig, OrbConfig
from ..geometry.camera import Calibration
from ..geometry.depth import DepthConfig
from ..geometry.stereo import StereoConfig
from ..imageio import read_image
from ..types import Features, FeatureVector
from ..verification.config import VerificationConfig
from ..verification.result import Verification
from ..verification.verifier import Verifier, View
from ..vocabulary import Vocabulary, default_vocabulary
from .config import DetectorConfig
from .prepare import FramePreparer

__all__ = ["ImagePairVerifier", "PairFrame", "PairVerification"]

logger = logging.getLogger(__name__)

ImageInput = np.ndarray | str | Path


@dataclass(frozen=True, eq=False)
class PairFrame:
    """One prepared frame of a pair.

    Attributes:
        image: the image the keypoints refer to (the left image as stored).
        view: features, direct index and 3D points.
    """

    image: np.ndarray
    view: View


Frame = PairFrame
"""The name of :class:`PairFrame` in ``stablecues.verification.images`` (deprecated)."""


@dataclass(frozen=True, eq=False)
class PairVerification:
    """Outcome of :meth:`ImagePairVerifier.verify`: the decision and both prepared frames."""

    verification: Verification
    query: PairFrame
    candidate: PairFrame
    calibration: Calibration


def _load(image: ImageInput, *, unchanged: bool = False) -> np.ndarray:
    if isinstance(image, np.ndarray):
        return image
    return read_image(image, "unchanged" if unchanged else "bgr")


class ImagePairVerifier:
    """Prepares frames from images and verifies pairs of them.

    Args:
        calib: calibration of the camera (raw or rectified stereo, RGB-D, or monocular).
        config: verification settings.
        n_features: ORB features per image (when ``features`` is not given).
        use_vocabulary: match through the vocabulary's direct index (else brute force).
        stereo: sparse stereo settings.
        depth: depth-image lifting settings.
        vocabulary: the vocabulary (default: the shipped one).
        features: the feature extractor's settings (any registered extractor).
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
        vocabulary: Vocabulary | None = None,
        features: ExtractorConfig | None = None,
    ) -> None:
        self.calibration = calib
        detector_config = DetectorConfig(
            features=features or OrbConfig(n_features=n_features),
            masking=None,
            verification=config or VerificationConfig(),
        )
        self.preparer = FramePreparer(
            detector_config, vocabulary or default_vocabulary(detector_config.features.name), calib,
            stereo=stereo, depth=depth,
        )
        self.use_vocabulary = use_vocabulary

    @property
    def verifier(self) -> Verifier:
        """The verifier the detector would use for this calibration."""
        return self.preparer.verifier(self.calibration)

    def extract(self, image: np.ndarray) -> tuple[Features, FeatureVector | None]:
        """Features of an image and their direct index (None without vocabulary)."""
        prep = self.preparer.prepare(self._frame(image))
        return prep.features, (prep.fvec if self.use_vocabulary else None)

    def _frame(
        self, image: np.ndarray, right: np.ndarray | None = None, depth: np.ndarray | None = None
    ) -> types.Frame:
        return types.Frame(index=0, name="", timestamp=math.nan, image=image, right=right, depth=depth,
                           calibration=self.calibration)

    def frame(
        self,
        image: ImageInput,
        *,
        right: ImageInput | None = None,
        depth: ImageInput | None = None,
    ) -> PairFrame:
        """Prepare one frame: extract, index, lift to 3D.

        Args:
            image: the (left) image or its path.
            right: the right image of a stereo pair (needs a stereo calibration).
            depth: a depth image registered to ``image`` (raw units, needs a depth scale).
        """
        left = _load(image)
        if right is not None and depth is not None:
            raise InputError("give a right image or a depth image, not both")
        right_img = depth_img = None
        if right is not None:
            if not self.calibration.is_stereo:
                raise CalibrationError(f"{self.calibration.source}: a right image needs a stereo calibration")
            right_img = _load(right)
        elif depth is not None:
            if self.calibration.depth_scale is None:
                raise CalibrationError(
                    f"{self.calibration.source}: a depth image needs a depth scale (DepthMapFactor)"
                )
            depth_img = _load(depth, unchanged=True)
            if depth_img.ndim != 2:
                raise InputError(f"depth image: expected one channel, got shape {depth_img.shape}")
        prep = self.preparer.prepare(self._frame(left, right_img, depth_img))
        return PairFrame(image=left, view=View(prep.features, prep.fvec if self.use_vocabulary else None,
                                               prep.points))

    def verify_frames(self, query: PairFrame, candidate: PairFrame) -> PairVerification:
        """Verify two prepared frames (query = the current one, candidate = the earlier one)."""
        result = self.verifier.verify(query.view, candidate.view)
        return PairVerification(result, query, candidate, self.calibration)

    def verify(
        self,
        image_a: ImageInput,
        image_b: ImageInput,
        *,
        right_a: ImageInput | None = None,
        right_b: ImageInput | None = None,
        depth_a: ImageInput | None = None,
        depth_b: ImageInput | None = None,
    ) -> PairVerification:
        """Verify image A (query) against image B (candidate).

        The relative pose in the result takes points from B's camera to A's camera.
        """
        if (right_a is None) != (right_b is None) or (depth_a is None) != (depth_b is None):
            raise InputError("give right images (or depth images) for both frames or for neither")
        qa = self.frame(image_a, right=right_a, depth=depth_a)
        qb = self.frame(image_b, right=right_b, depth=depth_b)
        return self.verify_frames(qa, qb)

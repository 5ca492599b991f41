"""Stereo rectification of a calibrated raw rig (``cv2.stereoRectify`` + cached remap tables)."""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import CalibrationError, InputError
from .camera import UNDISTORT_CRITERIA, Calibration, PinholeCamera, Rectification

__all__ = ["StereoRectifier", "rectification_of"]


def rectification_of(calib: Calibration, *, alpha: float = 0.0) -> Rectification:
    """The rectification of a raw stereo calibration.

    Uses the file's own rectification when it has one (ORB-SLAM settings with ``LEFT.R``/``P``),
    else ``cv2.stereoRectify`` with ``CALIB_ZERO_DISPARITY``. OpenCV 5 wants the translation as a
    3x1 array.

    Args:
        calib: a stereo calibration with both cameras, extrinsics and known image size.
        alpha: OpenCV's free scaling (0: only valid pixels, 1: all source pixels kept).
    """
    if calib.rectification is not None:
        return calib.rectification
    if calib.right is None or calib.rotation is None or calib.translation is None:
        raise CalibrationError(f"{calib.source}: rectification needs a right camera and stereo extrinsics")
    size = calib.left.image_size
    if size is None:
        raise CalibrationError(f"{calib.source}: rectification needs the image size (width, height)")
    r1, r2, p1, p2, _q, _roi1, _roi2 = cv2.stereoRectify(
        calib.left.K,
        calib.left.dist,
        calib.right.K,
        calib.right.dist,
        size,
        np.asarray(calib.rotation, np.float64),
        np.asarray(calib.translation, np.float64).reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=alpha,
    )
    return Rectification(R1=r1, R2=r2, P1=p1, P2=p2)


class StereoRectifier:
    """Rectifies raw stereo images and keypoints of one rig; the remap tables are built once.

    Args:
        calib: raw stereo calibration (``rectified=False``) with both cameras and extrinsics.
        alpha: OpenCV's free scaling parameter of ``stereoRectify``.

    Attributes:
        raw: the input calibration.
        rectification: ``R1, R2, P1, P2`` of the rig.
        rectified: the calibration of the rectified pair: both cameras ``P1``'s intrinsics without
            distortion, ``rectified=True``, baseline ``-P2[0,3] / P2[0,0]``, depth scale kept.
    """

    def __init__(self, calib: Calibration, *, alpha: float = 0.0) -> None:
        if calib.rectified:
            raise CalibrationError(f"{calib.source}: calibration is already rectified")
        self.raw = calib
        self.rectification = rectification_of(calib, alpha=alpha)
        size = calib.left.image_size
        if size is None:
            raise CalibrationError(f"{calib.source}: rectification needs the image size (width, height)")
        self._size = size
        cam = PinholeCamera.from_matrix(self.rectification.P1[:, :3], width=size[0], height=size[1])
        baseline = self.rectification.baseline
        if not baseline > 0:
            raise CalibrationError(
                f"{calib.source}: rectified baseline is {baseline}; expected the right camera on the +x side"
            )
        self.rectified = Calibration.rectified_stereo(
            cam, baseline, depth_scale=calib.depth_scale, source=f"{calib.source} (rectified)"
        )
        self._maps: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None

    def _ensure_maps(self) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        if self._maps is None:
            if self.raw.right is None:  # checked in rectification_of; keeps mypy informed
                raise CalibrationError(f"{self.raw.source}: no right camera")
            rect = self.rectification
            maps = []
            for cam, r, p in ((self.raw.left, rect.R1, rect.P1), (self.raw.right, rect.R2, rect.P2)):
                m1, m2 = cv2.initUndistortRectifyMap(cam.K, cam.dist, r, p, self._size, cv2.CV_16SC2)
                maps.append((m1, m2))
            self._maps = (maps[0], maps[1])
        return self._maps

    def _check(self, name: str, image: np.ndarray) -> None:
        if not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
            raise InputError(f"{name}: expected an image array, got {type(image).__name__}")
        h, w = image.shape[:2]
        if (w, h) != self._size:
            raise InputError(f"{name}: expected a {self._size[0]}x{self._size[1]} image, got {w}x{h}")

    def rectify_left(self, image: np.ndarray) -> np.ndarray:
        """Rectified left image (same size and dtype)."""
        self._check("left image", image)
        (m1, m2), _ = self._ensure_maps()
        return cv2.remap(image, m1, m2, cv2.INTER_LINEAR)

    def rectify_right(self, image: np.ndarray) -> np.ndarray:
        """Rectified right image (same size and dtype)."""
        self._check("right image", image)
        _, (m1, m2) = self._ensure_maps()
        return cv2.remap(image, m1, m2, cv2.INTER_LINEAR)

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Both images rectified."""
        return self.rectify_left(left), self.rectify_right(right)

    def rectify_keypoints(self, pixels: np.ndarray) -> np.ndarray:
        """Raw left-image pixels mapped to the rectified left image.

        Args:
            pixels: (N, 2) pixel coordinates in the raw (distorted) left image.

        Returns:
            (N, 2) float64 pixel coordinates in the rectified left image.
        """
        pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
        if pixels.shape[0] == 0:
            return np.zeros((0, 2))
        rect = self.rectification
        out = cv2.undistortPoints(
            pixels.reshape(-1, 1, 2),
            self.raw.left.K,
            self.raw.left.dist,
            R=rect.R1,
            P=rect.P1,
            criteria=UNDISTORT_CRITERIA,
        )
        return out.reshape(-1, 2).astype(np.float64)

    @property
    def rotation_raw_to_rectified(self) -> np.ndarray:
        """(3, 3) rotation ``R1`` taking raw left-camera coordinates to the rectified left frame."""
        return self.rectification.R1

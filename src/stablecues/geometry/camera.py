"""Pinhole camera with radial-tangential distortion, and the calibration of a (stereo) rig.

Conventions used throughout :mod:`stablecues.geometry`:

* Pixel coordinates are ``(x, y)`` = (column, row), origin at the centre of the top-left pixel,
  as OpenCV uses them.
* A camera frame has x to the right, y down and z forward (optical axis); depth means z.
* A rigid transform written ``R, t`` "from frame a to frame b" maps a point's coordinates as
  ``X_b = R @ X_a + t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import CalibrationError, InputError, check_array
from ..limits import MAX_IMAGE_PIXELS

__all__ = ["PinholeCamera", "Rectification", "Calibration", "UNDISTORT_CRITERIA"]

#: OpenCV's default of 5 undistortion iterations leaves errors of ~0.1 px at the corners of
#: strongly distorted images (EuRoC, k1 = -0.28); 50 iterations converge to 1e-9.
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9)


def _as_points(name: str, points: np.ndarray, dims: int) -> np.ndarray:
    """Validate an ``(N, dims)`` float array and return it as float64."""
    points = np.asarray(points)
    check_array(name, points, shape=(None, dims))
    if not np.issubdtype(points.dtype, np.floating) and not np.issubdtype(points.dtype, np.integer):
        raise InputError(f"{name}: expected a numeric array, got dtype {points.dtype}")
    return points.astype(np.float64, copy=False)


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole camera with OpenCV's radial-tangential (plumb-bob) distortion.

    Attributes:
        fx: focal length along x, pixels.
        fy: focal length along y, pixels.
        cx: principal point x, pixels.
        cy: principal point y, pixels.
        width: image width in pixels, or None when the calibration file does not say.
        height: image height in pixels, or None when unknown.
        distortion: ``(k1, k2, p1, p2[, k3])`` in OpenCV's order; empty for an ideal pinhole.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int | None = None
    height: int | None = None
    distortion: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not np.isfinite(value):
                raise CalibrationError(f"camera {name}: expected a finite number, got {value}")
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if len(self.distortion) not in (0, 4, 5):
            raise CalibrationError(
                f"camera distortion: expected 0, 4 (k1 k2 p1 p2) or 5 (+k3) numbers, "
                f"got {len(self.distortion)}"
            )
        if not all(np.isfinite(c) for c in self.distortion):
            raise CalibrationError(f"camera distortion: expected finite numbers, got {self.distortion}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if value is not None and int(value) <= 0:
                raise CalibrationError(f"camera {name}: expected a positive size, got {value}")
        size = self.image_size
        if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:
            raise CalibrationError(
                f"camera size {size[0]} x {size[1]}: over the {MAX_IMAGE_PIXELS} pixels accepted"
            )

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the conventional name
        """(3, 3) float64 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """(5,) float64 distortion coefficients ``k1 k2 p1 p2 k3`` (zeros when ideal)."""
        d = np.zeros(5)
        d[: len(self.distortion)] = self.distortion
        return d

    @property
    def has_distortion(self) -> bool:
        return any(abs(c) > 0.0 for c in self.distortion)

    @property
    def image_size(self) -> tuple[int, int] | None:
        """``(width, height)`` or None when unknown."""
        if self.width is None or self.height is None:
            return None
        return int(self.width), int(self.height)

    @staticmethod
    def from_matrix(
        K: np.ndarray,  # noqa: N803
        distortion: np.ndarray | tuple[float, ...] = (),
        width: int | None = None,
        height: int | None = None,
    ) -> PinholeCamera:
        """Camera from a 3x3 (or the left 3x3 of a 3x4 projection) matrix."""
        K = np.asarray(K, np.float64)  # noqa: N806
        if K.shape not in ((3, 3), (3, 4)):
            raise CalibrationError(f"camera matrix: expected 3x3 or 3x4, got {K.shape}")
        dist = tuple(float(c) for c in np.asarray(distortion, np.float64).ravel())
        if len(dist) == 5 and dist[4] == 0.0:
            dist = dist[:4]
        if dist and not any(dist):
            dist = ()
        return PinholeCamera(
            fx=float(K[0, 0]),
            fy=float(K[1, 1]),
            cx=float(K[0, 2]),
            cy=float(K[1, 2]),
            width=width,
            height=height,
            distortion=dist,
        )

    def normalize(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalised image coordinates of pixels.

        Args:
            pixels: (N, 2) pixel coordinates (x, y) in the (distorted) image.

        Returns:
            (N, 2) float64 coordinates ``(X/Z, Y/Z)`` on the ideal image plane.
        """
        pixels = _as_points("pixels", pixels, 2)
        if pixels.shape[0] == 0:
            return np.zeros((0, 2))
        if not self.has_distortion:
            return np.stack(((pixels[:, 0] - self.cx) / self.fx, (pixels[:, 1] - self.cy) / self.fy), axis=1)
        out = cv2.undistortPoints(
            pixels.reshape(-1, 1, 2), self.K, self.dist, None, None, None, UNDISTORT_CRITERIA
        )
        return out.reshape(-1, 2).astype(np.float64)

    def undistort_points(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels as an ideal pinhole camera with the same K would see them.

        Args:
            pixels: (N, 2) pixel coordinates in the distorted image.

        Returns:
            (N, 2) float64 undistorted pixel coordinates.
        """
        n = self.normalize(pixels)
        return np.stack((n[:, 0] * self.fx + self.cx, n[:, 1] * self.fy + self.cy), axis=1)

    def unproject(self, pixels: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
        """3D points in the camera frame from pixels and depths (z).

        Args:
            pixels: (N, 2) pixel coordinates in the (distorted) image.
            depth: (N,) depth z of each point in metres; None gives rays with z = 1.

        Returns:
            (N, 3) float64 points; NaN where the depth is NaN.
        """
        n = self.normalize(pixels)
        z = np.ones(n.shape[0]) if depth is None else np.asarray(depth, np.float64)
        if z.shape != (n.shape[0],):
            raise InputError(f"depth: expected shape ({n.shape[0]},), got {z.shape}")
        return np.stack((n[:, 0] * z, n[:, 1] * z, z), axis=1)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixels of 3D points given in the camera frame (distortion applied).

        Args:
            points: (N, 3) points in the camera frame.

        Returns:
            (N, 2) float64 pixel coordinates; NaN for points with z <= 0 or non-finite.
        """
        points = _as_points("points", points, 3)
        out = np.full((points.shape[0], 2), np.nan)
        ok = np.isfinite(points).all(axis=1) & (points[:, 2] > 0)
        if not ok.any():
            return out
        p = points[ok]
        if self.has_distortion:
            proj, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
            out[ok] = proj.reshape(-1, 2)
        else:
            out[ok, 0] = self.fx * p[:, 0] / p[:, 2] + self.cx
            out[ok, 1] = self.fy * p[:, 1] / p[:, 2] + self.cy
        return out


@dataclass(frozen=True, eq=False)
class Rectification:
    """Stereo rectification of a raw rig, as ``cv2.stereoRectify`` returns it.

    Attributes:
        R1: (3, 3) rotation from the raw left camera frame to the rectified left frame.
        R2: (3, 3) rotation from the raw right camera frame to the rectified right frame.
        P1: (3, 4) projection matrix of the rectified left camera.
        P2: (3, 4) projection matrix of the rectified right camera (``P2[0, 3] = -fx * B``).
    """

    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray

    def __post_init__(self) -> None:
        for name, shape in (("R1", (3, 3)), ("R2", (3, 3)), ("P1", (3, 4)), ("P2", (3, 4))):
            value = np.asarray(getattr(self, name), np.float64)
            if value.shape != shape:
                raise CalibrationError(f"rectification {name}: expected shape {shape}, got {value.shape}")
            object.__setattr__(self, name, value)

    @property
    def baseline(self) -> float:
        """Baseline in metres of the rectified pair, ``-P2[0, 3] / P2[0, 0]``."""
        return float(-self.P2[0, 3] / self.P2[0, 0])


@dataclass(frozen=True, eq=False)
class Calibration:
    """Calibration of a monocular camera, an RGB-D camera or a stereo rig.

    Attributes:
        left: the left (or only) camera; images and keypoints refer to it.
        right: the right camera of a stereo rig, or None.
        rotation: (3, 3) float64 rotation from the left camera frame to the right one
            (``X_right = rotation @ X_left + translation``), or None without a right camera.
        translation: (3,) float64 translation from left to right in metres, or None.
        depth_scale: raw depth-image units per metre (ORB-SLAM's DepthMapFactor, e.g. 5000 for
            TUM, 1000 for most Kinect recordings), or None when there is no depth camera.
        rectified: True when left and right images are already rectified (row-aligned, no
            distortion, right camera = left camera shifted by ``baseline`` along x).
        rectification: precomputed rectification of a raw rig (ORB-SLAM settings with LEFT.R/P),
            or None to compute it with ``cv2.stereoRectify``.
        bf: ``fx * baseline`` as given by the file (ORB-SLAM's Camera.bf), or None.
        source: the file the calibration was read from, for messages.
    """

    left: PinholeCamera
    right: PinholeCamera | None = None
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    depth_scale: float | None = None
    rectified: bool = False
    rectification: Rectification | None = None
    bf: float | None = None
    source: str = field(default="")

    def __post_init__(self) -> None:
        if (self.rotation is None) != (self.translation is None):
            raise CalibrationError(f"{self.source}: stereo extrinsics need both a rotation and a translation")
        if self.rotation is not None:
            rot = np.asarray(self.rotation, np.float64)
            trans = np.asarray(self.translation, np.float64).reshape(-1)
            if rot.shape != (3, 3) or trans.shape != (3,):
                raise CalibrationError(
                    f"{self.source}: stereo extrinsics: expected a 3x3 rotation and 3 translation "
                    f"numbers, got {rot.shape} and {trans.shape}"
                )
            if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-4):
                raise CalibrationError(f"{self.source}: stereo rotation is not orthonormal")
            object.__setattr__(self, "rotation", rot)
            object.__setattr__(self, "translation", trans)
        if self.depth_scale is not None and not self.depth_scale > 0:
            raise CalibrationError(f"{self.source}: depth scale must be positive, got {self.depth_scale}")

    @property
    def is_stereo(self) -> bool:
        return self.right is not None and self.baseline is not None

    @property
    def baseline(self) -> float | None:
        """Stereo baseline in metres (rectified: from ``bf``), or None without a right camera."""
        if self.rectification is not None:
            return self.rectification.baseline
        if self.translation is not None:
            return float(np.linalg.norm(self.translation))
        if self.bf is not None:
            return float(self.bf / self.left.fx)
        return None

    @property
    def has_depth(self) -> bool:
        return self.depth_scale is not None

    @staticmethod
    def rectified_stereo(
        camera: PinholeCamera, baseline: float, *, depth_scale: float | None = None, source: str = ""
    ) -> Calibration:
        """A rectified stereo rig: the right camera is ``camera`` shifted by ``baseline`` along +x.

        Args:
            camera: intrinsics shared by both rectified images (no distortion).
            baseline: distance between the optical centres in metres (> 0).
            depth_scale: optional depth-image scale, kept as is.
            source: file name for messages.
        """
        if not baseline > 0:
            raise CalibrationError(f"{source}: stereo baseline must be positive, got {baseline}")
        return Calibration(
            left=camera,
            right=camera,
            rotation=np.eye(3),
            translation=np.array([-baseline, 0.0, 0.0]),
            depth_scale=depth_scale,
            rectified=True,
            bf=camera.fx * baseline,
            source=source,
        )

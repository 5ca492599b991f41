"""3D points of keypoints with their uncertainty, and the noise models that give it.

Every lifted point carries two standard deviations, enough to propagate noise to a distance
between points (the triangle check) without storing a full 3x3 covariance:

* ``sigma_depth``: along the viewing ray, of the depth z (the dominant term for stereo and
  structured-light depth). The covariance it contributes is ``sigma_depth**2 * r r^T`` with
  ``r = X / z`` (the ray scaled to z = 1).
* ``sigma_lateral``: across the ray, isotropic in x and y, from the keypoint's localisation
  error ``pixel_sigma * scale_factor**octave`` pixels times ``z / f``. It also covers a keypoint
  detected on a slightly different physical point when the place is seen again.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, InputError, check_array
from .camera import Calibration

__all__ = [
    "KINECT_DEPTH_COEFF",
    "STEREO_DISPARITY_SIGMA",
    "NoiseModel",
    "Points3D",
    "relative_points_meta",
    "relative_points_from_meta",
]

#: Depth noise of a structured-light Kinect (v1): sigma_z = 1.425e-3 * z**2 metres
#: (Khoshelham & Elberink, "Accuracy and resolution of Kinect depth data", Sensors 2012: the
#: random error grows quadratically with range, about 4 cm at 5 m).
KINECT_DEPTH_COEFF = 1.425e-3

#: Effective disparity noise in pixels of sparse stereo with a parabola sub-pixel fit. Sub-pixel
#: estimators reach ~0.1-0.2 px on clean texture; calibration/rectification error and
#: patch foreshortening raise it, and ~0.3 px is what we measured on EuRoC (docs/method.md section 6).
STEREO_DISPARITY_SIGMA = 0.3


@dataclass(frozen=True)
class NoiseModel:
    """Noise of lifted 3D points: ``sigma_z = depth_offset + depth_coeff * z**2``.

    Both stereo and structured-light depth have a quadratic law: with disparity noise
    ``sigma_d`` px, ``z = f B / d`` gives ``sigma_z = z**2 * sigma_d / (f B)``.

    Attributes:
        depth_coeff: metres^-1 coefficient of ``z**2``.
        focal: focal length in pixels (for the lateral term).
        depth_offset: constant term of sigma_z in metres (e.g. depth quantisation floor).
        pixel_sigma: keypoint localisation noise in pixels at pyramid level 0 (ORB-SLAM: 1 px).
        scale_factor: pyramid scale factor; level ``o`` has noise ``pixel_sigma * scale**o``.
    """

    depth_coeff: float
    focal: float
    depth_offset: float = 0.0
    pixel_sigma: float = 1.0
    scale_factor: float = 1.2

    def __post_init__(self) -> None:
        if not (
            self.depth_coeff >= 0 and self.focal > 0 and self.depth_offset >= 0 and self.pixel_sigma >= 0
        ):
            raise ConfigError(f"invalid noise model {self}")
        if not self.scale_factor >= 1.0:
            raise ConfigError(f"noise model scale_factor must be >= 1, got {self.scale_factor}")

    @staticmethod
    def stereo(
        focal: float, baseline: float, sigma_disparity: float = STEREO_DISPARITY_SIGMA, **kwargs: float
    ) -> NoiseModel:
        """Noise of rectified stereo: ``sigma_z = z**2 * sigma_disparity / (focal * baseline)``."""
        if not (focal > 0 and baseline > 0):
            raise ConfigError(f"stereo noise needs positive focal and baseline, got {focal}, {baseline}")
        return NoiseModel(depth_coeff=sigma_disparity / (focal * baseline), focal=focal, **kwargs)

    @staticmethod
    def kinect(focal: float, coeff: float = KINECT_DEPTH_COEFF, **kwargs: float) -> NoiseModel:
        """Noise of a structured-light depth camera, ``sigma_z = coeff * z**2`` (see KINECT_DEPTH_COEFF)."""
        return NoiseModel(depth_coeff=coeff, focal=focal, **kwargs)

    @staticmethod
    def for_calibration(calib: Calibration, **kwargs: float) -> NoiseModel:
        """The model matching a calibration: depth camera if it has a depth scale, else stereo.

        Raises:
            ConfigError: for a monocular calibration (no depth scale, no baseline).
        """
        focal = calib.left.fx
        if calib.depth_scale is not None:
            return NoiseModel.kinect(focal, **kwargs)
        baseline = calib.baseline
        if baseline is not None and baseline > 0:
            sigma_d = kwargs.pop("sigma_disparity", STEREO_DISPARITY_SIGMA)
            return NoiseModel.stereo(focal, baseline, sigma_d, **kwargs)
        raise ConfigError(f"{calib.source}: no depth or stereo in this calibration, so no 3D noise model")

    def sigma_depth(self, z: np.ndarray) -> np.ndarray:
        """(N,) float64 standard deviation of depth at depths ``z`` (metres)."""
        z = np.asarray(z, np.float64)
        return self.depth_offset + self.depth_coeff * z * z

    def sigma_lateral(self, z: np.ndarray, octaves: np.ndarray | None = None) -> np.ndarray:
        """(N,) float64 lateral standard deviation in metres at depths ``z`` and pyramid levels."""
        z = np.asarray(z, np.float64)
        px = np.full(z.shape, self.pixel_sigma)
        if octaves is not None:
            px = px * np.power(self.scale_factor, np.asarray(octaves, np.float64))
        return px * np.abs(z) / self.focal

    def points(
        self, xyz: np.ndarray, octaves: np.ndarray | None = None, sigma_depth: np.ndarray | None = None
    ) -> Points3D:
        """Points3D from coordinates, with sigmas from this model.

        Args:
            xyz: (N, 3) points in the camera frame (NaN where unknown).
            octaves: (N,) pyramid level of each keypoint (None: level 0).
            sigma_depth: (N,) depth sigmas to use instead of the model's (NaN: use the model).

        Returns:
            The points; NaN rows stay NaN.
        """
        xyz = np.asarray(xyz)
        check_array("points3d", xyz, shape=(None, 3))
        z = xyz[:, 2].astype(np.float64)
        if octaves is not None and np.asarray(octaves).shape != (xyz.shape[0],):
            raise InputError(f"octaves: expected shape ({xyz.shape[0]},), got {np.asarray(octaves).shape}")
        sd = self.sigma_depth(z)
        if sigma_depth is not None:
            given = np.asarray(sigma_depth, np.float64)
            if given.shape != (xyz.shape[0],):
                raise InputError(f"sigma_depth: expected shape ({xyz.shape[0]},), got {given.shape}")
            sd = np.where(np.isfinite(given), given, sd)
        return Points3D(
            xyz=xyz.astype(np.float32),
            sigma_depth=sd.astype(np.float32),
            sigma_lateral=self.sigma_lateral(z, octaves).astype(np.float32),
        )


@dataclass(frozen=True, eq=False)
class Points3D:
    """3D points of one frame's keypoints, in that frame's camera, with their noise.

    Attributes:
        xyz: (N, 3) float32 coordinates in metres in the camera frame; NaN rows are unknown.
        sigma_depth: (N,) float32 standard deviation of depth (z) in metres.
        sigma_lateral: (N,) float32 standard deviation across the viewing ray in metres.
        metric: True when the coordinates are in metres (stereo, depth, a SLAM map); False for a
            monocular reconstruction, whose unit (the baseline to its neighbour) is unknown:
            only shapes can be compared then.
    """

    xyz: np.ndarray
    sigma_depth: np.ndarray
    sigma_lateral: np.ndarray
    metric: bool = True

    def __post_init__(self) -> None:
        check_array("points3d", self.xyz, dtype=np.float32, shape=(None, 3))
        n = self.xyz.shape[0]
        check_array("sigma_depth", self.sigma_depth, dtype=np.float32, shape=(n,))
        check_array("sigma_lateral", self.sigma_lateral, dtype=np.float32, shape=(n,))

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: finite coordinates in front of the camera and finite sigmas."""
        with np.errstate(invalid="ignore"):
            return (
                np.isfinite(self.xyz).all(axis=1)
                & (self.xyz[:, 2] > 0)
                & np.isfinite(self.sigma_depth)
                & np.isfinite(self.sigma_lateral)
            )

    @staticmethod
    def empty(n: int = 0) -> Points3D:
        """``n`` unknown points (all NaN)."""
        return Points3D(
            xyz=np.full((n, 3), np.nan, np.float32),
            sigma_depth=np.full(n, np.nan, np.float32),
            sigma_lateral=np.full(n, np.nan, np.float32),
        )

    def subset(self, index: np.ndarray) -> Points3D:
        """Points selected by a boolean mask or an integer index array."""
        index = np.asarray(index)
        return Points3D(self.xyz[index], self.sigma_depth[index], self.sigma_lateral[index], self.metric)


def relative_points_meta(points: Points3D, source: str) -> dict[str, object]:
    """What a map entry keeps beside the coordinates of monocular (non-metric) points: their
    source and their depth sigmas (float16, base64), which depend on each point's
    triangulation angle and so cannot be recomputed from the depth alone."""
    sigma = np.nan_to_num(points.sigma_depth, nan=np.inf).astype("<f2")
    return {"points": source, "sigma_depth": base64.b64encode(sigma.tobytes()).decode("ascii")}


def relative_points_from_meta(
    xyz: np.ndarray, meta: dict[str, object], model: NoiseModel, octaves: np.ndarray | None = None
) -> Points3D | None:
    """The monocular points of a map entry (see :func:`relative_points_meta`), or None when the
    entry's points are metric (or its record is not one of ours)."""
    source, packed = meta.get("points"), meta.get("sigma_depth")
    if not (isinstance(source, str) and source.startswith("mono") and isinstance(packed, str)):
        return None
    try:
        sigma = np.frombuffer(base64.b64decode(packed, validate=True), "<f2").astype(np.float64)
    except ValueError:
        return None
    if sigma.shape != (np.asarray(xyz).shape[0],):
        return None
    sigma[~np.isfinite(sigma)] = np.nan
    pts = model.points(xyz, octaves, sigma_depth=sigma)
    valid = np.isfinite(sigma)
    sd = np.where(valid, pts.sigma_depth, np.nan).astype(np.float32)
    return Points3D(pts.xyz, sd, pts.sigma_lateral, metric=False)

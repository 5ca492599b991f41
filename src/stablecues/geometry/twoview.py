"""3D points of a monocular frame, triangulated against a neighbouring frame of the stream.

Without stereo, depth or map points a frame has no 3D of its own; a SLAM front end gets it from
the motion between frames. Here: the frame's matches with an earlier frame of the stream give
the essential matrix (RANSAC, five points) from the camera's intrinsics, the relative pose
``R, t`` (``|t| = 1``: monocular scale is unknown, so points come out in units of the baseline),
and the 3D point of every inlier match, in the current frame's camera.

Each point's depth standard deviation comes from its triangulation angle ``theta`` (the angle
between the two viewing rays): with ray ranges ``r_a`` (current) and ``r_b`` (neighbour) and
an angular noise ``s = sigma_px / f`` on each ray, the law of sines gives
``sigma_range**2 = s**2 * (r_a**2 cos**2 theta + r_b**2) / sin**2 theta``: points near the
epipole (forward motion) or far away are uncertain, and those below ``min_angle_deg`` are
dropped. The lateral sigma is the usual ``sigma_px * z / f``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError, InputError, check_array
from .camera import PinholeCamera
from .points import Points3D

__all__ = ["TwoViewConfig", "TwoView", "guess_camera", "triangulate_two_view", "GUESSED_FOCAL_FACTOR"]

#: A focal length guessed from the image size, ``f = 1.2 * max(width, height)`` pixels (COLMAP's
#: prior; a 45-50 degree horizontal field of view, common for dashboard and robot cameras).
GUESSED_FOCAL_FACTOR = 1.2


@dataclass(frozen=True)
class TwoViewConfig:
    """Settings of two-view triangulation.

    Attributes:
        threshold_px: RANSAC threshold of the essential matrix, pixels.
        confidence: RANSAC confidence.
        min_inliers: essential-matrix inliers needed to trust the relative pose.
        min_median_angle_deg: median triangulation angle needed (too little parallax: the
            pose and the points are unreliable, try an older neighbour).
        min_angle_deg: points with a smaller triangulation angle are dropped.
        max_reprojection_px: points reprojecting further than this in either view are dropped.
        pixel_sigma: keypoint localisation noise in pixels (level 0).
        max_iterations: RANSAC iterations at most. A pair runs fewer when ``min_inliers`` of its
            matches are a large share of them: ``iteration_margin`` times the iterations after
            which a set of that share of inliers would have given an all-inlier sample of five
            with probability ``confidence`` (more cannot find the ``min_inliers`` the pair
            needs; a pair with more inliers stops earlier by RANSAC's own rule).
        iteration_margin: the factor above. Twice gives the same outcome, inliers, poses and
            points as 4 and as 1000 iterations on every pair that triangulates, and the same
            failures, on the CamVid revisit sets, CamVid train and val, the corridor, the desk
            loop and KITTI (1,669 pairs); a pair that fails runs half as long as at 4.
    """

    threshold_px: float = 1.0
    confidence: float = 0.999
    min_inliers: int = 30
    min_median_angle_deg: float = 1.0
    min_angle_deg: float = 0.5
    max_reprojection_px: float = 2.0
    pixel_sigma: float = 1.0
    max_iterations: int = 1000
    iteration_margin: float = 2.0

    def __post_init__(self) -> None:
        for ok, what in (
            (self.threshold_px > 0, f"threshold_px must be > 0, got {self.threshold_px}"),
            (0 < self.confidence < 1, f"confidence must be in (0, 1), got {self.confidence}"),
            (self.min_inliers >= 5, f"min_inliers must be >= 5 (five points fix a motion), "
                                    f"got {self.min_inliers}"),
            (self.max_iterations >= 1, f"max_iterations must be >= 1, got {self.max_iterations}"),
            (1 <= self.iteration_margin < math.inf,
             f"iteration_margin must be a finite number >= 1, got {self.iteration_margin}"),
        ):
            if not ok:
                raise ConfigError(f"two-view settings: {what}")

    def iterations(self, m: int) -> int:
        """RANSAC iterations for ``m`` matches (see ``max_iterations``)."""
        share = self.min_inliers / max(m, 1)
        needed = 1.0 if share >= 1.0 else math.log(1.0 - self.confidence) / math.log1p(-(share**5))
        return int(max(1, min(self.max_iterations, math.ceil(self.iteration_margin * needed))))


@dataclass(frozen=True, eq=False)
class TwoView:
    """Outcome of :func:`triangulate_two_view`.

    Attributes:
        points: (M,) points of the matches, in the current camera, baseline units (NaN: none).
        rotation: (3, 3) rotation current -> neighbour camera (``X_b = R X_a + t``), or None.
        translation: (3,) unit translation, or None.
        n_inliers: essential-matrix inliers.
        median_angle_deg: median triangulation angle of the kept points (0 when none).
        reason: why no points came out ("" when they did).
        baseline_limited: the pair failed for too little baseline (too little parallax, or too
            few points triangulated well, e.g. a rotation only), so a neighbour further back
            may do; False when it triangulated or when its matches do not hold one motion.
    """

    points: Points3D
    rotation: np.ndarray | None
    translation: np.ndarray | None
    n_inliers: int
    median_angle_deg: float
    reason: str = ""
    baseline_limited: bool = False

    @property
    def ok(self) -> bool:
        return self.rotation is not None


def guess_camera(width: int, height: int) -> PinholeCamera:
    """A pinhole camera for an image of unknown intrinsics: ``f = 1.2 max(w, h)``, centred."""
    if not (width > 0 and height > 0):
        raise InputError(f"image size must be positive, got {width}x{height}")
    f = GUESSED_FOCAL_FACTOR * max(width, height)
    return PinholeCamera(f, f, width / 2.0, height / 2.0, width, height)


def _fail(m: int, reason: str, n_inliers: int = 0, baseline_limited: bool = False) -> TwoView:
    empty = Points3D.empty(m)
    return TwoView(Points3D(empty.xyz, empty.sigma_depth, empty.sigma_lateral, metric=False), None, None,
                   n_inliers, 0.0, reason, baseline_limited)


def triangulate_two_view(
    pixels_current: np.ndarray,
    pixels_neighbour: np.ndarray,
    camera: PinholeCamera,
    config: TwoViewConfig | None = None,
    octaves: np.ndarray | None = None,
) -> TwoView:
    """Triangulate matched keypoints of the current frame against a neighbouring frame.

    Args:
        pixels_current: (M, 2) keypoints of the matches in the current image.
        pixels_neighbour: (M, 2) the same matches in the neighbour image.
        camera: the camera of both frames (distortion is removed first).
        config: settings.
        octaves: (M,) pyramid levels of the current keypoints (lateral sigma), or None.

    Returns:
        the points (one per match, NaN where not triangulated) and the relative pose.
    """
    cfg = config or TwoViewConfig()
    pa = np.asarray(pixels_current, np.float64)
    pb = np.asarray(pixels_neighbour, np.float64)
    check_array("current pixels", pa, shape=(None, 2))
    m = pa.shape[0]
    check_array("neighbour pixels", pb, shape=(m, 2))
    if m < cfg.min_inliers:
        return _fail(m, f"{m} matches with the neighbour, need {cfg.min_inliers}")
    if camera.has_distortion:
        pa, pb = camera.undistort_points(pa), camera.undistort_points(pb)
    k = camera.K
    try:
        e, mask = cv2.findEssentialMat(pa, pb, k, cv2.USAC_DEFAULT, cfg.confidence, cfg.threshold_px,
                                       cfg.iterations(m))
    except cv2.error:
        e, mask = None, None
    if e is None or mask is None or e.shape != (3, 3):
        return _fail(m, "no essential matrix")
    inl = mask.ravel().astype(bool)
    if int(inl.sum()) < cfg.min_inliers:
        return _fail(m, f"{int(inl.sum())} essential-matrix inliers, need {cfg.min_inliers}", int(inl.sum()))
    _, rot, t, pose_mask = cv2.recoverPose(e, pa[inl], pb[inl], k)
    rot, t = np.asarray(rot, np.float64), np.asarray(t, np.float64).ravel()
    xyz = np.full((m, 3), np.nan)
    xyz[inl] = _triangulate(k, rot, t, pa[inl], pb[inl])
    keep, angle = _well_conditioned(xyz, k, rot, t, pa, pb, inl & np.isfinite(xyz).all(axis=1), cfg)
    n_in = int(inl.sum())
    if int(keep.sum()) < cfg.min_inliers:  # e.g. a rotation only: most points "behind" a camera
        return _fail(m, f"{int(keep.sum())} well-triangulated points, need {cfg.min_inliers} "
                        "(too little translation?)", n_in, baseline_limited=True)
    if np.median(angle[keep]) < cfg.min_median_angle_deg:
        return _fail(m, f"too little parallax (median {float(np.median(angle[keep])):.2f} deg)", n_in,
                     baseline_limited=True)
    points = _with_sigmas(xyz, keep, angle, rot, t, camera.fx, cfg.pixel_sigma, octaves)
    return TwoView(points, rot, t, n_in, float(np.median(angle[keep])))


def _triangulate(k: np.ndarray, rot: np.ndarray, t: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    p_a = k @ np.hstack([np.eye(3), np.zeros((3, 1))])
    p_b = k @ np.hstack([rot, t[:, None]])
    hom = cv2.triangulatePoints(p_a, p_b, pa.T, pb.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (hom[:3] / hom[3]).T


def _well_conditioned(
    xyz: np.ndarray, k: np.ndarray, rot: np.ndarray, t: np.ndarray, pa: np.ndarray, pb: np.ndarray,
    candidates: np.ndarray, cfg: TwoViewConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """(M,) kept mask (in front of both cameras, reprojecting, enough angle), (M,) angles in deg."""
    centre_b = -rot.T @ t  # the neighbour's centre in the current camera
    with np.errstate(invalid="ignore", divide="ignore"):
        xb = xyz @ rot.T + t
        ra, rb = xyz, xyz - centre_b
        cos = np.sum(ra * rb, axis=1) / (np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1))
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        proj_a = xyz @ k.T
        proj_b = xb @ k.T
        err_a = np.linalg.norm(proj_a[:, :2] / proj_a[:, 2:] - pa, axis=1)
        err_b = np.linalg.norm(proj_b[:, :2] / proj_b[:, 2:] - pb, axis=1)
        keep = (
            candidates & (xyz[:, 2] > 0) & (xb[:, 2] > 0)
            & (err_a <= cfg.max_reprojection_px) & (err_b <= cfg.max_reprojection_px)
            & (angle >= cfg.min_angle_deg)
        )
    return keep, np.nan_to_num(angle)


def _with_sigmas(
    xyz: np.ndarray, keep: np.ndarray, angle_deg: np.ndarray, rot: np.ndarray, t: np.ndarray, focal: float,
    pixel_sigma: float, octaves: np.ndarray | None,
) -> Points3D:
    """Points3D with the triangulation's depth sigma (module docstring) and the lateral sigma."""
    m = xyz.shape[0]
    centre_b = -rot.T @ t
    px = np.full(m, pixel_sigma)
    if octaves is not None:
        px = px * np.power(1.2, np.asarray(octaves, np.float64))
    s = px / focal
    th = np.radians(np.where(keep, angle_deg, 90.0))
    ra = np.linalg.norm(np.where(keep[:, None], xyz, 1.0), axis=1)
    rb = np.linalg.norm(np.where(keep[:, None], xyz - centre_b, 1.0), axis=1)
    sigma_range = s * np.sqrt((ra * np.cos(th)) ** 2 + rb**2) / np.sin(th)
    z = np.where(keep, xyz[:, 2], np.nan)
    sigma_z = sigma_range * np.abs(z) / ra  # the range error projected on the depth axis
    out = np.where(keep[:, None], xyz, np.nan)
    return Points3D(
        xyz=out.astype(np.float32),
        sigma_depth=np.where(keep, sigma_z, np.nan).astype(np.float32),
        sigma_lateral=np.where(keep, s * np.abs(z), np.nan).astype(np.float32),
        metric=False,
    )

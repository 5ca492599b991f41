"""Relative pose of a loop by PnP: candidate-frame 3D points against query-frame pixels.

Direction: the result ``R, t`` takes points from the **candidate** camera frame to the
**query** camera frame, ``X_query = R @ X_candidate + t``. With camera-to-world poses
``T_w_query``, ``T_w_candidate`` this is ``inv(T_w_query) @ T_w_candidate``, i.e. the pose of the
candidate camera expressed in the query camera (the loop edge a pose graph needs).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError, InputError, check_array
from .camera import PinholeCamera

__all__ = ["PnPConfig", "PoseEstimate", "estimate_pose_pnp", "rotation_angle_deg", "fundamental_ransac"]


@dataclass(frozen=True)
class PnPConfig:
    """Settings of PnP with RANSAC.

    Attributes:
        reprojection_px: RANSAC inlier threshold in pixels. A correct match misses its
            reprojection by the query keypoint's noise (1 px at level 0, 1.2^o at level o) plus
            the candidate point's depth noise seen from the query's viewpoint (about
            ``f * baseline_between_views * sigma_z / z**2``, 1-3 px for a metre between views
            at EuRoC's stereo noise); 4 px keeps them.
        iterations: largest number of RANSAC iterations (P3P samples). 300 finds an
            all-inlier sample with 99.9 % confidence down to a 40 % inlier ratio.
        confidence: RANSAC confidence.
        refine: refine the RANSAC pose on its inliers (robust, noise-weighted Gauss-Newton,
            symmetric when both frames have 3D), re-select the inliers, refine again.
    """

    reprojection_px: float = 4.0
    iterations: int = 300
    confidence: float = 0.999
    refine: bool = True

    def __post_init__(self) -> None:
        if not (self.reprojection_px > 0 and self.iterations > 0 and 0 < self.confidence < 1):
            raise ConfigError(f"invalid PnP settings {self}")


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """Outcome of PnP.

    Attributes:
        success: whether a pose was found.
        rotation: (3, 3) float64 rotation candidate -> query (identity when not found).
        translation: (3,) float64 translation candidate -> query, metres (zeros when not found).
        inliers: (M,) bool mask over the correspondences given.
        rmse_px: root-mean-square reprojection error of the inliers in pixels (NaN if none).
    """

    success: bool
    rotation: np.ndarray
    translation: np.ndarray
    inliers: np.ndarray
    rmse_px: float

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 homogeneous transform candidate -> query."""
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.translation
        return out

    @staticmethod
    def failed(m: int) -> PoseEstimate:
        return PoseEstimate(False, np.eye(3), np.zeros(3), np.zeros(m, bool), float("nan"))


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees."""
    c = (np.trace(rotation) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (np.cross without its axis juggling)."""
    return np.stack(
        (
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ),
        axis=1,
    )


def _so3_exp(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3)
    k = _skew((w / theta)[None])[0]
    return np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)


@dataclass(frozen=True)
class _Term:
    """Reprojection residuals of one direction, in pixels divided by the keypoint's sigma.

    Forward: points X in the candidate frame seen at undistorted normalised coordinates ``n``
    in the query image, residual ``f * (pi(R X + t) - n) / sigma``. Reverse: points X in the
    query frame seen in the candidate image, residual ``f * (pi(R^T (X - t)) - n) / sigma``.
    """

    points: np.ndarray  # (N, 3)
    normalised: np.ndarray  # (N, 2)
    scale: np.ndarray  # (N, 2) focal / sigma
    forward: bool

    def select(self, mask: np.ndarray) -> _Term:
        return _Term(self.points[mask], self.normalised[mask], self.scale[mask], self.forward)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
        if self.forward:
            return self.points @ rotation.T + translation
        return (self.points - translation) @ rotation

    def residuals(self, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
        """(N, 2) sigma-normalised residuals; inf for points behind the camera."""
        y = self.transformed(rotation, translation)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (y[:, :2] / y[:, 2:3] - self.normalised) * self.scale
        r[~(y[:, 2] > 1e-9)] = np.inf
        return r

    def linearise(self, rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (N, 2) and their (2N, 6) Jacobian w.r.t. a left update ``(dt, dw)`` of (R, t):
        ``R' = exp(dw) R``, ``t' = exp(dw) t + dt``."""
        y = self.transformed(rotation, translation)
        n = y.shape[0]
        x, yy, z = y[:, 0], y[:, 1], y[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / z
            r = (y[:, :2] * iz[:, None] - self.normalised) * self.scale
        r[~(z > 1e-9)] = np.inf
        # rows of d(residual)/dy: ju = (a, 0, -a x/z), jv = (0, b, -b y/z)
        a = self.scale[:, 0] * iz
        b = self.scale[:, 1] * iz
        cu = -a * x * iz
        cv = -b * yy * iz
        jac = np.empty((n, 2, 6))
        # for a row vector j: j^T [v]x = (j x v)^T
        if self.forward:  # y = R X + t: dy = dt - [y]x dw, so d/dw = y x j
            jac[:, 0, 0], jac[:, 0, 1], jac[:, 0, 2] = a, 0.0, cu
            jac[:, 1, 0], jac[:, 1, 1], jac[:, 1, 2] = 0.0, b, cv
            jac[:, 0, 3] = yy * cu
            jac[:, 0, 4] = z * a - x * cu
            jac[:, 0, 5] = -yy * a
            jac[:, 1, 3] = yy * cv - z * b
            jac[:, 1, 4] = -x * cv
            jac[:, 1, 5] = x * b
        else:  # y = R^T (X - t): dy = -R^T dt + R^T [X]x dw, so d/dt = -j R^T, d/dw = (j R^T) x X
            ju = np.stack((a, np.zeros(n), cu), axis=1) @ rotation.T
            jv = np.stack((np.zeros(n), b, cv), axis=1) @ rotation.T
            jac[:, 0, :3] = -ju
            jac[:, 1, :3] = -jv
            jac[:, 0, 3:] = _cross(ju, self.points)
            jac[:, 1, 3:] = _cross(jv, self.points)
        return r, jac.reshape(2 * n, 6)


def _refine(
    terms: list[_Term], rotation: np.ndarray, translation: np.ndarray, huber: float, iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Robust (Huber IRLS) Gauss-Newton over the residuals of all terms."""
    for _ in range(iterations):
        h = np.zeros((6, 6))
        g = np.zeros(6)
        for term in terms:
            if term.points.shape[0] == 0:
                continue
            r, j = term.linearise(rotation, translation)
            norm = np.sqrt(r[:, 0] ** 2 + r[:, 1] ** 2)
            ok = np.isfinite(norm)
            w = np.where(ok & (norm > huber), huber / np.maximum(norm, 1e-12), 1.0)
            w[~ok] = 0.0
            w2 = np.repeat(w, 2)
            rr = np.where(np.isfinite(r), r, 0.0).reshape(-1)
            jw = j * w2[:, None]
            h += jw.T @ j
            g += jw.T @ rr
        try:
            delta = -np.linalg.solve(h + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        dr = _so3_exp(delta[3:])
        rotation = dr @ rotation
        translation = dr @ translation + delta[:3]
        if float(np.abs(delta).max()) < 1e-6:  # micro-radians and micrometres
            break
    return rotation, translation


_GATE = float(np.sqrt(5.991))  # 95 % chi-square gate of 2 DOF, in sigmas


def _ransac_pnp(
    obj: np.ndarray, img: np.ndarray, camera: PinholeCamera, config: PnPConfig, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``cv2.solvePnPRansac`` (AP3P) on finite correspondences, seeded.

    Args:
        obj: (K, 3) float64 candidate points.
        img: (K, 2) float64 query pixels.

    Returns:
        ``(rotation, translation, inliers)``: (3, 3) and (3,) float64 and a (K,) bool mask,
        or None when RANSAC finds fewer than 4 inliers.

    Raises:
        InputError: OpenCV's solver threw on a degenerate configuration.
    """
    cv2.setRNGSeed(seed)
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj,
            img,
            camera.K,
            camera.dist,
            iterationsCount=config.iterations,
            reprojectionError=config.reprojection_px,
            confidence=config.confidence,
            flags=cv2.SOLVEPNP_AP3P,
        )
    except cv2.error as exc:  # degenerate configurations make some solvers throw
        raise InputError(f"PnP failed: {exc}".splitlines()[0]) from None
    if not ok or inl is None or len(inl) < 4:
        return None
    inliers = np.zeros(obj.shape[0], bool)
    inliers[inl.ravel()] = True
    return cv2.Rodrigues(rvec)[0], np.asarray(tvec, np.float64).reshape(3), inliers


def _reverse_term(
    points_query: np.ndarray | None,
    pixels_candidate: np.ndarray | None,
    sigma_candidate: np.ndarray | None,
    camera: PinholeCamera,
    m: int,
) -> tuple[_Term, np.ndarray]:
    """The reverse reprojection term (query points into the candidate image) of the finite rows.

    Returns:
        The term and the (K,) int64 indices of the matches it holds.

    Raises:
        InputError: ``points_query`` not (m, 3) or ``pixels_candidate`` not (m, 2).
    """
    pq = np.asarray(points_query, np.float64)
    pc = np.asarray(pixels_candidate, np.float64)
    check_array("points_query", pq, shape=(m, 3))
    check_array("pixels_candidate", pc, shape=(m, 2))
    sc = np.ones(m) if sigma_candidate is None else np.asarray(sigma_candidate, np.float64)
    ridx = np.flatnonzero(np.isfinite(pq).all(axis=1) & np.isfinite(pc).all(axis=1))
    focal = np.array([camera.fx, camera.fy])
    term = _Term(pq[ridx], camera.normalize(pc[ridx]), focal[None, :] / sc[ridx, None], forward=False)
    return term, ridx


def _refine_and_reselect(
    terms: list[_Term], masks: list[np.ndarray], rotation: np.ndarray, translation: np.ndarray
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Refine on the inliers, re-select them with the gate, refine again (at most twice).

    Args:
        terms: the forward term, then the reverse term when both frames have 3D.
        masks: the starting inliers of each term.
        rotation, translation: the starting pose.

    Returns:
        The refined pose and the inlier mask of each term.
    """
    for _ in range(2):  # refine on the RANSAC inliers, re-select, refine on those
        if sum(int(mk.sum()) for mk in masks) < 4:
            break
        selected = [t.select(mk) for t, mk in zip(terms, masks, strict=True)]
        rotation, translation = _refine(selected, rotation, translation, _GATE, iterations=3)
        new = [np.linalg.norm(t.residuals(rotation, translation), axis=1) <= _GATE for t in terms]
        if new[0].sum() < 4:
            break
        unchanged = all(np.array_equal(a, b) for a, b in zip(new, masks, strict=True))
        masks = new
        if unchanged:
            break
    return rotation, translation, masks


def estimate_pose_pnp(
    points_candidate: np.ndarray,
    pixels_query: np.ndarray,
    camera: PinholeCamera,
    config: PnPConfig = PnPConfig(),
    *,
    sigma_query: np.ndarray | None = None,
    points_query: np.ndarray | None = None,
    pixels_candidate: np.ndarray | None = None,
    sigma_candidate: np.ndarray | None = None,
    seed: int = 0,
) -> PoseEstimate:
    """Relative pose from candidate 3D points and their query pixels: RANSAC, then refinement.

    1. ``cv2.solvePnPRansac`` (AP3P minimal solver) with a fixed pixel threshold;
    2. robust Gauss-Newton refinement on the inliers, each residual divided by its
       keypoint's noise (``sigma_query``, e.g. ``1.2**octave`` pixels as ORB-SLAM weighs
       them), Huber loss at the 95 % chi-square gate of 2 DOF (sqrt(5.991) sigma);
    3. inliers re-selected with that gate and the pose refined again.

    When both frames have 3D (``points_query`` and ``pixels_candidate`` given) the refinement
    is symmetric: it also minimises the reprojection of the query's 3D points into the
    candidate image. Both depth maps then constrain the pose, which removes much of PnP's
    coupling between rotation and lateral translation with a narrow field of view.

    Args:
        points_candidate: (M, 3) points in the candidate camera frame (NaN rows are ignored).
        pixels_query: (M, 2) pixels of the same matches in the query image (``camera``'s
            possibly distorted image).
        camera: the camera of both images.
        config: RANSAC and refinement settings.
        sigma_query: (M,) keypoint noise in pixels of the query keypoints (default 1).
        points_query: (M, 3) points of the matches in the query camera frame (NaN: unknown).
        pixels_candidate: (M, 2) pixels of the matches in the candidate image.
        sigma_candidate: (M,) keypoint noise in pixels of the candidate keypoints (default 1).
        seed: seed of OpenCV's RNG, so that results repeat.

    Returns:
        The pose candidate -> query; ``inliers`` are the matches whose candidate 3D point
        reprojects into the query image within the gate.
    """
    points_candidate = np.asarray(points_candidate)
    pixels_query = np.asarray(pixels_query)
    check_array("PnP points", points_candidate, shape=(None, 3))
    m = points_candidate.shape[0]
    check_array("PnP pixels", pixels_query, shape=(m, 2))
    symmetric = points_query is not None and pixels_candidate is not None
    if (points_query is None) != (pixels_candidate is None):
        raise InputError("symmetric PnP refinement needs both points_query and pixels_candidate")
    sq = np.ones(m) if sigma_query is None else np.asarray(sigma_query, np.float64)
    if sq.shape != (m,):
        raise InputError(f"sigma_query: expected shape ({m},), got {sq.shape}")
    finite = np.isfinite(points_candidate).all(axis=1) & np.isfinite(pixels_query).all(axis=1)
    idx = np.flatnonzero(finite)
    if idx.size < 4:
        return PoseEstimate.failed(m)
    obj = np.ascontiguousarray(points_candidate[idx], np.float64)
    img = np.ascontiguousarray(pixels_query[idx], np.float64)
    found = _ransac_pnp(obj, img, camera, config, seed)
    if found is None:
        return PoseEstimate.failed(m)
    rotation, translation, inliers = found
    focal = np.array([camera.fx, camera.fy])
    fwd = _Term(obj, camera.normalize(img), focal[None, :] / sq[idx, None], forward=True)
    if config.refine:
        terms = [fwd]
        masks = [inliers]
        if symmetric:
            rev, ridx = _reverse_term(points_query, pixels_candidate, sigma_candidate, camera, m)
            # the reverse term starts from the RANSAC inliers that also have a query point
            terms.append(rev)
            masks.append(np.isin(ridx, idx[inliers]))
        rotation, translation, masks = _refine_and_reselect(terms, masks, rotation, translation)
        inliers = masks[0]
    r = fwd.residuals(rotation, translation) * sq[idx, None]  # back to (undistorted) pixels
    err = np.linalg.norm(r, axis=1)
    rmse = float(np.sqrt(np.mean(err[inliers] ** 2))) if inliers.any() else float("nan")
    full = np.zeros(m, bool)
    full[idx[inliers]] = True
    return PoseEstimate(True, rotation, translation, full, rmse)


_FUNDAMENTAL_METHODS = {"ransac": cv2.FM_RANSAC, "usac": cv2.USAC_FAST}


def fundamental_ransac(
    pixels_query: np.ndarray,
    pixels_candidate: np.ndarray,
    *,
    threshold_px: float = 2.0,
    confidence: float = 0.99,
    max_iterations: int = 500,
    method: str = "ransac",
) -> tuple[np.ndarray | None, np.ndarray]:
    """Fundamental matrix with RANSAC, as DLoopDetector's geometric check.

    Args:
        pixels_query: (M, 2) pixels in the query image.
        pixels_candidate: (M, 2) pixels of the same matches in the candidate image.
        threshold_px: largest distance to the epipolar line of an inlier, pixels.
        confidence: RANSAC confidence.
        max_iterations: largest number of RANSAC iterations.
        method: ``"ransac"`` (OpenCV's classic 7-point RANSAC, as DLoopDetector) or ``"usac"``
            (OpenCV's USAC with local optimisation and early rejection of hopeless models:
            five to nine times faster on 20-120 matches, and it keeps more of the true inliers).

    Returns:
        ``(F, inliers)``: (3, 3) float64 F with ``x_query^T F x_candidate = 0`` (None when not
        found) and an (M,) bool inlier mask.
    """
    pixels_query = np.asarray(pixels_query, np.float64)
    pixels_candidate = np.asarray(pixels_candidate, np.float64)
    check_array("F pixels (query)", pixels_query, shape=(None, 2))
    m = pixels_query.shape[0]
    check_array("F pixels (candidate)", pixels_candidate, shape=(m, 2))
    if m < 8:
        return None, np.zeros(m, bool)
    flag = _FUNDAMENTAL_METHODS.get(method)
    if flag is None:
        raise InputError(f"fundamental method {method!r}: expected one of {', '.join(_FUNDAMENTAL_METHODS)}")
    try:
        f, mask = cv2.findFundamentalMat(
            pixels_candidate, pixels_query, flag, threshold_px, confidence, max_iterations
        )
    except cv2.error:
        return None, np.zeros(m, bool)
    if f is None or mask is None or f.shape != (3, 3):
        return None, np.zeros(m, bool)
    return np.asarray(f, np.float64), mask.ravel().astype(bool)

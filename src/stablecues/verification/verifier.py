"""The entry point the loop detector calls per candidate: :class:`Verifier`."""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, InputError
from ..geometry.camera import Calibration, PinholeCamera
from ..geometry.points import NoiseModel, Points3D
from ..geometry.pose import PoseEstimate, estimate_pose_pnp, fundamental_ransac
from ..geometry.triangles import TriangleCheck, check_triangles
from ..types import Entry, Features, FeatureVector
from .config import VerificationConfig
from .matching import Matches, match_features
from .result import Method, Status, Verification

__all__ = ["View", "Verifier"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class View:
    """What the verifier needs of one frame.

    Attributes:
        features: the frame's features.
        fvec: its direct index (None: brute-force matching).
        points: 3D point per feature in the frame's camera with sigmas, or None (no 3D).
    """

    features: Features
    fvec: FeatureVector | None = None
    points: Points3D | None = None

    def __post_init__(self) -> None:
        if self.fvec is not None and len(self.fvec) != len(self.features):
            raise InputError(f"view: {len(self.features)} features but {len(self.fvec)} feature-vector nodes")
        if self.points is not None and len(self.points) != len(self.features):
            raise InputError(f"view: {len(self.features)} features but {len(self.points)} 3D points")


class Verifier:
    """Geometric verification of loop candidates.

    Args:
        config: settings (method, ratio, tolerance, acceptance ...).
        camera: the query camera the keypoints refer to (the rectified left camera when features
            come from rectified images). Needed for PnP; the fundamental check undistorts with it.
        noise: noise model turning stored ``(N, 3)`` points (database entries, map points without
            sigma) into :class:`Points3D`. Needed for ``tolerance="noise"`` with such points.

    Raises:
        ConfigError: a method that needs a camera without one.
    """

    def __init__(
        self,
        config: VerificationConfig | None = None,
        camera: PinholeCamera | None = None,
        noise: NoiseModel | None = None,
    ) -> None:
        config = config or VerificationConfig()
        if camera is None and (
            config.method == "pnp" or (config.method == "triangles" and config.min_pnp_inliers > 0)
        ):
            raise ConfigError(
                f"verification method {config.method!r} with min_pnp_inliers={config.min_pnp_inliers} "
                f"needs the query camera for PnP"
            )
        self.config = config
        self.camera = camera
        self.noise = noise
        self._triangle_config = config.triangle_config()
        self._pnp_config = config.pnp_config()

    @classmethod
    def from_calibration(cls, calib: Calibration, config: VerificationConfig | None = None) -> Verifier:
        """A verifier for frames of one calibrated camera (its left camera, its noise model).

        Give the *rectified* calibration when features come from rectified stereo images.
        """
        try:
            noise: NoiseModel | None = NoiseModel.for_calibration(calib)
        except ConfigError:
            noise = None
        return cls(config, calib.left, noise)

    # --- inputs -----------------------------------------------------------------------------

    def points_from_xyz(self, xyz: np.ndarray | None, features: Features) -> Points3D | None:
        """Stored ``(N, 3)`` points (NaN unknown) with sigmas from this verifier's noise model."""
        if xyz is None:
            return None
        if self.noise is None:
            if self.config.tolerance == "noise":
                raise ConfigError(
                    "noise tolerance with stored 3D points needs a NoiseModel (Verifier(noise=...))"
                )
            xyz = np.asarray(xyz)
            n = xyz.shape[0]
            # the relative tolerance never reads the sigmas; zeros keep the points valid
            return Points3D(np.asarray(xyz, np.float32), np.zeros(n, np.float32), np.zeros(n, np.float32))
        return self.noise.points(xyz, features.octaves)

    def view_of_entry(self, entry: Entry) -> View:
        """The View of a database entry (its features, direct index and stored 3D points)."""
        return View(entry.features, entry.fvec, self.points_from_xyz(entry.points3d, entry.features))

    def verify_entry(self, query: View, entry: Entry) -> Verification:
        """Verify the query frame against a database entry."""
        return self.verify(query, self.view_of_entry(entry))

    # --- the check --------------------------------------------------------------------------

    def verify(self, query: View, candidate: View) -> Verification:
        """Verify one (query, candidate) pair.

        Args:
            query: the current frame.
            candidate: the earlier frame (database entry) proposed as a loop.

        Returns:
            The decision, the matches, triangles, inliers and relative pose (candidate -> query).
        """
        cfg = self.config
        t0 = time.perf_counter()
        use_fvec = query.fvec is not None and candidate.fvec is not None
        matches = match_features(
            query.features,
            candidate.features,
            query.fvec if use_fvec else None,
            candidate.fvec if use_fvec else None,
            ratio=cfg.ratio,
            max_distance=cfg.max_distance,
            cross_check=cfg.cross_check,
        )
        timings = {"matching": (time.perf_counter() - t0) * 1e3}

        method = Method(cfg.method)
        fallback = False
        if method is Method.TRIANGLES and (query.points is None or candidate.points is None):
            fallback = True
            method = (
                Method.PNP if candidate.points is not None and self.camera is not None else Method.FUNDAMENTAL
            )
        elif method is Method.PNP and (candidate.points is None or self.camera is None):
            fallback = True
            method = Method.FUNDAMENTAL
        return self._with_pixels(
            self._decide(query, candidate, matches, method, fallback, t0, timings), query, candidate
        )

    def _decide(
        self,
        query: View,
        candidate: View,
        matches: Matches,
        method: Method,
        fallback: bool,
        t0: float,
        timings: dict[str, float],
    ) -> Verification:
        cfg = self.config
        if fallback and not cfg.fallback:
            return self._finish(
                False,
                Method(cfg.method),
                Status.TOO_FEW_3D,
                "no 3D points (fallback disabled)",
                matches,
                None,
                t0,
                timings,
            )
        if fallback:
            logger.debug("no 3D points for %s: falling back to %s", cfg.method, method.value)

        if method is Method.FUNDAMENTAL:
            return self._fundamental(query, candidate, matches, fallback, t0, timings)
        if method is Method.PNP:
            return self._pnp_only(query, candidate, matches, fallback, t0, timings)
        return self._triangles(query, candidate, matches, t0, timings)

    def _finish(
        self,
        accepted: bool,
        method: Method,
        status: Status,
        reason: str,
        matches: Matches,
        inliers: np.ndarray | None,
        t0: float,
        timings: dict[str, float],
        **extra: object,
    ) -> Verification:
        timings["total"] = (time.perf_counter() - t0) * 1e3
        if inliers is None:
            inliers = np.zeros(len(matches), bool)
        return Verification(
            accepted=accepted,
            method=method,
            status=status,
            reason=reason,
            matches=matches,
            inliers=inliers,
            timings=timings,
            **extra,  # type: ignore[arg-type]
        )

    @staticmethod
    def _with_pixels(result: Verification, query: View, candidate: View) -> Verification:
        m = result.matches
        return dataclasses.replace(
            result,
            pixels_query=query.features.keypoints[m.query],
            pixels_candidate=candidate.features.keypoints[m.candidate],
        )

    def _fundamental(
        self,
        query: View,
        candidate: View,
        matches: Matches,
        fallback: bool,
        t0: float,
        timings: dict[str, float],
    ) -> Verification:
        cfg = self.config
        note = " (no 3D points: fundamental-matrix fallback)" if fallback else ""
        if len(matches) < cfg.min_fundamental_inliers:
            return self._finish(
                False,
                Method.FUNDAMENTAL,
                Status.TOO_FEW_MATCHES,
                f"{len(matches)} matches, need {cfg.min_fundamental_inliers}{note}",
                matches,
                None,
                t0,
                timings,
                fallback=fallback,
            )
        t = time.perf_counter()
        pq = query.features.keypoints[matches.query].astype(np.float64)
        pc = candidate.features.keypoints[matches.candidate].astype(np.float64)
        if self.camera is not None and self.camera.has_distortion:
            pq = self.camera.undistort_points(pq)
            pc = self.camera.undistort_points(pc)
        f, inliers = fundamental_ransac(
            pq,
            pc,
            threshold_px=cfg.fundamental_threshold_px,
            confidence=cfg.fundamental_confidence,
            max_iterations=cfg.fundamental_iterations,
        )
        timings["fundamental"] = (time.perf_counter() - t) * 1e3
        n_in = int(inliers.sum())
        if f is None:
            return self._finish(
                False,
                Method.FUNDAMENTAL,
                Status.FUNDAMENTAL_FAILED,
                f"no fundamental matrix from {len(matches)} matches{note}",
                matches,
                inliers,
                t0,
                timings,
                fallback=fallback,
            )
        accepted = n_in >= cfg.min_fundamental_inliers
        return self._finish(
            accepted,
            Method.FUNDAMENTAL,
            Status.ACCEPTED if accepted else Status.TOO_FEW_FUNDAMENTAL_INLIERS,
            f"{n_in} of {len(matches)} matches fit a fundamental matrix, "
            f"need {cfg.min_fundamental_inliers}{note}",
            matches,
            inliers,
            t0,
            timings,
            fallback=fallback,
            fundamental=f,
        )

    def _pose(
        self, query: View, candidate: View, matches: Matches, timings: dict[str, float]
    ) -> PoseEstimate:
        """PnP of the candidate's 3D points against the query's keypoints; the refinement is
        symmetric when the query has 3D points too."""
        t = time.perf_counter()
        if candidate.points is None or self.camera is None:
            raise ConfigError("PnP needs candidate 3D points and the query camera")
        pixel_sigma, scale = (self.noise.pixel_sigma, self.noise.scale_factor) if self.noise else (1.0, 1.2)
        pts = candidate.points.xyz[matches.candidate].astype(np.float64)
        pts[~candidate.points.valid[matches.candidate]] = np.nan
        pix = query.features.keypoints[matches.query].astype(np.float64)
        sq = pixel_sigma * np.power(scale, query.features.octaves[matches.query].astype(np.float64))
        qpts = cpix = sc = None
        if query.points is not None:
            qpts = query.points.xyz[matches.query].astype(np.float64)
            qpts[~query.points.valid[matches.query]] = np.nan
            cpix = candidate.features.keypoints[matches.candidate].astype(np.float64)
            c_oct = candidate.features.octaves[matches.candidate].astype(np.float64)
            sc = pixel_sigma * np.power(scale, c_oct)
        pose = estimate_pose_pnp(
            pts,
            pix,
            self.camera,
            self._pnp_config,
            sigma_query=sq,
            points_query=qpts,
            pixels_candidate=cpix,
            sigma_candidate=sc,
        )
        timings["pnp"] = (time.perf_counter() - t) * 1e3
        return pose

    def _pnp_only(
        self,
        query: View,
        candidate: View,
        matches: Matches,
        fallback: bool,
        t0: float,
        timings: dict[str, float],
    ) -> Verification:
        cfg = self.config
        note = " (query has no 3D points: PnP fallback)" if fallback else ""
        need = max(cfg.min_pnp_inliers, 4)
        if len(matches) < need:
            return self._finish(
                False,
                Method.PNP,
                Status.TOO_FEW_MATCHES,
                f"{len(matches)} matches, need {need}{note}",
                matches,
                None,
                t0,
                timings,
                fallback=fallback,
            )
        if candidate.points is not None and int(candidate.points.valid[matches.candidate].sum()) < need:
            n3 = int(candidate.points.valid[matches.candidate].sum())
            return self._finish(
                False,
                Method.PNP,
                Status.TOO_FEW_3D,
                f"{n3} matches with a 3D point, need {need}{note}",
                matches,
                None,
                t0,
                timings,
                fallback=fallback,
            )
        pose = self._pose(query, candidate, matches, timings)
        return self._decide_pose(pose, Method.PNP, matches, t0, timings, f"{note}", fallback=fallback)

    def _decide_pose(
        self,
        pose: PoseEstimate,
        method: Method,
        matches: Matches,
        t0: float,
        timings: dict[str, float],
        prefix: str,
        **extra: object,
    ) -> Verification:
        cfg = self.config
        if not pose.success:
            return self._finish(
                False,
                method,
                Status.PNP_FAILED,
                f"{prefix}PnP found no pose".strip(),
                matches,
                None,
                t0,
                timings,
                **extra,
            )
        accepted = pose.n_inliers >= cfg.min_pnp_inliers
        return self._finish(
            accepted,
            method,
            Status.ACCEPTED if accepted else Status.TOO_FEW_PNP_INLIERS,
            f"{prefix}{pose.n_inliers} PnP inliers (need {cfg.min_pnp_inliers}), "
            f"rmse {pose.rmse_px:.2f} px".strip(),
            matches,
            pose.inliers,
            t0,
            timings,
            rotation=pose.rotation,
            translation=pose.translation,
            rmse_px=pose.rmse_px,
            **extra,
        )

    def _triangles(
        self, query: View, candidate: View, matches: Matches, t0: float, timings: dict[str, float]
    ) -> Verification:
        cfg = self.config
        if query.points is None or candidate.points is None:  # handled by verify(); keeps mypy informed
            raise ConfigError("triangle check needs 3D points in both frames")
        need = cfg.triangles_needed
        if len(matches) < 3 * need:
            return self._finish(
                False,
                Method.TRIANGLES,
                Status.TOO_FEW_MATCHES,
                f"{len(matches)} matches, need {3 * need} for {need} triangles",
                matches,
                None,
                t0,
                timings,
            )
        t = time.perf_counter()
        tc: TriangleCheck = check_triangles(
            query.points.subset(matches.query),
            candidate.points.subset(matches.candidate),
            self._triangle_config,
        )
        timings["triangles"] = (time.perf_counter() - t) * 1e3
        extra: dict[str, object] = {"triangles": tc.triangles, "n_triangles_agree": tc.n_agree}
        summary = f"{tc.n_agree} of {cfg.n_triangles} triangles agree ({tc.n_checked} formed), need {need}"
        if tc.n_agree < need:
            if tc.n_usable < 3 * need:
                status = Status.TOO_FEW_3D
                summary += f"; only {tc.n_usable} matches have 3D in both frames"
            elif tc.n_checked < need or (cfg.acceptance == "all" and tc.n_checked < cfg.n_triangles):
                status = Status.TOO_FEW_TRIANGLES
            else:
                status = Status.TRIANGLES_DISAGREE
            vertices = self._vertex_mask(tc, len(matches))
            return self._finish(
                False, Method.TRIANGLES, status, summary, matches, vertices, t0, timings, **extra
            )
        if self.camera is None:  # min_pnp_inliers == 0 (checked in __init__): no pose
            return self._finish(
                True,
                Method.TRIANGLES,
                Status.ACCEPTED,
                summary + "; no camera, no pose",
                matches,
                self._vertex_mask(tc, len(matches)),
                t0,
                timings,
                **extra,
            )
        pose = self._pose(query, candidate, matches, timings)
        if not pose.success and cfg.min_pnp_inliers == 0:  # PnP only gives the pose here, no vote
            return self._finish(
                True,
                Method.TRIANGLES,
                Status.ACCEPTED,
                summary + "; PnP found no pose",
                matches,
                self._vertex_mask(tc, len(matches)),
                t0,
                timings,
                **extra,
            )
        return self._decide_pose(pose, Method.TRIANGLES, matches, t0, timings, summary + "; ", **extra)

    @staticmethod
    def _vertex_mask(tc: TriangleCheck, m: int) -> np.ndarray:
        mask = np.zeros(m, bool)
        for tri in tc.triangles:
            if tri.agree:
                mask[list(tri.matches)] = True
        return mask

"""The entry point the loop detector calls per candidate: :class:`Verifier`."""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ConfigError, InputError
from ..geometry.camera import Calibration, PinholeCamera
from ..geometry.points import NoiseModel, Points3D, relative_points_from_meta
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
        weights: (N,) stability weight per feature (semantic weighting), or None; orders the
            matches for triangles (``VerificationConfig.stable_ranking``).
    """

    features: Features
    fvec: FeatureVector | None = None
    points: Points3D | None = None
    weights: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.features)
        if self.fvec is not None and len(self.fvec) != n:
            raise InputError(f"view: {n} features but {len(self.fvec)} feature-vector nodes")
        if self.points is not None and len(self.points) != n:
            raise InputError(f"view: {n} features but {len(self.points)} 3D points")
        if self.weights is not None:
            w = np.asarray(self.weights)
            if (w.shape != (n,) or not np.issubdtype(w.dtype, np.floating)
                    or not bool(np.all(np.isfinite(w) & (w >= 0)))):
                raise InputError(f"view: feature weights must be {n} finite non-negative numbers, one "
                                 f"per feature, got shape {w.shape} of {w.dtype}")


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
        self._similar_config = dataclasses.replace(self._triangle_config, tolerance="similar")
        self._pnp_config = config.pnp_config()
        self._lighterglue: Any = None  # the LighterGlue matcher, opened on first use

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
        """The View of a database entry (its features, direct index, stored 3D points and
        feature weights; the sigmas of monocular points are read from the entry's record).

        Raises:
            InputError: stored feature weights that are not one finite non-negative number per
                feature.
        """
        points = None
        if entry.points3d is not None and self.camera is not None:
            model = NoiseModel(0.0, self.camera.fx) if self.noise is None else self.noise
            octaves = entry.features.octaves
            points = relative_points_from_meta(entry.points3d, dict(entry.meta), model, octaves)
        if points is None:
            points = self.points_from_xyz(entry.points3d, entry.features)
        try:
            return View(entry.features, entry.fvec, points, entry.arrays.get("weights"))
        except InputError as exc:
            raise InputError(f"database entry {entry.entry_id}: {exc}") from None

    def verify_entry(self, query: View, entry: Entry, *, must_beat: int = 0) -> Verification:
        """Verify the query frame against a database entry (``must_beat``: see :meth:`verify`)."""
        return self.verify(query, self.view_of_entry(entry), must_beat=must_beat)

    # --- the check --------------------------------------------------------------------------

    def verify(self, query: View, candidate: View, *, must_beat: int = 0) -> Verification:
        """Verify one (query, candidate) pair.

        Args:
            query: the current frame.
            candidate: the earlier frame (database entry) proposed as a loop.
            must_beat: the inliers the pair must reach to matter (those of a loop already
                accepted for this query). With fewer matches than that it cannot (inliers are
                a subset of the matches), so the geometry is not run: the result is
                ``OUTRANKED``, not accepted. 0: always run it.

        Returns:
            The decision, the matches, triangles, inliers and relative pose (candidate -> query).
        """
        cfg = self.config
        result = self._verify_with(cfg.matcher, query, candidate, must_beat)
        if (cfg.rescue_inliers and cfg.matcher != "lighterglue" and not result.accepted
                and result.status is not Status.OUTRANKED and result.n_inliers >= cfg.rescue_inliers):
            return self._verify_with("lighterglue", query, candidate, must_beat)
        return result

    def _verify_with(self, matcher: str, query: View, candidate: View, must_beat: int) -> Verification:
        """:meth:`verify` with the correspondences of ``matcher``."""
        cfg = self.config
        t0 = time.perf_counter()
        matches = self._match(matcher, query, candidate)
        static = 0
        if cfg.static_px is not None and len(matches):
            moved = np.linalg.norm(query.features.keypoints[matches.query].astype(np.float64)
                                   - candidate.features.keypoints[matches.candidate], axis=1) > cfg.static_px
            static = len(matches) - int(np.count_nonzero(moved))
            if static > _SAME_VIEW * min(len(query.features), len(candidate.features)):
                static = 0  # most of the frame is pixel for pixel the candidate: the same view
            if static:
                matches = matches.subset(moved)
        timings = {"matching": (time.perf_counter() - t0) * 1e3}
        configured = Method(cfg.method)
        method = self._method_for(configured, query, candidate)
        fallback = method is not configured
        if len(matches) < must_beat:
            ctx = _Context(query, candidate, matches, method, fallback, t0, timings, static, matcher)
            return ctx.finish(Status.OUTRANKED, f"{len(matches)} matches cannot reach the {must_beat} "
                                                "inliers of a loop already accepted (not checked)")
        if fallback and not cfg.fallback:
            ctx = _Context(query, candidate, matches, configured, False, t0, timings, static, matcher)
            return ctx.finish(Status.TOO_FEW_3D, "no 3D points (fallback disabled)")
        if fallback:
            logger.debug("no 3D points for %s: falling back to %s", cfg.method, method.value)
        if method is Method.TRIANGLES and not _metric(query.points, candidate.points):
            method = Method.SIMILAR_TRIANGLES  # a monocular side: its scale is unknown
        ctx = _Context(query, candidate, matches, method, fallback, t0, timings, static, matcher)
        return self._checks[method](ctx)

    def _match(self, matcher: str, query: View, candidate: View) -> Matches:
        """The correspondences of ``matcher`` (see ``VerificationConfig.matcher``)."""
        cfg = self.config
        if matcher == "lighterglue":
            if self._lighterglue is None:
                from .lighterglue import LighterGlueMatcher

                self._lighterglue = LighterGlueMatcher()
            return self._lighterglue.match(query.features, candidate.features, cfg.match_confidence)
        mnn = matcher == "mnn"
        use_fvec = not mnn and query.fvec is not None and candidate.fvec is not None
        return match_features(
            query.features,
            candidate.features,
            query.fvec if use_fvec else None,
            candidate.fvec if use_fvec else None,
            ratio=cfg.ratio,
            max_distance=cfg.max_distance,
            cross_check=cfg.cross_check or mnn,
        )

    @property
    def _checks(self) -> dict[Method, Callable[[_Context], Verification]]:
        """The verifier of each method."""
        return {
            Method.TRIANGLES: self._triangles,
            Method.SIMILAR_TRIANGLES: self._triangles,
            Method.PNP: self._pnp_only,
            Method.FUNDAMENTAL: self._fundamental,
        }

    def _method_for(self, configured: Method, query: View, candidate: View) -> Method:
        """The method that can run on these views: the configured one, or its fallback (PnP when
        only the candidate has 3D points, the fundamental matrix when it has none)."""
        if configured is Method.TRIANGLES and (query.points is None or candidate.points is None):
            # PnP stands in only with metric candidate points: monocular ones are too sparse
            pnp = candidate.points is not None and candidate.points.metric and self.camera is not None
            return Method.PNP if pnp else Method.FUNDAMENTAL
        if configured is Method.PNP and (candidate.points is None or self.camera is None):
            return Method.FUNDAMENTAL
        return configured

    def _fundamental(self, ctx: _Context) -> Verification:
        cfg = self.config
        matches = ctx.matches
        note = " (no 3D points: fundamental-matrix fallback)" if ctx.fallback else ""
        if len(matches) < cfg.min_fundamental_inliers:
            return ctx.finish(
                Status.TOO_FEW_MATCHES, f"{len(matches)} matches, need {cfg.min_fundamental_inliers}{note}"
            )
        t = time.perf_counter()
        pq = ctx.query.features.keypoints[matches.query].astype(np.float64)
        pc = ctx.candidate.features.keypoints[matches.candidate].astype(np.float64)
        if self.camera is not None and self.camera.has_distortion:
            pq = self.camera.undistort_points(pq)
            pc = self.camera.undistort_points(pc)
        f, inliers = fundamental_ransac(
            pq,
            pc,
            threshold_px=cfg.fundamental_threshold_px,
            confidence=cfg.fundamental_confidence,
            max_iterations=cfg.fundamental_iterations,
            method=cfg.fundamental_method,
        )
        ctx.timings["fundamental"] = (time.perf_counter() - t) * 1e3
        n_in = int(inliers.sum())
        if f is None:
            return ctx.finish(
                Status.FUNDAMENTAL_FAILED,
                f"no fundamental matrix from {len(matches)} matches{note}",
                inliers=inliers,
            )
        need = max(cfg.min_fundamental_inliers, math.ceil(cfg.min_fundamental_ratio * len(matches) - 1e-9))
        accepted = n_in >= need
        ratio = ""
        if cfg.min_fundamental_ratio:
            ratio = f" ({n_in / len(matches):.0%}, need {cfg.min_fundamental_ratio:.0%})"
        return ctx.finish(
            Status.ACCEPTED if accepted else Status.TOO_FEW_FUNDAMENTAL_INLIERS,
            f"{n_in} of {len(matches)} matches fit a fundamental matrix{ratio}, "
            f"need {cfg.min_fundamental_inliers}{note}",
            inliers=inliers,
            fundamental=f,
        )

    def _pose(self, ctx: _Context) -> PoseEstimate:
        """PnP of the candidate's 3D points against the query's keypoints; the refinement is
        symmetric when the query has 3D points too."""
        t = time.perf_counter()
        query, candidate, matches = ctx.query, ctx.candidate, ctx.matches
        if candidate.points is None or self.camera is None:
            raise ConfigError("PnP needs candidate 3D points and the query camera")
        pixel_sigma, scale = (self.noise.pixel_sigma, self.noise.scale_factor) if self.noise else (1.0, 1.2)
        pts = candidate.points.xyz[matches.candidate].astype(np.float64)
        pts[~candidate.points.valid[matches.candidate]] = np.nan
        pix = query.features.keypoints[matches.query].astype(np.float64)
        sq = pixel_sigma * np.power(scale, query.features.octaves[matches.query].astype(np.float64))
        qpts = cpix = sc = None
        # the symmetric refinement needs both frames in one (metric) unit
        if query.points is not None and _metric(query.points, candidate.points):
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
        ctx.timings["pnp"] = (time.perf_counter() - t) * 1e3
        return pose

    def _pnp_only(self, ctx: _Context) -> Verification:
        cfg = self.config
        matches, candidate = ctx.matches, ctx.candidate
        note = " (query has no 3D points: PnP fallback)" if ctx.fallback else ""
        need = max(cfg.min_pnp_inliers, 4)
        if len(matches) < need:
            return ctx.finish(Status.TOO_FEW_MATCHES, f"{len(matches)} matches, need {need}{note}")
        if candidate.points is not None and int(candidate.points.valid[matches.candidate].sum()) < need:
            n3 = int(candidate.points.valid[matches.candidate].sum())
            return ctx.finish(Status.TOO_FEW_3D, f"{n3} matches with a 3D point, need {need}{note}")
        return self._decide_pose(ctx, self._pose(ctx), note)

    def _decide_pose(self, ctx: _Context, pose: PoseEstimate, prefix: str, **extra: Any) -> Verification:
        need = self.config.min_pnp_inliers
        if not pose.success:
            return ctx.finish(Status.PNP_FAILED, f"{prefix}PnP found no pose".strip(), **extra)
        return ctx.finish(
            Status.ACCEPTED if pose.n_inliers >= need else Status.TOO_FEW_PNP_INLIERS,
            f"{prefix}{pose.n_inliers} PnP inliers (need {need}), rmse {pose.rmse_px:.2f} px".strip(),
            inliers=pose.inliers,
            rotation=pose.rotation,
            translation=pose.translation,
            rmse_px=pose.rmse_px,
            **extra,
        )

    def _triangles(self, ctx: _Context) -> Verification:
        cfg = self.config
        query, candidate, matches = ctx.query, ctx.candidate, ctx.matches
        if query.points is None or candidate.points is None:  # handled by verify(); keeps mypy informed
            raise ConfigError("triangle check needs 3D points in both frames")
        need = cfg.triangles_needed
        if len(matches) < 3 * need:
            return ctx.finish(
                Status.TOO_FEW_MATCHES, f"{len(matches)} matches, need {3 * need} for {need} triangles"
            )
        t = time.perf_counter()
        similar = ctx.method is Method.SIMILAR_TRIANGLES
        triangle_config = self._similar_config if similar else self._triangle_config
        tc: TriangleCheck = check_triangles(
            query.points.subset(matches.query),
            candidate.points.subset(matches.candidate),
            triangle_config,
            order=self._triangle_order(query, candidate, matches),
        )
        ctx.timings["triangles"] = (time.perf_counter() - t) * 1e3
        extra: dict[str, Any] = {"triangles": tc.triangles, "n_triangles_agree": tc.n_agree}
        kind = "similar triangles" if similar else "triangles"
        summary = f"{tc.n_agree} of {cfg.n_triangles} {kind} agree ({tc.n_checked} formed), need {need}"
        vertices = _vertex_mask(tc, len(matches))
        if similar and tc.n_checked < need and cfg.fallback:
            # a monocular frame triangulates only what it shares with its neighbour, and points
            # of little parallax are too uncertain to form sides: when too few triangles can be
            # formed from the loop's matches, the epipolar check decides
            ctx.method, ctx.fallback = Method.FUNDAMENTAL, True
            return self._fundamental(ctx)
        if tc.n_agree < need:
            status, note = self._triangle_rejection(tc)
            return ctx.finish(status, summary + note, inliers=vertices, **extra)
        if self.camera is None:  # min_pnp_inliers == 0 (checked in __init__): no pose
            return ctx.finish(Status.ACCEPTED, summary + "; no camera, no pose", inliers=vertices, **extra)
        pose = self._pose(ctx)
        if not pose.success and cfg.min_pnp_inliers == 0:  # PnP only gives the pose here, no vote
            return ctx.finish(Status.ACCEPTED, summary + "; PnP found no pose", inliers=vertices, **extra)
        return self._decide_pose(ctx, pose, summary + "; ", **extra)

    def _triangle_order(self, query: View, candidate: View, matches: Matches) -> np.ndarray | None:
        """The order in which matches enter triangles (None: their rank, by descriptor distance).

        With stability weights on both sides (``stable_ranking``): descriptor confidence times
        the geometric mean of the two features' weights, best first, ties in rank order. A
        weight is how often features of the feature's class come back on a revisit, relative to
        the average, so the product ranks a match by how likely it is both right and lasting.
        """
        if not self.config.stable_ranking or query.weights is None or candidate.weights is None:
            return None
        w = np.sqrt(np.asarray(query.weights, np.float64)[matches.query]
                    * np.asarray(candidate.weights, np.float64)[matches.candidate])
        return np.argsort(-(matches.confidence.astype(np.float64) * w), kind="stable")

    def _triangle_rejection(self, tc: TriangleCheck) -> tuple[Status, str]:
        """Why too few triangles agreed, and a note for the reason line."""
        cfg = self.config
        need = cfg.triangles_needed
        if tc.n_usable < 3 * need:
            return Status.TOO_FEW_3D, f"; only {tc.n_usable} matches have 3D in both frames"
        if tc.n_checked < need or (cfg.acceptance == "all" and tc.n_checked < cfg.n_triangles):
            return Status.TOO_FEW_TRIANGLES, ""
        return Status.TRIANGLES_DISAGREE, ""


def _metric(*points: Points3D | None) -> bool:
    """Whether every side has metric 3D points (stereo, depth, map points)."""
    return all(p is not None and p.metric for p in points)


def _vertex_mask(tc: TriangleCheck, m: int) -> np.ndarray:
    """(m,) bool: the matches that are vertices of agreeing triangles."""
    mask = np.zeros(m, bool)
    for tri in tc.triangles:
        if tri.agree:
            mask[list(tri.matches)] = True
    return mask


#: with ``static_px``, static matches are left out unless they are more than this fraction of
#: the smaller frame's features: then the frame is the candidate seen again from the same pose
#: (or the same image twice), not an overlay, which covers a part of the frame (a timestamp on
#: CamVid: 24 % of its features; the pasted cars of the swapped sets' false loops: 2-17 %)
_SAME_VIEW = 0.5


@dataclass(eq=False)
class _Context:
    """One verification in progress, and the one place its :class:`Verification` is built."""

    query: View
    candidate: View
    matches: Matches
    method: Method
    fallback: bool
    t0: float
    timings: dict[str, float]
    static: int = 0  # matches left out as fixed to the camera (``static_px``)
    matcher: str = "ratio"  # the matcher that found ``matches``

    def finish(
        self, status: Status, reason: str, *, inliers: np.ndarray | None = None, **geometry: Any
    ) -> Verification:
        """The result: accepted exactly when ``status`` is ACCEPTED; ``geometry`` holds the
        optional fields (triangles, pose, fundamental matrix) of :class:`Verification`."""
        self.timings["total"] = (time.perf_counter() - self.t0) * 1e3
        m = self.matches
        if self.static:
            reason += f"; {self.static} matches at the same pixels in both images left out"
        return Verification(
            accepted=status is Status.ACCEPTED,
            method=self.method,
            status=status,
            reason=reason,
            matches=m,
            inliers=np.zeros(len(m), bool) if inliers is None else inliers,
            fallback=self.fallback,
            matcher=self.matcher,
            timings=self.timings,
            pixels_query=self.query.features.keypoints[m.query],
            pixels_candidate=self.candidate.features.keypoints[m.candidate],
            **geometry,
        )

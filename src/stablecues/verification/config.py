"""Settings of geometric verification, with named presets."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import merge
from ..errors import ConfigError
from ..geometry.pose import PnPConfig
from ..geometry.triangles import TriangleConfig

__all__ = ["VerificationConfig", "PRESETS", "preset"]

_METHODS = ("triangles", "fundamental", "pnp")
_MATCHERS = ("ratio", "mnn", "lighterglue")
_ACCEPTANCE = ("all", "majority", "at_least")


@dataclass(frozen=True)
class VerificationConfig:
    """Settings of the verifier; the defaults are what we can justify from the noise model.

    Attributes:
        method: ``"triangles"`` (the paper), ``"pnp"`` or ``"fundamental"`` (DLoopDetector).
        matcher: how the correspondences are found before any geometry: ``"ratio"`` (DBoW2 /
            ORB-SLAM: Lowe's ratio test, through the vocabulary's direct index when both
            frames have one, else over all features) or ``"mnn"`` (mutual nearest neighbours over
            all features, brute force, with the same ``ratio`` and ``max_distance`` gates: the
            usual matcher of learned descriptors, which a day/night change moves too far for
            the direct index's shared vocabulary nodes) or ``"lighterglue"`` (XFeat's learned
            matcher, a small LightGlue run by onnxruntime, :mod:`stablecues.verification.lighterglue`:
            XFeat features only; ``ratio`` and ``max_distance`` do not apply, ``match_confidence``
            does; about 200 ms a pair of 1000 features on one core, 40x the ``"mnn"`` matching).
        match_confidence: the confidence a LighterGlue match needs (LightGlue's
            ``filter_threshold``, 0.1).
        rescue_inliers: with the ``"ratio"`` or ``"mnn"`` matcher, a pair they reject that still
            reached this many geometric inliers is verified again with LighterGlue matches, whose
            decision stands (the result names ``"lighterglue"``); 0: never. XFeat features only.
        ratio: Lowe's ratio for matching. 0.8 is Lowe's value; ORB-SLAM uses 0.75 for loop
            search. Matches are further filtered by the geometry, so we keep more.
        max_distance: largest Hamming distance of a match (of 256 bits). ORB-SLAM's TH_LOW is
            50 for frame-to-frame search; a loop sees the place from another viewpoint, and
            the geometric check is the filter, so 64 (a quarter of the bits).
        cross_check: require mutual best matches.
        n_triangles: T, the number of triangles checked.
        tolerance: ``"noise"`` (default: each side's allowed difference is ``k_sigma`` times its
            propagated standard deviation) or ``"relative"`` (the paper's fixed fraction).
        k_sigma: the noise gate; 3 sigma lets a correct side fail with probability 0.27 %.
        relative_tolerance: the paper's 2 %.
        min_angle_deg: triangles with a smaller angle are skipped as near-collinear.
        min_side_sigma: sides shorter than this many of their own sigmas are too small.
        acceptance: ``"all"`` of T, a strict ``"majority"`` of T, or ``"at_least"`` min_agree
            (triangles that could not be formed count as disagreeing).
        min_agree: for ``"at_least"``. Default 2 of 10: a triangle only agrees when all three
            of its matches are correct, so with a realistic 60-80 % inlier ratio among ranked
            matches only 20-50 % of true triangles agree (0.6^3 to 0.8^3), which rules out "all"
            and "majority"; two congruent triangles from wrong matches, under a 3-sigma gate,
            are improbable, and PnP (``min_pnp_inliers``) must confirm the loop as well.
        min_pnp_inliers: PnP inliers an accepted loop needs (about 20, docs/method.md section 6;
            a pose from fewer is not reliable enough for a pose graph). Also the acceptance
            threshold of the PnP-only verifier.
        pnp_reprojection_px: PnP RANSAC threshold (see :class:`~stablecues.geometry.PnPConfig`).
        pnp_iterations: PnP RANSAC iterations.
        fundamental_threshold_px: DLoopDetector's ``max_reprojection_error`` (2 px).
        fundamental_confidence: RANSAC confidence of the fundamental matrix (0.99).
        fundamental_iterations: DLoopDetector's ``max_ransac_iterations`` (500).
        fundamental_method: ``"usac"`` (OpenCV's USAC: local optimisation, early rejection of
            hopeless models; 0.7-1.1 ms instead of 5-7 ms on 20-120 matches) or ``"ransac"``
            (OpenCV's classic RANSAC, as DLoopDetector).
        min_fundamental_inliers: fundamental-matrix inliers a loop needs (DLoopDetector's
            ``min_Fpoints`` is 12, which accepts a KITTI pair 148 m apart with 12 of 69 matches).
        min_fundamental_ratio: the fraction of the ratio-tested matches that must be inliers
            (0: no ratio test, as DLoopDetector). Wrong candidates share a few dozen chance
            matches of which RANSAC always fits 10-14; a true revisit keeps half or more.
        fallback: without 3D points, fall back to PnP (candidate has 3D) or the fundamental
            matrix (it has none) instead of rejecting with ``TOO_FEW_3D``.
        stable_ranking: when both frames carry per-feature stability weights (semantic
            weighting, ``DetectorConfig.weighting``), matches enter the triangles in order of
            descriptor confidence times the geometric mean of the two weights, not of descriptor
            distance alone: stable structure first, cars and road texture last. Without
            weights, or where the weighting faded to 1 (outside the network's domain), the
            order is the distance order. Off by default: on the development sets triangles form
            only on the EuRoC stereo pairs, where it changed which ones agree (10 -> 8 and
            6 -> 7 of 10, ``loops.json``) with no loop gained.
        static_px: matches whose keypoints lie within this many pixels of each other in the two
            images are left out before any geometry: what has not moved in the image between
            two visits of a place is fixed to the camera (a timestamp or logo overlay, the
            vehicle's own bonnet, dirt on the lens, objects pasted at their own pixels), not
            evidence of the place, and it fits every geometric model (a timestamp burnt into two
            CamVid frames of different drives made 241 of 252 matches fit one fundamental matrix).
            0.5 px: ORB puts the same image content at the same coordinates, and a true match
            between two visits moves more (bench_loops.py: no loop of the development sets lost,
            the swapped-objects sets without the network 0.0 -> 0.78; 1.5 px lost one). None:
            keep all (the ``paper`` and ``dloop`` presets, as published). When the static
            matches are more than half the frame's features the frame is the candidate seen
            again from the same pose (or the same image twice), and they are kept.
    """

    method: str = "triangles"
    matcher: str = "ratio"
    match_confidence: float = 0.1
    rescue_inliers: int = 0
    ratio: float = 0.8
    max_distance: int = 64
    cross_check: bool = False
    n_triangles: int = 10
    tolerance: str = "noise"
    k_sigma: float = 3.0
    relative_tolerance: float = 0.02
    min_angle_deg: float = 10.0
    min_side_sigma: float = 3.0
    acceptance: str = "at_least"
    min_agree: int = 2
    min_pnp_inliers: int = 20
    pnp_reprojection_px: float = 4.0
    pnp_iterations: int = 300
    fundamental_threshold_px: float = 2.0
    fundamental_confidence: float = 0.99
    fundamental_iterations: int = 500
    fundamental_method: str = "usac"
    min_fundamental_inliers: int = 20
    min_fundamental_ratio: float = 0.35
    fallback: bool = True
    stable_ranking: bool = False
    static_px: float | None = 0.5

    def __post_init__(self) -> None:
        if self.static_px is not None and not self.static_px >= 0.0:
            raise ConfigError(f"static_px must be >= 0 or None, got {self.static_px}")
        if self.method not in _METHODS:
            raise ConfigError(f"verification method {self.method!r}: expected one of {', '.join(_METHODS)}")
        if self.matcher not in _MATCHERS:
            raise ConfigError(f"matcher {self.matcher!r}: expected one of {', '.join(_MATCHERS)}")
        if self.rescue_inliers < 0:
            raise ConfigError(f"rescue_inliers must be >= 0, got {self.rescue_inliers}")
        if not 0.0 <= self.match_confidence < 1.0:
            raise ConfigError(f"match_confidence must be in [0, 1), got {self.match_confidence}")
        if self.acceptance not in _ACCEPTANCE:
            raise ConfigError(f"acceptance {self.acceptance!r}: expected one of {', '.join(_ACCEPTANCE)}")
        if self.acceptance == "at_least" and not 1 <= self.min_agree <= self.n_triangles:
            raise ConfigError(
                f"min_agree must be in 1..n_triangles ({self.n_triangles}), got {self.min_agree}"
            )
        if self.min_pnp_inliers < 0 or self.min_fundamental_inliers < 8:
            raise ConfigError("min_pnp_inliers must be >= 0 and min_fundamental_inliers >= 8")
        if self.fundamental_method not in ("usac", "ransac"):
            raise ConfigError(f"fundamental_method {self.fundamental_method!r}: expected 'usac' or 'ransac'")
        if not 0.0 <= self.min_fundamental_ratio <= 1.0:
            raise ConfigError(f"min_fundamental_ratio must be in [0, 1], got {self.min_fundamental_ratio}")
        self.triangle_config()  # validates the triangle settings
        self.pnp_config()

    def triangle_config(self) -> TriangleConfig:
        return TriangleConfig(
            n_triangles=self.n_triangles,
            tolerance=self.tolerance,
            k_sigma=self.k_sigma,
            relative_tolerance=self.relative_tolerance,
            min_angle_deg=self.min_angle_deg,
            min_side_sigma=self.min_side_sigma,
        )

    def pnp_config(self) -> PnPConfig:
        return PnPConfig(reprojection_px=self.pnp_reprojection_px, iterations=self.pnp_iterations)

    @property
    def triangles_needed(self) -> int:
        """How many agreeing triangles the acceptance rule needs."""
        if self.acceptance == "all":
            return self.n_triangles
        if self.acceptance == "majority":
            return self.n_triangles // 2 + 1
        return self.min_agree


#: Named configurations. ``paper``: the paper's triangle check as written: 2 % relative
#: tolerance, every triangle must agree, no PnP gate; the paper leaves T to the user ("every
#: three best-scored features" make a triangle), we read it as T = 3. ``dloop``:
#: DLoopDetector's fundamental-matrix check with its 0.6 ratio and 12 inliers. ``pnp``: PnP
#: inliers only.
PRESETS: dict[str, dict[str, object]] = {
    "default": {},
    "paper": {"tolerance": "relative", "acceptance": "all", "min_pnp_inliers": 0, "n_triangles": 3,
              "static_px": None},
    "dloop": {"method": "fundamental", "ratio": 0.6, "min_fundamental_inliers": 12,
              "min_fundamental_ratio": 0.0, "fundamental_method": "ransac", "static_px": None},
    "pnp": {"method": "pnp"},
    # learned float descriptors (XFeat): mutual nearest neighbours over all features with a loose
    # ratio (0.9) and distance (100 of 256: cosine >= 0.69); Gardens Point day/night pairs of one
    # place keep 15-170 fundamental inliers, pairs of places 50 apart <= 12 (bench_learned.py)
    "learned": {"matcher": "mnn", "ratio": 0.9, "max_distance": 100},
}


def preset(name: str, **overrides: object) -> VerificationConfig:
    """A named configuration with optional overrides (unknown keys raise ConfigError)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown verification preset {name!r}; known: {', '.join(PRESETS)}")
    return merge(merge(VerificationConfig(), PRESETS[name]), overrides)

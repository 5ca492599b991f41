"""Settings of the loop detector and its named presets."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

from ..config import merge, select_by
from ..errors import ConfigError
from ..features import ExtractorConfig, OrbConfig, extractor_config_class
from ..geometry.twoview import TwoViewConfig
from ..semantics.masking import MASKING_PRESETS, MaskingConfig
from ..semantics.weighting import WeightingConfig
from ..verification.config import VerificationConfig
from ..verification.config import preset as verification_preset
from .presets import _PRESETS, preset_names


@dataclass(frozen=True)
class QueryConfig:
    """DLoopDetector's query logic.

    Attributes:
        exclude_recent: the latest entries never proposed as loops (DLoopDetector's dislocal).
        exclude_recent_s: also exclude entries newer than this many seconds (when frames have
            timestamps); None: frames only.
        run_break: shorten the excluded window to the current *run* of frames: a frame whose
            BoW score with the previous frame falls below this fraction of the median of the
            previous ``run_history`` such scores starts a new run (the camera jumped: a cut
            between recordings, a new traversal, a relocalisation), and entries before the run
            are proposed again once ``exclude_recent_min`` newer entries exist. None: the fixed
            window of ``exclude_recent`` entries only.
        run_history: adjacent scores the median of ``run_break`` is taken over.
        run_break_score: a cut also needs the score with the previous frame under this (the
            level of unrelated frames), so that a camera starting to move after standing still,
            whose adjacent score drops from near 1 to a moving camera's, starts no run. None:
            the relative drop alone.
        exclude_recent_min: a run never shrinks the window below this many entries (nor
            widens it beyond ``exclude_recent``).
        max_results: database results considered per query.
        use_nss: normalise scores by the score between the frame and the previous one.
        alpha: minimum (normalised) score of a candidate.
        min_nss_factor: a previous-frame score below this cannot normalise (frame skipped).
        island_gap: largest gap in entry ids inside one island of candidates.
        temporal_k: consecutive temporally consistent queries, counting the current one, before a
            candidate is verified (1: no temporal check).
        temporal_gap: largest gap between the islands of consecutive frames to be consistent.
        max_query_gap: largest gap in frames between consecutive consistent queries.
        islands_verified: how many islands, best first, are verified (DLoopDetector: 1, the
            best island's best entry); of those accepted, the one with the most geometric
            inliers is the loop.
        refine: the entries up to this many ids either side of the accepted island's best entry
            (inside the island) are verified too, and the one with the most inliers is the loop
            (0: the island's best entry, as DLoopDetector).
        viewpoint_steps: at most this many steps from the accepted entry to a neighbour (id - 1
            or id + 1, accepted too) seen from a nearer viewpoint, judged by the image scale of
            the inlier matches (:attr:`~stablecues.verification.result.Verification.scale_change`);
            0: no walk. The loop's confidence keeps the larger inlier count of the entry it
            started from and the one it ends on; it reports the nearest one, whose relative
            pose is the smallest.
        viewpoint_scale: the walk starts only when the scale change is larger than this (log).
        viewpoint_margin: a step must lower the scale change by at least this much (the
            estimate's noise: a median over a few dozen inlier pairs).
        viewpoint_inliers: a step needs at least this fraction of the accepted entry's inliers.
        sequence: SeqSLAM's sequence stage (:mod:`stablecues.detection.sequence`): the last
            ``sequence`` queries' results (this one included) are kept, and a candidate's
            sequence score is the mean normalised score along the best line through them
            (:attr:`LoopDecision.sequence_score`). With ``DetectorConfig.confidence =
            "sequence"`` the loop's confidence is its inliers times that score. 0 or 1: no
            sequence stage. The history restarts with each run of frames (``run_break``) and,
            after a map is reopened, is re-queried from the stored entries.
        sequence_rank: also rank the candidates by their sequence score instead of this
            frame's score alone (islands, verification and the temporal window then run on
            that ranking), SeqSLAM's own use of it. Off in every preset: measured before the
            scores were capped, alone it moved the night pairings less than the sequence
            confidence does (docs/learned.md), and with the capped scores it is not measured.
        sequence_choice: among the verified islands, the loop is the one whose inliers times
            sequence score is highest (the confidence ``"sequence"`` ranks loops by), not the one
            with the most inliers: by night a wrong place fits a fundamental matrix to 30-50
            chance matches as often as the right one does, and the frames before seldom draw
            a line through it. Needs ``sequence`` >= 2.
        sequence_tolerance: each step of the line may land this many entries either side.
        other_sessions_first: when frames carry sessions (:attr:`~stablecues.types.Frame.session`),
            the islands of another session than the query's are verified first, and one of them
            accepted is the loop: the islands of the session under way are then not verified.
            A view from the walk under way shares its light and its side of the path with the
            query and fits more matches than the place itself seen in another pass, so a
            repeated part of the same walk (a second locker bank down a corridor) outscores the
            true place; across sessions the comparison is even (docs/learned.md). No effect on
            a single stream (every frame session 0).
        vlad: weight of the second retrieval vote, VLAD (:mod:`stablecues.vocabulary.vlad`):
            each entry keeps the VLAD vector of its float descriptors, and a candidate's score is
            ``(1 - vlad) * BoW score + vlad * VLAD score``, both normalised by the previous
            frame (the VLAD score as ``(s - m) / (s_prev - m)``, ``m`` the median similarity to
            the map, the level of unrelated places); the candidates are the BoW results and the
            ``max_results`` most VLAD-similar entries. 0: BoW alone (every preset; the ablation
            is in docs/learned.md); 1: VLAD alone. Float (learned) descriptors only.
        vlad_codebook: the VLAD codebook: ``"default"`` (the one shipped for the extractor) or
            the path of a ``.npy`` of (K, D) centres (``scripts/make_vlad_codebook.py``).
    """

    exclude_recent: int = 20
    exclude_recent_s: float | None = None
    run_break: float | None = None
    run_history: int = 5
    run_break_score: float | None = None
    exclude_recent_min: int = 0
    max_results: int = 50
    use_nss: bool = True
    alpha: float = 0.3
    min_nss_factor: float = 0.005
    island_gap: int = 3
    temporal_k: int = 3
    temporal_gap: int = 3
    max_query_gap: int = 2
    islands_verified: int = 1
    refine: int = 0
    viewpoint_steps: int = 0
    viewpoint_scale: float = 0.15
    viewpoint_margin: float = 0.05
    viewpoint_inliers: float = 0.75
    sequence: int = 0
    sequence_rank: bool = False
    sequence_choice: bool = False
    sequence_tolerance: int = 1
    other_sessions_first: bool = True
    vlad: float = 0.0
    vlad_codebook: str = "default"

    def __post_init__(self) -> None:
        if not 0.0 <= self.vlad <= 1.0:
            raise ConfigError(f"query.vlad (the VLAD vote's weight) must be in [0, 1], got {self.vlad}")
        if self.sequence_choice and self.sequence < 2:
            raise ConfigError(f"query.sequence_choice ranks islands by their sequence score: it needs "
                              f"query.sequence >= 2, got {self.sequence}")
        if self.sequence < 0 or self.sequence_tolerance < 0:
            raise ConfigError(f"sequence >= 0 and sequence_tolerance >= 0 are required, got "
                              f"{self.sequence} and {self.sequence_tolerance}")
        if self.exclude_recent < 0 or self.max_results < 1 or self.temporal_k < 1:
            raise ConfigError("exclude_recent >= 0, max_results >= 1 and temporal_k >= 1 are required")
        if self.islands_verified < 1:
            raise ConfigError(f"islands_verified must be >= 1, got {self.islands_verified}")
        if self.run_break is not None and not 0.0 < self.run_break < 1.0:
            raise ConfigError(f"run_break must be in (0, 1) or None, got {self.run_break}")
        if self.run_break_score is not None and not 0.0 < self.run_break_score <= 1.0:
            raise ConfigError(f"run_break_score must be in (0, 1] or None, got {self.run_break_score}")
        if self.run_history < 1 or self.exclude_recent_min < 0:
            raise ConfigError("run_history >= 1 and exclude_recent_min >= 0 are required")
        if self.viewpoint_steps < 0 or not (self.viewpoint_scale >= 0 and self.viewpoint_margin >= 0
                                            and 0 <= self.viewpoint_inliers <= 1):
            raise ConfigError("viewpoint_steps >= 0, viewpoint_scale >= 0, viewpoint_margin >= 0 and "
                              "viewpoint_inliers in [0, 1] are required")


@dataclass(frozen=True)
class MonocularConfig:
    """3D for frames without stereo, depth or map points: triangulated against a neighbour.

    Attributes:
        neighbours: how many of the latest frames of the stream are tried, newest first; the
            first with enough parallax and essential-matrix inliers gives the points. An older
            one is tried only when the newer ones lacked baseline (parallax, or points
            triangulated well), not when they had too few matches or no one motion held them.
        ratio: Lowe's ratio of the matches with the neighbour (frame-to-frame: strict).
        min_inliers: essential-matrix inliers a neighbour needs.
        min_median_angle_deg: median triangulation angle a neighbour needs (parallax).
        threshold_px: essential-matrix RANSAC threshold, pixels.
    """

    neighbours: int = 3
    ratio: float = 0.75
    min_inliers: int = 30
    min_median_angle_deg: float = 1.0
    threshold_px: float = 1.0

    def __post_init__(self) -> None:
        if self.neighbours < 1 or not 0 < self.ratio <= 1:
            raise ConfigError(f"monocular: neighbours >= 1 and ratio in (0, 1] are required, got {self}")
        try:  # the two-view settings these give, checked now rather than at the first frame
            TwoViewConfig(threshold_px=self.threshold_px, min_inliers=self.min_inliers,
                          min_median_angle_deg=self.min_median_angle_deg)
        except ConfigError as exc:
            raise ConfigError(f"monocular: {str(exc).removeprefix('two-view settings: ')}") from None


@dataclass(frozen=True)
class DetectorConfig:
    """Everything the loop detector does, as one frozen value.

    Attributes:
        features: the feature extractor's settings; ``name`` picks the extractor ("orb", the
            default, "sift", or any registered with
            :func:`~stablecues.features.register_extractor`), e.g. the override
            ``{"features": {"name": "sift", "n_features": 500}}``.
        masking: semantic feature selection, or None for none.
        semantic_source: "network" (the shipped segmentation network) or "labels" (the frame's
            own label image, e.g. ground truth of a synthetic sequence).
        segmentation_samples: Monte-Carlo samples T (None: the weights' default).
        segmentation_precision: which of the shipped network's weights run: "float32" (as
            trained) or "int8" (its static int8 quantisation, ``scripts/quantize_segnet.py``:
            about half the time a pass, 99.6 % of the pixels given the same class on CamVid
            ``val``).
        verification: geometric verification, or None to accept every temporally consistent
            candidate (DBoW2 without geometry).
        query: database query, islands and temporal consistency.
        similarity: keep each frame's scores against all earlier entries (for the report's
            similarity matrix).
        weighting: semantic weighting of features in the BoW vector by the stability of their
            class and the network's certainty (:mod:`stablecues.semantics.weighting`), or None.
        monocular: triangulate frames that have no other 3D against a neighbouring frame of
            the stream (the triangle check then compares shapes), or None for no such 3D.
        confidence: what ranks accepted loops (the score precision-recall curves sweep):
            "inliers", the geometric inliers of the verified loop (plus the normalised BoW
            score, below 1, to break ties), "sequence", those inliers times the loop entry's
            sequence score (``query.sequence`` >= 2: a loop whose preceding frames also scored
            its preceding entries ranks above a lone frame that fits one wrong place), or
            "bow", the normalised BoW score alone (as DLoopDetector). Without verification it
            is always the BoW score.
        min_confidence: a verified loop whose confidence is under this is refused (status
            ``low_confidence``): the operating point of a ranking whose verification gates are
            loose on purpose (``learned``). 0: every verified loop stands.
        domain_window: how many recent frames of the stream (this one included) decide whether
            the stream is in the segmentation network's domain: the median of their frame
            certainties gates the weighting (``weighting.domain``) and the mask
            (``masking.min_frame_certainty``), so one unsure frame of a street drive stays in
            and one sure frame of a corridor stays out. 1: every frame alone.
        vocabulary: where the words come from: "trained" (the shipped vocabulary of the
            extractor, or the one given to the detector) or "incremental" (words learned from
            the map's own descriptors as frames are added, no training set:
            :mod:`stablecues.vocabulary.incremental`; saved beside a map file as ``MAP.words``).
        incremental_threshold: the incremental vocabulary's merge distance (Hamming bits for
            binary descriptors, Euclidean distance for float ones); None: its default for the
            descriptors' kind.
    """

    features: ExtractorConfig = field(
        default_factory=OrbConfig, metadata=select_by("name", extractor_config_class)
    )
    masking: MaskingConfig | None = None
    semantic_source: Literal["network", "labels"] = "network"
    segmentation_samples: int | None = None
    segmentation_precision: Literal["float32", "int8"] = "float32"
    verification: VerificationConfig | None = field(default_factory=VerificationConfig)
    query: QueryConfig = field(default_factory=QueryConfig)
    similarity: bool = True
    weighting: WeightingConfig | None = None
    monocular: MonocularConfig | None = None
    confidence: Literal["inliers", "sequence", "bow"] = "inliers"
    min_confidence: float = 0.0
    domain_window: int = 30
    vocabulary: Literal["trained", "incremental"] = "trained"
    incremental_threshold: float | None = None

    def __post_init__(self) -> None:
        if self.vocabulary not in ("trained", "incremental"):
            raise ConfigError(f"vocabulary: expected 'trained' or 'incremental', got {self.vocabulary!r}")
        t = self.incremental_threshold
        if t is not None and not (isinstance(t, int | float) and math.isfinite(t) and t >= 0):
            raise ConfigError(f"incremental_threshold: expected a finite number >= 0 or None, got {t!r}")
        if self.domain_window < 1:
            raise ConfigError(f"domain_window: expected >= 1 frames, got {self.domain_window}")
        if self.confidence not in ("inliers", "sequence", "bow"):
            raise ConfigError(f"confidence: expected 'inliers', 'sequence' or 'bow', got {self.confidence!r}")
        if not self.min_confidence >= 0.0:
            raise ConfigError(f"min_confidence: expected >= 0, got {self.min_confidence}")
        if self.confidence == "sequence" and self.query.sequence < 2:
            raise ConfigError(f"confidence 'sequence' needs query.sequence >= 2 (frames), got "
                              f"{self.query.sequence}")
        if self.segmentation_precision not in ("float32", "int8"):
            raise ConfigError(f"segmentation_precision: expected 'float32' or 'int8', got "
                              f"{self.segmentation_precision!r}")
        v = self.verification
        glue = v is not None and (v.matcher == "lighterglue" or v.rescue_inliers > 0)
        if glue and self.features.name != "xfeat":
            raise ConfigError(f"verification.matcher 'lighterglue' (or rescue_inliers) matches XFeat "
                              f"features, not {self.features.name!r}: set features.name to 'xfeat' or "
                              "another matcher")
        if self.semantic_source not in ("network", "labels"):
            raise ConfigError(
                f"semantic_source: expected 'network' or 'labels', got {self.semantic_source!r}"
            )


def _verif(name: str | None) -> VerificationConfig | None:
    return None if name is None else verification_preset(name)


def _mask(name: str | None) -> MaskingConfig | None:
    return None if name is None else MASKING_PRESETS[name]


def preset(name: str = "default", overrides: dict[str, Any] | None = None) -> DetectorConfig:
    """A named configuration, with optional overrides (unknown keys are rejected)."""
    if name not in _PRESETS:
        raise ConfigError(f"unknown preset {name!r}; known: {', '.join(preset_names())}")
    mask, verif, extra, _ = _PRESETS[name]
    cfg = merge(DetectorConfig(masking=_mask(mask), verification=_verif(verif)), extra)
    return merge(cfg, overrides)

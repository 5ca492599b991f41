"""The loop detector: a stream of frames in, loop decisions out.

Per frame, as DLoopDetector (Galvez-Lopez & Tardos 2012) with the paper's additions:

1. ORB features; optionally only those on meaningful structure (semantic masking);
2. the BoW vector and direct index from the vocabulary;
3. a database query excluding the most recent entries; scores normalised by the score
   between the frame and the previous one; candidates under ``alpha`` dropped;
4. candidates grouped into islands of nearby entries; the best island must be temporally
   consistent with the islands of the previous ``temporal_k`` frames;
5. geometric verification of the island's best entry (3D triangles, PnP or the fundamental
   matrix); the accepted loop comes with the relative pose;
6. the frame is stored (with its keypoints and 3D points) whatever the decision.

The state lives in the database file: reopening a detector on the same file continues where
it stopped (the temporal window is restored from the last entries' records).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..database import Database
from ..types import Frame
from ..errors import ConfigError, InputError
from ..features import OrbExtractor
from ..imageio import to_grey
from ..types import BowVector, Features, FeatureVector
from ..vocabulary import Scoring, Vocabulary, default_vocabulary, score
from .config import DetectorConfig
from .decision import Island, LoopDecision, Status

log = logging.getLogger(__name__)


def compute_islands(ids: np.ndarray, scores: np.ndarray, gap: int) -> list[Island]:
    """Group candidate entries whose ids are at most ``gap`` apart (DLoopDetector's islands).

    Args:
        ids: (K,) entry ids.
        scores: (K,) their scores.
        gap: largest id difference inside an island.

    Returns:
        islands, each with its best entry and the sum of its scores.
    """
    if ids.size == 0:
        return []
    order = np.argsort(ids, kind="stable")
    ids, scores = ids[order], scores[order]
    cuts = np.flatnonzero(np.diff(ids) > gap) + 1
    islands = []
    for part_ids, part_scores in zip(np.split(ids, cuts), np.split(scores, cuts), strict=True):
        b = int(np.argmax(part_scores))
        islands.append(Island(int(part_ids[0]), int(part_ids[-1]), int(part_ids[b]),
                              float(part_scores[b]), float(part_scores.sum())))
    return islands


class LoopDetector:
    """Streaming loop-closure detection.

    Args:
        config: settings (see :mod:`stablecues.detection.config` for presets).
        vocabulary: the vocabulary; default: the shipped one.
        database: SQLite file to keep the map in (reopened and continued when it exists), or
            None to keep everything in memory.
        calibration: camera calibration used when a frame carries none.
        segmenter: a callable ``image -> SegmentationResult`` replacing the shipped network.
    """

    def __init__(
        self,
        config: DetectorConfig | None = None,
        vocabulary: Vocabulary | None = None,
        database: str | Path | None = None,
        calibration: Any | None = None,
        segmenter: Callable[[np.ndarray], Any] | None = None,
    ) -> None:
        self.config = config or DetectorConfig()
        self.vocabulary = vocabulary or default_vocabulary()
        if self.vocabulary.scoring in (Scoring.KL, Scoring.DOT_PRODUCT):
            raise ConfigError("the loop detector needs a similarity scoring in [0, 1] (L1, L2, "
                              "chi-square or Bhattacharyya), not KL or dot product")
        self.db = Database(self.vocabulary, database)
        self.extractor = OrbExtractor(self.config.features)
        self.calibration = calibration
        self._segmenter = segmenter
        self._lifters: dict[int, Any] = {}
        self._verifiers: dict[int, Any] = {}
        self.last_similarity: np.ndarray | None = None
        self._restore_state()

    # ------------------------------------------------------------------ state
    def _restore_state(self) -> None:
        n = len(self.db)
        self._timestamps: list[float] = self.db.column("timestamp") if n else []
        metas = self.db.column("meta") if n else []
        self._entry_frames: list[int] = [int(m.get("frame", i)) for i, m in enumerate(metas)]
        self._prev_bow: BowVector | None = self.db.entry(n - 1).bow if n else None
        self._window_n = 0
        self._window_island: tuple[int, int] | None = None
        self._window_query = -(10**9)
        if metas:
            last = metas[-1]
            isl = last.get("window_island")
            if isl is not None:
                self._window_island = (int(isl[0]), int(isl[1]))
                self._window_n = int(last.get("window_n", 0))
                self._window_query = int(last.get("window_query", n - 1))

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> LoopDetector:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return len(self.db)

    # ------------------------------------------------------------------ helpers
    def _segment(self, frame: Frame) -> Any:
        from ..semantics.inference import SegmentationModel, SegmentationResult

        if self.config.semantic_source == "labels":
            if frame.labels is None:
                raise InputError(f"frame {frame.index} ({frame.name}): semantic_source='labels' but "
                                 "the frame has no label image")
            lab = np.asarray(frame.labels, np.uint8)
            h, w = lab.shape
            return SegmentationResult(lab, np.ones((h, w), np.float32), np.zeros((h, w), np.float32),
                                      0, np.zeros((11, 1, 1), np.float32))
        if self._segmenter is None:
            model = SegmentationModel.load()
            t = self.config.segmentation_samples
            self._segmenter = lambda image: model.predict(image, t)
        return self._segmenter(frame.image)

    def _calib(self, frame: Frame) -> Any | None:
        return frame.calibration if frame.calibration is not None else self.calibration

    def _noise(self, calib: Any | None) -> Any:
        """The noise model of the 3D points of frames with this calibration: the stereo lifter's
        own (rectified focal, its disparity noise) for stereo rigs, the calibration's for depth
        cameras, and a generic one for map points without a stereo or depth calibration, so that
        query and stored points always get the same model."""
        from ..geometry import NoiseModel, StereoLifter

        if calib is not None and calib.is_stereo:
            lifter = self._lifters.get(id(calib))
            if lifter is None:
                lifter = self._lifters[id(calib)] = StereoLifter(calib)
            return lifter.noise
        if calib is not None:
            try:
                return NoiseModel.for_calibration(calib)
            except ConfigError:
                pass
        # map points from a SLAM system, nothing known of their sensor: 1 % depth noise at 1 m
        focal = calib.left.fx if calib is not None else 500.0
        return NoiseModel(0.01, focal)

    def _lift(self, frame: Frame, features: Features, calib: Any | None) -> Any | None:
        """3D points of the features in the frame's camera (Points3D), or None."""
        from ..geometry import lift_depth, lift_map_points

        where = f"frame {frame.index} ({frame.name})"
        try:
            if frame.points3d is not None:
                pts = np.asarray(frame.points3d)
                if pts.shape != (len(features), 3):
                    raise InputError(f"points3d has shape {pts.shape}, expected ({len(features)}, 3), "
                                     "one per feature")
                return lift_map_points(pts, self._noise(calib), octaves=features.octaves)
            if calib is None:
                return None
            if frame.right is not None and calib.is_stereo:
                self._noise(calib)  # builds the lifter
                return self._lifters[id(calib)].lift(features, frame.image, frame.right)
            if frame.depth is not None:
                raw = np.issubdtype(np.asarray(frame.depth).dtype, np.integer)  # a 16-bit PNG as read
                return lift_depth(features, frame.depth, calib.left,
                                  depth_scale=calib.depth_scale if raw else None)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
        return None

    def _verifier(self, calib: Any | None) -> Any:
        from ..config import merge
        from ..verification.verifier import Verifier

        key = id(calib)
        v = self._verifiers.get(key)
        if v is None:
            cfg = self.config.verification
            if cfg is None:
                raise ConfigError("verification is off in this configuration")
            if calib is None:
                if cfg.method == "pnp":
                    raise ConfigError("PnP verification needs a calibration (the query camera)")
                v = Verifier(merge(cfg, {"min_pnp_inliers": 0}), noise=self._noise(None))
            else:
                v = Verifier(cfg, calib.left, self._noise(calib))
            self._verifiers[key] = v
        return v

    def _exclusion_limit(self, timestamp: float) -> int:
        """Entries with id below this may be proposed (the recent window excluded)."""
        q = self.config.query
        n = len(self.db)
        hi = n - q.exclude_recent
        if q.exclude_recent_s is not None and math.isfinite(timestamp) and self._timestamps:
            ts = np.asarray(self._timestamps)
            # eligible only when strictly older than the window, as the evaluator counts it
            newer = np.flatnonzero(np.nan_to_num(ts, nan=-np.inf) >= timestamp - q.exclude_recent_s)
            if newer.size:
                hi = min(hi, int(newer[0]))
        return max(hi, 0)

    def _update_window(self, island: Island, entry: int) -> int:
        """DLoopDetector's temporal window: consecutive consistent queries including this one."""
        q = self.config.query
        if self._window_island is None or entry - self._window_query > q.max_query_gap:
            self._window_n = 1
        else:
            a1, a2 = self._window_island
            b1, b2 = island.first, island.last
            fit = (b1 <= a1 <= b2) or (a1 <= b1 <= a2)
            if not fit:
                fit = max(a1 - b2, b1 - a2) <= q.temporal_gap
            self._window_n = self._window_n + 1 if fit else 1
        self._window_island = (island.first, island.last)
        self._window_query = entry
        return self._window_n

    # ------------------------------------------------------------------ the loop
    def process(self, frame: Frame, features: Features | None = None, *, store: bool = True) -> LoopDecision:
        """Detect a loop for one frame, then store the frame.

        Args:
            frame: the frame (image, timestamp, optional right / depth image, map points,
                calibration, pose).
            features: the frame's features when a SLAM system hands its own in (their order
                must match ``frame.points3d``); extracted here otherwise.
            store: add the frame to the database afterwards (False: a pure query, as for the
                query pass of a place-recognition benchmark).

        Returns:
            the decision, with the stage that decided and the time of every stage.
        """
        prep = self._prepare(frame, features)
        timings, t = prep.timings, time.perf_counter()
        entry = len(self.db)
        found: dict[str, Any] = {}
        status = self._query(prep.bow, frame, entry, found)
        timings["query"] = (time.perf_counter() - t) * 1e3
        verification = None
        if status is None:
            t = time.perf_counter()
            status, verification = self._verify(prep, found["candidate"])
            timings["verify"] = (time.perf_counter() - t) * 1e3
        if store:
            self._store(frame, prep)
        timings["total"] = (time.perf_counter() - prep.t_start) * 1e3
        cand = found.get("candidate", -1)
        confidence = found.get("score", 0.0)
        if verification is not None and self.config.confidence == "inliers":
            confidence = float(verification.n_inliers) + min(confidence, 0.999)
        return LoopDecision(
            frame_index=int(frame.index), entry_id=entry if store else -1, status=status,
            candidate=cand, candidate_frame=self._entry_frames[cand] if cand >= 0 else -1,
            raw_score=found.get("raw_score", 0.0), score=found.get("score", 0.0), confidence=confidence,
            nss_factor=found.get("nss_factor", math.nan), island=found.get("island"),
            consistent=found.get("consistent", 0), verification=verification,
            n_features=prep.n_features, n_kept=len(prep.features), mask_fallback=prep.mask_fallback,
            timings=timings,
        )

    def store(self, frame: Frame, features: Features | None = None) -> int:
        """Add a frame to the database without looking for a loop; returns its entry id."""
        prep = self._prepare(frame, features)
        entry = len(self.db)
        self._store(frame, prep)
        return entry

    def _prepare(self, frame: Frame, features: Features | None) -> _Prepared:
        """Features, semantic selection, BoW and direct index, 3D points of one frame."""
        cfg = self.config
        timings: dict[str, float] = {}
        t_start = t = time.perf_counter()

        def lap(name: str) -> None:
            nonlocal t
            now = time.perf_counter()
            timings[name] = (now - t) * 1e3
            t = now

        if features is None:
            if frame.points3d is not None:
                raise InputError(f"frame {frame.index}: map points need the SLAM system's own "
                                 "features (process(frame, features=...)) to pair with")
            features = self.extractor.extract(to_grey(frame.image, f"frame {frame.index} image"))
        lap("extract")
        n_features = len(features)
        mask_fallback = False
        keep = None
        if cfg.masking is not None and cfg.masking.mode != "none" and n_features:
            from ..semantics.masking import select_features

            seg = self._segment(frame)
            lap("segment")
            kept, report = select_features(features, seg, cfg.masking)
            mask_fallback = bool(report.fallback)
            if not mask_fallback:
                keep = np.flatnonzero(report.passed)
            features = kept
            lap("mask")
        bow, fvec = self.vocabulary.transform(features.descriptors)
        lap("transform")
        points = None
        if cfg.verification is not None:
            if frame.points3d is not None and keep is not None:
                frame = _with_points(frame, np.asarray(frame.points3d)[keep])
            points = self._lift(frame, features, self._calib(frame))
            lap("lift")
        return _Prepared(features, bow, fvec, points, n_features, mask_fallback, timings, t_start,
                         self._calib(frame))

    def _verify(self, prep: _Prepared, candidate: int) -> tuple[Status, Any]:
        if self.config.verification is None:
            return Status.LOOP_DETECTED, None
        from ..verification.verifier import View

        verifier = self._verifier(prep.calibration)
        result = verifier.verify_entry(View(prep.features, prep.fvec, prep.points), self.db.entry(candidate))
        return (Status.LOOP_DETECTED if result.accepted else Status.NO_GEOMETRICAL_CONSISTENCY), result

    def _store(self, frame: Frame, prep: _Prepared) -> None:
        t = time.perf_counter()
        meta: dict[str, Any] = {"frame": int(frame.index), "name": frame.name}
        if self._window_island is not None:
            meta.update(window_island=list(self._window_island), window_n=self._window_n,
                        window_query=self._window_query)
        xyz = None if prep.points is None else prep.points.xyz
        self.db.add(prep.bow, prep.fvec, prep.features, points3d=xyz, timestamp=float(frame.timestamp),
                    pose=frame.pose, meta=meta)
        self._timestamps.append(float(frame.timestamp))
        self._entry_frames.append(int(frame.index))
        # the database keeps float32 weights: use the same rounding now as after a reopen, so a
        # resumed run normalises scores exactly as an uninterrupted one
        self._prev_bow = BowVector(prep.bow.words, prep.bow.weights.astype(np.float32).astype(np.float64))
        prep.timings["add"] = (time.perf_counter() - t) * 1e3

    def _query(self, bow: BowVector, frame: Frame, entry: int, out: dict[str, Any]) -> Status | None:
        """Steps 3-4; returns the rejecting status, or None when a candidate must be verified."""
        q = self.config.query
        hi = self._exclusion_limit(float(frame.timestamp))
        if self.config.similarity:
            self.last_similarity = self.db.scores(bow).astype(np.float32)
        if hi <= 0:
            return Status.CLOSE_MATCHES_ONLY
        results = self.db.query(bow, max_results=q.max_results, max_id=hi)
        if not results:
            return Status.NO_DB_RESULTS
        ids = np.array([r.entry_id for r in results])
        raw = np.array([r.score for r in results])
        ns = 1.0
        if q.use_nss:
            if self._prev_bow is None:
                return Status.LOW_NSS_FACTOR
            ns = score(bow, self._prev_bow, self.vocabulary.scoring)
            out["nss_factor"] = ns
            if ns < q.min_nss_factor:
                return Status.LOW_NSS_FACTOR
        norm = raw / ns
        ok = norm >= q.alpha
        best = int(np.argmax(norm))
        out.update(candidate=int(ids[best]), raw_score=float(raw[best]), score=float(norm[best]))
        if not ok.any():
            return Status.LOW_SCORES
        islands = compute_islands(ids[ok], norm[ok], q.island_gap)
        island = max(islands, key=lambda i: i.score)
        consistent = self._update_window(island, entry)
        out.update(candidate=island.best, raw_score=float(raw[ids == island.best][0]),
                   score=island.best_score, island=island, consistent=consistent)
        if consistent < q.temporal_k:
            return Status.NO_TEMPORAL_CONSISTENCY
        return None


@dataclass
class _Prepared:
    """One frame, ready to query and store."""

    features: Features
    bow: BowVector
    fvec: FeatureVector
    points: Any | None
    n_features: int
    mask_fallback: bool
    timings: dict[str, float]
    t_start: float
    calibration: Any | None


def _with_points(frame: Frame, points: np.ndarray) -> Frame:
    import dataclasses

    return dataclasses.replace(frame, points3d=points)

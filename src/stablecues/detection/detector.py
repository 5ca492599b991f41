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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..database import Database
from ..errors import ConfigError
from ..geometry.camera import Calibration
from ..geometry.points import relative_points_meta
from ..types import BowVector, Features, Frame
from ..verification.result import Verification
from ..verification.verifier import Verifier
from ..vocabulary import Scoring, Vocabulary, default_vocabulary, score
from .config import DetectorConfig
from .decision import Checked, Island, LoopDecision, Status
from .prepare import FramePreparer, PreparedFrame, Segmenter

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


@dataclass
class _Query:
    """What the query stage found for one frame (steps 3-4).

    ``status`` is the rejecting stage, or None when the islands must be verified.
    """

    status: Status | None = None
    candidate: int = -1
    raw_score: float = 0.0
    score: float = 0.0
    nss_factor: float = math.nan
    island: Island | None = None
    consistent: int = 0
    results: list[tuple[int, float]] = field(default_factory=list)
    islands: list[Island] = field(default_factory=list)
    raw_of: dict[int, float] = field(default_factory=dict)


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
        calibration: Calibration | None = None,
        segmenter: Segmenter | None = None,
    ) -> None:
        self.config = config or DetectorConfig()
        self.vocabulary = vocabulary or default_vocabulary()
        if self.vocabulary.scoring in (Scoring.KL, Scoring.DOT_PRODUCT):
            raise ConfigError("the loop detector needs a similarity scoring in [0, 1] (L1, L2, "
                              "chi-square or Bhattacharyya), not KL or dot product")
        self.db = Database(self.vocabulary, database)
        self.preparer = FramePreparer(self.config, self.vocabulary, calibration, segmenter)
        self.last_similarity: np.ndarray | None = None
        self._restore_state()

    @property
    def calibration(self) -> Calibration | None:
        """The calibration used for frames that carry none."""
        return self.preparer.calibration

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
        if self.config.monocular is not None:  # the latest entries are the next frame's neighbours
            for k in range(max(0, n - self.config.monocular.neighbours), n):
                e = self.db.entry(k)
                self.preparer.remember(e.features, e.fvec)
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
        prep = self.preparer.prepare(frame, features)
        timings, t = prep.timings, time.perf_counter()
        entry = len(self.db)
        found = self._query(prep.bow, frame, entry)
        timings["query"] = (time.perf_counter() - t) * 1e3
        status = found.status
        verification: Verification | None = None
        checked: tuple[Checked, ...] = ()
        if status is None:
            t = time.perf_counter()
            status, verification, checked = self._verify(prep, found)
            timings["verify"] = (time.perf_counter() - t) * 1e3
        if store:
            self._store(frame, prep)
        timings["total"] = (time.perf_counter() - prep.t_start) * 1e3
        cand = found.candidate
        confidence = found.score
        if verification is not None and self.config.confidence == "inliers":
            confidence = float(verification.n_inliers) + min(confidence, 0.999)
        frames = self._entry_frames
        return LoopDecision(
            frame_index=int(frame.index), entry_id=entry if store else -1, status=status,
            candidate=cand, candidate_frame=frames[cand] if cand >= 0 else -1,
            raw_score=found.raw_score, score=found.score, confidence=confidence,
            nss_factor=found.nss_factor, island=found.island, consistent=found.consistent,
            verification=verification,
            results=tuple((frames[e], sc) for e, sc in found.results),
            islands=tuple((frames[i.first], frames[i.last], frames[i.best], i.score) for i in found.islands),
            checked=checked, points_source=prep.points_source, n_features=prep.n_features,
            n_kept=len(prep.features),
            mask_fallback=prep.mask_fallback, timings=timings,
        )

    def store(self, frame: Frame, features: Features | None = None) -> int:
        """Add a frame to the database without looking for a loop; returns its entry id."""
        prep = self.preparer.prepare(frame, features)
        entry = len(self.db)
        self._store(frame, prep)
        return entry

    def _verify(
        self, prep: PreparedFrame, found: _Query
    ) -> tuple[Status, Verification | None, tuple[Checked, ...]]:
        """Step 5: verify the best ``islands_verified`` islands; the accepted one with the most
        geometric inliers is the loop (``found`` is updated to name it)."""
        if self.config.verification is None:
            return Status.LOOP_DETECTED, None, ()
        verifier = self.preparer.verifier(prep.calibration)
        checked = []
        for island in found.islands[: self.config.query.islands_verified]:
            result = verifier.verify_entry(prep.view, self.db.entry(island.best))
            checked.append(Checked(island, self._entry_frames[island.best], result))
        accepted = [c for c in checked if c.verification.accepted]
        if not accepted:
            return Status.NO_GEOMETRICAL_CONSISTENCY, checked[0].verification, tuple(checked)
        best = max(accepted, key=lambda c: (c.verification.n_inliers, c.island.best_score))
        entry, result = best.island.best, best.verification
        for e, r in self._refine(prep, verifier, best.island, checked):
            if r.accepted and r.n_inliers > result.n_inliers:
                entry, result = e, r
        if entry != found.candidate:
            norm = dict(found.results)
            found.candidate, found.island = entry, best.island
            found.score = norm.get(entry, best.island.best_score)
            found.raw_score = found.raw_of.get(entry, 0.0)
        return Status.LOOP_DETECTED, result, tuple(checked)

    def _refine(
        self, prep: PreparedFrame, verifier: Verifier, island: Island, checked: list[Checked]
    ) -> list[tuple[int, Verification]]:
        """The entries of the accepted island next to its best one (``query.refine`` either side),
        verified too: the neighbour that fits the geometry best is the loop's entry."""
        r = self.config.query.refine
        out = []
        for e in range(max(island.first, island.best - r), min(island.last, island.best + r) + 1):
            if e != island.best:
                result = verifier.verify_entry(prep.view, self.db.entry(e))
                checked.append(Checked(island, self._entry_frames[e], result))
                out.append((e, result))
        return out

    def _store(self, frame: Frame, prep: PreparedFrame) -> None:
        t = time.perf_counter()
        meta: dict[str, object] = {"frame": int(frame.index), "name": frame.name}
        if self._window_island is not None:
            meta.update(window_island=list(self._window_island), window_n=self._window_n,
                        window_query=self._window_query)
        xyz = None if prep.points is None else prep.points.xyz
        if prep.points is not None and not prep.points.metric and prep.points_source is not None:
            meta.update(relative_points_meta(prep.points, prep.points_source))
        self.db.add(prep.bow, prep.fvec, prep.features, points3d=xyz, timestamp=float(frame.timestamp),
                    pose=frame.pose, meta=meta)
        self._timestamps.append(float(frame.timestamp))
        self._entry_frames.append(int(frame.index))
        # the database keeps float32 weights: use the same rounding now as after a reopen, so a
        # resumed run normalises scores exactly as an uninterrupted one
        self._prev_bow = BowVector(prep.bow.words, prep.bow.weights.astype(np.float32).astype(np.float64))
        prep.timings["add"] = (time.perf_counter() - t) * 1e3

    def _query(self, bow: BowVector, frame: Frame, entry: int) -> _Query:
        """Steps 3-4: the candidate and the stage that rejected it (None: verify it)."""
        q = self.config.query
        out = _Query()
        hi = self._exclusion_limit(float(frame.timestamp))
        if self.config.similarity:
            self.last_similarity = self.db.scores(bow).astype(np.float32)
        if hi <= 0:
            out.status = Status.CLOSE_MATCHES_ONLY
            return out
        results = self.db.query(bow, max_results=q.max_results, max_id=hi)
        if not results:
            out.status = Status.NO_DB_RESULTS
            return out
        ids = np.array([r.entry_id for r in results])
        raw = np.array([r.score for r in results])
        ns = 1.0
        if q.use_nss:
            if self._prev_bow is None:
                out.status = Status.LOW_NSS_FACTOR
                return out
            ns = out.nss_factor = score(bow, self._prev_bow, self.vocabulary.scoring)
            if ns < q.min_nss_factor:
                out.status = Status.LOW_NSS_FACTOR
                return out
        norm = raw / ns
        out.results = [(int(e), float(v)) for e, v in zip(ids, norm, strict=True)]
        out.raw_of = {int(e): float(v) for e, v in zip(ids, raw, strict=True)}
        ok = norm >= q.alpha
        best = int(np.argmax(norm))
        out.candidate, out.raw_score, out.score = int(ids[best]), float(raw[best]), float(norm[best])
        if not ok.any():
            out.status = Status.LOW_SCORES
            return out
        out.islands = sorted(compute_islands(ids[ok], norm[ok], q.island_gap), key=lambda i: -i.score)
        island = out.islands[0]
        out.consistent = self._update_window(island, entry)
        out.candidate, out.raw_score = island.best, out.raw_of[island.best]
        out.score, out.island = island.best_score, island
        if out.consistent < q.temporal_k:
            out.status = Status.NO_TEMPORAL_CONSISTENCY
        return out

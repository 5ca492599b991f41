"""The loop detector: a stream of frames in, loop decisions out.

Per frame, as DLoopDetector (Galvez-Lopez & Tardos 2012) with the paper's additions:

1. ORB features; optionally only those on meaningful structure (semantic masking);
2. the BoW vector and direct index from the vocabulary;
3. a database query excluding the most recent entries; scores normalised by the score
   between the frame and the previous one; candidates under ``alpha`` dropped;
4. candidates grouped into islands of nearby entries; the best island must be temporally
   consistent with the islands of the previous ``temporal_k`` frames;
5. geometric verification of the island's best entry (3D triangles, PnP or the fundamental
   matrix); the accepted loop comes with the relative pose (from PnP with a calibration; from
   the matched 3D points alone, a RANSAC rigid alignment, when a SLAM system hands in map
   points without one);
6. the frame is stored (with its keypoints and 3D points) whatever the decision.

The state lives in the database file: reopening a detector on the same file continues where
it stopped (the temporal window is restored from the last entries' records).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..database import Database
from ..errors import ConfigError, InputError
from ..geometry.camera import Calibration
from ..geometry.points import Points3D, relative_points_meta
from ..geometry.rotations import quat_from_rotvec, quat_to_matrix
from ..types import BowVector, FeaturesLike, Frame
from ..verification.result import Verification
from ..verification.verifier import Verifier, View
from ..vocabulary import Scoring, Vocabulary, default_vocabulary, score
from ..vocabulary.incremental import IncrementalVocabulary
from .config import DetectorConfig
from .decision import Checked, Island, LoopDecision, Status
from .prepare import FramePreparer, PreparedFrame, Segmenter, as_calibration
from .sequence import Scored, SequenceHistory, sequence_scores
from .vladvote import VladVote

log = logging.getLogger(__name__)
#: ``must_beat`` for a candidate that cannot win whatever it matches (its rank weight is 0)
_NEVER = 1 << 30


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


def _kabsch(query: np.ndarray, cand: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rotation and translation with ``query ~ R @ cand + t`` (Kabsch /
    Umeyama without scale): (3, 3) and (3,) float64."""
    w = weights / weights.sum()
    qc, cc = w @ query, w @ cand
    h = (cand - cc).T @ ((query - qc) * w[:, None])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rot, qc - rot @ cc


def _covariances(points: Points3D, index: np.ndarray) -> np.ndarray:
    """(M, 3, 3) covariance of each point: its depth sigma along the viewing ray, its lateral
    sigma across it."""
    xyz = points.xyz[index].astype(np.float64)
    dist = np.linalg.norm(xyz, axis=1)
    u = xyz / dist[:, None]
    along = np.square(points.sigma_depth[index] * dist / xyz[:, 2])
    across = np.square(points.sigma_lateral[index].astype(np.float64))
    uu = u[:, :, None] * u[:, None, :]
    return (along - across)[:, None, None] * uu + across[:, None, None] * np.eye(3)


def _chi2(q: np.ndarray, c: np.ndarray, cov_q: np.ndarray, cov_c: np.ndarray, rot: np.ndarray,
          t: np.ndarray) -> np.ndarray:
    """(M,) squared Mahalanobis distance of ``q - (rot @ c + t)`` under both points' noise."""
    r = q - c @ rot.T - t
    cov = cov_q + rot @ cov_c @ rot.T + 1e-12 * np.eye(3)
    return np.einsum("ij,ij->i", r, np.linalg.solve(cov, r[:, :, None])[:, :, 0])


def _refine_rigid(q: np.ndarray, c: np.ndarray, cov_q: np.ndarray, cov_c: np.ndarray, rot: np.ndarray,
                  t: np.ndarray, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on the sum of squared Mahalanobis residuals (depth errors weigh little along
    the rays, lateral ones much): the refined ``rot, t``."""
    for _ in range(iterations):
        p = c @ rot.T + t
        r = q - p
        w = np.linalg.inv(cov_q + rot @ cov_c @ rot.T + 1e-12 * np.eye(3))
        jac = np.zeros((len(q), 3, 6))  # d r / d (w, delta) for rot <- exp(w) rot, t <- exp(w) t + delta
        jac[:, 0, 1], jac[:, 0, 2], jac[:, 1, 0] = -p[:, 2], p[:, 1], p[:, 2]  # [p]x
        jac[:, 1, 2], jac[:, 2, 0], jac[:, 2, 1] = -p[:, 0], -p[:, 1], p[:, 0]
        jac[:, :, 3:] = -np.eye(3)
        jw = np.transpose(jac, (0, 2, 1)) @ w
        h = np.einsum("nij,njk->ik", jw, jac)
        g = np.einsum("nij,nj->i", jw, r)
        try:
            step = np.linalg.solve(h, -g)
        except np.linalg.LinAlgError:
            break
        dr = quat_to_matrix(quat_from_rotvec(step[:3]))
        rot, t = dr @ rot, dr @ t + step[3:]
        if np.linalg.norm(step) < 1e-9:
            break
    return rot, t


def _ransac_iterations(inlier_fraction: float, confidence: float) -> int:
    """Triples to draw so that one is all inliers with ``confidence`` (huge when none fits)."""
    p = inlier_fraction**3
    if p <= 0.0:
        return 2**31
    if p >= 1.0:
        return 1
    return int(math.ceil(math.log(1.0 - confidence) / math.log1p(-p)))


def align_points(
    query: Points3D,
    candidate: Points3D,
    *,
    max_chi2: float = 11.34,
    min_inliers: int = 6,
    confidence: float = 0.999,
    max_iterations: int = 500,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """The rigid motion taking matched candidate points onto query points, robust to wrong
    matches (MSAC on triples, then weighted Kabsch refits on the inliers).

    A pair is an inlier when its residual's squared Mahalanobis distance under the two points'
    covariances (depth sigma along the viewing ray, lateral sigma across it) is under
    ``max_chi2`` (11.34: 99 % of 3-dof chi-square).

    Args:
        query: (M,) points of the matches in the query camera.
        candidate: (M,) the matched points in the candidate camera.
        max_chi2: inlier threshold on the squared Mahalanobis distance.
        min_inliers: fewest inliers for a pose.
        confidence: RANSAC's stopping confidence.
        max_iterations: most triples tried.
        seed: the sampling seed (results are deterministic).

    Returns:
        ``(rotation (3, 3), translation (3,), inliers (M,) bool, rms metres)`` with
        ``X_query = rotation @ X_candidate + translation``, or None without ``min_inliers``.
    """
    valid = np.flatnonzero(query.valid & candidate.valid)
    if valid.size < max(min_inliers, 3):
        return None
    q, c = query.xyz[valid].astype(np.float64), candidate.xyz[valid].astype(np.float64)
    cov_q, cov_c = _covariances(query, valid), _covariances(candidate, valid)
    weights = 3.0 / np.maximum(np.trace(cov_q, axis1=1, axis2=2) + np.trace(cov_c, axis1=1, axis2=2), 1e-12)
    rng = np.random.default_rng(seed)
    best, best_cost = np.zeros(valid.size, bool), math.inf
    n_iter, i = max_iterations, 0
    while i < n_iter:
        i += 1
        s = rng.choice(valid.size, 3, replace=False)
        if np.linalg.norm(np.cross(c[s[1]] - c[s[0]], c[s[2]] - c[s[0]])) < 1e-9:
            continue  # a degenerate (collinear) triple
        ratio = _chi2(q, c, cov_q, cov_c, *_kabsch(q[s], c[s], np.ones(3))) / max_chi2
        cost = float(np.minimum(ratio, 1.0).sum())  # MSAC: a tighter fit of as many pairs wins
        if cost < best_cost:
            best, best_cost = ratio < 1.0, cost
            n_iter = min(n_iter, _ransac_iterations(best.sum() / valid.size, confidence))
    for _ in range(3):  # refit on the inliers, reselect
        if best.sum() < max(min_inliers, 3):
            return None
        rot, t = _kabsch(q[best], c[best], weights[best])
        rot, t = _refine_rigid(q[best], c[best], cov_q[best], cov_c[best], rot, t)
        best = _chi2(q, c, cov_q, cov_c, rot, t) < max_chi2
    if best.sum() < min_inliers:
        return None
    inliers = np.zeros(len(query), bool)
    inliers[valid[best]] = True
    rms = float(np.sqrt(np.mean(np.sum(np.square(q[best] - c[best] @ rot.T - t), axis=1))))
    return rot, t, inliers, rms


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
    limit: int = 0
    support: int = 0
    current: Scored = field(default_factory=Scored.empty)
    window: list[Scored] = field(default_factory=list)


class LoopDetector:
    """Streaming loop-closure detection.

    Args:
        config: settings (see :mod:`stablecues.detection.config` for presets).
        vocabulary: the vocabulary; default: the shipped one.
        database: SQLite file to keep the map in (reopened and continued when it exists), or
            None to keep everything in memory.
        calibration: camera calibration used when a frame carries none: a
            :class:`~stablecues.geometry.Calibration` or the path of a calibration file
            (ORB-SLAM settings, EuRoC/Kalibr ``sensor.yaml``, KITTI ``calib.txt``) or a TUM
            camera name (``fr1``, ``fr2``, ``fr3``).
        segmenter: a callable ``image -> SegmentationResult`` replacing the shipped network.

    Raises:
        CalibrationError: a calibration path that does not exist or does not hold one.
        InputError: a calibration that is neither.
        ConfigError: a vocabulary whose scoring is not a similarity in [0, 1].
    """

    def __init__(
        self,
        config: DetectorConfig | None = None,
        vocabulary: Vocabulary | IncrementalVocabulary | None = None,
        database: str | Path | None = None,
        calibration: Calibration | str | Path | None = None,
        segmenter: Segmenter | None = None,
    ) -> None:
        calibration = as_calibration(calibration)  # a bad path fails before the database opens
        self.config = config or DetectorConfig()
        self.vocabulary: Vocabulary | IncrementalVocabulary = (
            vocabulary or self._vocabulary_of(self.config))
        if self.vocabulary.scoring in (Scoring.KL, Scoring.DOT_PRODUCT):
            raise ConfigError("the loop detector needs a similarity scoring in [0, 1] (L1, L2, "
                              "chi-square or Bhattacharyya), not KL or dot product")
        self.db = Database(self.vocabulary, database)
        self.preparer = FramePreparer(self.config, self.vocabulary, calibration, segmenter)
        self._vlad = VladVote.of(self.config, self.vocabulary.descriptor_kind)
        self.last_similarity: np.ndarray | None = None
        self._restore_state()

    @staticmethod
    def _vocabulary_of(config: DetectorConfig) -> Vocabulary | IncrementalVocabulary:
        """The shipped vocabulary of the configuration's extractor, or a new incremental one
        for its descriptors (``config.vocabulary``)."""
        if config.vocabulary == "incremental":
            from ..features import make_extractor

            kind = make_extractor(config.features).descriptor_kind
            return IncrementalVocabulary(kind, threshold=config.incremental_threshold)
        return default_vocabulary(config.features.name)

    @property
    def calibration(self) -> Calibration | None:
        """The calibration used for frames that carry none."""
        return self.preparer.calibration

    # ------------------------------------------------------------------ state
    def _restore_state(self) -> None:
        n = len(self.db)
        self._timestamps: list[float] = self.db.column("timestamp") if n else []
        # a removed entry keeps its id but not its meta (null): it is never proposed again
        metas = [m if isinstance(m, dict) else {} for m in (self.db.column("meta") if n else [])]
        present = self.db.ids() if n else np.zeros(0, np.int64)
        self._entry_frames: list[int] = [int(m.get("frame", i)) for i, m in enumerate(metas)]
        self._index_said = False
        self._processed = self._close_only = 0  # frames processed, and those with no older entry
        latest = int(present[-1]) if present.size else -1  # the newest entry still in the map
        self._prev_bow: BowVector | None = self.db.entry(latest).bow if latest >= 0 else None
        # scores of the latest entries with their predecessors, and the first entry of the run
        keep = self.config.query.run_history
        recent = present[max(present.size - keep, 0):].tolist()
        self._adjacent: list[float] = [float(metas[i]["adjacent"]) for i in recent
                                       if isinstance(metas[i].get("adjacent"), int | float)]
        self._run_start = int(metas[latest].get("run", 0)) if latest >= 0 else 0
        self._continuity: tuple[float, int] = (math.nan, self._run_start)
        self._window_n = 0
        self._window_island: tuple[int, int] | None = None
        self._window_query = -(10**9)
        self.preparer.restore_certainties([float(m["certainty"]) for m in metas if "certainty" in m])
        if self._vlad is not None:
            self._vlad.restore(self.db, present)
        self._sequence = SequenceHistory(self.config.query.sequence)
        if self.config.query.sequence >= 2 and latest >= 0:
            self._restore_sequence(present, metas)
        if self.config.monocular is not None:  # the latest entries are the next frame's neighbours
            for k in present[max(present.size - self.config.monocular.neighbours, 0):].tolist():
                e = self.db.entry(k)
                self.preparer.remember(e.features, e.fvec)
        if latest >= 0:
            last = metas[latest]
            isl = last.get("window_island")
            if isl is not None:
                self._window_island = (int(isl[0]), int(isl[1]))
                self._window_n = int(last.get("window_n", 0))
                self._window_query = int(last.get("window_query", n - 1))

    def _restore_sequence(self, present: np.ndarray, metas: list[dict[str, Any]]) -> None:
        """The sequence history of a reopened map: the latest stored entries of the current run
        queried again as they were (each entry's ``limit``, its score with its predecessor), so
        that a resumed stream scores its sequences as an uninterrupted one."""
        q = self.config.query
        self._sequence.start(self._run_start)
        recent = [int(e) for e in present[max(present.size - (q.sequence - 1), 0):].tolist()
                  if int(e) >= self._run_start]
        for e in recent:  # oldest first: push puts the newest at the front
            m = metas[e]
            limit, ns = m.get("limit"), (m.get("adjacent") if q.use_nss else 1.0)
            if (not isinstance(limit, int) or not isinstance(ns, int | float) or limit <= 0
                    or ns < q.min_nss_factor):
                self._sequence.push(Scored.empty())
                continue
            bow = self.db.entry(e).bow
            scored = self.db.scored(bow, max_id=limit)
            results = self.db.best(*scored, q.max_results)
            ids = np.array([r.entry_id for r in results], np.int64)
            raw = np.array([r.score for r in results])
            norm = raw / float(ns)
            vector = self._vlad.row(e) if self._vlad is not None else None
            if self._vlad is not None and vector is not None and ids.size:
                ids, _, norm = self._vlad.fuse(self.db, ids, raw, float(ns), vector, self._vlad.row(e - 1),
                                               limit, scored)
            self._sequence.push(Scored.capped(ids, norm))

    def close(self, *, hint: bool = True) -> None:
        """Close the map; a stream whose every frame fell inside the exclusion window (none was
        ever compared with an earlier one) is said in a logged warning (``hint=False``: not, for
        a caller that says it its own way or closes after an error)."""
        if hint and self._processed and self._close_only == self._processed:
            log.warning("all %d frames fell inside the exclusion window (query.exclude_recent = %d): no "
                        "frame was compared with an earlier one; on a short stream lower it",
                        self._processed, self.config.query.exclude_recent)
            self._processed = 0
        self.db.close()

    @property
    def next_index(self) -> int:
        """The frame index a stream continuing this map should give its next frame: one past
        the latest stored frame's (0 for an empty map), so that a reopened map's second run
        numbers on where the first stopped."""
        return self._entry_frames[-1] + 1 if self._entry_frames else 0

    @property
    def next_session(self) -> int:
        """The :attr:`~stablecues.types.Frame.session` a new recording added to this map should
        give its frames: one past the highest stored (0 for an empty map)."""
        sessions = self.db.index.sessions()
        return int(sessions.max()) + 1 if sessions.size else 0

    def _session_of(self, frame: Frame) -> int:
        """The frame's session: its own, or (None) the map's current one (:attr:`Database.session`,
        which :meth:`Database.new_session` moves on)."""
        return int(self.db.session) if frame.session is None else frame.session

    def __enter__(self) -> LoopDetector:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close(hint=exc[0] is None)  # after an error the error is what matters

    def __len__(self) -> int:
        return len(self.db)

    # ------------------------------------------------------------------ helpers
    def _continuity_of(self, bow: BowVector, session: int) -> tuple[float, int]:
        """(the frame's score with the previous entry, the first entry of the run the frame
        belongs to): a new run, starting at the frame itself, when that score falls below
        ``run_break`` times the median of the latest adjacent scores (and below
        ``run_break_score``), or when the frame starts another session than the latest entry's."""
        q = self.config.query
        n = len(self.db)
        if self._prev_bow is None:
            return math.nan, n
        adjacent = score(bow, self._prev_bow, self.vocabulary.scoring)
        if n and session != int(self.db.index.sessions()[n - 1]):  # the latest entry's session
            return adjacent, n
        recent = self._adjacent[-q.run_history:]
        if (q.run_break is not None and len(recent) >= 2 and adjacent < q.run_break * float(np.median(recent))
                and (q.run_break_score is None or adjacent < q.run_break_score)):
            return adjacent, n
        return adjacent, self._run_start

    def _exclusion_limit(self, timestamp: float) -> int:
        """Entries with id below this may be proposed (the recent window excluded)."""
        q = self.config.query
        n = len(self.db)
        window = q.exclude_recent
        if q.run_break is not None:  # entries before the current run are another place
            window = min(window, max(q.exclude_recent_min, n - self._continuity[1]))
        hi = n - window
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
    def process(
        self, frame: Frame, features: FeaturesLike | None = None, *, store: bool = True
    ) -> LoopDecision:
        """Detect a loop for one frame, then store the frame.

        Args:
            frame: the frame (image, timestamp, optional right / depth image, map points,
                calibration, pose).
            features: the frame's features when a SLAM system hands its own in (their order
                must match ``frame.points3d``): :class:`~stablecues.types.Features` or a
                ``(keypoints, descriptors)`` pair as OpenCV's ``detectAndCompute`` returns it
                (or ``frame.features``); extracted here otherwise.
            store: add the frame to the database afterwards (False: a pure query, as for the
                query pass of a place-recognition benchmark).

        Returns:
            the decision, with the stage that decided and the time of every stage.
        """
        self._check_index(frame)
        prep = self.preparer.prepare(frame, features)
        vlad = self._vlad_of(prep)
        timings, t = prep.timings, time.perf_counter()
        entry = len(self.db)
        self._continuity = self._continuity_of(prep.bow, self._session_of(frame))
        found = self._query(prep.bow, frame, entry, vlad)
        self._sequence.push(found.current)
        timings["query"] = (time.perf_counter() - t) * 1e3
        status = found.status
        self._processed += 1
        self._close_only += status is Status.CLOSE_MATCHES_ONLY
        verification: Verification | None = None
        checked: tuple[Checked, ...] = ()
        if status is None:
            t = time.perf_counter()
            status, verification, checked = self._verify(prep, found, self._session_of(frame))
            timings["verify"] = (time.perf_counter() - t) * 1e3
        if store:
            self._store(frame, prep, limit=found.limit, vlad=vlad)
        timings["total"] = (time.perf_counter() - prep.t_start) * 1e3
        cand = found.candidate
        confidence = found.score
        seq = math.nan
        if found.window and cand >= 0:
            seq = float(sequence_scores(np.array([cand]), found.window,
                                        tolerance=self.config.query.sequence_tolerance)[0])
        if verification is not None and self.config.confidence == "inliers":
            confidence = float(max(verification.n_inliers, found.support)) + min(confidence, 0.999)
        elif verification is not None and self.config.confidence == "sequence":
            confidence = float(max(verification.n_inliers, found.support)) * seq
        if status is Status.LOOP_DETECTED and not confidence >= self.config.min_confidence:
            status = Status.LOW_CONFIDENCE
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
            mask_fallback=prep.mask_fallback, timings=timings, sequence_score=seq,
        )

    def store(self, frame: Frame, features: FeaturesLike | None = None) -> int:
        """Add a frame to the database without looking for a loop; returns its entry id
        (``features`` as in :meth:`process`)."""
        prep = self.preparer.prepare(frame, features)
        vlad = self._vlad_of(prep)
        entry = len(self.db)
        self._continuity = self._continuity_of(prep.bow, self._session_of(frame))
        self._sequence.start(self._continuity[1])
        self._sequence.push(Scored.empty())  # no query: a gap in the sequence, frames stay aligned
        self._store(frame, prep, vlad=vlad)
        return entry

    def _check_index(self, frame: Frame) -> None:
        """A frame index not after the latest stored one (repeated, or going back: two frames
        then share an index and a loop's ``candidate_frame`` is ambiguous) is said once."""
        if self._entry_frames and int(frame.index) <= self._entry_frames[-1] and not self._index_said:
            log.warning("frame index %d does not follow the latest stored frame %d (repeated or going back; "
                        "number a continuing stream from detector.next_index); further ones not reported",
                        int(frame.index), self._entry_frames[-1])
            self._index_said = True

    def _vlad_of(self, prep: PreparedFrame) -> np.ndarray | None:
        """The frame's VLAD vector (``query.vlad``; timed as the stage ``vlad``), else None."""
        if self._vlad is None:
            return None
        t = time.perf_counter()
        out = self._vlad.encode(prep.features.descriptors)
        prep.timings["vlad"] = (time.perf_counter() - t) * 1e3
        return out

    def _verify(
        self, prep: PreparedFrame, found: _Query, session: int = 0
    ) -> tuple[Status, Verification | None, tuple[Checked, ...]]:
        """Step 5: verify the best ``islands_verified`` islands; the accepted one with the most
        geometric inliers (``query.sequence_choice``: the most inliers times sequence score) is
        the loop (``found`` is updated to name it); with ``query.other_sessions_first`` one of
        another session than ``session`` (the query's) before any of that session."""
        if self.config.verification is None:
            return Status.LOOP_DETECTED, None, ()
        q = self.config.query
        verifier = self.preparer.verifier(prep.calibration)
        checked = []
        islands = found.islands[: q.islands_verified]
        # what each island's inliers are multiplied by to rank it: 1, or its sequence score
        weight = np.ones(len(islands))
        if q.sequence_choice and found.window:
            weight = sequence_scores(np.array([i.best for i in islands], np.int64), found.window,
                                     tolerance=q.sequence_tolerance)
        # query.other_sessions_first: the islands of other sessions first, one of them accepted
        # is the loop and the islands of the session under way are not verified
        sessions = self.db.index.sessions()  # each entry's (the map keeps them)
        other = [q.other_sessions_first and int(sessions[i.best]) != session for i in islands]
        accepted: list[tuple[Checked, float, bool]] = []  # (what was checked, weight, other session)
        top = 0.0  # the best accepted island's rank: a candidate whose matches cannot beat it is cut short
        for k in sorted(range(len(islands)), key=lambda k: not other[k]):
            island, w = islands[k], float(weight[k])
            if accepted and accepted[0][2] and not other[k]:
                break
            most = 0 if top <= 0 else (math.floor(top / w) if w > 0 else _NEVER)
            result = verifier.verify(prep.view, self._candidate(verifier, island.best), must_beat=most)
            checked.append(Checked(island, self._entry_frames[island.best], result))
            if result.accepted:
                accepted.append((checked[-1], w, other[k]))
                top = max(top, result.n_inliers * w)
        if not accepted:
            return Status.NO_GEOMETRICAL_CONSISTENCY, checked[0].verification, tuple(checked)
        best = max(accepted, key=lambda c: (c[2], c[0].verification.n_inliers * c[1],
                                            c[0].verification.n_inliers, c[0].island.best_score))[0]
        entry, result = best.island.best, best.verification
        for e, r in self._refine(prep, verifier, best.island, checked, result.n_inliers):
            if r.accepted and r.n_inliers > result.n_inliers:
                entry, result = e, r
        found.support = result.n_inliers  # the place's geometric support, kept when the walk moves on
        if self.config.query.viewpoint_steps:
            entry, result = self._nearest_viewpoint(prep, verifier, entry, result, checked, best.island,
                                                    found.limit)
        if result.pose is None and verifier.camera is None:
            result = self._align(prep, verifier, entry, result)
        if entry != found.candidate:
            norm = dict(found.results)
            found.candidate, found.island = entry, best.island
            found.score = norm.get(entry, best.island.best_score)
            found.raw_score = found.raw_of.get(entry, 0.0)
        return Status.LOOP_DETECTED, result, tuple(checked)

    def _present(self, entry: int) -> bool:
        """Whether a map entry is still there (not removed by :meth:`Database.remove`)."""
        alive = self.db.index.alive()
        return alive is None or bool(alive[entry])

    def _candidate(self, verifier: Verifier, entry: int) -> View:
        """The verifier's view of a map entry; a malformed stored array names the map."""
        try:
            return verifier.view_of_entry(self.db.entry(entry))
        except InputError as exc:
            where = self.db.path if self.db.path is not None else "the detector's map (in memory)"
            raise InputError(f"{where}: {exc}") from None

    def _refine(
        self, prep: PreparedFrame, verifier: Verifier, island: Island, checked: list[Checked], inliers: int
    ) -> list[tuple[int, Verification]]:
        """The entries of the accepted island next to its best one (``query.refine`` either side),
        verified too: the neighbour that fits the geometry best (more than ``inliers``, the
        best so far) is the loop's entry."""
        r = self.config.query.refine
        out = []
        for e in range(max(island.first, island.best - r), min(island.last, island.best + r) + 1):
            if e != island.best and self._present(e):
                result = verifier.verify(prep.view, self._candidate(verifier, e), must_beat=inliers + 1)
                checked.append(Checked(island, self._entry_frames[e], result))
                out.append((e, result))
                if result.accepted:
                    inliers = max(inliers, result.n_inliers)
        return out

    def _nearest_viewpoint(
        self, prep: PreparedFrame, verifier: Verifier, entry: int, result: Verification,
        checked: list[Checked], island: Island, hi: int,
    ) -> tuple[int, Verification]:
        """Step along the map from the accepted entry towards the viewpoint nearest the query's:
        while the image scale between the query and the entry (:attr:`Verification.scale_change`)
        is off by more than ``viewpoint_scale``, the entry's neighbours (id - 1, id + 1) are
        verified, and the accepted one whose scale change is smaller by ``viewpoint_margin`` is
        taken; at most ``viewpoint_steps`` steps, never to ids from ``hi`` on (the excluded
        recent entries)."""
        q = self.config.query
        # where each frame already checked sits in ``checked``: a walk verifies in full, and its
        # result replaces one cut short earlier (``must_beat``)
        where = {c.frame: k for k, c in enumerate(checked)}
        seen: dict[int, Verification] = {entry: result}
        z = abs(result.scale_change)
        need = q.viewpoint_inliers * result.n_inliers
        for _ in range(q.viewpoint_steps):
            if not z > q.viewpoint_scale:  # also NaN: nothing to go by
                break
            step = None
            for e in (entry - 1, entry + 1):
                if not (0 <= e < hi and self._present(e)):
                    continue
                r = seen.get(e)
                if r is None:
                    r = seen[e] = verifier.verify(prep.view, self._candidate(verifier, e))
                    frame = self._entry_frames[e]
                    if frame in where:
                        checked[where[frame]] = Checked(checked[where[frame]].island, frame, r)
                    else:
                        where[frame] = len(checked)
                        checked.append(Checked(island, frame, r))
                ze = abs(r.scale_change)
                if (r.accepted and r.n_inliers >= need and ze < z - q.viewpoint_margin
                        and (step is None or ze < step[2])):
                    step = (e, r, ze)
            if step is None:
                break
            entry, result, z = step
        return entry, result

    def _align(
        self, prep: PreparedFrame, verifier: Verifier, entry: int, result: Verification
    ) -> Verification:
        """The relative pose of an accepted loop from its matched 3D points alone (map points
        without a calibration, so no camera for PnP): ``result`` with the pose and its inliers,
        or unchanged when the points are not metric in both frames or fit no rigid motion."""
        cand = self._candidate(verifier, entry).points
        query = prep.points
        if query is None or cand is None or not (query.metric and cand.metric):
            return result
        m = result.matches
        fit = align_points(query.subset(m.query), cand.subset(m.candidate))
        if fit is None:
            return dataclasses.replace(result, reason=result.reason + "; no rigid 3D-3D fit, no pose")
        rotation, translation, inliers, rms = fit
        return dataclasses.replace(
            result, rotation=rotation, translation=translation, inliers=inliers,
            reason=result.reason + f"; pose from a 3D-3D fit: {int(inliers.sum())} of {len(m)} matches "
                                   f"within 99 % noise, rms {rms:.3f} m")

    def _store(
        self, frame: Frame, prep: PreparedFrame, limit: int = 0, vlad: np.ndarray | None = None
    ) -> None:
        t = time.perf_counter()
        meta = self._entry_meta(frame, prep, limit)
        xyz = None if prep.points is None else prep.points.xyz
        session = self._session_of(frame)
        arrays = {} if prep.weights is None else {"weights": prep.weights}
        if vlad is not None:
            arrays["vlad"] = vlad.astype(np.float16)
        bow, fvec = prep.bow, prep.fvec
        learned = isinstance(self.vocabulary, IncrementalVocabulary)
        if isinstance(self.vocabulary, IncrementalVocabulary):  # its words grow with the map
            bow, fvec = self.vocabulary.learn(self.db.stored_form(prep.features.descriptors), prep.weights)
        try:
            self.db.add(bow, fvec, prep.features, points3d=xyz, timestamp=float(frame.timestamp),
                        pose=frame.pose, meta=meta, arrays=arrays or None, session=session)
        except BaseException:
            if learned:  # the words learned this frame, the map did not take it: back to the map's
                self.db.resync_words()
            raise
        if self._vlad is not None and vlad is not None:
            self._vlad.append(vlad, entry=len(self.db) - 1)
        self._timestamps.append(float(frame.timestamp))
        self._entry_frames.append(int(frame.index))
        # the database keeps float32 weights: use the same rounding now as after a reopen, so a
        # resumed run normalises scores exactly as an uninterrupted one
        self._prev_bow = BowVector(bow.words, bow.weights.astype(np.float32).astype(np.float64))
        prep.timings["add"] = (time.perf_counter() - t) * 1e3

    def _entry_meta(self, frame: Frame, prep: PreparedFrame, limit: int) -> dict[str, object]:
        """The meta stored with a frame's entry (what a reopened map restores the detector's
        state from); keeps the run and the adjacent scores it records."""
        meta: dict[str, object] = {"frame": int(frame.index), "name": frame.name}
        if self.config.query.sequence >= 2 and limit > 0:  # to query it again after a reopen
            meta["limit"] = int(limit)
        adjacent, run_start = self._continuity
        if math.isfinite(adjacent):
            meta["adjacent"] = round(adjacent, 9)
            self._adjacent = [*self._adjacent, round(adjacent, 9)][-self.config.query.run_history:]
        if run_start:
            meta["run"] = run_start
        self._run_start = run_start
        if prep.certainty is not None:
            meta["certainty"] = prep.certainty
        if self._window_island is not None:
            meta.update(window_island=list(self._window_island), window_n=self._window_n,
                        window_query=self._window_query)
        if prep.points is not None and not prep.points.metric and prep.points_source is not None:
            meta.update(relative_points_meta(prep.points, prep.points_source))
        return meta

    def _query(self, bow: BowVector, frame: Frame, entry: int, vlad: np.ndarray | None = None) -> _Query:
        """Steps 3-4: the candidate and the stage that rejected it (None: verify it)."""
        q = self.config.query
        out = _Query()
        self._sequence.start(self._continuity[1])
        hi = self._exclusion_limit(float(frame.timestamp))
        out.limit = hi
        if self.config.similarity:
            self.last_similarity = self.db.scores(bow).astype(np.float32)
        if hi <= 0:
            out.status = Status.CLOSE_MATCHES_ONLY
            return out
        scored = self.db.scored(bow, max_id=hi)  # one pass of the index, for the vote too
        results = self.db.best(*scored, q.max_results)
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
        if self._vlad is not None and vlad is not None:
            ids, raw, norm = self._vlad.fuse(self.db, ids, raw, ns, vlad, self._vlad.latest, hi, scored)
        out.results = [(int(e), float(v)) for e, v in zip(ids, norm, strict=True)]
        out.raw_of = {int(e): float(v) for e, v in zip(ids, raw, strict=True)}
        out.current = Scored.capped(ids, norm)
        rank = norm
        if q.sequence >= 2:
            out.window = self._sequence.window(out.current)
            if q.sequence_rank:  # SeqSLAM: the candidates ranked by their line through the recent queries
                rank = sequence_scores(ids, out.window, tolerance=q.sequence_tolerance)
        ok = norm >= q.alpha
        best = int(np.argmax(norm))
        out.candidate, out.raw_score, out.score = int(ids[best]), float(raw[best]), float(norm[best])
        if not ok.any():
            out.status = Status.LOW_SCORES
            return out
        out.islands = sorted(compute_islands(ids[ok], rank[ok], q.island_gap), key=lambda i: -i.score)
        island = out.islands[0]
        out.consistent = self._update_window(island, entry)
        out.candidate, out.raw_score = island.best, out.raw_of[island.best]
        out.score, out.island = out.raw_of[island.best] / ns, island
        if out.consistent < q.temporal_k:
            out.status = Status.NO_TEMPORAL_CONSISTENCY
        return out

"""Inverse index: scores equal pairwise DBoW2 scores for every scoring, whatever the segments
look like; maintenance in bounded steps (inline or in a background thread); removal."""

from __future__ import annotations

import numpy as np
import pytest

import stablecues.database.segments as segments
from stablecues.database import InvertedIndex
from stablecues.database.inverted import FAN_IN, MERGE_FAN_IN
from stablecues.database.segments import MergeJob
from stablecues.types import BowVector
from stablecues.vocabulary import Scoring, score
from stablecues.vocabulary.scoring import normalise

N_WORDS = 500


def vectors(n: int, scoring: Scoring, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        size = 0 if i % 37 == 5 else 40  # a few empty entries too
        w = np.unique(rng.integers(0, N_WORDS, size)).astype(np.int32)
        v = normalise(rng.random(w.size) + 0.01, scoring)
        out.append((w, v))
    return out


def as_stored(v: np.ndarray) -> np.ndarray:
    return v.astype(np.float32).astype(np.float64)  # the index keeps float32 weights


def brute(vecs: list[tuple[np.ndarray, np.ndarray]], q: tuple[np.ndarray, np.ndarray], scoring: Scoring,
          hi: int) -> dict[int, float]:
    qb = BowVector(q[0], q[1])
    out = {}
    for e, (w, v) in enumerate(vecs[:hi]):
        if np.intersect1d(q[0], w).size:
            out[e] = score(qb, BowVector(w, as_stored(v)), scoring)
    return out


def build(vecs: list[tuple[np.ndarray, np.ndarray]], scoring: Scoring, background: bool = False,
          tail: int = 300, chunk: int = 500) -> InvertedIndex:
    idx = InvertedIndex(N_WORDS, scoring, tail_limit=tail, background=background, chunk=chunk)
    for e, (w, v) in enumerate(vecs):
        assert idx.add(w, v.astype(np.float32), session=e % 3) == e
    return idx


@pytest.mark.parametrize("scoring", list(Scoring))
@pytest.mark.parametrize("csr_from", [1 << 30, 64])  # binary search / CSR word tables
def test_scores_equal_pairwise_scores(
    scoring: Scoring, csr_from: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(segments, "CSR_MIN", csr_from)
    vecs = vectors(200, scoring)
    idx = build(vecs, scoring)
    assert len(idx.segments) >= 2 and idx.n_entries == 200
    assert any(seg.indptr is not None for seg in idx.segments) == (csr_from == 64)
    for qi in (17, 150, 199):
        q = vecs[qi]
        ids, s = idx.scores(q[0], q[1], max_id=180, min_id=3)
        want = {e: v for e, v in brute(vecs, q, scoring, 180).items() if e >= 3}
        assert ids.tolist() == sorted(want)
        # KL adds ~30 for the missing words and subtracts most of it again: absolute rounding
        atol = 1e-6 if scoring == Scoring.KL else 1e-12
        np.testing.assert_allclose(s, [want[e] for e in ids.tolist()], rtol=1e-9, atol=atol)


def test_scores_do_not_depend_on_the_segments() -> None:
    """Background, inline and fully merged indexes give bit-identical scores."""
    vecs = vectors(400, Scoring.L1, seed=3)
    inline = build(vecs, Scoring.L1)
    background = build(vecs, Scoring.L1, background=True)
    merged = build(vecs, Scoring.L1, tail=1 << 30)
    merged.flush()
    assert len(merged.segments) == 1
    try:
        for qi in range(0, 400, 41):
            q = vecs[qi]
            a, b, c = (x.scores(q[0], q[1]) for x in (inline, background, merged))
            for other in (b, c):
                assert np.array_equal(a[0], other[0]) and np.array_equal(a[1], other[1])
        background.flush()
        q = vecs[3]
        assert np.array_equal(background.scores(q[0], q[1])[1], inline.scores(q[0], q[1])[1])
    finally:
        background.close()


def test_maintenance_runs_in_bounded_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    """Inline maintenance does at most one step per add, and a step handles at most about one
    chunk of postings (or FAN_IN sealed blocks), whatever the index size."""
    steps: list[int] = []
    real_step = MergeJob.step

    def counting_step(self: MergeJob) -> bool:
        before = self.next
        done = real_step(self)
        w0, w1 = self.bounds[before], self.bounds[min(before + 1, len(self.bounds) - 1)]
        steps.append(sum(post.shape[0] for _, _, post in self._parts(w0, w1)))
        return done

    monkeypatch.setattr(MergeJob, "step", counting_step)
    calls: list[int] = []
    real = InvertedIndex.step

    def one_step(self: InvertedIndex) -> int | None:
        calls.append(1)
        return real(self)

    monkeypatch.setattr(InvertedIndex, "step", one_step)
    vecs = vectors(1500, Scoring.L1, seed=5)
    idx = InvertedIndex(N_WORDS, Scoring.L1, tail_limit=200, chunk=400)
    per_add, unsorted = [], []
    for w, v in vecs:
        calls.clear()
        idx.add(w, v.astype(np.float32))
        per_add.append(len(calls))
        unsorted.append(len(idx._blocks))
    assert max(per_add) == 1
    # sealed blocks are sorted FAN_IN at a time, as soon as FAN_IN of them wait
    assert max(unsorted) == FAN_IN - 1
    assert steps and max(steps) <= 2 * 400 + 40  # a chunk, plus one word's run at most
    # segments stay O(log n): at most MERGE_FAN_IN - 1 per size class, plus jobs in progress
    classes = int(np.log(idx.n_postings / (FAN_IN * 200)) / np.log(MERGE_FAN_IN)) + 2
    assert len(idx.segments) <= (MERGE_FAN_IN - 1) * classes + MERGE_FAN_IN


def test_sessions_and_removal() -> None:
    vecs = vectors(120, Scoring.L1, seed=7)
    idx = build(vecs, Scoring.L1)
    assert idx.sessions().tolist() == [e % 3 for e in range(120)]
    q = vecs[10]
    ids, _ = idx.scores(q[0], q[1])
    assert 10 in ids.tolist()
    idx.remove(np.array([10, 11, 50]))
    ids2, s2 = idx.scores(q[0], q[1])
    assert not {10, 11, 50} & set(ids2.tolist())
    before = idx.n_postings
    idx.compact()
    assert idx.n_postings < before and len(idx.segments) == 1
    ids3, s3 = idx.scores(q[0], q[1])
    assert np.array_equal(ids2, ids3) and np.array_equal(s2, s3)


def test_merge_job_shifts_and_drops() -> None:
    vecs = vectors(90, Scoring.L1, seed=9)
    idx = build(vecs, Scoring.L1, tail=1 << 30)
    idx.flush()
    (seg,) = idx.segments
    alive = np.ones(90, bool)
    alive[[0, 5]] = False
    job = MergeJob([seg], idx._memory_sink, N_WORDS, chunk=100, alive=alive, shift=1000, session_shift=7)
    while not job.step():
        pass
    out = job.result
    assert out is not None and (out.lo, out.hi) == (1000, 1090)
    ent, w = segments.split(out.postings)
    e0, w0 = segments.split(seg.postings)
    keep = alive[e0]
    assert np.array_equal(ent, e0[keep] + 1000) and np.array_equal(w, w0[keep])
    assert np.array_equal(out.sessions, np.asarray(seg.sessions) + 7)


def test_reset_drops_jobs_in_progress(monkeypatch: pytest.MonkeyPatch) -> None:
    """A refresh that replaces the segments while a merge step runs: the merge's result is
    thrown away, not installed over the new segments."""
    vecs = vectors(200, Scoring.L1, seed=11)
    idx = build(vecs, Scoring.L1, tail=1 << 30)
    idx.flush()
    other = build(vecs[:120], Scoring.L1, tail=300)
    other.flush()
    (seg,) = idx.segments
    with idx._lock:  # a job on the one segment, as persisting it would be
        idx._start([seg])
    real = MergeJob.step

    def step_and_reset(self: MergeJob) -> bool:
        idx.reset(other.segments, 120, other.sessions())  # meanwhile, in another thread
        return real(self)

    monkeypatch.setattr(MergeJob, "step", step_and_reset)
    assert idx.step() is not None  # the step ran ...
    monkeypatch.setattr(MergeJob, "step", real)
    idx.flush()  # ... and its result went nowhere: the index is the new one
    assert idx.n_entries == 120 and idx.segments[-1].hi == 120
    q = vecs[7]
    a, b = idx.scores(q[0], q[1]), other.scores(q[0], q[1])
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and idx.n_entries == 120


def test_a_segment_smaller_than_a_group_is_merged_not_stranded() -> None:
    """Blocks are sorted FAN_IN at a time into groups; a smaller segment (a group flushed early,
    or what a reopen reads back from the entries) shares the groups' size class, so later
    merges take it in instead of leaving it between larger segments for good."""
    vecs = vectors(400, Scoring.L1, seed=9)
    idx = InvertedIndex(N_WORDS, Scoring.L1, tail_limit=200, chunk=400)
    for w, v in vecs[:7]:
        idx.add(w, v.astype(np.float32))
    idx.flush()
    (small,) = idx.segments
    assert small.size < FAN_IN * 200  # less than one group
    for w, v in vecs[7:]:
        idx.add(w, v.astype(np.float32))
    idx.flush()
    assert all(s is not small for s in idx.segments)
    assert idx.segments[0].lo == 0 and idx.segments[0].size > FAN_IN * FAN_IN * 200
    q = vecs[3]
    want = brute(vecs, q, Scoring.L1, 400)
    ids, s = idx.scores(q[0], q[1])
    np.testing.assert_allclose(s, [want[e] for e in ids.tolist()], rtol=1e-9)

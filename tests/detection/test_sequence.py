"""The sequence stage (SeqSLAM's line through the recent queries' scores)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from test_run_break import STEP, _wall

from stablecues import Frame, LoopDetector, preset
from stablecues.detection.decision import Status
from stablecues.detection.sequence import Scored, SequenceHistory, sequence_scores
from stablecues.errors import ConfigError


def _results(pairs: dict[int, float]) -> Scored:
    return Scored.of(np.array(list(pairs), np.int64), np.array(list(pairs.values())))


def test_a_line_of_scores_beats_a_lone_spike() -> None:
    """Entry 50 scores highest for the current query alone, but only entry 20 is on a line:
    the four previous queries scored 19, 18, 17, 16."""
    history = [_results({20: 0.5, 50: 0.9}), _results({19: 0.6, 70: 0.3}), _results({18: 0.5}),
               _results({17: 0.55, 90: 0.8}), _results({16: 0.5})]
    s = sequence_scores(np.array([20, 50]), history)
    assert s[0] == pytest.approx((0.5 + 0.6 + 0.5 + 0.55 + 0.5) / 5)
    assert s[1] == pytest.approx(0.9 / 5)  # nothing of its line in the history
    # alone, the current query's own scores
    assert sequence_scores(np.array([20, 50]), history[:1]).tolist() == [0.5, 0.9]


def test_the_best_speed_and_the_tolerance_count() -> None:
    """A map recorded at half the query's frame rate (entries advance 0.5 a frame) and one at
    twice it (2 a frame): both lines are found; a step off the line by one entry still counts
    with tolerance 1, not with 0."""
    slow = [_results({40: 1.0}), _results({40: 1.0}), _results({39: 1.0}), _results({39: 1.0})]
    fast = [_results({40: 1.0}), _results({38: 1.0}), _results({36: 1.0}), _results({34: 1.0})]
    assert sequence_scores(np.array([40]), slow)[0] == pytest.approx(1.0)
    assert sequence_scores(np.array([40]), fast)[0] == pytest.approx(1.0)
    off = [_results({40: 1.0}), _results({38: 1.0}), _results({37: 1.0})]  # speed 1, one entry late
    assert sequence_scores(np.array([40]), off, speeds=(1.0,), tolerance=1)[0] == pytest.approx(1.0)
    assert sequence_scores(np.array([40]), off, speeds=(1.0,), tolerance=0)[0] == pytest.approx(1 / 3)
    assert sequence_scores(np.array([], np.int64), off).shape == (0,)


def test_the_history_is_kept_per_run() -> None:
    h = SequenceHistory(3)
    h.start(0)
    for k in range(5):
        h.push(_results({k: 1.0}))
    window = h.window(_results({9: 1.0}))
    assert [int(w.ids[0]) for w in window] == [9, 4, 3]  # the current one, then the newest two
    h.start(0)
    assert len(h) == 3  # the same run: kept
    h.start(7)
    assert len(h) == 0  # a new run: another place


def _stream() -> list[Frame]:
    """Frames 0-11 drive along a wall; frame 12 cuts back to the start (5 px off) and frames
    12-19 drive the same stretch again."""
    pano = _wall(11)
    xs = [STEP * i for i in range(12)] + [5 + STEP * i for i in range(8)]
    return [Frame(index=i, name=f"{i}.png", timestamp=float(i),
                  image=np.ascontiguousarray(pano[:, x:x + 320])) for i, x in enumerate(xs)]


def _config(confidence: str = "sequence", length: int = 4, rank: bool = False, least: float = 0.0) -> object:
    return preset("fast", {"query": {"exclude_recent": 20, "run_break": 0.4, "run_break_score": 0.1,
                                     "exclude_recent_min": 3, "sequence": length, "sequence_rank": rank},
                           "confidence": confidence, "min_confidence": least, "similarity": False})


def _decisions(det: LoopDetector, frames: list[Frame]) -> list[tuple[object, ...]]:
    return [(d.status, d.candidate_frame, d.confidence, d.sequence_score) for d in map(det.process, frames)]


@pytest.mark.parametrize("rank", [False, True])
def test_the_second_drive_is_found_along_its_line_with_a_sequence_confidence(rank: bool) -> None:
    frames = _stream()
    det = LoopDetector(_config(rank=rank))
    found = {}
    for f in frames:
        d = det.process(f)
        if d.accepted:
            assert d.verification is not None and math.isfinite(d.sequence_score)
            assert d.confidence == pytest.approx(d.verification.n_inliers * d.sequence_score)
            assert d.extras()["sequence_score"] == pytest.approx(d.sequence_score, abs=1e-6)
            found[f.index] = (d.candidate_frame, d.sequence_score)
    assert set(found) >= set(range(13, 20)), found
    assert all(abs(cand - (i - 12)) <= 1 for i, (cand, _) in found.items())
    # without the stage, no sequence score, and the confidence is the inliers + BoW score
    plain = LoopDetector(preset("fast", {"query": {"exclude_recent": 20, "run_break": 0.4,
                                                   "run_break_score": 0.1, "exclude_recent_min": 3},
                                         "similarity": False}))
    d = [plain.process(f) for f in frames][-1]
    assert d.accepted and math.isnan(d.sequence_score) and "sequence_score" not in d.extras()


def test_a_reopened_map_scores_its_sequences_as_an_uninterrupted_one(tmp_path: Path) -> None:
    frames = _stream()
    config = _config(rank=True)  # the ranking too reads the history
    whole = _decisions(LoopDetector(config), frames)
    path = tmp_path / "map.sqlite"
    with LoopDetector(config, database=path) as det:
        first = _decisions(det, frames[:15])  # reopened in the middle of the second drive
    with LoopDetector(config, database=path) as det:
        rest = _decisions(det, frames[15:])
    assert [d[:2] for d in first + rest] == [d[:2] for d in whole]
    got = np.array([d[2:] for d in first + rest], float)
    want = np.array([d[2:] for d in whole], float)
    np.testing.assert_allclose(got, want, rtol=1e-6, equal_nan=True)
    assert any(s is Status.LOOP_DETECTED for s, *_ in rest)


def test_min_confidence_refuses_a_weak_loop() -> None:
    """The operating point: the same loops, refused (status low_confidence) when their
    confidence is under min_confidence, kept when it is over."""
    frames = _stream()
    det = LoopDetector(_config())
    base = [det.process(f) for f in frames]
    confs = sorted(d.confidence for d in base if d.accepted)
    cut = (confs[0] + confs[-1]) / 2
    gated = LoopDetector(_config(least=cut))
    for b, d in zip(base, map(gated.process, frames), strict=True):
        assert d.candidate_frame == b.candidate_frame and d.confidence == pytest.approx(b.confidence)
        if b.accepted:
            assert d.status is (Status.LOOP_DETECTED if b.confidence >= cut else Status.LOW_CONFIDENCE)
        else:
            assert d.status is b.status
    with pytest.raises(ConfigError, match="min_confidence"):
        preset("fast", {"min_confidence": -1.0})


def test_sequence_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match="query.sequence >= 2"):
        preset("fast", {"confidence": "sequence"})
    for bad in ({"sequence": -1}, {"sequence_tolerance": -1}):
        with pytest.raises(ConfigError, match="sequence"):
            preset("fast", {"query": bad})


@pytest.mark.parametrize("choice", [False, True])
def test_sequence_choice_takes_the_island_on_the_line_over_one_with_more_inliers(choice: bool) -> None:
    """Entry 9 is the query's own view (the most inliers), entry 3 the place 5 px off; the
    recent queries drew a line through 3 only. Ranked by inliers the loop is 9, by inliers
    times the sequence score it is 3; the islands cut short by ``must_beat`` stay consistent."""
    from stablecues.detection.decision import Island
    from stablecues.detection.detector import _Query

    pano = _wall(11)
    xs = [STEP * i for i in range(9)] + [5 + STEP * 3]
    query_cfg = {"sequence": 4, "sequence_choice": choice, "refine": 0, "viewpoint_steps": 0}
    det = LoopDetector(preset("fast", {"query": query_cfg, "confidence": "sequence", "similarity": False}))

    def view(i: int, x: int) -> Frame:
        image = np.ascontiguousarray(pano[:, x:x + 320])
        return Frame(index=i, name=f"{i}.png", timestamp=float(i), image=image)

    for i, x in enumerate(xs):
        det.store(view(i, x))
    query = view(20, xs[9])
    prep = det.preparer.prepare(query, None)
    found = _Query(islands=[Island(9, 9, 9, 1.0, 1.0), Island(3, 3, 3, 0.9, 0.9)], candidate=9)
    found.window = [_results({9: 1.0, 3: 1.0}), _results({2: 1.0}), _results({1: 1.0}), _results({0: 1.0})]
    status, result, checked = det._verify(prep, found)
    assert status is Status.LOOP_DETECTED and result is not None
    inliers = {c.frame: c.verification.n_inliers for c in checked}
    assert inliers[9] > 0
    if choice:
        assert found.candidate == 3 and result.n_inliers == inliers[3]
        assert inliers[3] * 1.0 > inliers[9] * 0.25  # entry 9's line holds the current query alone
    else:
        assert found.candidate == 9 and inliers[9] > inliers.get(3, 0)
    with pytest.raises(ConfigError, match="sequence_choice"):
        preset("fast", {"query": {"sequence_choice": True}})

"""The excluded window shrinks to the current run after a cut: a place left by a cut (a new
traversal, a jump between recordings) can be found again sooner than ``exclude_recent`` frames,
while a continuous stream keeps its whole window; a reopened map continues the same runs."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from stablecues import Frame, LoopDetector, preset
from stablecues.detection.decision import Status
from stablecues.errors import ConfigError

STEP = 40  # pixels between consecutive views of the wall (320-pixel views overlap by 7/8)


def _wall(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pano = np.full((240, 1000), 110, np.uint8)
    for _ in range(1200):
        x, y = int(rng.integers(0, 1000)), int(rng.integers(0, 240))
        cv2.rectangle(pano, (x, y), (x + int(rng.integers(3, 25)), y + int(rng.integers(3, 25))),
                      int(rng.integers(0, 256)), -1)
    return cv2.GaussianBlur(pano, (3, 3), 0)


def _stream() -> list[Frame]:
    """Frames 0-9 drive along a wall; frame 10 cuts back to where frame 0 was (5 px off) and
    frames 10-13 drive the first stretch again."""
    pano = _wall(7)
    xs = [STEP * i for i in range(10)] + [5 + STEP * i for i in range(4)]
    return [Frame(index=i, name=f"{i}.png", timestamp=float(i),
                  image=np.ascontiguousarray(pano[:, x:x + 320])) for i, x in enumerate(xs)]


def _config(run_break: float | None, score: float | None = 0.1) -> object:
    """Runs break at a drop to ``run_break`` of the median adjacent score, under ``score``
    (this wall's cut scores 0.052: a drive back along the same texture)."""
    return preset("fast", {"query": {"exclude_recent": 20, "run_break": run_break, "run_break_score": score,
                                     "exclude_recent_min": 3}, "similarity": False})


def _decisions(det: LoopDetector, frames: list[Frame]) -> list[tuple[object, ...]]:
    return [(d.status, d.candidate_frame) for d in map(det.process, frames)]


def test_a_cut_starts_a_run_and_the_place_before_it_is_found_again() -> None:
    frames = _stream()
    fixed = _decisions(LoopDetector(_config(None)), frames)
    runs = _decisions(LoopDetector(_config(0.4)), frames)
    # the continuous drive keeps its whole window either way: nothing older than 20 frames
    assert all(status is Status.CLOSE_MATCHES_ONLY for status, _ in fixed)
    assert runs[:10] == fixed[:10]
    # after the cut, the first stretch is proposed again and the revisits are verified loops
    found = {i: cand for i, (status, cand) in enumerate(runs) if status is Status.LOOP_DETECTED}
    assert set(found) >= {10, 11, 12}
    for i, cand in found.items():
        assert abs(cand - (i - 10)) <= 1  # the same stretch of wall


def test_a_drop_above_the_unrelated_level_is_no_cut() -> None:
    """A camera that starts moving drops its adjacent score sharply, but not to the level of
    unrelated frames: with the level under the cut's score there is no run, as with no runs."""
    frames = _stream()
    fixed = _decisions(LoopDetector(_config(None)), frames)
    assert _decisions(LoopDetector(_config(0.4, 0.04)), frames) == fixed


def test_a_reopened_map_continues_its_runs(tmp_path: Path) -> None:
    frames = _stream()
    whole = _decisions(LoopDetector(_config(0.4)), frames)
    path = tmp_path / "map.sqlite"
    with LoopDetector(_config(0.4), database=path) as det:
        first = _decisions(det, frames[:11])  # the cut (frame 10) is stored before the reopen
    with LoopDetector(_config(0.4), database=path) as det:
        rest = _decisions(det, frames[11:])
    assert first + rest == whole


def test_run_settings_are_checked() -> None:
    for bad in ({"run_break": 1.5}, {"run_break": 0.0}, {"run_history": 0}, {"exclude_recent_min": -1},
                {"run_break_score": 0.0}, {"run_break_score": 2.0}):
        try:
            preset("fast", {"query": bad})
        except ConfigError:
            continue
        raise AssertionError(f"{bad} was accepted")

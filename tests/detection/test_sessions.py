"""Sessions (``Frame.session``): a loop to another recording session's place is preferred over a
view of the session under way when both verify (``query.other_sessions_first``), a new session
starts a new run of frames, and the map keeps each entry's session (``Database`` sessions: a frame
without one takes the map's current session; ``LoopDetector.next_session`` names the next)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_run_break import STEP, _wall

from stablecues import Frame, LoopDetector, preset
from stablecues.detection.decision import Island, Status
from stablecues.detection.detector import _Query
from stablecues.errors import InputError

PANO = _wall(11)
#: entries 0-8 drive along the wall in session 0; entry 9, in session 1, is the query's own view
XS = [STEP * i for i in range(9)] + [5 + STEP * 3]
SESSIONS = [0] * 9 + [1]


def _view(i: int, x: int, session: int | None) -> Frame:
    return Frame(index=i, name=f"{i}.png", timestamp=float(i), image=np.ascontiguousarray(PANO[:, x:x + 320]),
                 session=session)


def _detector(first: bool, database: Path | None = None) -> LoopDetector:
    query = {"other_sessions_first": first, "refine": 0, "viewpoint_steps": 0}
    return LoopDetector(preset("fast", {"query": query, "similarity": False}),
                        database=None if database is None else str(database))


def _choose(det: LoopDetector, session: int) -> tuple[int, dict[int, int]]:
    """The loop of a query at the place of entries 3 and 9 (9 its very view, 3 five pixels off),
    both islands proposed, 9 first; and the inliers of what was verified (0: not verified)."""
    prep = det.preparer.prepare(_view(20, XS[9], session), None)
    found = _Query(islands=[Island(9, 9, 9, 1.0, 1.0), Island(3, 3, 3, 0.9, 0.9)], candidate=9)
    status, result, checked = det._verify(prep, found, session)
    assert status is Status.LOOP_DETECTED and result is not None
    return found.candidate, {c.frame: c.verification.n_inliers for c in checked}


@pytest.mark.parametrize("first", [True, False])
def test_the_other_session_wins_over_a_view_of_the_session_under_way(first: bool) -> None:
    """Entry 9 (the query's session, its very view) fits more matches than entry 3 (session 0,
    5 px off). With ``other_sessions_first`` entry 3 is verified first, accepted, and the loop;
    entry 9 is then not verified at all. Without it the most inliers win: entry 9."""
    det = _detector(first)
    for i, x in enumerate(XS):
        det.store(_view(i, x, SESSIONS[i]))
    loop, inliers = _choose(det, session=1)
    if first:
        assert loop == 3 and inliers[3] > 0 and 9 not in inliers
    else:
        assert loop == 9 and inliers[9] > inliers.get(3, 0)
    # a query of session 0 has no other session to prefer here but 1: entry 9 is the other one
    loop, _ = _choose(det, session=0)
    assert loop == 9


def test_a_single_stream_is_unchanged() -> None:
    """Every frame session 0: the option has nothing to prefer, the most inliers win."""
    det = _detector(True)
    for i, x in enumerate(XS):
        det.store(_view(i, x, 0))
    loop, inliers = _choose(det, session=0)
    assert loop == 9 and inliers[9] > inliers.get(3, 0)


def test_a_new_session_starts_a_run_and_a_reopened_map_keeps_the_sessions(tmp_path: Path) -> None:
    """The first frame of session 1 starts a run (the frames before it are another place); the
    sessions are stored with the entries (only where not 0), so a reopened map prefers the
    same island."""
    db = tmp_path / "map.sqlite"
    det = _detector(True, db)
    assert det.next_session == 0
    for i, x in enumerate(XS):
        det.store(_view(i, x, SESSIONS[i]))
        assert det._continuity[1] == (9 if i == 9 else 0)
    before = _choose(det, session=1)
    assert det.db.index.sessions().tolist() == SESSIONS  # the map's own session of each entry
    det.close()
    again = _detector(True, db)
    assert again.db.index.sessions().tolist() == SESSIONS and again._run_start == 9
    assert again.next_session == 2  # a third recording added to this map
    assert _choose(again, session=1) == before
    again.close()


def test_a_frame_without_a_session_takes_the_maps_current_one() -> None:
    """``Frame.session`` None: the map's session (0, then what ``Database.new_session`` gives)."""
    det = _detector(True)
    for i, x in enumerate(XS):
        if i == 9:
            assert det.db.new_session() == 1
        det.store(_view(i, x, None))
    assert det.db.index.sessions().tolist() == SESSIONS and det._continuity[1] == 9
    loop, _ = _choose(det, session=1)
    assert loop == 3


@pytest.mark.parametrize("bad", [-1, True, 1.5, "1"])
def test_a_session_that_is_not_an_integer_ge_0_is_refused(bad: object) -> None:
    with pytest.raises(InputError, match=r"frame 4: session must be None or an integer >= 0"):
        Frame(index=4, name="4.png", timestamp=0.0, image=np.zeros((8, 8), np.uint8), session=bad)  # type: ignore[arg-type]
    assert Frame(index=4, name="4.png", timestamp=0.0, image=np.zeros((8, 8), np.uint8),
                 session=np.int64(2)).session == 2

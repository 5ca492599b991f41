"""The loss funnel in the evaluation document: computed by evaluate_run, kept in its JSON, checked
when read back."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stablecues.errors import DatasetError
from stablecues.evaluation.evaluate import (
    evaluate_run,
    evaluation_funnel,
    load_evaluation,
    save_evaluation,
)
from stablecues.evaluation.funnel import Funnel, format_funnel, loss_funnel
from stablecues.groundtruth import GroundTruth
from stablecues.runs import RunWriter, load_run

N = 30


def _extra(cand: int, verified: bool) -> dict[str, object]:
    return {"results": [[cand, 0.5]], "islands": [[cand, cand, cand, 0.5]],
            "checked": [[cand, verified, 9, 20]]}


def _run(path: Path) -> Path:
    """Frames 20..29 revisit 0..9 (j = i - 20), one frame a second with a 5 s stop before frame 25;
    20, 22 and 24 accepted, 26 wrongly."""
    with RunWriter(path, {}, {"dataset": "x"}, stages=["total"]) as w:
        for i in range(N):
            t = float(i) if i < 25 else i + 5.0
            if i in (20, 22, 24):
                w.add(i, t, "loop_detected", i - 20, 10.0 + i, 1.0, True, {"total": 1.0},
                      _extra(i - 20, True))
            elif i == 26:
                w.add(i, t, "loop_detected", 15, 50.0, 1.0, True, {"total": 1.0}, _extra(15, True))
            elif i >= 20:
                w.add(i, t, "no_geometrical_consistency", i - 20, 1.0, 1.0, False, {"total": 1.0},
                      _extra(i - 20, False))
            else:
                w.add(i, t, "no_db_results", -1, float("nan"), float("nan"), False, {"total": 1.0}, {})
    return path


def _gt() -> GroundTruth:
    m = np.zeros((N, N), bool)
    for i in range(20, N):
        m[i, i - 20] = True
    return GroundTruth(m)


def test_evaluate_run_keeps_the_funnel(tmp_path: Path) -> None:
    run = load_run(_run(tmp_path / "run"))
    gt = _gt()
    ev, doc = evaluate_run(run, gt, protocol="exact", exclude=2)
    funnel = Funnel.from_dict(doc["funnel"])
    assert funnel == loss_funnel(run, gt.matrix, ev)
    # 26 accepted a wrong loop above every true one: R@100P is 0, the true ones are below threshold
    assert funnel.rows[26] == "wrong_accepted" and funnel.rows[20] == "below_threshold"
    assert funnel.counts["geometry"] == 6 and funnel.positives == ev.positives == 10
    assert funnel.counts["found"] == ev.tp_at_100p == 0
    # round trip through the JSON file
    save_evaluation(doc, tmp_path / "eval.json")
    back = load_evaluation(tmp_path / "eval.json")
    assert evaluation_funnel(back) == funnel
    assert "wrong_accepted" in format_funnel(funnel)


def test_funnel_honours_the_exclusion_in_seconds(tmp_path: Path) -> None:
    run = load_run(_run(tmp_path / "run"))
    # the loops of frames 20..24 are 20 s back, those of 25..29 25 s: 22 s leaves only the latter
    ev, doc = evaluate_run(run, _gt(), protocol="exact", exclude=2, exclude_s=22.0)
    funnel = Funnel.from_dict(doc["funnel"])
    assert ev.positives == funnel.positives == 5 and sorted(funnel.rows) == [25, 26, 27, 28, 29]


@pytest.mark.parametrize(
    ("funnel", "message"),
    [
        ([1, 2], "should be an object"),
        ({"counts": {"found": 1, "nowhere": 2}, "positives": 3}, "should map stages"),
        ({"counts": {"found": -1}, "positives": -1}, "should map stages"),
        ({"counts": {"found": 1, "geometry": 2}, "positives": 4}, "sum of its counts"),
        ({"counts": {"found": 1}, "positives": 1, "rows": {"x": "found"}}, "rows should map"),
        ({"counts": {"found": 1}, "positives": 1, "rows": {"3": "lost"}}, "rows should map"),
    ],
)
def test_malformed_funnel_is_refused(tmp_path: Path, funnel: object, message: str) -> None:
    _, doc = evaluate_run(load_run(_run(tmp_path / "run")), _gt(), protocol="exact")
    doc["funnel"] = funnel
    path = tmp_path / "eval_exact.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=message) as err:
        load_evaluation(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_older_evaluations_without_a_funnel_still_load(tmp_path: Path) -> None:
    _, doc = evaluate_run(load_run(_run(tmp_path / "run")), _gt(), protocol="exact")
    del doc["funnel"]
    save_evaluation(doc, tmp_path / "old.json")
    assert evaluation_funnel(load_evaluation(tmp_path / "old.json")) is None

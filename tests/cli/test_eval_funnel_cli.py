"""``stablecues eval`` prints the loss funnel and keeps it in its JSON; ``stablecues report`` shows it
and every accepted loop; ``eval --help`` prints a plain percent sign."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from stablecues.cli.main import main
from stablecues.evaluation.funnel import STAGES
from stablecues.groundtruth import save_ground_truth
from stablecues.runs import RunWriter

N = 50


def _run(root: Path) -> Path:
    """Frames 40..49 revisit 0..9; 40..44 accepted (44 at the wrong place), 45..49 lost at geometry."""
    gt = np.zeros((N, N), bool)
    for i in range(40, N):
        gt[i, i - 40] = True
    gt_file = save_ground_truth(root / "loops.npy", gt)
    meta = {"dataset": str(root / "absent"), "format": "folder", "ground_truth": str(gt_file), "exclude": 5}
    with RunWriter(root / "run", {"verification": {"method": "triangles"}}, meta, stages=["total"]) as w:
        for i in range(N):
            if i < 40:
                w.add(i, i / 10, "low_scores", -1, math.nan, math.nan, False, {"total": 1.0})
                continue
            cand = 20 if i == 44 else i - 40
            ok = i < 45
            extra = {"results": [[cand, 0.5]], "islands": [[cand, cand, cand, 0.5]],
                     "checked": [[cand, ok, 20, 30]], "verifier": "triangles", "reason": "r"}
            w.add(i, i / 10, "loop_detected" if ok else "no_geometrical_consistency", cand, 100.0 - i,
                  1.0, ok, {"total": 1.0}, extra)
    return root / "run"


def test_eval_prints_and_writes_the_funnel(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _run(tmp_path)
    assert main(["eval", str(run), "--json", str(tmp_path / "e.json")]) == 0
    text = capsys.readouterr().out
    assert "where the true loop was lost" in text and "positive queries" in text
    for stage in STAGES:
        assert stage in text
    doc = json.loads((tmp_path / "e.json").read_text())
    funnel = doc["funnel"]
    assert funnel["positives"] == doc["positives"] == 10
    assert funnel["counts"]["geometry"] == 5 and funnel["counts"]["wrong_accepted"] == 1
    assert funnel["counts"]["found"] == doc["tp_at_100p"] == 4
    assert funnel["rows"]["44"] == "wrong_accepted" and funnel["rows"]["45"] == "geometry"
    assert json.loads((run / "eval_exact.json").read_text())["funnel"] == funnel


def test_eval_help_has_a_plain_percent(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "100 % precision" in text and "%%" not in text and "loss funnel" in text


def test_report_shows_funnel_and_every_loop(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _run(tmp_path)
    assert main(["eval", str(run)]) == 0
    out = tmp_path / "page.html"
    assert main(["report", str(run), "--out", str(out), "--max-loops", "3"]) == 0
    assert f"written: {out}" in capsys.readouterr().out
    text = out.read_text()
    assert "Loss funnel" in text and "Accepted loops (5)" in text
    assert text.count("data-verdict='true'") == 4 and text.count("data-verdict='false'") == 1
    assert text.count("class='nopic'") == 5  # the dataset is absent and the run kept no picture
    assert main(["report", str(run), "--out", str(out), "--max-loops", "-1"]) == 1
    assert "max_loops" in capsys.readouterr().err

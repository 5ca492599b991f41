"""A tiny ``stablecues demo`` end to end: generation, three presets, evaluation, report."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from stablecues.cli.main import main


def test_tiny_demo_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--frames", "60", "--width", "192", "--height", "144",
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "R@100P" in text and "report:" in text
    assert "semantic masks from" in text  # says where the masks came from
    report = (out / "report.html").read_text()
    assert "<h2>Summary</h2>" in report and "semantics" in report
    for name in ("paper", "bow", "default"):
        doc = json.loads((out / "runs" / name / "eval_tolerance_2.json").read_text())
        assert 0.0 <= doc["recall_at_100p"] <= 1.0 and doc["positives"] > 0
        assert (out / "runs" / name / "similarity.npy").exists()
    assert (out / "sequence" / "loops.npy").exists()

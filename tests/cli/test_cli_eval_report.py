"""The eval, results and report commands end to end on fake run directories made with RunWriter."""

from __future__ import annotations

import json
import logging
import math
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.cli.main import main
from stablecues.groundtruth import save_ground_truth
from stablecues.runs import RunWriter

N = 160
EXCLUDE = 20


def _ground_truth() -> np.ndarray:
    """Frames 110..159 revisit frames 10..59 (loop with j = i - 100, +-1)."""
    gt = np.zeros((N, N), bool)
    for i in range(110, N):
        for j in (i - 101, i - 100, i - 99):
            gt[i, j] = True
    return gt


def _fake_run(path: Path, gt: np.ndarray, noise: float, seed: int, gt_file: Path | None) -> None:
    rng = np.random.default_rng(seed)
    sim = np.tril(rng.random((N, N)) * noise, -1)
    sim[gt] += 0.3 + 0.4 * rng.random(int(gt.sum()))
    stages = ["features", "bow_query", "verification"]
    meta = {"dataset": "/fake", "format": "folder", "preset": f"fake-{seed}", "exclude": EXCLUDE}
    meta["ground_truth"] = None if gt_file is None else str(gt_file)
    with RunWriter(path, {"noise": noise}, meta, stages=stages) as w:
        for i in range(N):
            limit = i - EXCLUDE - 1
            stage = {"features": 10 + rng.random(), "bow_query": 2 + rng.random()}
            if limit < 0:
                w.add(i, i / 10, "no_results", -1, math.nan, math.nan, False, stage)
                continue
            j = int(np.argmax(sim[i, : limit + 1]))
            s = float(sim[i, j])
            if s < 0.3:
                w.add(i, i / 10, "low_score", j, s, s, False, stage)
                continue
            stage["verification"] = 5 + rng.random()
            ok = s > 0.45
            w.add(i, i / 10, "accepted" if ok else "geometry_rejected", j, s, s * 0.1, ok, stage)
            if ok and i % 20 == 0:
                pic = np.zeros((60, 160, 3), np.uint8)
                cv2.line(pic, (10, 10), (150, 50), (0, 255, 0), 2)
                w.add_match_picture(f"loop_{i:04d}_{j:04d}", pic)
        w.set_similarity(sim)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    root = tmp_path_factory.mktemp("runs")
    gt = _ground_truth()
    gt_file = save_ground_truth(root / "loops.npy", gt)
    _fake_run(root / "run_a", gt, 0.4, 1, gt_file)
    _fake_run(root / "run_b", gt, 0.8, 2, None)
    return root / "run_a", root / "run_b", gt_file


def test_eval_writes_json(
    runs: tuple[Path, Path, Path], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    run_a, run_b, gt_file = runs
    out = tmp_path / "a.json"
    assert main(["eval", str(run_a), "--protocol", "exact", "--json", str(out)]) == 0  # GT from meta.json
    text = capsys.readouterr().out
    assert "R@100P" in text and "bow_query" in text
    doc = json.loads(out.read_text())
    for key in ("recall_at_100p", "auc", "tp", "fp", "fn", "positives", "protocol", "tolerance", "exclude"):
        assert key in doc
    assert doc["gt_file"] == str(gt_file) and len(doc["gt_sha256"]) == 64
    assert doc["exclude"] == EXCLUDE and doc["positives"] == 50
    assert set(doc["timing_ms"]["features"]) >= {"mean", "std", "min", "max"}
    assert len(doc["pr_curve"]["recall"]) == len(doc["pr_curve"]["thresholds"]) > 0
    assert 0 < doc["recall_at_100p"] <= 1 and (run_a / "eval_exact.json").is_file()
    assert main(["eval", str(run_a), "--protocol", "ibow", "--tolerance", "2", "--detections", "all"]) == 0
    assert (run_a / "eval_ibow_2.json").is_file()
    assert (
        main(["eval", str(run_b), "--gt", str(gt_file), "--protocol", "tolerance", "--tolerance", "0"]) == 0
    )
    assert main(["eval", str(run_b), "--gt", str(gt_file)]) == 0
    capsys.readouterr()
    # no ground truth recorded and none given: one clear line, exit 1
    shutil.copytree(run_b, tmp_path / "copy")
    meta = json.loads((tmp_path / "copy" / "meta.json").read_text())
    assert meta["ground_truth"] is None
    assert main(["eval", str(tmp_path / "copy")]) == 1
    assert "--gt" in capsys.readouterr().err


def test_results_table(
    runs: tuple[Path, Path, Path], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    run_a, run_b, _ = runs
    assert main(["eval", str(run_a)]) == 0
    capsys.readouterr()
    out = tmp_path / "rows.json"
    assert (
        main(["results", str(run_a), str(run_b), "--json", str(out), "--csv", str(tmp_path / "r.csv")]) == 0
    )
    text = capsys.readouterr().out
    assert "R@100P" in text and "fake-1" in text
    rows = json.loads(out.read_text())
    assert {r["protocol"] for r in rows} >= {"exact"}
    assert (tmp_path / "r.csv").read_text().startswith("run,preset,protocol")


def test_report_html(runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    run_a, run_b, _ = runs
    assert main(["eval", str(run_a)]) == 0 and main(["eval", str(run_b), "--gt", str(runs[2])]) == 0
    html_file = tmp_path / "report.html"
    assert main(["report", str(run_a), str(run_b), "--out", str(html_file)]) == 0
    text = html_file.read_text()
    assert text.count("data:image/png;base64,") >= 6  # PR, 2x matrices, 2x status, match pictures
    assert "Precision-recall" in text and "bow_query" in text and "geometry_rejected" in text
    # the summary says in words where each run lost its loops, from its funnel (issue 35)
    assert "Where the loops were lost" in text and re.search(r"run_a</b> found \d+ of 50 loops", text)
    assert 'src="http' not in text and "<script" not in text  # self-contained, static


def test_report_says_which_runs_it_cannot_score(
    runs: tuple[Path, Path, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A run never evaluated, or evaluated under another protocol than the one shown, was listed
    with "-" under its loops and no word (issue 35): its row says why and a warning names it."""
    run_a, run_b, gt_file = runs
    fresh, other = tmp_path / "fresh", tmp_path / "other"
    shutil.copytree(run_b, fresh)
    shutil.copytree(run_b, other)
    for d in (fresh, other):
        for f in d.glob("eval_*.json"):
            f.unlink()
    assert main(["eval", str(run_a)]) == 0
    tolerant = ["--protocol", "tolerance", "--tolerance", "2"]
    assert main(["eval", str(other), "--gt", str(gt_file), *tolerant]) == 0
    caplog.set_level(logging.WARNING)
    html_file = tmp_path / "report.html"
    three = [str(run_a), str(fresh), str(other)]
    assert main(["report", *three, "--protocol", "exact", "--out", str(html_file)]) == 0
    text = html_file.read_text()
    assert ">not evaluated<" in text and "not evaluated under exact (only tolerance +-2)" in text
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(str(fresh) in m and "not evaluated;" in m for m in warned)
    assert any(str(other) in m and "not evaluated under exact" in m for m in warned)
    assert not any(str(run_a) in m for m in warned)
    assert "1st apart" in text and "first frame" in text  # the warm-up kept out of ms/frame


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def test_report_renders_in_headless_chromium(runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    browser = _chromium()
    if browser is None:
        pytest.skip("chromium is not installed (apt-get install -y chromium)")
    run_a, run_b, gt_file = runs
    assert main(["eval", str(run_a)]) == 0
    html_file = tmp_path / "report.html"
    assert main(["report", str(run_a), str(run_b), "--out", str(html_file)]) == 0
    shot = tmp_path / "shot.png"
    with tempfile.TemporaryDirectory() as profile:
        cmd = [
            browser,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            f"--user-data-dir={profile}",
            f"--screenshot={shot}",
            "--window-size=1200,2000",
            html_file.resolve().as_uri(),
        ]
        subprocess.run(cmd, check=False, capture_output=True, timeout=120)
    assert shot.is_file(), "chromium wrote no screenshot"
    image = cv2.imread(str(shot), cv2.IMREAD_GRAYSCALE)
    assert image is not None and image.shape == (2000, 1200)
    # non-blank: a white page with dark text, plots and tables
    assert image.std() > 20 and (image < 100).mean() > 0.01 and (image > 240).mean() > 0.3


def test_eval_interleaved_release_view_from_meta(tmp_path: Path) -> None:
    full = np.zeros((8, 8), bool)
    full[6, 0] = full[7, 1] = True  # left 3 - left 0, right 3 - right 0
    save_ground_truth(tmp_path / "gt.npy", full)
    meta = {"ground_truth": str(tmp_path / "gt.npy"), "gt_view": "left", "dataset_frames": 4, "preset": "x"}
    with RunWriter(tmp_path / "run", {}, meta) as w:
        for i in range(4):
            w.add(
                i, float(i), "accepted" if i == 3 else "no_results", 0 if i == 3 else -1, 0.9, 0.9, i == 3, {}
            )
    assert main(["eval", str(tmp_path / "run")]) == 0
    doc = json.loads((tmp_path / "run" / "eval_exact.json").read_text())
    assert doc["gt_view"] == "left" and doc["gt_frames"] == 4 and (doc["tp"], doc["fp"]) == (1, 0)
    assert main(["report", str(tmp_path / "run"), "--out", str(tmp_path / "r.html")]) == 0
    assert "detections not overlaid" not in (tmp_path / "r.html").read_text()

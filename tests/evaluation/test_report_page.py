"""The HTML report: every accepted loop listed and marked, the verifier named, the loss funnel,
readable PR curves, pictures beside the page; rendered in headless Chromium when it is there."""

from __future__ import annotations

import html
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.errors import ConfigError
from stablecues.evaluation import evaluate_run, load_ground_truth, load_run
from stablecues.evaluation.evaluate import eval_file_name, save_evaluation
from stablecues.evaluation.plots import full_precision_point, pr_zoom_limits
from stablecues.evaluation.report import build_report
from stablecues.groundtruth import save_ground_truth
from stablecues.runs import RunWriter

N = 40
EXCLUDE = 5
# accepted loops: frame -> (candidate, score, verifier that decided, true in the ground truth)
ACCEPTED = {
    22: (2, 12.0, "triangles", False),  # frame 22 has no loop at all
    30: (5, 50.0, "triangles", True),
    32: (7, 40.0, "pnp", True),  # PnP stood in for the configured triangle check
    35: (20, 45.0, "triangles", False),  # a positive query, the wrong place
    38: (13, 30.0, "triangles", True),
}
STORED = (30, 5)  # the one loop with a match picture kept by the run
FIGURE_RE = re.compile(
    r"<figure class='loop (\w+)' id='r(\d+)-loop-(\d+)' data-query='(\d+)' "
    r"data-candidate='(\d+)' data-verdict='(\w+)'>(.*?)</figure>",
    re.S,
)


def _ground_truth() -> np.ndarray:
    """Frames 30..39 revisit frames 5..14 (j = i - 25)."""
    gt = np.zeros((N, N), bool)
    for i in range(30, N):
        gt[i, i - 25] = True
    return gt


def make_run(root: Path, *, with_dataset: bool = True) -> Path:
    """A run of 40 frames over a folder of images, evaluated (exact protocol); returns its directory."""
    data = root / "data"
    (data / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(N):
        image = np.full((48, 64, 3), (i * 6, 120, 255 - i * 6), np.uint8)
        image[rng.random((48, 64)) < 0.1] = 0
        cv2.imwrite(str(data / "images" / f"{i:04d}.png"), image)
    gt_file = save_ground_truth(data / "loops.npy", _ground_truth())
    meta = {"dataset": str(data), "format": "folder", "dataset_frames": N, "ground_truth": str(gt_file),
            "preset": "test", "exclude": EXCLUDE}
    config = {"verification": {"method": "triangles"}}
    run_dir = root / "run"
    with RunWriter(run_dir, config, meta, stages=["total"]) as w:
        for i in range(N):
            if i in ACCEPTED:
                cand, score, verifier, _ = ACCEPTED[i]
                extra = {"results": [[cand, 0.5]], "islands": [[cand, cand, cand, 0.5]],
                         "checked": [[cand, True, 30, 40]], "verifier": verifier,
                         "reason": f"{verifier} said yes ({i})", "inliers": 30}
                w.add(i, i / 10, "loop_detected", cand, score, score, True, {"total": 1.0}, extra)
            elif i >= 30:  # positives lost at the geometry stage
                extra = {"results": [[i - 25, 0.5]], "islands": [[i - 25, i - 25, i - 25, 0.5]],
                         "checked": [[i - 25, False, 3, 40]]}
                w.add(i, i / 10, "no_geometrical_consistency", i - 25, 1.0, 1.0, False, {"total": 1.0}, extra)
            else:
                w.add(i, i / 10, "close_matches_only", -1, float("nan"), float("nan"), False, {"total": 1.0})
        picture = np.zeros((60, 200, 3), np.uint8)
        cv2.line(picture, (10, 10), (190, 50), (0, 255, 0), 2)
        w.add_match_picture(f"loop_{STORED[0]:05d}_{STORED[1]:05d}", picture)
    run = load_run(run_dir)
    _, doc = evaluate_run(run, load_ground_truth(gt_file), protocol="exact", exclude=EXCLUDE)
    save_evaluation(doc, run_dir / eval_file_name("exact", 0))
    if not with_dataset:
        shutil.rmtree(data / "images")
    return run_dir


def _figures(text: str) -> dict[int, tuple[str, int, str, str]]:
    """query frame -> (class, candidate, verdict, inner html) of each loop card."""
    out = {}
    for cls, _, fid, query, cand, verdict, inner in FIGURE_RE.findall(text):
        assert fid == query
        out[int(query)] = (cls, int(cand), verdict, inner)
    return out


def test_every_accepted_loop_is_listed_marked_and_pictured(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path)
    page = build_report([load_run(run_dir)], tmp_path / "out" / "report.html")
    text = page.read_text()
    cards = _figures(text)
    assert sorted(cards) == sorted(ACCEPTED)
    assert "Accepted loops (5)" in text and "accepted loops (5)" in text  # heading and contents
    for frame, (cand, _, verifier, true) in ACCEPTED.items():
        cls, card_cand, verdict, inner = cards[frame]
        assert card_cand == cand and cls == verdict == ("true" if true else "false")
        inner = html.unescape(inner)
        assert f"verifier: <b>{verifier}" in inner and f"{verifier} said yes ({frame})" in inner
        assert ("\u2713 true" if true else "\u2717 false") in inner
    assert "pnp (stood in for triangles)" in html.unescape(cards[32][3])
    assert "ground truth of frame 22: no loop" in cards[22][3]
    assert "ground truth of frame 35: loops with 10" in cards[35][3]
    # pictures: beside the page, linked relatively, one thumbnail and one full size per loop
    files = tmp_path / "out" / "report_files" / "run1"
    for frame, (cand, *_) in ACCEPTED.items():
        name = f"loop_{frame:05d}_{cand:05d}"
        assert (files / f"{name}_thumb.jpg").is_file() and (files / f"{name}.jpg").is_file()
        assert f"src='report_files/run1/{name}_thumb.jpg'" in text
        assert f"id='r1-view-{frame}'" in text and f"href='#r1-view-{frame}'" in text  # click to enlarge
    thumb = cv2.imread(str(files / "loop_00030_00005_thumb.jpg"))
    full = cv2.imread(str(files / "loop_00030_00005.jpg"))
    assert thumb.shape[1] == 360 and full.shape[1] == 200 + 10  # the stored picture, framed
    # the verdict is on the picture too: a green banner for a true loop, a red one for a false
    false = cv2.imread(str(files / "loop_00022_00002.jpg"))
    assert np.allclose(full[-40, 2], (55, 127, 26), atol=40)  # the frame's left edge
    assert np.allclose(false[-30, 2], (40, 40, 198), atol=40)
    # previous / next browse the enlarged pictures in frame order
    assert "<a href='#r1-view-30'>\u2039 previous</a>" in text.split("id='r1-view-32'")[1].split("</div>")[0]
    assert 'src="http' not in text and "src='http" not in text and "<script" not in text


def test_funnel_and_pr_sections(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path)
    text = build_report([load_run(run_dir)], tmp_path / "report.html").read_text()
    assert "id='r1-funnel'" in text and "Loss funnel" in text
    funnel = text.split("id='r1-funnel'")[1].split("<h3")[0]
    # positives 30..39: 30, 32, 38 found or below the threshold, 35 wrong, the other six geometry
    assert "<td class=\"l\">geometry</td>" in funnel and "<td class=\"\">6</td>" in funnel
    assert "<td class=\"l\">wrong_accepted</td>" in funnel
    assert "1 loop(s) were accepted on queries that have no loop" in funnel  # frame 22
    assert "zoom on where they are" in text
    assert text.count("data:image/png;base64,") == 4  # PR, funnel, matrices, statuses


def test_pictures_from_the_run_only_when_the_dataset_is_gone(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path, with_dataset=False)
    text = build_report([load_run(run_dir)], tmp_path / "report.html").read_text()
    cards = _figures(text)
    assert sorted(cards) == sorted(ACCEPTED)  # every loop still listed and marked
    assert "<img" in cards[30][3] and "no picture" not in cards[30][3]  # the stored match picture
    assert all("no picture" in cards[f][3] for f in ACCEPTED if f != 30)
    assert "4 loop(s) without a picture" in text and "not opened" in text


def test_max_loops_limits_pictures_not_the_list(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path)
    text = build_report([load_run(run_dir)], tmp_path / "report.html", max_loops=2).read_text()
    cards = _figures(text)
    assert len(cards) == 5 and sum("<img" in c[3] for c in cards.values()) == 2
    assert "<img" in cards[22][3] and "<img" in cards[38][3]  # spread: first and last
    with pytest.raises(ConfigError, match="max_loops"):
        build_report([load_run(run_dir)], tmp_path / "report.html", max_loops=-1)


def test_picture_folder_that_is_a_link_is_refused(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path)
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "report_files").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(ConfigError, match="symbolic link"):
        build_report([load_run(run_dir)], tmp_path / "report.html")
    assert not any((tmp_path / "elsewhere").iterdir())


def test_unevaluated_run_lists_loops_without_marks(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path)
    (run_dir / "eval_exact.json").unlink()
    text = build_report([load_run(run_dir)], tmp_path / "report.html").read_text()
    cards = _figures(text)
    assert {c[2] for c in cards.values()} == {"unknown"} and "Loss funnel" not in text


def test_pr_zoom_limits() -> None:
    flat = [("a", np.array([0.1, 0.4]), np.array([1.0, 1.0])), ("b", np.array([0.2]), np.array([1.0]))]
    assert pr_zoom_limits(flat) == pytest.approx((0.44, 0.9))
    low = [("a", np.array([0.5, 1.0]), np.array([1.0, 0.5]))]
    assert pr_zoom_limits(low) == pytest.approx((1.0, 0.44))
    assert full_precision_point(np.array([0.1, 0.3, 0.4]), np.array([1.0, 1.0, 0.8])) == 0.3
    assert full_precision_point(np.array([0.1]), np.array([0.5])) == 0.0


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def _screenshot(browser: str, url: str, out: Path, size: tuple[int, int]) -> np.ndarray:
    with tempfile.TemporaryDirectory() as profile:
        cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
               "--disable-background-networking", "--disable-component-update", "--disable-sync",
               f"--user-data-dir={profile}", f"--screenshot={out}", f"--window-size={size[0]},{size[1]}", url]
        subprocess.run(cmd, check=False, capture_output=True, timeout=120)
    assert out.is_file(), "chromium wrote no screenshot"
    image = cv2.imread(str(out))
    assert image is not None and image.shape == (size[1], size[0], 3)
    return image


def test_report_in_headless_chromium(tmp_path: Path) -> None:
    browser = _chromium()
    if browser is None:
        pytest.skip("chromium is not installed (apt-get install -y chromium)")
    run_dir = make_run(tmp_path)
    page = build_report([load_run(run_dir)], tmp_path / "report.html").resolve()
    shot = _screenshot(browser, page.as_uri(), tmp_path / "page.png", (1200, 6000))
    grey = cv2.cvtColor(shot, cv2.COLOR_BGR2GRAY)
    # a white page with dark text, plots and tables, all the way down to the loops
    assert grey.std() > 20 and (grey < 100).mean() > 0.01 and (grey > 240).mean() > 0.3
    assert (grey[3000:] < 240).mean() > 0.02  # the lower half is not blank
    # the true / false marks are drawn: green and red borders of the loop cards
    green = np.all(np.abs(shot.astype(int) - (55, 127, 26)) < 30, axis=2).sum()
    red = np.all(np.abs(shot.astype(int) - (40, 40, 198)) < 30, axis=2).sum()
    assert green > 500 and red > 500
    # clicking a thumbnail (its link target) shows the picture enlarged over a dark page
    big = _screenshot(browser, page.as_uri() + "#r1-view-35", tmp_path / "big.png", (1200, 800))
    big_grey = cv2.cvtColor(big, cv2.COLOR_BGR2GRAY)
    assert np.median(big_grey) < 60 < np.median(grey)
    assert np.all(np.abs(big.astype(int) - (40, 40, 198)) < 30, axis=2).sum() > 2000  # the red banner

"""The README's commands are the ones CI runs, and its Python snippets run as written."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import REPO, shared_path


def test_ci_runs_the_readme_test_command() -> None:
    readme = (REPO / "README.md").read_text()
    ci = (REPO / ".ci" / "run").read_text()
    test_lines = [line for line in readme.splitlines() if "pytest" in line and "pip install" in line]
    assert test_lines, "README.md has no install-and-test command"
    assert test_lines[0].strip() in ci


def test_readme_shows_the_demo() -> None:
    assert "stablecues demo" in (REPO / "README.md").read_text()


README_LIMIT = 12_000  # characters: a user's guide read in minutes; the rest lives in docs/


def test_readme_stays_short() -> None:
    assert len((REPO / "README.md").read_text(encoding="utf-8")) <= README_LIMIT


def test_readme_results_table_is_the_bench_figures() -> None:
    """The README's results table is what ``scripts/readme_results.py`` prints from
    ``bench/results/`` (its figures, row by row; the date line from git may differ)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("readme_results", REPO / "scripts" / "readme_results.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    rows = [line for line in module.table().splitlines() if line.startswith("|")]
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert "\n".join(rows) in readme
    assert re.search(r"measured up to \d{4}-\d\d-\d\d on a shared 2-core", readme)


# --- the SLAM-loop snippets, executed exactly as the README writes them --------------------------

def slam_snippets() -> list[str]:
    """The ```python blocks of the README's "In a SLAM loop" section, verbatim."""
    readme = (REPO / "README.md").read_text()
    section = readme.split("## In a SLAM loop\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, re.DOTALL)


def test_the_slam_section_has_both_snippets() -> None:
    blocks = slam_snippets()
    assert len(blocks) == 2
    assert "calibration=" in blocks[0] and "right=right" in blocks[0]
    assert "points3d=xyz" in blocks[1] and "features=(keypoints, descriptors)" in blocks[1]


def euroc_revisits() -> list[tuple[np.ndarray, np.ndarray]]:
    """A real EuRoC stereo stream with two revisits: loop pairs 0 and 2, the 19 frames of
    V1_01_micro, then loop pairs 1 and 3 (frames 21 and 22 re-view the places of frames 0 and 1
    from other poses; the default preset proposes only entries 20 or more frames old)."""
    root = shared_path("euroc")

    def grey(path: Path) -> np.ndarray:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        assert image is not None, path
        return image

    def pair(i: int) -> tuple[np.ndarray, np.ndarray]:
        folder = root / "loop_pairs"
        return grey(folder / f"left_img_{i}.png"), grey(folder / f"right_img_{i}.png")

    cam0 = root / "V1_01_micro" / "mav0" / "cam0" / "data"
    micro = [(grey(p), grey(cam0.parents[1] / "cam1" / "data" / p.name)) for p in sorted(cam0.glob("*.png"))]
    return [pair(0), pair(2), *micro, pair(1), pair(3)]


def run_snippet(code: str, namespace: dict[str, object], capsys: pytest.CaptureFixture[str]) -> list[str]:
    """Execute a README block as written; the lines it printed."""
    exec(compile(code, "README.md", "exec"), namespace)
    return capsys.readouterr().out.splitlines()


def loops_printed(lines: list[str]) -> dict[int, tuple[int, str]]:
    """``frame -> (candidate frame, the rest of the line)`` of "i closes a loop with j ..." lines."""
    out = {}
    for line in lines:
        m = re.match(r"(\d+) closes a loop with (\d+) (.*)", line)
        assert m, line
        out[int(m[1])] = (int(m[2]), m[3])
    return out


def translation_of(text: str) -> np.ndarray:
    return np.array([float(v) for v in re.findall(r"-?\d+(?:\.\d*)?", text)[:3]])


def test_readme_stereo_snippet_runs_on_real_data(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    frames = euroc_revisits()
    shutil.copy(shared_path("calibration", "EuRoC_stereo.yaml"), tmp_path / "cam.yaml")
    monkeypatch.chdir(tmp_path)
    stream = [(left, right, 0.05 * i) for i, (left, right) in enumerate(frames)]
    first: dict[str, object] = {"stream": stream}
    loops = loops_printed(run_snippet(slam_snippets()[0], first, capsys))
    assert set(loops) == {21, 22} and loops[21][0] == 0 and loops[22][0] == 1
    for _, rest in loops.values():  # the EuRoC revisits are decimetres apart
        assert rest.endswith(" m") and 0.1 < np.linalg.norm(translation_of(rest)) < 1.5
    assert (tmp_path / "map.sqlite").is_file()
    # run again (the first program ended: its detector closed): the map reopens and the frames
    # are numbered on after the first run's, so a candidate names one frame, of one run
    first["detector"].close()  # type: ignore[attr-defined]
    again = loops_printed(run_snippet(slam_snippets()[0], {"stream": stream}, capsys))
    n = len(stream)
    assert again and min(again) >= n and any(cand < n for cand, _ in again.values()), again


def test_readme_map_point_snippet_runs_on_real_data(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A SLAM system's keyframes: its own ORB keypoints (OpenCV's), and one map point per
    keypoint from its stereo depth (here the library's stereo lifter stands in for the SLAM
    system's map); the detector gets no calibration, so the pose comes from the map points."""
    from stablecues.geometry import StereoLifter, load_calibration
    from stablecues.types import Features

    calib = load_calibration(shared_path("calibration", "EuRoC_stereo.yaml"))
    lifter = StereoLifter(calib)
    orb = cv2.ORB_create(1000)
    keyframes = []
    for i, (left, right) in enumerate(euroc_revisits()):
        keypoints, descriptors = orb.detectAndCompute(left, None)
        features = Features.from_cv2(keypoints, descriptors, image_size=(left.shape[1], left.shape[0]))
        xyz = lifter.lift(features, left, right).xyz  # NaN where stereo found no depth
        keyframes.append((left, keypoints, descriptors, xyz, 0.05 * i))
    monkeypatch.chdir(tmp_path)
    loops = loops_printed(run_snippet(slam_snippets()[1], {"keyframes": keyframes}, capsys))
    assert set(loops) == {21, 22} and loops[21][0] == 0 and loops[22][0] == 1
    for _, rest in loops.values():
        assert 0.1 < np.linalg.norm(translation_of(rest)) < 1.5

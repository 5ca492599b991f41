"""The scripts of examples/ run on the real data and find the known revisits with sane poses."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from conftest import REPO, shared_path


def example(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"example_{name}", REPO / "examples" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(name: str, args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str], str]:
    code = example(name).main(args)
    out = capsys.readouterr()
    return code, out.out.splitlines(), out.err


def kinect_sources() -> list[str]:
    folder = shared_path("rgbd_kinect5")
    return [f"{folder / 'color' / f'{i}.png'},{folder / 'depth' / f'{i}.pgm'}" for i in range(1, 6)]


KINECT = ["--intrinsics", "518", "519", "325.5", "253.5", "--depth-scale", "1000", "--exclude-recent", "1"]


def errors_of(lines: list[str]) -> list[tuple[float, float]]:
    """(translation error m, rotation error deg) of every printed loop."""
    out = []
    for line in lines:
        if line.startswith("loop:"):
            m = re.search(r"error ([\d.]+) m, ([\d.]+) deg", line)
            assert m, line
            out.append((float(m[1]), float(m[2])))
    return out


def test_stereo_example_finds_the_euroc_revisits(capsys: pytest.CaptureFixture[str]) -> None:
    pairs = shared_path("euroc", "loop_pairs")

    def pair(i: int) -> str:
        return f"{pairs / f'left_img_{i}.png'},{pairs / f'right_img_{i}.png'}"

    code, lines, _ = run("stereo_euroc", [
        "--calib", str(shared_path("calibration", "EuRoC_stereo.yaml")),
        pair(0), pair(2), str(shared_path("euroc", "V1_01_micro")), pair(1), pair(3),
    ], capsys)
    assert code == 0
    loops = [line for line in lines if line.startswith("loop:")]
    assert len(loops) == 2 and lines[-1].startswith("23 frames, 2 loops")
    assert loops[0].startswith("loop: frame 21 (left_img_1.png) -> frame 0 (left_img_0.png)")
    assert loops[1].startswith("loop: frame 22 (left_img_3.png) -> frame 1 (left_img_2.png)")
    for line in loops:  # the EuRoC revisits are decimetres apart
        m = re.search(r"\(([\d.]+) m\)", line)
        assert m and 0.1 < float(m[1]) < 1.5, line


def test_rgbd_example_poses_match_the_ground_truth(capsys: pytest.CaptureFixture[str]) -> None:
    poses = str(shared_path("rgbd_kinect5", "pose.txt"))
    code, lines, _ = run("rgbd_tum", [*KINECT, "--poses", poses, *kinect_sources()], capsys)
    assert code == 0 and lines[-1].startswith("5 frames, ")
    errors = errors_of(lines)
    assert len(errors) >= 2 and all(t < 0.2 and r < 3.0 for t, r in errors), lines


def test_rgbd_example_takes_a_tum_camera_name(capsys: pytest.CaptureFixture[str]) -> None:
    folder = shared_path("tum", "fr2_rgbd_pair")
    sources = [f"{folder / f'{i}.png'},{folder / f'{i}_depth.png'}" for i in (1, 2)]
    code, lines, _ = run("rgbd_tum", ["--calib", "fr2", "--exclude-recent", "0", *sources], capsys)
    assert code == 0 and lines[0].startswith("loop: frame 1 -> frame 0, t = ")
    t = np.array([float(v) for v in re.findall(r"-?\d+\.\d+", lines[0].split("t = ")[1])[:3]])
    assert 0.01 < np.linalg.norm(t) < 0.5  # consecutive frames of a hand-held camera


def test_map_point_example_needs_no_calibration(capsys: pytest.CaptureFixture[str]) -> None:
    poses = str(shared_path("rgbd_kinect5", "pose.txt"))
    code, lines, _ = run("slam_map_points", [*KINECT, "--poses", poses, *kinect_sources()], capsys)
    assert code == 0 and lines[-1].startswith("5 keyframes, ")
    errors = errors_of(lines)
    assert len(errors) >= 2 and all(t < 0.2 and r < 3.0 for t, r in errors), lines


def test_examples_report_bad_input_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run("rgbd_tum", ["--calib", str(tmp_path / "none.yaml"), "a.png,b.png"], capsys)
    assert code == 1 and err.strip() == f"error: calibration file {tmp_path / 'none.yaml'} does not exist"
    with pytest.raises(SystemExit, match="cannot read image"):
        example("stereo_euroc").main(["--calib", "fr2", f"{tmp_path / 'l.png'},{tmp_path / 'r.png'}"])


def test_learned_example_closes_loops_by_night(capsys: pytest.CaptureFixture[str]) -> None:
    """Gardens Point places 0-19 by day, then by night: the learned preset accepts loops, each at
    most 8 places from the true one; ORB's default accepts none (bench_learned.py)."""
    gp = shared_path("gardens_point_dev")
    args = [str(gp / "day_right"), str(gp / "night_right"), "--places", "20"]
    code, lines, _ = run("learned_day_night", args, capsys)
    assert code == 0
    offs = [int(m[1]) for line in lines if (m := re.search(r", (\d+) places off", line))]
    assert len(offs) >= 5 and max(offs) <= 8, lines
    assert all("matcher mnn, verifier fundamental" in line for line in lines if line.startswith("loop:"))
    assert lines[-1].startswith("40 frames, ") and "(learned)" in lines[-1]
    code, lines, err = run("learned_day_night", [str(gp / "nowhere")], capsys)
    assert code == 1 and "error:" in err and "nowhere" in err

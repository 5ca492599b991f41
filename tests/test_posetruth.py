"""Loop ground truth from poses (issue 35): the rule on made-up trajectories, real TUM and EuRoC
trajectories checked pair by pair from the files' own numbers, and `gt poses` / `eval --gt-poses`
through the command line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from stablecues.cli.main import main
from stablecues.errors import DatasetError, InputError
from stablecues.geometry.rotations import quat_to_matrix
from stablecues.posetruth import LoopRule, PoseSource, frame_poses, pose_ground_truth


def _pose(x: float, y: float, yaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    out = np.eye(4)
    out[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    out[:3, 3] = [x, y, 0]
    return out


def test_the_rule_on_a_made_up_walk() -> None:
    """Frame 3 comes back to frame 0 facing the same way (a loop), frame 4 to frame 1 facing the
    other way (no loop unless any orientation counts), frame 5 has no pose."""
    poses = np.stack([_pose(0, 0, 0), _pose(5, 0, 0), _pose(10, 0, 90), _pose(0.2, 0, 10),
                      _pose(5, 0.1, 180), np.full((4, 4), np.nan)])
    times = np.arange(6) * 10.0
    src = PoseSource(poses, times, "walk", None)
    gt = pose_ground_truth(src, LoopRule(0.5, 30.0, min_gap_s=15))
    assert list(zip(*np.nonzero(gt.matrix), strict=True)) == [(3, 0)]
    assert gt.notes["from_poses"]["frames_without_pose"] == 1
    assert "within 0.5 (m), orientations within 30 deg, at least 15 s apart" in gt.notes["from_poses"]["rule"]
    anyway = pose_ground_truth(src, LoopRule(0.5, None, min_gap_s=15)).matrix
    assert list(zip(*np.nonzero(anyway), strict=True)) == [(3, 0), (4, 1)]
    assert not pose_ground_truth(src, LoopRule(0.5, 30.0, min_gap_s=31)).matrix.any()
    assert not pose_ground_truth(src, LoopRule(0.5, 5.0, min_gap_s=0)).matrix.any()  # 10 deg apart
    untimed = PoseSource(poses, None, "walk", None)
    assert pose_ground_truth(untimed, LoopRule(0.5, 30.0, min_gap_frames=4)).matrix.sum() == 0
    assert pose_ground_truth(untimed, LoopRule(0.5, 30.0, min_gap_frames=3)).matrix[3, 0]
    # without times no 20 s gap applies: a camera would close loops with its last frames
    with pytest.raises(InputError, match="no times.*--min-gap-frames N"):
        pose_ground_truth(untimed, LoopRule(0.5, 30.0))
    for bad in ({"max_distance": -1}, {"max_distance": 1, "max_angle_deg": 200},
                {"max_distance": 1, "min_gap_s": float("nan")}):
        with pytest.raises(InputError):
            LoopRule(**bad)  # type: ignore[arg-type]


def _rows(path: Path) -> np.ndarray:
    """The file's own numbers (t x y z qx qy qz qw), read here without the project's reader."""
    return np.array([[float(v) for v in line.split()] for line in path.read_text().splitlines()
                     if line.strip() and not line.startswith("#")])


def _hand_check(rows: np.ndarray, i: int, j: int) -> tuple[float, float, float]:
    """Distance, angle (from the quaternions: 2 acos |q_i . q_j|) and time between two rows."""
    qi, qj = rows[i, 4:8] / np.linalg.norm(rows[i, 4:8]), rows[j, 4:8] / np.linalg.norm(rows[j, 4:8])
    angle = math.degrees(2 * math.acos(min(1.0, abs(float(qi @ qj)))))
    return float(np.linalg.norm(rows[i, 1:4] - rows[j, 1:4])), angle, float(rows[i, 0] - rows[j, 0])


@pytest.mark.parametrize(("parts", "every", "distance"), [
    (("tum", "fr2_desk", "fr2_desk_groundtruth_from_evo.txt"), 100, 0.3),
    (("euroc", "V1_01_groundtruth_tum.txt"), 10, 0.5),
])
def test_real_trajectories_pair_by_pair(parts: tuple[str, ...], every: int, distance: float,
                                        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`gt poses` on the real TUM fr2/desk (every 100th mocap pose: about 2 Hz) and EuRoC V1_01
    (every 10th) trajectories: every loop pair, and every pair it leaves out, checked against
    distance, angle and time computed here from the file's numbers by another formula; on
    fr2/desk the loops are where the walk around the desk closes: its last 15 % against its
    first 15 %."""
    path = shared_path(*parts)
    out = tmp_path / "gt.npy"
    assert main(["gt", "poses", str(path), "--every", str(every), "--max-distance", str(distance),
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "loop rule: positions within" in printed and "30 deg, at least 20 s apart" in printed
    gt = np.load(out)
    rows = _rows(path)[::every]
    assert gt.shape == (len(rows), len(rows)) and gt.sum() > 10
    i, j = np.tril_indices(len(rows), -1)
    for a, b in zip(i.tolist(), j.tolist(), strict=True):
        d, angle, dt = _hand_check(rows, a, b)
        expected = d <= distance and angle <= 30 + 1e-6 and dt >= 20
        if abs(angle - 30) > 1e-3 and abs(d - distance) > 1e-9:  # leave exact ties to rounding
            assert bool(gt[a, b]) == expected, (a, b, d, angle, dt)
    if parts[0] == "tum":
        qi, qj = np.nonzero(gt)
        t0, span = rows[0, 0], rows[-1, 0] - rows[0, 0]
        assert rows[qi, 0].min() - t0 >= 0.85 * span and rows[qj, 0].max() - t0 <= 0.15 * span


def test_a_dataset_own_poses_and_a_trajectory_matched_by_time(tmp_path: Path) -> None:
    """The real fr2/desk frames take their poses from the trajectory beside them (nearest in time,
    as TUM's associate does); the same file given with --poses gives the same poses, each the
    file's pose nearest the frame's time. A folder whose frames carry none says so in one line."""
    root = shared_path("tum", "fr2_desk")
    traj = root / "fr2_desk_groundtruth_from_evo.txt"
    own = frame_poses(root, dataset_format="tum")
    src = frame_poses(root, trajectory=traj, dataset_format="tum")
    assert own.file == traj
    np.testing.assert_array_equal(own.poses, src.poses)
    rows = _rows(traj)
    assert src.poses.shape == (20, 4, 4) and np.isfinite(src.poses).all()
    assert src.times is not None
    for k in (0, 7, 19):
        nearest = int(np.argmin(np.abs(rows[:, 0] - src.times[k])))
        assert abs(rows[nearest, 0] - src.times[k]) <= 0.02
        np.testing.assert_allclose(src.poses[k, :3, 3], rows[nearest, 1:4])
        np.testing.assert_allclose(src.poses[k, :3, :3], quat_to_matrix(rows[nearest, 4:8]), atol=1e-9)
    plain = tmp_path / "plain"
    plain.mkdir()
    for k in range(3):
        (plain / f"{k}.png").write_bytes((root / sorted(p.name for p in root.glob("*.png"))[k]).read_bytes())
    with pytest.raises(DatasetError, match="carry no poses .* --poses FILE"):
        frame_poses(plain)


def test_eval_gt_poses_equals_eval_on_the_written_matrix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`eval --gt-poses` on a run of a folder with poses.txt scores as `gt poses` + `eval --gt`,
    names the rule, and refuses without --max-distance or beside --gt, in one line each."""
    from stablecues.synthetic import SyntheticTownConfig, write_sequence

    seq = write_sequence(SyntheticTownConfig(frames=24, width=192, height=144, seed=5, loops=2),
                         tmp_path / "seq", right=False, labels=False, progress=False)
    run = tmp_path / "run"
    assert main(["run", str(seq), "--out", str(run), "--preset", "fast", "--no-progress", "--pictures", "0",
                 "--set", "query.exclude_recent=3"]) == 0
    rule = ["--max-distance", "8", "--min-gap-frames", "4", "--max-angle", "45"]
    assert main(["gt", "poses", str(seq), "--out", str(tmp_path / "gt.npy"), *rule]) == 0
    capsys.readouterr()
    assert main(["eval", str(run), "--gt", str(tmp_path / "gt.npy"), "--json", str(tmp_path / "a.json")]) == 0
    assert main(["eval", str(run), "--gt-poses", str(seq), *rule, "--json", str(tmp_path / "b.json")]) == 0
    out = capsys.readouterr().out
    assert "loop rule    positions within 8 (m), orientations within 45 deg" in out
    import json

    a, b = (json.loads((tmp_path / f"{k}.json").read_text()) for k in "ab")
    for key in ("tp", "fp", "fn", "positives", "recall_at_100p", "gt_loops"):
        assert a[key] == b[key], key
    # the matrix is kept beside the run (report reads it back), the pose file and its hash in the notes
    assert b["gt_file"] == str(run / "gt_poses.npy") and b["gt_notes"]["from_poses"]["max_distance"] == 8
    assert b["gt_notes"]["from_poses"]["pose_file"] == str(seq / "poses.txt")
    assert len(b["gt_notes"]["from_poses"]["pose_file_sha256"]) == 64
    assert main(["report", str(run), "--out", str(tmp_path / "r.html")]) == 0
    assert "ground truth not shown" not in capsys.readouterr().err
    assert main(["eval", str(run), "--gt-poses", str(seq)]) == 1
    assert "needs --max-distance" in capsys.readouterr().err
    assert main(["eval", str(run), "--gt-poses", str(seq), "--gt", str(tmp_path / "gt.npy"), *rule]) == 1

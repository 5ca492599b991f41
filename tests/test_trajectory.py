"""stablecues.trajectory: TUM, KITTI, EuRoC and times.txt round trips with known poses, the
quaternion order on a hand case, malformed files, and associating time stamps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stablecues.errors import DatasetError, InputError
from stablecues.geometry.rotations import quat_to_matrix
from stablecues.trajectory import (
    associate,
    nearest,
    ns_to_seconds,
    read_euroc,
    read_kitti,
    read_number_rows,
    read_times,
    read_tum,
    write_euroc,
    write_kitti,
    write_times,
    write_tum,
)

YAW_90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
H = 0.5**0.5
KITTI_ROW = "1 0 0 0 0 1 0 0 0 0 1 0\n"


def _known_poses(n: int = 7, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(n,) times in seconds near a real epoch and (n, 4, 4) random rigid poses."""
    rng = np.random.default_rng(seed)
    times = 1_403_715_273.0 + np.cumsum(rng.uniform(0.05, 0.1, n))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.uniform(-10, 10, (n, 3))
    return times, poses


# ----------------------------------------------------------------------------------------------
# round trips


def test_tum_round_trip(tmp_path: Path) -> None:
    times, poses = _known_poses()
    path = tmp_path / "sub" / "traj.txt"  # folders are created
    assert write_tum(path, times, poses, comments=("made by a test",)) == len(times)
    assert path.read_text().startswith("# made by a test\n")
    t, p = read_tum(path)
    np.testing.assert_allclose(t, times, atol=1e-6)  # microseconds written
    np.testing.assert_allclose(p[:, :3, 3], poses[:, :3, 3], atol=1e-4)  # 0.1 mm written
    np.testing.assert_allclose(p[:, :3, :3], poses[:, :3, :3], atol=1e-6)
    np.testing.assert_array_equal(p[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (len(times), 1)))


def test_tum_writes_only_finite_poses(tmp_path: Path) -> None:
    times, poses = _known_poses(4)
    times[1] = np.nan
    poses[2, 0, 3] = np.nan
    assert write_tum(tmp_path / "t.txt", times, poses) == 2
    t, _ = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(t, times[[0, 3]], atol=1e-6)
    with pytest.raises(InputError, match="times"):
        write_tum(tmp_path / "t.txt", times[:3], poses)
    with pytest.raises(InputError, match="poses"):
        write_tum(tmp_path / "t.txt", times, poses[:, :3])


def test_kitti_round_trip(tmp_path: Path) -> None:
    _, poses = _known_poses()
    write_kitti(tmp_path / "00.txt", poses)
    lines = (tmp_path / "00.txt").read_text().splitlines()
    assert len(lines) == len(poses) and all(len(line.split()) == 12 for line in lines)
    np.testing.assert_allclose(read_kitti(tmp_path / "00.txt"), poses, rtol=1e-8, atol=1e-12)


def test_euroc_round_trip(tmp_path: Path) -> None:
    times, poses = _known_poses()
    write_euroc(tmp_path / "data.csv", times, poses)
    header, first = (tmp_path / "data.csv").read_text().splitlines()[:2]
    assert header.startswith("#timestamp [ns]") and first.split(",")[0].isdigit()
    t, p = read_euroc(tmp_path / "data.csv")
    np.testing.assert_allclose(t, times, atol=1e-6)
    np.testing.assert_allclose(p, poses, atol=1e-8)


def test_euroc_reads_the_17_column_ground_truth(tmp_path: Path) -> None:
    extra = ",0" * 9  # velocity and IMU biases, ignored
    (tmp_path / "data.csv").write_text(
        "#timestamp, p_RS_R_x [m], ...\n"
        f"1403715273262142976,1,2,3,{H},0,0,{H}{extra}\n"
        f"1403715273312143104,4,5,6,1,0,0,0{extra}\n"
    )
    t, p = read_euroc(tmp_path / "data.csv")
    assert t[0] == ns_to_seconds(np.array([1403715273262142976]))[0]
    np.testing.assert_allclose(p[0, :3, :3], YAW_90, atol=1e-12)
    np.testing.assert_array_equal(p[1, :3, 3], [4, 5, 6])
    np.testing.assert_array_equal(p[1, :3, :3], np.eye(3))


def test_times_round_trip(tmp_path: Path) -> None:
    times = np.array([0.0, 0.103526, 1311868164.363181])
    write_times(tmp_path / "times.txt", times)
    assert (tmp_path / "times.txt").read_text().splitlines()[1] == "0.103526"
    np.testing.assert_array_equal(read_times(tmp_path / "times.txt"), times)
    (tmp_path / "empty.txt").write_text("")
    assert read_times(tmp_path / "empty.txt").shape == (0,)


def test_empty_files_give_empty_trajectories(tmp_path: Path) -> None:
    (tmp_path / "e.txt").write_text("# only a comment\n\n")
    t, p = read_tum(tmp_path / "e.txt")
    assert t.shape == (0,) and p.shape == (0, 4, 4)
    assert read_kitti(tmp_path / "e.txt").shape == (0, 4, 4)
    t, p = read_euroc(tmp_path / "e.txt")
    assert t.shape == (0,) and p.shape == (0, 4, 4)


# ----------------------------------------------------------------------------------------------
# quaternion order: (x, y, z, w) in TUM files, (w, x, y, z) in EuRoC's


def test_tum_quaternion_is_xyzw_on_a_90_degree_yaw(tmp_path: Path) -> None:
    (tmp_path / "t.txt").write_text(f"1.0 0 0 0 0 0 {H} {H}\n")
    _, p = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(p[0, :3, :3], YAW_90, atol=1e-12)
    np.testing.assert_allclose(p[0, :3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)  # x -> y
    pose = np.eye(4)
    pose[:3, :3] = YAW_90
    write_tum(tmp_path / "w.txt", np.array([1.0]), pose[None])
    fields = (tmp_path / "w.txt").read_text().split()
    assert fields[4:] == ["0.0000000", "0.0000000", "0.7071068", "0.7071068"]  # qx qy qz qw


def test_unnormalised_quaternions_are_normalised(tmp_path: Path) -> None:
    rot = quat_to_matrix(np.array([[0, 0, 0, 2.0]]))  # unnormalised identity
    np.testing.assert_allclose(rot[0], np.eye(3))
    (tmp_path / "t.txt").write_text("0 0 0 0 0 0 3 3\n")
    _, p = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(p[0, :3, :3], YAW_90, atol=1e-12)


def test_euroc_quaternion_is_wxyz(tmp_path: Path) -> None:
    pose = np.eye(4)
    pose[:3, :3] = YAW_90
    write_euroc(tmp_path / "data.csv", np.array([2.0]), pose[None])
    values = (tmp_path / "data.csv").read_text().splitlines()[1].split(",")
    assert values[0] == "2000000000"
    np.testing.assert_allclose([float(v) for v in values[4:]], [H, 0, 0, H], atol=1e-9)  # qw qx qy qz


# ----------------------------------------------------------------------------------------------
# malformed files name the file and the line


@pytest.mark.parametrize(
    ("reader", "text", "message"),
    [
        (
            read_tum,
            "# t x y z qx qy qz qw\n0 1 2 3 0 0 0 1\n1 2 3 0 0 0 1\n",
            r"needs 8 numbers per line, line 3 has 7",
        ),
        (
            read_tum,
            "0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 zero 1\n",
            r"line 2 is not numeric: '0.1 1 2 3 0 0 zero 1'",
        ),
        (
            read_kitti,
            "1 0 0 0 0 1 0 0 0 0 1 0\n" * 6 + "1 0 0 0 0 1 0 0 0 0 1\n",
            r"needs 12 numbers per line, line 7 has 11",
        ),
        (read_euroc, "#h\n1,2,3,4,1,0,0\n", r"needs 8 or 17 numbers per line, line 2 has 7"),
        (read_euroc, "1,2,3,4,1,0,0,0\n2" + ",0" * 16 + "\n", r"needs 8 numbers per line, line 2 has 17"),
        (read_times, "0.0\n0.1 0.2\n", r"needs 1 numbers per line, line 2 has 2"),
    ],
)
def test_malformed_lines(tmp_path: Path, reader: object, text: str, message: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=message) as info:
        reader(path)  # type: ignore[operator]
    assert str(info.value).startswith(f"{path}: ")


def test_missing_files_and_zero_quaternions(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"absent.txt: TUM trajectory .* file not found"):
        read_tum(tmp_path / "absent.txt")
    with pytest.raises(DatasetError, match=r"absent.txt: KITTI poses .* file not found"):
        read_kitti(tmp_path / "absent.txt")
    (tmp_path / "zero.txt").write_text("0 1 2 3 0 0 0 0\n")
    with pytest.raises(DatasetError, match=r"zero.txt: TUM trajectory: .*zero"):
        read_tum(tmp_path / "zero.txt")
    (tmp_path / "zero.csv").write_text("1,1,2,3,0,0,0,0\n")
    with pytest.raises(DatasetError, match=r"zero.csv: EuRoC ground truth: .*zero"):
        read_euroc(tmp_path / "zero.csv")


def test_read_number_rows_separators_and_comments(tmp_path: Path) -> None:
    (tmp_path / "n.txt").write_text("% a settings-style comment\n# another\n1, 2 ,3\n\n4 5 6\n")
    rows = read_number_rows(tmp_path / "n.txt", 3, "numbers")
    np.testing.assert_array_equal(rows, [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "e.txt").write_text("")
    assert read_number_rows(tmp_path / "e.txt", (8, 17), "numbers").shape == (0, 8)


# ----------------------------------------------------------------------------------------------
# time stamps


def test_ns_to_seconds() -> None:
    ns = np.array([1403715273262142976, 1_500_000_000, 0])
    s = ns_to_seconds(ns)
    assert s.dtype == np.float64 and s[1] == 1.5 and s[2] == 0.0
    # as near the true value as a float64 at this epoch can be (its spacing is about 240 ns)
    assert abs(s[0] - 1403715273.262142976) <= np.spacing(s[0])


def test_association_helpers() -> None:
    q = np.array([0.0, 1.0, 2.0])
    r = np.array([2.01, 0.5, 1.0, 0.99])
    assert associate(q, r, 0.02).tolist() == [-1, 2, 0]
    assert nearest(q, r, 0.6).tolist() == [1, 2, 0]
    assert nearest(q, np.array([5.0]), 0.1).tolist() == [-1, -1, -1]


def test_associate_is_one_to_one_nearest_first() -> None:
    q = np.array([1.00, 1.01])
    r = np.array([1.012, 0.97])
    # both queries are nearest reference 0; the closer pair (1.01, 1.012) takes it first and
    # 1.00 falls back to reference 1, 0.03 away
    assert associate(q, r, 0.035).tolist() == [1, 0]
    assert nearest(q, r, 0.035).tolist() == [0, 0]  # nearest may use a reference twice
    assert associate(q, r, 0.02).tolist() == [-1, 0]  # no second choice within 0.02
    assert associate(q, np.array([]), 1.0).tolist() == [-1, -1]
    assert associate(np.array([]), r, 1.0).tolist() == []


def test_nearest_hand_cases() -> None:
    r = np.array([3.0, 1.0, 2.0])  # any order; indices refer to this order
    assert nearest(np.array([0.0, 1.4, 1.6, 2.5, 9.0]), r, 10.0).tolist() == [1, 1, 2, 2, 0]
    assert nearest(np.array([1.5]), r, 1.0).tolist() == [1]  # a tie takes the earlier time
    assert nearest(np.array([2.2, np.nan]), r, 0.1).tolist() == [-1, -1]
    assert nearest(np.array([0.5, 7.0]), np.array([1.0]), 0.5).tolist() == [0, -1]
    assert nearest(np.array([]), r, 1.0).tolist() == []

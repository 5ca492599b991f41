"""A pose per frame: camera mounts, headings, pose matrices; the real zr10 recording end to end."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path

pytest.importorskip("pymap3d")

from stablecues.errors import InputError  # noqa: E402
from stablecues.geometry.rotations import (  # noqa: E402
    euler_zyx_to_quat,
    matrix_to_quat,
    quat_multiply,
    quat_to_matrix,
    yaw_of,
)
from stablecues.mav import FlightLog, geo, read_log  # noqa: E402
from stablecues.mav.export import write_image_folder  # noqa: E402
from stablecues.mav.frames import read_frames  # noqa: E402
from stablecues.mav.loops import loops_from_trajectory  # noqa: E402
from stablecues.mav.poses import MOUNTS, pose_matrices, poses_for_frames  # noqa: E402
from stablecues.mav.solutions import log_solution  # noqa: E402
from stablecues.trajectory import read_tum  # noqa: E402


def test_mounts_and_yaw() -> None:
    # level body heading north-east (NED yaw 45 deg)
    q_body = geo.ned_to_enu_quat(euler_zyx_to_quat(np.zeros(1), np.zeros(1), np.radians([45.0])))
    for mount, axis, want in (("forward", 2, [np.sqrt(0.5), np.sqrt(0.5), 0]), ("nadir", 2, [0, 0, -1])):
        q_cam = quat_multiply(q_body, matrix_to_quat(MOUNTS[mount]))
        r = quat_to_matrix(q_cam)[0]
        np.testing.assert_allclose(r[:, axis], want, atol=1e-9)  # optical axis in ENU
    # a turn about the vertical changes yaw_of by the same angle, whatever the mount
    q_turned = geo.ned_to_enu_quat(euler_zyx_to_quat(np.zeros(1), np.zeros(1), np.radians([75.0])))
    for mount in MOUNTS:
        m = matrix_to_quat(MOUNTS[mount])
        d = yaw_of(quat_multiply(q_turned, m)) - yaw_of(quat_multiply(q_body, m))
        assert float(geo.wrap_angle(d)[0]) == pytest.approx(np.radians(-30.0))  # ENU yaw is counter-clockwise
    for m in MOUNTS.values():
        assert np.linalg.det(m) == pytest.approx(1.0)


def test_pose_matrices_mark_frames_without_a_pose() -> None:
    q = np.array([[0.0, 0.0, np.sin(0.5), np.cos(0.5)], [np.nan] * 4, [0.0, 0.0, 0.0, 2.0]])
    p = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [np.nan, 0.0, 0.0]])
    poses = pose_matrices(p, q)
    assert poses.shape == (3, 4, 4) and np.isnan(poses[1:]).all()
    np.testing.assert_allclose(poses[0, :3, :3], quat_to_matrix(q[0]), atol=1e-15)
    np.testing.assert_array_equal(poses[0, :3, 3], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(poses[0, 3], [0.0, 0.0, 0.0, 1.0])
    with pytest.raises(InputError):
        pose_matrices(p, q[:2])


def _read(path: Path) -> FlightLog:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_log(path)


def test_zr10_poses_and_revisit_ground_truth(tmp_path: Path) -> None:
    pytest.importorskip("pymavlink")
    folder = shared_path("mav", "zr10_aerial_camera_gnss")
    log = _read(folder / "gps.csv")
    assert log.kind == "gnss_csv" and len(log.gnss) == 5155
    assert log.duration == pytest.approx(652, abs=1)
    frames = read_frames(folder / "images", folder / "image_metadata.csv")
    assert len(frames) == 17 and frames.is_utc
    solution = log_solution(log)  # no IMU: the GNSS track
    assert solution.name == "gnss"
    poses = poses_for_frames(frames, log, solution)
    assert poses.valid.all() and not poses.has_attitude
    # the frames' own geotags were assigned from this track: the interpolated poses agree
    tags = geo.geodetic_to_enu(frames.geotags[:, 0], frames.geotags[:, 1], frames.geotags[:, 2], poses.origin)
    assert np.abs(tags - poses.positions).max() < 0.1
    # 70 m above ground: the frames fly about 60-70 m above the first fix
    assert 50 < np.median(poses.positions[:, 2]) < 80
    # the clock offset estimated from the geotags is ~0
    est = poses_for_frames(frames, log, solution, offset="estimate")
    assert abs(est.offset) < 0.05

    gt = loops_from_trajectory(poses.positions, max_distance=8.0, times=poses.frame_times, min_gap_s=20.0)
    assert gt.shape == (17, 17) and not np.triu(gt).any()
    ids = [int(n[4:8]) for n in poses.names]
    pairs = {(ids[i], ids[j]) for i, j in zip(*np.nonzero(gt), strict=True)}
    for query, earlier in ((67, 15), (33, 18), (196, 104), (191, 127)):
        assert (query, earlier) in pairs
    # consecutive frames of the first lane are 3 s apart: never loops with a 20 s gap
    assert not any(q <= 18 for q, _ in pairs)

    out = write_image_folder(tmp_path / "ds", frames, poses, loops=gt)
    assert len(list((out / "images").iterdir())) == 17
    assert np.array_equal(np.load(out / "loops.npy"), gt)
    t, tum = read_tum(out / "poses.txt")
    p = tum[:, :3, 3]
    np.testing.assert_allclose(p, poses.positions, atol=1e-3)
    np.testing.assert_allclose(np.loadtxt(out / "times.txt"), t, atol=1e-6)
    # no attitude in a GNSS track: a level, north-facing body; the yaws say so
    np.testing.assert_allclose(poses.yaws, np.pi / 2, atol=1e-9)  # body x (nose) along ENU y

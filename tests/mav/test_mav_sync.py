"""Camera sync, poses per frame, TUM files, loop ground truth, time columns (no shared data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from stablecues.errors import DatasetError, InputError  # noqa: E402
from stablecues.mav import FlightLog, NavSolution, geo, read_log, sync  # noqa: E402
from stablecues.mav.tables import time_column_seconds  # noqa: E402

ORIGIN = (50.0, 10.0, 100.0)


def test_time_columns_units_and_clocks(tmp_path: Path) -> None:
    p = tmp_path / "x.csv"
    t, utc = time_column_seconds(p, "utc_usec", ["1768273457875381", "1768273460875381"])
    assert utc and t[1] - t[0] == pytest.approx(3.0)
    t, utc = time_column_seconds(p, "#timestamp [ns]", ["1403636579763555584", "1403636579813555456"])
    assert utc and t[1] - t[0] == pytest.approx(0.05, abs=1e-6)
    # no unit in the name: the one giving plausible intervals (here 0.125 s in microseconds)
    t, utc = time_column_seconds(p, "timestamp", ["182092193", "182217193", "182342193"])
    assert not utc and t[0] == pytest.approx(182.092193)
    t, utc = time_column_seconds(p, "time", ["1.5", "1.6"])
    assert not utc and t[0] == 1.5
    t, utc = time_column_seconds(p, "utc", ["2026-01-13 03:04:17.875381+00:00", "2026-01-13T03:04:20.875381"])
    assert utc and t[0] == pytest.approx(1768273457.875381) and t[1] - t[0] == pytest.approx(3.0)
    with pytest.raises(DatasetError, match="ISO 8601"):
        time_column_seconds(p, "utc", ["yesterday"])


def _track_log(tmp_path: Path, *, speed: float = 5.0) -> Path:
    """A CSV GNSS track flying east at ``speed`` m/s for 60 s, 10 Hz, boot clock plus UTC."""
    t = np.arange(0.0, 60.0, 0.1)
    enu = np.column_stack([speed * t, np.zeros_like(t), 20.0 + 0 * t])
    llh = geo.enu_to_geodetic(enu, ORIGIN)
    boot0, utc0 = 100.0, 1.7e9
    rows = ["timestamp,utc_usec,lat,lon,alt_msl"]
    for k in range(len(t)):
        stamps = f"{int((boot0 + t[k]) * 1e6)},{int((utc0 + t[k]) * 1e6)}"
        rows.append(f"{stamps},{llh[k, 0]:.9f},{llh[k, 1]:.9f},{llh[k, 2]:.3f}")
    path = tmp_path / "track.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


def _images(folder: Path, names: list[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"\x89PNG fake")


def test_gnss_csv_log_and_frame_clocks(tmp_path: Path) -> None:
    log = read_log(_track_log(tmp_path))
    assert log.kind == "gnss_csv" and len(log.gnss) == 600
    assert log.boot_time_offset == pytest.approx(100.0) and log.utc_offset == pytest.approx(1.7e9)
    _images(tmp_path / "img", ["a.png", "b.png", "c.png"])
    # CSV with names (in another order) and UTC times
    (tmp_path / "times.csv").write_text(
        "image,utc\nc.png,1700000030.0\na.png,1700000010.0\nb.png,1700000020.0\n"
    )
    frames = sync.read_frames(tmp_path / "img", tmp_path / "times.csv")
    assert [p.name for p in frames.paths] == ["a.png", "b.png", "c.png"] and frames.is_utc
    np.testing.assert_allclose(sync.frame_log_times(frames, log), [10.0, 20.0, 30.0])
    np.testing.assert_allclose(sync.frame_log_times(frames, log, offset=0.5), [10.5, 20.5, 30.5])
    poses = sync.poses_for_frames(frames, log, sync.gnss_solution(log))
    np.testing.assert_allclose(poses.positions[:, 0], [50.0, 100.0, 150.0], atol=0.01)
    np.testing.assert_allclose(poses.positions[:, 2], 0.0, atol=0.01)  # about the first fix
    # boot-clock times in times.txt, one per image
    (tmp_path / "img" / "times.txt").write_text("110\n120\n130\n")
    frames = sync.read_frames(tmp_path / "img")
    np.testing.assert_allclose(sync.frame_log_times(frames, log), [10.0, 20.0, 30.0])
    np.testing.assert_allclose(sync.frame_log_times(frames, log, clock="log"), [110.0, 120.0, 130.0])
    # a frame outside the track gets no pose
    (tmp_path / "img" / "times.txt").write_text("110\n120\n500\n")
    poses = sync.poses_for_frames(sync.read_frames(tmp_path / "img"), log, sync.gnss_solution(log))
    assert poses.valid.tolist() == [True, True, False] and np.isnan(poses.positions[2]).all()


def test_recording_layouts(tmp_path: Path) -> None:
    # stereo recording, timestamps as names (ns)
    rec = tmp_path / "rec"
    names = ["1700000000000000000.png", "1700000000050000000.png"]
    _images(rec / "left", names)
    _images(rec / "right", names)
    frames = sync.read_frames(rec)
    assert frames.right is not None and [p.parent.name for p in frames.right] == ["right", "right"]
    assert frames.is_utc and frames.times[1] - frames.times[0] == pytest.approx(0.05)
    # EuRoC: mav0/cam0/data + data.csv
    cam = tmp_path / "euroc" / "mav0" / "cam0"
    _images(cam / "data", ["1403636579763555584.png", "1403636579813555456.png"])
    (cam / "data.csv").write_text(
        "#timestamp [ns],filename\n1403636579763555584,1403636579763555584.png\n"
        "1403636579813555456,1403636579813555456.png\n"
    )
    frames = sync.read_frames(tmp_path / "euroc")
    assert len(frames) == 2 and frames.source.endswith("data.csv") and frames.is_utc
    # no times anywhere: a clear error
    _images(tmp_path / "plain", ["a.png"])
    with pytest.raises(DatasetError, match="no capture times"):
        sync.read_frames(tmp_path / "plain")
    # CSV rows that do not match the images
    (tmp_path / "bad.csv").write_text("image,time\nzzz.png,1\n")
    with pytest.raises(DatasetError, match="no row for image a.png"):
        sync.read_frames(tmp_path / "plain", tmp_path / "bad.csv")


def test_estimate_clock_offset_recovers_a_shift() -> None:
    t = np.arange(0.0, 60.0, 0.1)
    pos = np.column_stack([4.0 * t, 10 * np.sin(t / 5), np.zeros_like(t)])
    track = NavSolution("track", ORIGIN, t, pos, np.full_like(pos, np.nan), np.full((len(t), 4), np.nan))
    true_frame_times = np.arange(5.0, 50.0, 2.5)
    tags_enu = np.column_stack([np.interp(true_frame_times, t, pos[:, k]) for k in range(3)])
    tags = geo.enu_to_geodetic(tags_enu, ORIGIN)
    # the camera clock runs 1.37 s behind: its times must be shifted by +1.37
    offset, rms = sync.estimate_clock_offset(true_frame_times - 1.37, tags, track)
    assert offset == pytest.approx(1.37, abs=0.01) and rms < 0.05
    with pytest.raises(InputError):
        sync.estimate_clock_offset(true_frame_times[:1], tags[:1], track)


def test_tum_round_trip_and_errors(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    q = geo.quat_normalize(rng.normal(size=(5, 4)))
    p = rng.normal(size=(5, 3))
    t = np.arange(5) * 0.1 + 1e9
    p[2] = np.nan  # skipped
    n = sync.write_tum(tmp_path / "a.txt", t, p, q, comments=("hello",))
    assert n == 4
    t2, p2, q2 = sync.read_tum(tmp_path / "a.txt")
    keep = [0, 1, 3, 4]
    np.testing.assert_allclose(t2, t[keep], atol=1e-6)
    np.testing.assert_allclose(p2, p[keep], atol=1e-4)
    np.testing.assert_allclose(q2, q[keep], atol=1e-6)
    (tmp_path / "b.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match="8 numbers"):
        sync.read_tum(tmp_path / "b.txt")


def test_loops_from_trajectory_with_heading() -> None:
    # out east along y=0, back west along y=2: revisits face the opposite way
    x = np.r_[np.arange(0, 50, 5.0), np.arange(45, -5, -5.0)]
    y = np.r_[np.zeros(10), np.full(10, 2.0)]
    pos = np.column_stack([x, y, np.zeros(20)])
    yaw_ned = np.r_[np.full(10, np.pi / 2), np.full(10, -np.pi / 2)]  # east, then west
    q = geo.ned_to_enu_quat(geo.euler_to_quat(np.zeros(20), np.zeros(20), yaw_ned))
    times = np.arange(20.0)
    gt = sync.loops_from_trajectory(pos, max_distance=3.0, times=times, min_gap_s=3.0)
    # return frame 10 + k is 2 m from outbound frame 9 - k, 2k + 1 s later: k = 0 is too recent
    assert gt[11, 8] and gt[19, 0] and not gt[10, 9] and not np.triu(gt).any()
    assert int(gt.sum()) == 9
    gt_heading = sync.loops_from_trajectory(pos, max_distance=3.0, quaternions=q, max_angle_deg=45.0)
    assert not gt_heading[10:, :10].any()  # opposite headings: no loop
    with pytest.raises(InputError, match="quaternions"):
        sync.loops_from_trajectory(pos, max_distance=3.0, max_angle_deg=45.0)


def test_mounts_and_yaw() -> None:
    # level body heading north-east (NED yaw 45 deg)
    q_body = geo.ned_to_enu_quat(geo.euler_to_quat(np.zeros(1), np.zeros(1), np.radians([45.0])))
    for mount, axis, want in (("forward", 2, [np.sqrt(0.5), np.sqrt(0.5), 0]), ("nadir", 2, [0, 0, -1])):
        q_cam = geo.quat_multiply(q_body, geo.matrix_to_quat(sync.MOUNTS[mount]))
        r = geo.quat_to_matrix(q_cam)[0]
        np.testing.assert_allclose(r[:, axis], want, atol=1e-9)  # optical axis in ENU
    # a turn about the vertical changes yaw_of by the same angle, whatever the mount
    q_turned = geo.ned_to_enu_quat(geo.euler_to_quat(np.zeros(1), np.zeros(1), np.radians([75.0])))
    for mount in sync.MOUNTS:
        m = geo.matrix_to_quat(sync.MOUNTS[mount])
        d = sync.yaw_of(geo.quat_multiply(q_turned, m)) - sync.yaw_of(geo.quat_multiply(q_body, m))
        assert float(geo.wrap_angle(d)[0]) == pytest.approx(np.radians(-30.0))  # ENU yaw is counter-clockwise
    for m in sync.MOUNTS.values():
        assert np.linalg.det(m) == pytest.approx(1.0)


def test_write_image_folder(tmp_path: Path) -> None:
    log = read_log(_track_log(tmp_path))
    names = ["110.0.png", "120.0.png", "900.0.png"]  # boot-clock seconds as names
    _images(tmp_path / "rec" / "left", names)
    _images(tmp_path / "rec" / "right", names)
    frames = sync.read_frames(tmp_path / "rec")
    assert not frames.is_utc
    poses = sync.poses_for_frames(frames, log, sync.gnss_solution(log), mount="forward")
    assert poses.valid.tolist() == [True, True, False]
    with pytest.raises(InputError):
        sync.write_image_folder(tmp_path / "ds", frames, poses, loops=np.zeros((3, 3), bool))
    (tmp_path / "cam.yaml").write_text("%YAML:1.0\nCamera.fx: 500.0\n")
    with pytest.raises(DatasetError, match="calibration"):
        sync.write_image_folder(tmp_path / "ds", frames, poses, calibration=tmp_path / "none.yaml")
    out = sync.write_image_folder(
        tmp_path / "ds", frames, poses, loops=np.zeros((2, 2), bool), calibration=tmp_path / "cam.yaml"
    )
    assert (out / "calib.yaml").read_text().startswith("%YAML:1.0")
    assert sorted(p.name for p in (out / "images").iterdir()) == ["000000_110.0.png", "000001_120.0.png"]
    assert sorted(p.name for p in (out / "right").iterdir()) == ["000000_110.0.png", "000001_120.0.png"]
    np.testing.assert_allclose(np.loadtxt(out / "times.txt"), [110.0, 120.0])
    t, p, q = sync.read_tum(out / "poses.txt")
    np.testing.assert_allclose(p[:, 0], [50.0, 100.0], atol=0.01)
    # no attitude in a GNSS track: level and facing north, so a forward camera looks north
    np.testing.assert_allclose(geo.quat_to_matrix(q)[:, :, 2], [[0, 1, 0], [0, 1, 0]], atol=1e-6)


def test_log_solution_sources(tmp_path: Path) -> None:
    log: FlightLog = read_log(_track_log(tmp_path))
    assert sync.log_solution(log).name == "gnss"  # no IMU: auto falls back to the track
    with pytest.raises(InputError, match="onboard"):
        sync.log_solution(log, "onboard")
    with pytest.raises(InputError, match="IMU"):
        sync.log_solution(log, "ekf")
    with pytest.raises(InputError):
        sync.resample_solution(sync.gnss_solution(log), 0.0)
    every = sync.resample_solution(sync.gnss_solution(log), 2.0)
    assert len(every) == 120 and np.isfinite(every.position).all()  # 0 to 59.5 s

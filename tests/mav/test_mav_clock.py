"""Frame times on a log's clock, and clock offsets estimated from geotags (no shared data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from flight_synth import TRACK_ORIGIN, fake_images, track_log  # noqa: E402

from stablecues.errors import DatasetError, InputError  # noqa: E402
from stablecues.mav import NavSolution, geo, read_log  # noqa: E402
from stablecues.mav.clock import estimate_clock_offset, frame_log_times  # noqa: E402
from stablecues.mav.frames import read_frames  # noqa: E402
from stablecues.mav.poses import poses_for_frames  # noqa: E402
from stablecues.mav.solutions import gnss_solution  # noqa: E402

ORIGIN = TRACK_ORIGIN


def test_gnss_csv_log_and_frame_clocks(tmp_path: Path) -> None:
    log = read_log(track_log(tmp_path))
    assert log.kind == "gnss_csv" and len(log.gnss) == 600
    assert log.boot_time_offset == pytest.approx(100.0) and log.utc_offset == pytest.approx(1.7e9)
    fake_images(tmp_path / "img", ["a.png", "b.png", "c.png"])
    # CSV with names (in another order) and UTC times
    (tmp_path / "times.csv").write_text(
        "image,utc\nc.png,1700000030.0\na.png,1700000010.0\nb.png,1700000020.0\n"
    )
    frames = read_frames(tmp_path / "img", tmp_path / "times.csv")
    assert [p.name for p in frames.paths] == ["a.png", "b.png", "c.png"] and frames.is_utc
    np.testing.assert_allclose(frame_log_times(frames, log), [10.0, 20.0, 30.0])
    np.testing.assert_allclose(frame_log_times(frames, log, offset=0.5), [10.5, 20.5, 30.5])
    poses = poses_for_frames(frames, log, gnss_solution(log))
    np.testing.assert_allclose(poses.positions[:, 0], [50.0, 100.0, 150.0], atol=0.01)
    np.testing.assert_allclose(poses.positions[:, 2], 0.0, atol=0.01)  # about the first fix
    # boot-clock times in times.txt, one per image
    (tmp_path / "img" / "times.txt").write_text("110\n120\n130\n")
    frames = read_frames(tmp_path / "img")
    np.testing.assert_allclose(frame_log_times(frames, log), [10.0, 20.0, 30.0])
    np.testing.assert_allclose(frame_log_times(frames, log, clock="log"), [110.0, 120.0, 130.0])
    # a frame outside the track gets no pose
    (tmp_path / "img" / "times.txt").write_text("110\n120\n500\n")
    poses = poses_for_frames(read_frames(tmp_path / "img"), log, gnss_solution(log))
    assert poses.valid.tolist() == [True, True, False] and np.isnan(poses.positions[2]).all()


def test_estimate_clock_offset_recovers_a_shift() -> None:
    t = np.arange(0.0, 60.0, 0.1)
    pos = np.column_stack([4.0 * t, 10 * np.sin(t / 5), np.zeros_like(t)])
    track = NavSolution("track", ORIGIN, t, pos, np.full_like(pos, np.nan), np.full((len(t), 4), np.nan))
    true_frame_times = np.arange(5.0, 50.0, 2.5)
    tags_enu = np.column_stack([np.interp(true_frame_times, t, pos[:, k]) for k in range(3)])
    tags = geo.enu_to_geodetic(tags_enu, ORIGIN)
    # the camera clock runs 1.37 s behind: its times must be shifted by +1.37
    offset, rms = estimate_clock_offset(true_frame_times - 1.37, tags, track)
    assert offset == pytest.approx(1.37, abs=0.01) and rms < 0.05
    with pytest.raises(InputError):
        estimate_clock_offset(true_frame_times[:1], tags[:1], track)


def test_clock_errors(tmp_path: Path) -> None:
    log = read_log(track_log(tmp_path))
    fake_images(tmp_path / "img", ["a.png"])
    (tmp_path / "img" / "times.txt").write_text("110\n")
    frames = read_frames(tmp_path / "img")
    with pytest.raises(InputError, match="clock"):
        frame_log_times(frames, log, clock="gps")  # type: ignore[arg-type]
    no_utc = type(log)(**{**log.__dict__, "utc_offset": float("nan")})
    with pytest.raises(DatasetError, match="no GNSS time"):
        frame_log_times(frames, no_utc, clock="utc")

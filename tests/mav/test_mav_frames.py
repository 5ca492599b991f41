"""A recording's frames and capture times: layouts, times files, CSV columns (no shared data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from flight_synth import fake_images  # noqa: E402

from stablecues.errors import DatasetError, ImageError  # noqa: E402
from stablecues.mav.frames import read_frames  # noqa: E402


def test_recording_layouts(tmp_path: Path) -> None:
    # stereo recording, timestamps as names (ns)
    rec = tmp_path / "rec"
    names = ["1700000000000000000.png", "1700000000050000000.png"]
    fake_images(rec / "left", names)
    fake_images(rec / "right", names)
    frames = read_frames(rec)
    assert frames.right is not None and [p.parent.name for p in frames.right] == ["right", "right"]
    assert frames.is_utc and frames.times[1] - frames.times[0] == pytest.approx(0.05)
    # EuRoC: mav0/cam0/data + data.csv
    cam = tmp_path / "euroc" / "mav0" / "cam0"
    fake_images(cam / "data", ["1403636579763555584.png", "1403636579813555456.png"])
    (cam / "data.csv").write_text(
        "#timestamp [ns],filename\n1403636579763555584,1403636579763555584.png\n"
        "1403636579813555456,1403636579813555456.png\n"
    )
    frames = read_frames(tmp_path / "euroc")
    assert len(frames) == 2 and frames.source.endswith("data.csv") and frames.is_utc
    # no times anywhere: a clear error
    fake_images(tmp_path / "plain", ["a.png"])
    with pytest.raises(DatasetError, match="no capture times"):
        read_frames(tmp_path / "plain")
    # CSV rows that do not match the images
    (tmp_path / "bad.csv").write_text("image,time\nzzz.png,1\n")
    with pytest.raises(DatasetError, match="no row for image a.png"):
        read_frames(tmp_path / "plain", tmp_path / "bad.csv")


def test_times_txt_and_csv_without_names(tmp_path: Path) -> None:
    fake_images(tmp_path / "img", ["10.png", "2.png", "1.png"])  # natural order: 1, 2, 10
    (tmp_path / "img" / "times.txt").write_text("# seconds\n1700000001.5\n1700000002.5\n1700000003.0\n")
    frames = read_frames(tmp_path / "img")
    assert [p.name for p in frames.paths] == ["1.png", "2.png", "10.png"] and frames.is_utc
    np.testing.assert_allclose(frames.times, [1700000001.5, 1700000002.5, 1700000003.0])
    assert frames.source.endswith("times.txt") and frames.right is None and frames.geotags is None
    (tmp_path / "img" / "times.txt").write_text("1.0\n2.0\n")
    with pytest.raises(DatasetError, match="2 times for 3 images"):
        read_frames(tmp_path / "img")
    (tmp_path / "img" / "times.txt").unlink()
    # a CSV without image names: one row per image, in name order; geotags without altitude
    (tmp_path / "t.csv").write_text("time,lat,lon\n3.0,50.0,10.0\n1.0,50.1,10.1\n2.0,50.2,10.2\n")
    frames = read_frames(tmp_path / "img", tmp_path / "t.csv")
    assert [p.name for p in frames.paths] == ["2.png", "10.png", "1.png"]  # sorted by time
    assert frames.geotags is not None and np.isnan(frames.geotags[:, 2]).all()
    np.testing.assert_allclose(frames.geotags[:, 0], [50.1, 50.2, 50.0])
    # a CSV alone: frames from its name column, relative to the CSV's folder
    (tmp_path / "n.csv").write_text("name,t\nimg/1.png,5\nimg/2.png,6\n")
    frames = read_frames(None, tmp_path / "n.csv")
    assert frames.paths[0] == tmp_path / "img" / "1.png" and not frames.is_utc
    with pytest.raises(DatasetError, match="image-name column"):
        read_frames(None, tmp_path / "t.csv")
    with pytest.raises(DatasetError, match="no column 'when'"):
        read_frames(tmp_path / "img", tmp_path / "t.csv", time_column="when")
    # a stereo folder with a right image missing; an empty folder
    fake_images(tmp_path / "st" / "left", ["1.0.png", "2.0.png"])
    fake_images(tmp_path / "st" / "right", ["1.0.png"])
    with pytest.raises(DatasetError, match="right image named 2.0"):
        read_frames(tmp_path / "st")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImageError, match="expected image files"):
        read_frames(tmp_path / "empty")
    with pytest.raises(DatasetError, match="not found"):
        read_frames(tmp_path / "nowhere")

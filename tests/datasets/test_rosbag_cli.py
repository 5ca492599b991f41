"""``stablecues info`` and ``stablecues run`` on ROS bags written from real EuRoC frames."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from test_rosbag import Cam, Euroc, euroc, stereo_cams, write_bag

from stablecues.cli.main import main

__all__ = ["euroc"]  # the fixture, shared with test_rosbag


def _decisions(run_dir: Path) -> list[list[str]]:
    """decisions.csv without its timing columns (t_*)."""
    with (run_dir / "decisions.csv").open() as fh:
        rows = list(csv.reader(fh))
    keep = [i for i, name in enumerate(rows[0]) if not name.startswith("t_")]
    return [[row[i] for i in keep] for row in rows]


def test_run_on_bag_matches_run_on_folder(
    tmp_path: Path, euroc: Euroc, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same detections, frame for frame, from the bag as from the EuRoC folder it was made of."""
    bag = write_bag(tmp_path / "v101_mcap", stereo_cams(euroc, "png"), "mcap")
    common = ["--preset", "fast", "--no-progress", "--set", "query.exclude_recent=4", "--max-frames", "10"]
    assert main(["run", str(bag), "--format", "rosbag", "--out", str(tmp_path / "from_bag"), *common]) == 0
    assert main(["run", str(euroc.root), "--out", str(tmp_path / "from_folder"), *common]) == 0
    out = capsys.readouterr().out
    assert out.count("10 frames") == 2
    from_bag = _decisions(tmp_path / "from_bag")
    assert from_bag == _decisions(tmp_path / "from_folder")
    assert sum(row[2] == "loop_detected" for row in from_bag[1:]) > 0
    meta = json.loads((tmp_path / "from_bag" / "meta.json").read_text())
    assert meta["format"] == "rosbag" and meta["stereo"] and meta["topic"] == "/cam0/image_raw"


def test_info_on_bag(tmp_path: Path, euroc: Euroc, capsys: pytest.CaptureFixture[str]) -> None:
    cams = stereo_cams(euroc)
    few = [Cam(c.topic, c.stamps[:5], c.images[:5], c.info, c.info_topic) for c in cams]
    bag = write_bag(tmp_path / "v101.bag", few, "ros1")
    assert main(["info", str(bag), "--json", str(tmp_path / "info.json")]) == 0
    out = capsys.readouterr().out
    assert "v101.bag: ROS bag, 4 topics" in out
    assert "/cam0/image_raw    sensor_msgs/msg/Image" in out and "752x480 mono8" in out
    assert (
        "frames: 5 stereo pairs from /cam0/image_raw (left) + /cam1/image_raw (right), header stamps" in out
    )
    assert "calibration: /cam0/camera_info + /cam1/camera_info: raw stereo, baseline 0.1101 m" in out
    summary = json.loads((tmp_path / "info.json").read_text())
    rows = {t["name"]: t for t in summary["topics"]}
    assert rows["/cam1/image_raw"]["count"] == 5 and rows["/cam1/image_raw"]["rate_hz"] == pytest.approx(4.0)
    assert summary["frames"]["dataset_frames"] == 5 and summary["calibration"]["kind"] == "stereo"
    assert main(["info", str(bag), "--mono", "--stamps", "bag"]) == 0
    assert "frames: 5 images from /cam0/image_raw, bag stamps" in capsys.readouterr().out
    assert main(["info", str(bag), "--topic", "/cam0/camera_info"]) == 0
    assert "frames: none chosen: " in capsys.readouterr().out


def test_info_on_folder_and_bad_bag(tmp_path: Path, euroc: Euroc, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["info", str(euroc.root)]) == 0
    out = capsys.readouterr().out
    assert "euroc dataset, 19 frames" in out and "752x480, 1 channel(s), stereo" in out
    broken = tmp_path / "broken.bag"
    broken.write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    assert main(["info", str(broken)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("stablecues info: error: ") and "broken.bag: not a readable ROS bag" in err
    assert "\n" not in err
    assert main(["run", str(broken), "--out", str(tmp_path / "run")]) == 1
    assert "broken.bag: not a readable ROS bag" in capsys.readouterr().err


def test_run_takes_the_bag_options(tmp_path: Path, euroc: Euroc, capsys: pytest.CaptureFixture[str]) -> None:
    """run --topic/--mono/--stamps reach the bag reader as info's do."""
    cams = stereo_cams(euroc)
    few = [Cam(c.topic, c.stamps[:6], c.images[:6], c.info, c.info_topic) for c in cams]
    bag = write_bag(tmp_path / "v101.bag", few, "ros1")
    out_dir = tmp_path / "mono"
    args = ["run", str(bag), "--out", str(out_dir), "--preset", "fast", "--no-progress",
            "--topic", "/cam1/image_raw", "--mono", "--stamps", "bag"]
    assert main(args) == 0
    assert "6 frames" in capsys.readouterr().out
    meta = json.loads((out_dir / "meta.json").read_text())
    assert meta["topic"] == "/cam1/image_raw" and not meta["stereo"]
    assert main(["run", str(bag), "--out", str(tmp_path / "bad"), "--topic", "/nope"]) == 1
    err = capsys.readouterr().err.strip()
    assert "/nope" in err and "\n" not in err
    # bag options on a dataset that is not a bag: refused, not ignored
    assert main(["run", str(euroc.root), "--out", str(tmp_path / "folder"), "--topic", "/cam0"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.endswith("--topic: for ROS bags only, and this dataset is read as a folder")
    assert "\n" not in err
    assert not (tmp_path / "folder").exists()

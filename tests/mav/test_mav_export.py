"""The image-folder dataset and TUM poses files written for posed frames (no shared data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from flight_synth import fake_images, track_log  # noqa: E402

from stablecues.errors import DatasetError, InputError  # noqa: E402
from stablecues.geometry.rotations import quat_to_matrix  # noqa: E402
from stablecues.mav import read_log  # noqa: E402
from stablecues.mav.export import tum_comments, write_image_folder, write_poses  # noqa: E402
from stablecues.mav.frames import read_frames  # noqa: E402
from stablecues.mav.poses import poses_for_frames  # noqa: E402
from stablecues.mav.solutions import gnss_solution  # noqa: E402
from stablecues.trajectory import read_tum  # noqa: E402


def test_write_image_folder(tmp_path: Path) -> None:
    log = read_log(track_log(tmp_path))
    names = ["110.0.png", "120.0.png", "900.0.png"]  # boot-clock seconds as names
    fake_images(tmp_path / "rec" / "left", names)
    fake_images(tmp_path / "rec" / "right", names)
    frames = read_frames(tmp_path / "rec")
    assert not frames.is_utc
    poses = poses_for_frames(frames, log, gnss_solution(log), mount="forward")
    assert poses.valid.tolist() == [True, True, False]
    with pytest.raises(InputError):
        write_image_folder(tmp_path / "ds", frames, poses, loops=np.zeros((3, 3), bool))
    (tmp_path / "cam.yaml").write_text("%YAML:1.0\nCamera.fx: 500.0\n")
    with pytest.raises(DatasetError, match="calibration"):
        write_image_folder(tmp_path / "ds", frames, poses, calibration=tmp_path / "none.yaml")
    out = write_image_folder(
        tmp_path / "ds", frames, poses, loops=np.zeros((2, 2), bool), calibration=tmp_path / "cam.yaml"
    )
    assert (out / "calib.yaml").read_text().startswith("%YAML:1.0")
    assert sorted(p.name for p in (out / "images").iterdir()) == ["000000_110.0.png", "000001_120.0.png"]
    assert sorted(p.name for p in (out / "right").iterdir()) == ["000000_110.0.png", "000001_120.0.png"]
    np.testing.assert_allclose(np.loadtxt(out / "times.txt"), [110.0, 120.0])
    t, tum = read_tum(out / "poses.txt")
    p = tum[:, :3, 3]
    np.testing.assert_allclose(p[:, 0], [50.0, 100.0], atol=0.01)
    # no attitude in a GNSS track: level and facing north, so a forward camera looks north
    np.testing.assert_allclose(tum[:, :3, 2], [[0, 1, 0], [0, 1, 0]], atol=1e-6)
    # the file itself: t x y z qx qy qz qw, the camera's (x, y, z, w) quaternion
    rows = np.loadtxt(out / "poses.txt")
    np.testing.assert_allclose(rows[:, 4:8], poses.quaternions[:2], atol=1e-7)
    np.testing.assert_allclose(quat_to_matrix(rows[:, 4:8]), tum[:, :3, :3], atol=1e-6)


def test_write_poses_with_its_header(tmp_path: Path) -> None:
    log = read_log(track_log(tmp_path))
    fake_images(tmp_path / "img", ["a.png", "b.png", "c.png"])
    (tmp_path / "img" / "times.txt").write_text("110\n120\n900\n")
    poses = poses_for_frames(read_frames(tmp_path / "img"), log, gnss_solution(log), mount="nadir")
    assert write_poses(tmp_path / "poses.txt", poses) == 2  # the frame at 900 s has no pose
    text = (tmp_path / "poses.txt").read_text().splitlines()
    assert text[: len(tum_comments(poses))] == [f"# {c}" for c in tum_comments(poses)]
    assert "no attitude in the source" in text[2] and "camera mount: nadir" in text[2]
    t, tum = read_tum(tmp_path / "poses.txt")
    np.testing.assert_allclose(t, [110.0, 120.0])
    np.testing.assert_allclose(tum[:, :3, 2], [[0, 0, -1], [0, 0, -1]], atol=1e-9)  # looking down
    np.testing.assert_allclose(tum[:, :3, 3], poses.positions[:2], atol=1e-4)

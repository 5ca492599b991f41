"""stablecues.datasets.euroc on a tiny ASL-layout sequence built in the test, and a malformed list."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.datasets import open_dataset
from stablecues.errors import DatasetError


def _img(path: Path, value: int, shape: tuple[int, ...] = (6, 8)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full(shape, value, np.uint8))


def test_euroc(tmp_path: Path) -> None:
    mav0 = tmp_path / "MH_09_test" / "mav0"
    stamps = [1_000_000_000_000_000_000 + k * 50_000_000 for k in range(3)]
    for cam in ("cam0", "cam1"):
        (mav0 / cam / "data").mkdir(parents=True)
        (mav0 / cam / "data.csv").write_text(
            "#timestamp [ns],filename\n" + "".join(f"{s},{s}.png\n" for s in stamps)
        )
        for k, s in enumerate(stamps):
            _img(mav0 / cam / "data" / f"{s}.png", k + (100 if cam == "cam1" else 0))
    t_bs = np.eye(4)
    t_bs[:3, 3] = [0.1, 0.0, 0.0]
    (mav0 / "cam0" / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: ["
        + ", ".join(str(v) for v in t_bs.ravel())
        + "]\nintrinsics: [458.0, 457.0, 367.0, 248.0]\nresolution: [8, 6]\ncamera_model: pinhole\n"
        + "distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n"
    )
    gt_dir = mav0 / "state_groundtruth_estimate0"
    gt_dir.mkdir()
    # body rotated 90 degrees about z (q_w, q_x, q_y, q_z), at x = k
    lines = "".join(f"{s},{k},0,0,0.7071068,0,0,0.7071068" + ",0" * 9 + "\n" for k, s in enumerate(stamps))
    (gt_dir / "data.csv").write_text("#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z,...\n" + lines)
    ds = open_dataset(tmp_path / "MH_09_test")
    assert ds.format == "euroc" and len(ds) == 3
    f = ds[1]
    assert f.timestamp == pytest.approx(1e9 + 0.05) and f.right is not None and f.right[0, 0] == 101
    assert f.pose is not None
    np.testing.assert_allclose(f.pose[:3, 3], [1.0, 0.1, 0.0], atol=1e-6)  # body x=1, cam offset rotated
    assert f.calibration_path == mav0 / "cam0" / "sensor.yaml"
    (mav0 / "cam0" / "data.csv").write_text("#timestamp [ns],filename\nabc,def.png\n")
    with pytest.raises(DatasetError, match="timestamp_ns,filename"):
        open_dataset(mav0)


def test_euroc_right_images_and_ground_truth_files(tmp_path: Path) -> None:
    seq = tmp_path / "V1_01_easy"
    mav0 = seq / "mav0"
    stamps = [1_403_715_273_262_142_976 + k * 50_000_000 for k in range(2)]
    for cam, offset in (("cam0", 0), ("cam1", 3_000_000)):  # cam1 3 ms late: too far
        (mav0 / cam / "data.csv").parent.mkdir(parents=True)
        (mav0 / cam / "data.csv").write_text("".join(f"{s + offset},{s}.png\n" for s in stamps))
        for s in stamps:
            _img(mav0 / cam / "data" / f"{s}.png", 1)
    with pytest.raises(DatasetError, match="cam1/data.csv: no right image within 2 ms of cam0/"):
        open_dataset(seq)
    ds = open_dataset(seq, stereo=False)
    assert ds[0].right is None and ds.poses is None and ds.calibration_path is None
    # a TUM body trajectory beside the sequence, named after it
    (tmp_path / "V1_01_groundtruth_tum.txt").write_text(f"{stamps[1] / 1e9:.9f} 1 2 3 0 0 0 1\n")
    poses = open_dataset(seq, stereo=False).poses
    assert poses is not None and np.isnan(poses[0]).all()
    np.testing.assert_allclose(poses[1, :3, 3], [1, 2, 3])  # no sensor.yaml: T_BS is the identity
    (mav0 / "cam0" / "data.csv").write_text(f"{stamps[0]},absent.png\n")
    with pytest.raises(DatasetError, match="lists absent.png, which is not in"):
        open_dataset(seq)
    (mav0 / "cam0" / "sensor.yaml").write_text("T_BS: {data: [1, 2]}\n")
    (mav0 / "cam0" / "data.csv").write_text(f"{stamps[0]},{stamps[0]}.png\n")
    with pytest.raises(DatasetError, match="expected T_BS with 16 numbers"):
        open_dataset(seq, stereo=False)

"""``stablecues verify`` end to end on real EuRoC images."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import shared_path
from stablecues.cli.main import main
from stablecues.detection import ImagePairVerifier
from stablecues.geometry import load_calibration
from stablecues.verification import VerificationConfig


def test_verify_stereo_pair_writes_json_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = shared_path("euroc", "loop_pairs")
    out_json, out_png = tmp_path / "r.json", tmp_path / "r.png"
    code = main(
        [
            "verify",
            str(d / "left_img_1.png"),
            str(d / "left_img_0.png"),
            "--calib",
            str(d / "sensorLeft.yaml"),
            "--right-a",
            str(d / "right_img_1.png"),
            "--right-b",
            str(d / "right_img_0.png"),
            "--json",
            str(out_json),
            "--plot",
            str(out_png),
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "ACCEPTED by triangles" in text and "pose B->A" in text
    record = json.loads(out_json.read_text())
    assert record["result"]["accepted"] is True
    assert record["result"]["n_triangles_agree"] >= 2
    assert len(record["result"]["rotation"]) == 3
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_verify_without_3d_falls_back(capsys: pytest.CaptureFixture[str]) -> None:
    d = shared_path("euroc", "loop_pairs")
    code = main(
        [
            "verify",
            str(d / "left_img_3.png"),
            str(d / "left_img_2.png"),
            "--calib",
            str(d / "sensorLeft.yaml"),
        ]
    )
    assert code == 0
    assert "by fundamental (fallback: no 3D points)" in capsys.readouterr().out


def test_verify_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "none.png"
    assert main(["verify", str(missing), str(missing), "--calib", str(tmp_path / "c.yaml")]) == 1
    assert "does not exist" in capsys.readouterr().err
    assert main(["verify", "a.png", "b.png", "--calib", "fr1", "--right-a", "x.png"]) == 1
    assert "--right-b" in capsys.readouterr().err


def test_kitti_pair_148_m_apart_is_rejected(capsys: pytest.CaptureFixture[str]) -> None:
    """KITTI 06 frames 435 and 01 are 148 m apart, headings 179 deg apart (its poses): 12 of 69
    matches fit a fundamental matrix, which DLoopDetector's 12-inlier rule accepts."""
    d = shared_path("kitti", "seq06_frames")
    calib = shared_path("calibration", "KITTI04-12.yaml")
    args = ["verify", str(d / "kitti06-435.png"), str(d / "kitti06-01.png"), "--calib", str(calib)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "REJECTED by fundamental" in text and "too_few_fundamental_inliers" in text
    # DLoopDetector's rule (12 inliers, no ratio, classic RANSAC) on the same matches accepts it
    classic = VerificationConfig(
        min_fundamental_inliers=12, min_fundamental_ratio=0.0, fundamental_method="ransac"
    )
    pair = ImagePairVerifier(load_calibration(calib), classic)
    res = pair.verify(d / "kitti06-435.png", d / "kitti06-01.png")
    assert res.verification.accepted and res.verification.n_inliers == 12


def test_verify_a_day_night_pair_with_learned_features(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    """Gardens Point, no calibration: one place by night against the same place by day is
    accepted with XFeat (ORB finds next to no matches there), places 30 apart are rejected; the
    result names the matcher and the verifier."""
    gp = shared_path("gardens_point_dev")
    night, day = gp / "night_right" / "Image040.jpg", gp / "day_right"
    out = tmp_path / "r.json"
    args = ["--features", "xfeat", "--n-features", "1000", "--preset", "learned"]
    assert main(["verify", str(night), str(day / "Image040.jpg"), *args, "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "ACCEPTED by fundamental" in text and "(matcher mnn)" in text
    record = json.loads(out.read_text())
    assert record["result"]["matcher"] == "mnn" and record["result"]["method"] == "fundamental"
    assert record["features"]["name"] == "xfeat" and record["calibration"].startswith("none")
    assert main(["verify", str(night), str(day / "Image070.jpg"), *args]) == 0
    assert "REJECTED" in capsys.readouterr().out
    assert main(["verify", str(night), str(day / "Image040.jpg")]) == 0  # ORB, the default
    assert "REJECTED" in capsys.readouterr().out


def test_verify_without_calibration_refuses_stereo(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["verify", "a.png", "b.png", "--right-a", "x.png", "--right-b", "y.png"]) == 1
    assert "need a calibration" in capsys.readouterr().err

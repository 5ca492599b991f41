"""Real-data acceptance: EuRoC loop pairs (stereo) and Kinect RGB-D relative poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from stablecues.detection.pair import ImagePairVerifier, PairFrame
from stablecues.geometry import Calibration, PinholeCamera, load_calibration, rotation_angle_deg
from stablecues.verification import Method, Status


@pytest.fixture(scope="module")
def euroc() -> tuple[ImagePairVerifier, list[PairFrame]]:
    folder = shared_path("euroc", "loop_pairs")
    pipeline = ImagePairVerifier(load_calibration(folder / "sensorLeft.yaml"))  # default settings
    frames = [
        pipeline.frame(folder / f"left_img_{i}.png", right=folder / f"right_img_{i}.png") for i in range(4)
    ]
    return pipeline, frames


@pytest.mark.parametrize(("query", "candidate"), [(1, 0), (0, 1), (3, 2), (2, 3)])
def test_euroc_true_loops_are_accepted(
    euroc: tuple[ImagePairVerifier, list[PairFrame]], query: int, candidate: int
) -> None:
    pipeline, frames = euroc
    res = pipeline.verify_frames(frames[query], frames[candidate]).verification
    assert res.accepted, res.reason
    assert res.method is Method.TRIANGLES and not res.fallback
    assert res.n_triangles_agree >= 2
    assert res.n_inliers >= 20
    # the two views are a few decimetres apart (EuRoC Vicon room revisits)
    assert res.translation is not None and 0.1 < np.linalg.norm(res.translation) < 1.5


@pytest.mark.parametrize(
    ("query", "candidate"), [(2, 0), (3, 0), (2, 1), (3, 1), (0, 2), (0, 3), (1, 2), (1, 3)]
)
def test_euroc_different_places_are_rejected(
    euroc: tuple[ImagePairVerifier, list[PairFrame]], query: int, candidate: int
) -> None:
    pipeline, frames = euroc
    res = pipeline.verify_frames(frames[query], frames[candidate]).verification
    assert not res.accepted
    assert res.status in (Status.TOO_FEW_MATCHES, Status.TOO_FEW_TRIANGLES, Status.TRIANGLES_DISAGREE)
    assert res.n_triangles_agree <= 1


def _pose(row: np.ndarray) -> np.ndarray:
    """Camera-to-world 4x4 from ``tx ty tz qx qy qz qw``."""
    x, y, z, w = row[3:7] / np.linalg.norm(row[3:7])
    rot = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = row[:3]
    return out


@pytest.fixture(scope="module")
def kinect() -> tuple[ImagePairVerifier, dict[int, PairFrame], np.ndarray, Path]:
    folder = shared_path("rgbd_kinect5")
    calib = Calibration(left=PinholeCamera(518.0, 519.0, 325.5, 253.5, 640, 480), depth_scale=1000.0)
    pipeline = ImagePairVerifier(calib)
    frames = {
        i: pipeline.frame(folder / "color" / f"{i}.png", depth=folder / "depth" / f"{i}.pgm")
        for i in (1, 2, 3)
    }
    return pipeline, frames, np.loadtxt(folder / "pose.txt"), folder


@pytest.mark.parametrize(("query", "candidate"), [(2, 1), (3, 2)])
def test_kinect_relative_pose(
    kinect: tuple[ImagePairVerifier, dict[int, PairFrame], np.ndarray, Path], query: int, candidate: int
) -> None:
    pipeline, frames, poses, _ = kinect
    res = pipeline.verify_frames(frames[query], frames[candidate]).verification
    assert res.accepted, res.reason
    assert res.rotation is not None and res.translation is not None
    # pose.txt is camera-to-world: candidate -> query is inv(T_w_query) T_w_candidate
    truth = np.linalg.inv(_pose(poses[query - 1])) @ _pose(poses[candidate - 1])
    assert np.linalg.norm(res.translation - truth[:3, 3]) < 0.05
    assert rotation_angle_deg(res.rotation.T @ truth[:3, :3]) < 2.0

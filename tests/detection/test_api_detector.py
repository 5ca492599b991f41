"""The detector's API without traps: a calibration as a path, features as OpenCV gives them, and
the relative pose of loops found with map points but no calibration (a rigid 3D-3D fit)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import shared_path
from stablecues import Frame, LoopDetector, preset
from stablecues.detection.detector import align_points
from stablecues.errors import CalibrationError, InputError
from stablecues.geometry import Calibration, NoiseModel, rotation_angle_deg
from stablecues.geometry.rotations import quat_from_rotvec, quat_to_matrix
from stablecues.types import DescriptorKind, Features

QUICK = {"query": {"exclude_recent": 0, "temporal_k": 1}, "similarity": False}


def textured(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((240, 320), 100, np.uint8)
    for _ in range(400):
        x, y = int(rng.integers(0, 320)), int(rng.integers(0, 240))
        cv2.rectangle(img, (x, y), (x + int(rng.integers(3, 20)), y + int(rng.integers(3, 20))),
                      int(rng.integers(0, 256)), -1)
    return cv2.GaussianBlur(img, (3, 3), 0)


def rigid(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return quat_to_matrix(quat_from_rotvec(rng.normal(0, 0.2, 3))), rng.normal(0, 0.5, 3)


# --- calibration as an object or a path -------------------------------------------------------------

def test_calibration_by_path_or_object(tmp_path: Path) -> None:
    src = shared_path("calibration", "EuRoC_stereo.yaml")
    by_str = LoopDetector(preset("fast"), calibration=str(src))
    assert isinstance(by_str.calibration, Calibration) and by_str.calibration.is_stereo
    by_path = LoopDetector(preset("fast"), calibration=src)
    assert by_path.calibration is not None and by_path.calibration.baseline == by_str.calibration.baseline
    assert LoopDetector(preset("fast"), calibration=by_str.calibration).calibration is by_str.calibration
    assert LoopDetector(preset("fast"), calibration="fr2").calibration.depth_scale == 5000  # type: ignore[union-attr]
    # a frame's own calibration may be a path too: loaded once, then reused
    shutil.copy(src, tmp_path / "cam.yaml")
    frame = Frame(index=0, name="0", timestamp=0.0, image=textured(), calibration=tmp_path / "cam.yaml")
    first = by_str.preparer.calibration_of(frame)
    assert first is not None and first.is_stereo and by_str.preparer.calibration_of(frame) is first


def test_bad_calibrations_are_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="nope.yaml does not exist"):
        LoopDetector(preset("fast"), calibration=tmp_path / "nope.yaml")
    with pytest.raises(InputError, match="calibration: expected a Calibration or the path .* got dict"):
        LoopDetector(preset("fast"), calibration={"fx": 500})  # type: ignore[arg-type]
    det = LoopDetector(preset("fast"))
    with pytest.raises(CalibrationError, match="missing.yaml does not exist"):
        det.process(Frame(index=0, name="0", timestamp=0.0, image=textured(), calibration="missing.yaml"))
    assert not (tmp_path / "nope.yaml").exists()


# --- features as OpenCV gives them ----------------------------------------------------------------

def test_opencv_pairs_give_the_same_decisions_as_features() -> None:
    orb = cv2.ORB_create(500)
    images = [textured(s % 3) for s in range(6)]  # three places, each seen twice
    runs = []
    for form in ("features", "pair", "frame"):
        det = LoopDetector(preset("fast", QUICK))
        out = []
        for i, img in enumerate(images):
            kps, desc = orb.detectAndCompute(img, None)
            frame = Frame(index=i, name=str(i), timestamp=float(i), image=img)
            if form == "features":
                d = det.process(frame, features=Features.from_cv2(kps, desc, image_size=(320, 240)))
            elif form == "pair":
                d = det.process(frame, features=(kps, desc))
            else:
                given = Frame(index=i, name=str(i), timestamp=float(i), image=img, features=(kps, desc))
                d = det.process(given)
            out.append((d.status, d.candidate_frame, round(d.score, 9), d.n_features))
        runs.append(out)
    assert runs[0] == runs[1] == runs[2]
    assert [r[:2] for r in runs[0][3:]] == [("loop_detected", 0), ("loop_detected", 1), ("loop_detected", 2)]
    assert all(r[3] == len(orb.detect(images[0], None)) for r in runs[0][:1])


def test_wrong_features_are_refused_with_the_frame_named() -> None:
    img = textured()
    kps, desc = cv2.ORB_create(200).detectAndCompute(img, None)
    det = LoopDetector(preset("fast"))
    frame = Frame(index=7, name="seven", timestamp=0.0, image=img)
    with pytest.raises(InputError, match=r"frame 7 \(seven\): features: expected Features or .* ndarray"):
        det.process(frame, features=desc)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"frame 7 \(seven\): descriptors: expected dtype uint8 .* int32"):
        det.store(frame, features=(kps, desc.astype(np.int32)))
    sift_kps, sift_desc = cv2.SIFT_create(100).detectAndCompute(img, None)
    with pytest.raises(InputError, match="128-dim float32 descriptors but the vocabulary holds 32-byte"):
        det.process(frame, features=(sift_kps, sift_desc))
    twice = Frame(index=7, name="seven", timestamp=0.0, image=img, features=(kps, desc))
    with pytest.raises(InputError, match="features given twice"):
        det.process(twice, features=(kps, desc))
    assert len(det) == 0  # nothing half-stored


def test_no_keypoints_is_a_normal_frame() -> None:
    det = LoopDetector(preset("fast"))
    flat = np.full((240, 320), 90, np.uint8)
    kps, desc = cv2.ORB_create(200).detectAndCompute(flat, None)
    assert desc is None and not kps
    d = det.process(Frame(index=0, name="flat", timestamp=0.0, image=flat), features=(kps, desc))
    assert d.n_features == 0 and len(det) == 1 and det.db.entry(0).features.descriptor_kind == DescriptorKind(
        "binary", 32)


# --- map points without calibration: the pose from the points -----------------------------------

def test_align_points_recovers_a_known_motion_among_outliers() -> None:
    rng = np.random.default_rng(3)
    rot, t = rigid(3)
    cand = rng.uniform([-2, -1.5, 1], [2, 1.5, 6], (200, 3))
    query = cand @ rot.T + t
    noise = NoiseModel(0.005, 500.0)
    q_pts = noise.points(query + rng.normal(0, 0.005, query.shape))
    wrong = rng.random(200) < 0.4  # 40 % wrong matches
    c_xyz = cand.copy()
    c_xyz[wrong] = rng.uniform([-2, -1.5, 1], [2, 1.5, 6], (int(wrong.sum()), 3))
    c_xyz[:5] = np.nan  # keypoints without a map point
    fit = align_points(q_pts, noise.points(c_xyz))
    assert fit is not None
    r_est, t_est, inliers, rms = fit
    assert rotation_angle_deg(r_est.T @ rot) < 0.5 and np.linalg.norm(t_est - t) < 0.02
    assert inliers.shape == (200,) and not inliers[:5].any()
    assert (inliers & wrong).sum() <= 3 and inliers.sum() >= 0.9 * (~wrong[5:]).sum()
    assert rms < 0.03
    assert align_points(q_pts.subset(np.arange(4)), noise.points(c_xyz).subset(np.arange(4))) is None


def test_map_points_without_calibration_give_the_loop_pose() -> None:
    """One place seen twice, the second time from a known rigid motion away: the SLAM system's
    map points of the two keyframes differ by that motion, and the loop's pose recovers it."""
    img = textured()
    kps, desc = cv2.ORB_create(500).detectAndCompute(img, None)
    uv = np.array([k.pt for k in kps])
    z = 3.0 + 0.01 * uv[:, 0]  # a slanted wall
    first = np.stack([(uv[:, 0] - 160) * z / 400, (uv[:, 1] - 120) * z / 400, z], axis=1)
    first[::10] = np.nan  # some keypoints have no map point
    rot, t = rigid(5)
    second = first @ rot.T + t
    det = LoopDetector(preset("fast", QUICK))
    det.process(Frame(index=0, name="a", timestamp=0.0, image=img, points3d=first), features=(kps, desc))
    d = det.process(Frame(index=1, name="b", timestamp=1.0, image=img, points3d=second), features=(kps, desc))
    assert d.accepted and d.candidate_frame == 0 and d.points_source == "map"
    pose = d.relative_pose
    assert pose is not None and d.verification is not None
    assert "3D-3D fit" in d.verification.reason and d.verification.n_inliers > 100
    assert rotation_angle_deg(pose[:3, :3].T @ rot) < 0.1 and np.linalg.norm(pose[:3, 3] - t) < 0.005


def test_map_points_on_real_rgbd_frames_match_the_ground_truth() -> None:
    """Kinect frames (rgbd_kinect5): ORB keypoints with map points from the depth image, no
    calibration given to the detector; each loop's pose is checked against pose.txt."""
    folder = shared_path("rgbd_kinect5")
    poses = np.loadtxt(folder / "pose.txt")
    fx, fy, cx, cy = 518.0, 519.0, 325.5, 253.5

    def camera_to_world(row: np.ndarray) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = quat_to_matrix(row[3:7]), row[:3]
        return out

    orb = cv2.ORB_create(1000)
    det = LoopDetector(preset("fast", {"query": {"exclude_recent": 1, "temporal_k": 1}}))
    checked = 0
    for i in range(5):
        image = cv2.imread(str(folder / "color" / f"{i + 1}.png"))
        depth = cv2.imread(str(folder / "depth" / f"{i + 1}.pgm"), cv2.IMREAD_UNCHANGED) / 1000.0
        kps, desc = orb.detectAndCompute(image, None)
        uv = np.array([k.pt for k in kps])
        zz = depth[np.round(uv[:, 1]).astype(int).clip(0, 479), np.round(uv[:, 0]).astype(int).clip(0, 639)]
        zz[zz <= 0] = np.nan
        xyz = np.stack([(uv[:, 0] - cx) * zz / fx, (uv[:, 1] - cy) * zz / fy, zz], axis=1)
        d = det.process(Frame(index=i, name=str(i), timestamp=float(i), image=image, points3d=xyz),
                        features=(kps, desc))
        if d.accepted:
            pose = d.relative_pose
            assert pose is not None, d.verification.reason if d.verification else d.status
            truth = np.linalg.inv(camera_to_world(poses[i])) @ camera_to_world(poses[d.candidate_frame])
            assert np.linalg.norm(pose[:3, 3] - truth[:3, 3]) < 0.2  # frames 4-6 m deep: cm-level depth noise
            assert rotation_angle_deg(pose[:3, :3].T @ truth[:3, :3]) < 3.0
            checked += 1
    assert checked >= 2


def test_the_extractor_name_picks_the_shipped_vocabulary() -> None:
    """features.name "sift" runs end to end on the shipped SIFT vocabulary: float descriptors in
    the BoW transform, the database and the matching of the geometric check."""
    images = [textured(seed) for seed in (0, 1, 2, 3)] + [textured(0)]  # the last revisits the first
    det = LoopDetector(preset("fast", {"features": {"name": "sift"}, "query": {"exclude_recent": 1}}))
    assert det.vocabulary.descriptor_kind.kind == "float"
    results = [det.process(Frame(i, f"{i}.png", float(i), im)) for i, im in enumerate(images)]
    det.close()
    assert results[-1].accepted and results[-1].candidate_frame == 0
    assert not any(r.accepted for r in results[:-1])


# --- nothing dropped without a word (issue 35) ---------------------------------------------------


def test_a_frame_the_calibration_does_not_describe_is_refused() -> None:
    """A TUM fr1 calibration (640x480) with 320x240 frames: one line naming both sizes."""
    det = LoopDetector(preset("fast", QUICK), calibration="fr1")
    want = r"frame 0 \(0\): a 320x240 image, but the calibration .* is for 640x480"
    with pytest.raises(InputError, match=want):
        det.process(Frame(index=0, name="0", timestamp=0.0, image=textured()))


def test_unused_images_repeated_indices_and_a_short_stream_are_said(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level("WARNING")
    path = tmp_path / "map.sqlite"
    det = LoopDetector(preset("fast", {"similarity": False}), database=path)
    img = textured()
    det.process(Frame(index=0, name="0", timestamp=0.0, image=img, right=img))
    det.process(Frame(index=1, name="1", timestamp=1.0, image=textured(1), right=img))
    said = [r.getMessage() for r in caplog.records]
    assert sum("has a right image but the detector has no calibration" in m for m in said) == 1  # once
    det.process(Frame(index=1, name="1b", timestamp=2.0, image=textured(2)))
    said = [r.getMessage() for r in caplog.records]
    assert any("frame index 1 does not follow the latest stored frame 1" in m for m in said)
    assert det.next_index == 2
    caplog.clear()
    det.close()  # 3 frames, all inside the 20-frame exclusion window
    assert any("all 3 frames fell inside the exclusion window (query.exclude_recent = 20)" in r.getMessage()
               for r in caplog.records)
    with LoopDetector(preset("fast", {"similarity": False}), database=path) as again:
        assert again.next_index == 2  # where a reopened map continues
    assert LoopDetector(preset("fast")).next_index == 0

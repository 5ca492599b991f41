"""A SLAM system's own features and map points handed to the loop detector.

    python examples/slam_map_points.py --intrinsics 518 519 325.5 253.5 --depth-scale 1000 \\
        --exclude-recent 1 --poses ../shared/data/rgbd_kinect5/pose.txt \\
        ../shared/data/rgbd_kinect5/color/1.png,../shared/data/rgbd_kinect5/depth/1.pgm ...

A SLAM system (ORB-SLAM and its kin) keeps, per keyframe, its ORB keypoints and descriptors and
the map point each keypoint observes. Here a stand-in front end makes those from RGB-D frames
(OpenCV ORB; map points back-projected from the depth image with ``--intrinsics``) and hands
them to the detector as they are: ``features=(keypoints, descriptors)`` and ``points3d`` in the
keyframe's camera frame, NaN where a keypoint has no map point. The detector gets no
calibration: the loop's relative pose comes from the matched map points (a RANSAC rigid fit).
With ``--poses`` (one camera-to-world pose ``tx ty tz qx qy qz qw`` per frame) each loop's pose
is compared with the ground truth.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

import cv2
import numpy as np

from stablecues import Frame, LoopDetector, StableCuesError, preset
from stablecues.geometry import rotation_angle_deg
from stablecues.geometry.rotations import quat_to_matrix


def read(path: str, flags: int) -> np.ndarray:
    image = cv2.imread(path, flags)
    if image is None:
        raise SystemExit(f"error: cannot read image {path}")
    return image


def camera_to_world(row: np.ndarray) -> np.ndarray:
    """4x4 pose from ``tx ty tz qx qy qz qw``."""
    out = np.eye(4)
    out[:3, :3] = quat_to_matrix(row[3:7])
    out[:3, 3] = row[:3]
    return out


def map_points(keypoints: Sequence[cv2.KeyPoint], depth: np.ndarray, intrinsics: Sequence[float],
               depth_scale: float) -> np.ndarray:
    """(N, 3) float32 point per keypoint in the camera frame, NaN without depth (what a SLAM
    system's keyframe knows of its map)."""
    fx, fy, cx, cy = intrinsics
    uv = np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2)
    h, w = depth.shape
    cols = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    z = depth[rows, cols].astype(np.float64) / depth_scale
    z[z <= 0] = np.nan
    return np.stack([(uv[:, 0] - cx) * z / fx, (uv[:, 1] - cy) * z / fy, z], axis=1).astype(np.float32)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sources", nargs="+", metavar="COLOR,DEPTH",
                        help="a colour image and its depth image")
    parser.add_argument("--intrinsics", type=float, nargs=4, required=True, metavar=("FX", "FY", "CX", "CY"),
                        help="the front end's camera (the detector is not given it)")
    parser.add_argument("--depth-scale", type=float, required=True, help="raw depth units per metre")
    parser.add_argument("--features", type=int, default=1000,
                        help="ORB features per keyframe (default: 1000)")
    parser.add_argument("--preset", default="default", help="detector preset (default: %(default)s)")
    parser.add_argument("--exclude-recent", type=int, default=None,
                        help="the latest N keyframes are never proposed as loops (preset: 20)")
    parser.add_argument("--poses", default=None, help="ground truth: tx ty tz qx qy qz qw per frame")
    args = parser.parse_args(argv)
    if any(s.count(",") != 1 for s in args.sources):
        parser.error("every SOURCE is COLOR,DEPTH")
    poses = None if args.poses is None else np.loadtxt(args.poses, ndmin=2)
    if poses is not None and (poses.shape[1] != 7 or len(poses) < len(args.sources)):
        parser.error(f"--poses: expected 7 numbers per line and one line per frame, got {poses.shape}")
    overrides = {} if args.exclude_recent is None else {"query": {"exclude_recent": args.exclude_recent}}
    orb = cv2.ORB.create(args.features)
    try:
        loops, start = 0, time.perf_counter()
        with LoopDetector(preset(args.preset, overrides)) as detector:  # no calibration
            for i, source in enumerate(args.sources):
                color, depth = source.split(",")
                image = read(color, cv2.IMREAD_COLOR)
                keypoints, descriptors = orb.detectAndCompute(image, None)  # the SLAM system's own
                depth_image = read(depth, cv2.IMREAD_UNCHANGED)
                xyz = map_points(keypoints, depth_image, args.intrinsics, args.depth_scale)
                frame = Frame(index=i, name=color, timestamp=float(i), image=image, points3d=xyz)
                d = detector.process(frame, features=(keypoints, descriptors))
                if not d.accepted:
                    continue
                loops += 1
                pose = d.relative_pose
                line = f"loop: frame {i} -> frame {d.candidate_frame}"
                if pose is None:
                    print(f"{line}, no pose: {d.verification.reason if d.verification else ''}")
                    continue
                line += f", t = {np.array2string(pose[:3, 3], precision=3)} m"
                if poses is not None:  # candidate -> query = inv(T_w_query) @ T_w_candidate
                    candidate = camera_to_world(poses[d.candidate_frame])
                    truth = np.linalg.inv(camera_to_world(poses[i])) @ candidate
                    line += (f", error {np.linalg.norm(pose[:3, 3] - truth[:3, 3]):.3f} m, "
                             f"{rotation_angle_deg(pose[:3, :3].T @ truth[:3, :3]):.2f} deg")
                print(line)
        per_frame = (time.perf_counter() - start) / len(args.sources) * 1e3
        print(f"{len(args.sources)} keyframes, {loops} loops, {per_frame:.0f} ms per keyframe")
    except StableCuesError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Loop closure on RGB-D frames (TUM RGB-D, Kinect recordings), one frame at a time.

    python examples/rgbd_tum.py --intrinsics 518 519 325.5 253.5 --depth-scale 1000 \\
        --exclude-recent 1 --poses ../shared/data/rgbd_kinect5/pose.txt \\
        ../shared/data/rgbd_kinect5/color/{1,2,3,4,5}.png,../shared/data/rgbd_kinect5/depth/{1,2,3,4,5}.pgm

(with the braces expanded pairwise: ``color/1.png,depth/1.pgm color/2.png,depth/2.pgm ...``).
Each SOURCE is ``COLOR,DEPTH``: a colour image and its registered 16-bit depth image in raw
units (``--depth-scale`` units per metre: 5000 for TUM, 1000 for most Kinect recordings). The
camera is a calibration file or TUM name (``--calib fr2``), or ``--intrinsics``. With
``--poses`` (one camera-to-world pose ``tx ty tz qx qy qz qw`` per frame, in order) each loop's
pose is compared with the ground truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from stablecues import Calibration, Frame, LoopDetector, PinholeCamera, StableCuesError, preset
from stablecues.geometry import load_calibration, rotation_angle_deg
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


def calibration_from(args: argparse.Namespace) -> Calibration:
    if args.calib is not None:
        calib = load_calibration(args.calib)
        if args.depth_scale is not None:
            calib = dataclasses.replace(calib, depth_scale=args.depth_scale)
        if calib.depth_scale is None:
            raise SystemExit(f"error: {args.calib} has no depth scale (DepthMapFactor); give --depth-scale")
        return calib
    if args.intrinsics is None or args.depth_scale is None:
        raise SystemExit("error: give --calib, or --intrinsics FX FY CX CY with --depth-scale")
    fx, fy, cx, cy = args.intrinsics
    camera = PinholeCamera(fx, fy, cx, cy)
    return Calibration(left=camera, depth_scale=args.depth_scale, source="--intrinsics")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sources", nargs="+", metavar="COLOR,DEPTH",
                        help="a colour image and its depth image")
    parser.add_argument("--calib", default=None,
                        help="calibration file, or a TUM camera name (fr1, fr2, fr3)")
    parser.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"))
    parser.add_argument("--depth-scale", type=float, default=None, help="raw depth units per metre")
    parser.add_argument("--preset", default="default", help="detector preset (default: %(default)s)")
    parser.add_argument("--exclude-recent", type=int, default=None,
                        help="the latest N frames are never proposed as loops (preset: 20)")
    parser.add_argument("--poses", default=None, help="ground truth: tx ty tz qx qy qz qw per frame")
    args = parser.parse_args(argv)
    if any(s.count(",") != 1 for s in args.sources):
        parser.error("every SOURCE is COLOR,DEPTH")
    poses = None if args.poses is None else np.loadtxt(args.poses, ndmin=2)
    if poses is not None and (poses.shape[1] != 7 or len(poses) < len(args.sources)):
        parser.error(f"--poses: expected 7 numbers per line and one line per frame, got {poses.shape}")
    overrides = {} if args.exclude_recent is None else {"query": {"exclude_recent": args.exclude_recent}}
    try:
        calib = calibration_from(args)
        loops, start = 0, time.perf_counter()
        with LoopDetector(preset(args.preset, overrides), calibration=calib) as detector:
            for i, source in enumerate(args.sources):
                color, depth = source.split(",")
                frame = Frame(index=i, name=Path(color).name, timestamp=float(i),
                              image=read(color, cv2.IMREAD_COLOR), depth=read(depth, cv2.IMREAD_UNCHANGED))
                d = detector.process(frame)
                if not d.accepted:
                    continue
                loops += 1
                line = f"loop: frame {i} -> frame {d.candidate_frame}"
                pose = d.relative_pose
                if pose is None:
                    print(line + ", no pose")
                    continue
                line += f", t = {np.array2string(pose[:3, 3], precision=3)} m"
                if poses is not None:  # candidate -> query = inv(T_w_query) @ T_w_candidate
                    candidate = camera_to_world(poses[d.candidate_frame])
                    truth = np.linalg.inv(camera_to_world(poses[i])) @ candidate
                    line += (f", error {np.linalg.norm(pose[:3, 3] - truth[:3, 3]):.3f} m, "
                             f"{rotation_angle_deg(pose[:3, :3].T @ truth[:3, :3]):.2f} deg")
                print(line)
        per_frame = (time.perf_counter() - start) / len(args.sources) * 1e3
        print(f"{len(args.sources)} frames, {loops} loops, {per_frame:.0f} ms per frame")
    except StableCuesError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

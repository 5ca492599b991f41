"""``stablecues gt``: loop ground truth made from camera poses."""

from __future__ import annotations

import argparse
from pathlib import Path

from .commands import summary
from .options import FORMAT_HELP, add_pose_truth_options, loop_rule_from_args


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser("gt", help=summary("gt"))
    sub = p.add_subparsers(dest="gt_command", metavar="ACTION", required=True)
    poses = sub.add_parser(
        "poses", help="loop ground truth from poses, for `stablecues eval --gt`",
        description="Mark frame i as revisiting the earlier frame j when their positions are within "
                    "--max-distance, their orientations within --max-angle, and they are --min-gap-s / "
                    "--min-gap-frames apart. SOURCE is a dataset whose frames carry poses (TUM, KITTI, "
                    "EuRoC, a folder with poses.txt), a dataset with --poses FILE matched to its frames "
                    "by time, or a trajectory file alone (TUM, KITTI poses, EuRoC data.csv), whose rows "
                    "are then the frames. Writes an N x N bool .npy (the project's convention).",
    )
    poses.add_argument("source", type=Path, metavar="SOURCE",
                       help="dataset folder / ROS bag, or trajectory file")
    poses.add_argument("--out", type=Path, required=True, help="the .npy to write")
    poses.add_argument("--poses", type=Path, metavar="FILE",
                       help="a trajectory for the frames of the dataset SOURCE (matched by time)")
    poses.add_argument("--format", default="auto", help=FORMAT_HELP)
    poses.add_argument("--every", type=int, default=1, metavar="K",
                       help="a trajectory file alone: keep every K-th pose as a frame (default 1)")
    add_pose_truth_options(poses)
    return p


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..outputs import check_output, output_file
    from ..posetruth import frame_poses, pose_ground_truth

    rule = loop_rule_from_args(args, "gt poses")
    check_output(args.out, "ground truth", make_folder=True)
    source = frame_poses(args.source, trajectory=args.poses, max_dt=args.max_dt, every=args.every,
                         dataset_format=args.format)
    gt = pose_ground_truth(source, rule)
    with output_file(args.out, "ground truth") as tmp:
        np.save(tmp, gt.matrix)
    info = gt.notes["from_poses"]
    missing = info["frames_without_pose"]
    print(f"{args.out}: {gt.n} frames, {int(gt.matrix.sum())} loop pairs "
          f"({int(gt.matrix.any(axis=1).sum())} frames revisit an earlier one) from {source.source}")
    lost = f"; {missing} frames have no pose and close no loop" if missing else ""
    print(f"loop rule: {info['rule']}{lost}")
    return 0

"""``stablecues info``: what a ROS bag holds (topics, types, counts, rates, image sizes) and which
topics a run would read; for a dataset folder, the dataset's summary."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from .commands import summary
from .options import FORMAT_HELP, add_rosbag_options, is_rosbag, rosbag_options


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "info",
        help=summary("info"),
        description="For a ROS bag (.bag, .db3, .mcap or a ROS 2 bag folder): every topic with its type, "
        "message count, rate and image size, then the image topics, stamps and CameraInfo that "
        "'stablecues run BAG' would use. For a dataset folder: its format, frames and files.",
    )
    p.add_argument("dataset", type=Path, help="ROS bag or dataset folder")
    p.add_argument("--format", default="auto", help=FORMAT_HELP)
    add_rosbag_options(p)
    p.add_argument("--json", type=Path, metavar="OUT", help="also write the summary as JSON")
    return p


def _rate(value: float | None) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.2f}"


def _print_bag(summary: dict[str, Any]) -> None:
    topics = summary["topics"]
    print(f"{summary['bag']}: ROS bag, {len(topics)} topics")
    width = max([len("topic")] + [len(t["name"]) for t in topics])
    twidth = max([len("type")] + [len(t["msgtype"]) for t in topics])
    print(f"  {'topic':<{width}}  {'type':<{twidth}}  {'messages':>8}  {'rate Hz':>8}  image")
    for t in topics:
        size = t["image_size"]
        image = "" if size is None else f"{size[0]}x{size[1]}"
        if t["encoding"]:
            image = f"{image} {t['encoding']}".strip()
        rate = _rate(t["rate_hz"])
        print(f"  {t['name']:<{width}}  {t['msgtype']:<{twidth}}  {t['count']:>8}  {rate:>8}  {image}")
    frames = summary["frames"]
    if frames is None:
        print(f"frames: none chosen: {summary['frames_error']}")
        return
    n = frames["dataset_frames"]
    kind = f"{n} stereo pairs" if frames["stereo"] else f"{n} images"
    used = frames["topic"] + (f" (left) + {frames['right_topic']} (right)" if frames["stereo"] else "")
    span = frames["last_time"] - frames["first_time"]
    print(f"frames: {kind} from {used}, {frames['stamps']} stamps, {span:.3f} s")
    if frames["unmatched_left_images"]:
        print(f"  {frames['unmatched_left_images']} left images without a right image were dropped")
    _print_calibration(summary, frames)


def _print_calibration(summary: dict[str, Any], frames: dict[str, Any]) -> None:
    calib = summary["calibration"]
    if summary["calibration_error"]:
        print(f"calibration: refused: {summary['calibration_error']}")
    elif calib is None:
        print("calibration: none (no calibrated CameraInfo beside the image topics)")
    else:
        rig = f"{'rectified' if calib['rectified'] else 'raw'} {calib['kind']}"
        if calib["baseline_m"] is not None:
            rig += f", baseline {calib['baseline_m']:.4f} m"
        print(
            f"calibration: {' + '.join(frames['camera_info'])}: {rig}, fx {calib['fx']:.3f} fy "
            f"{calib['fy']:.3f} cx {calib['cx']:.3f} cy {calib['cy']:.3f}"
        )


def _folder_summary(path: Path, format: str) -> dict[str, Any]:
    from ..datasets import open_dataset

    ds = open_dataset(path, format=format)
    out: dict[str, Any] = dict(ds.describe())
    times = ds.times
    known = times[~(times != times)] if len(times) else times
    out["first_time"] = float(known[0]) if len(known) else None
    out["last_time"] = float(known[-1]) if len(known) else None
    if len(ds):
        image = ds[0].image
        out["image_size"] = [int(image.shape[1]), int(image.shape[0])]
        out["image_channels"] = 1 if image.ndim == 2 else int(image.shape[2])
    return out


def _print_folder(summary: dict[str, Any]) -> None:
    print(f"{summary['dataset']}: {summary['format']} dataset, {summary['dataset_frames']} frames")
    size = summary.get("image_size")
    if size:
        print(
            f"  images: {size[0]}x{size[1]}, {summary['image_channels']} channel(s)"
            + (", stereo" if summary["stereo"] else "")
            + (", depth" if summary["depth"] else "")
        )
    if summary["first_time"] is not None:
        print(f"  time: {summary['first_time']:.6f} .. {summary['last_time']:.6f} s")
    for key in ("calibration", "ground_truth"):
        print(f"  {key.replace('_', ' ')}: {summary[key] or 'none'}")
    print(f"  poses: {'yes' if summary['poses'] else 'no'}")


def run(args: argparse.Namespace) -> int:
    from ..datasets.rosbag import bag_summary
    from ..outputs import check_output, write_output

    if args.json:
        check_output(args.json, "summary")  # before reading a whole bag
    if is_rosbag(args):
        summary = bag_summary(args.dataset, **rosbag_options(args))
        _print_bag(summary)
    else:
        summary = _folder_summary(args.dataset, args.format)
        _print_folder(summary)
    if args.json:
        write_output(args.json, json.dumps(summary, indent=2) + "\n", "summary")
        print(f"written: {args.json}")
    return 0

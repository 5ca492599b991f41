"""``stablecues mav``: drone flight logs -- summary, plots, camera poses, loop ground truth.

stablecues mav info LOG
stablecues mav plot LOG --out DIR
stablecues mav poses LOG [--frames DIR --times CSV] --out poses.txt [--dataset DIR]
stablecues mav gt poses.txt --out gt.png          (TUM or KITTI poses; also writes gt.npy)
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from ..errors import InputError
from .commands import summary

if TYPE_CHECKING:
    from ..mav import FlightLog, NavSolution


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "mav",
        help=summary("mav"),
        description="Read ArduPilot dataflash (.bin/.log), PX4 ULog (.ulg) or CSV GNSS tracks; fuse "
        "IMU, GNSS, barometer and compass into poses; pair them with camera frames; build loop "
        "ground truth; draw the flight figures.",
    )
    sub = p.add_subparsers(dest="mav_command", metavar="ACTION")

    info = sub.add_parser("info", help="summary of a flight log (duration, sensors, flight modes)")
    info.add_argument("log", type=Path, metavar="LOG")
    info.add_argument(
        "--ekf", action="store_true", help="also run the EKF and compare it with the onboard one"
    )

    plot = sub.add_parser("plot", help="trajectory, altitude with flight modes, lat/lon/alt, roll/pitch/yaw")
    plot.add_argument("log", type=Path, metavar="LOG")
    plot.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the PNG files")
    plot.add_argument("--no-ekf", action="store_true", help="do not draw this package's EKF solution")
    plot.add_argument("--dpi", type=int, default=150)

    poses = sub.add_parser("poses", help="a pose per camera frame (or at a fixed rate) as a TUM file")
    poses.add_argument("log", type=Path, metavar="LOG")
    poses.add_argument("--out", type=Path, required=True, metavar="POSES_TXT", help="TUM poses file to write")
    poses.add_argument("--frames", type=Path, metavar="DIR", help="image folder or recording folder")
    poses.add_argument("--times", type=Path, metavar="CSV", help="CSV of capture times (and image names)")
    poses.add_argument("--time-column", metavar="NAME", help="time column of the CSV (default: auto)")
    poses.add_argument(
        "--clock",
        choices=("auto", "utc", "boot", "log"),
        default="auto",
        help="clock of the frame times: UNIX (mapped by GNSS time), autopilot boot clock, "
        "seconds since log start, or auto (UNIX when they look like it, else boot)",
    )
    poses.add_argument(
        "--offset",
        default="0",
        metavar="S|estimate",
        help="seconds added to the frame times after the clock mapping, or 'estimate' "
        "(fit from the frames' geotags against the GNSS track)",
    )
    poses.add_argument(
        "--source",
        choices=("auto", "ekf", "onboard", "gnss"),
        default="auto",
        help="pose source: this package's EKF, the autopilot's EKF, or the GNSS track "
        "(auto: ekf when the log has IMU and GNSS)",
    )
    poses.add_argument(
        "--mount",
        choices=("body", "forward", "nadir"),
        default="body",
        help="camera mounting: body frame (FRD), forward- or down-looking optical frame",
    )
    poses.add_argument("--rate", type=float, default=10.0, metavar="HZ", help="pose rate without --frames")
    poses.add_argument(
        "--dataset",
        type=Path,
        metavar="DIR",
        help="also write the image-folder dataset (images, times.txt, poses.txt, loops.npy)",
    )
    poses.add_argument(
        "--calib", type=Path, metavar="YAML", help="camera settings (ORB-SLAM style) copied into --dataset"
    )
    _add_gt_options(poses)

    gt = sub.add_parser("gt", help="loop ground truth (.npy) and its picture from TUM or KITTI poses")
    gt.add_argument("poses", type=Path, metavar="POSES_TXT", help="TUM (t x y z qx qy qz qw) or KITTI poses")
    gt.add_argument("--times", type=Path, metavar="TIMES_TXT", help="times of KITTI poses (one per line)")
    gt.add_argument("--out", type=Path, required=True, metavar="PNG", help="picture to write")
    gt.add_argument("--npy", type=Path, metavar="NPY", help="ground-truth matrix (default: --out with .npy)")
    _add_gt_options(gt)
    return p


def _add_gt_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--max-distance", type=float, default=10.0, metavar="M", help="loop distance (default 10 m)"
    )
    p.add_argument("--max-angle", type=float, default=None, metavar="DEG", help="largest heading difference")
    p.add_argument(
        "--min-gap-s",
        type=float,
        default=None,
        metavar="S",
        help="smallest time between a pair (default 20 s; none for KITTI poses without --times)",
    )
    p.add_argument("--min-gap-frames", type=int, default=0, metavar="N", help="smallest index difference")


def _read(path: Path, *, quiet: bool = False) -> FlightLog:
    """read_log, printing its warnings as one line each (the summary repeats them when quiet)."""
    from ..mav import read_log

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        log = read_log(path)
    if not quiet:
        for w in caught:
            print(f"warning: {w.message}", file=sys.stderr)
    return log


def run(args: argparse.Namespace) -> int:
    action = getattr(args, "mav_command", None)
    if action == "info":
        return _info(args)
    if action == "plot":
        return _plot(args)
    if action == "poses":
        return _poses(args)
    if action == "gt":
        return _gt(args)
    print("stablecues mav: expected an action: info, plot, poses or gt", file=sys.stderr)
    return 2


def _info(args: argparse.Namespace) -> int:
    from ..mav import compare_solutions, run_ekf

    log = _read(args.log, quiet=True)
    print(log.summary())
    if args.ekf:
        solution, report = run_ekf(log)
        print(
            f"  EKF: {len(solution)} states from {report.start_time:.1f} s, "
            f"GNSS lag {report.gnss_lag_s:.3f} s, IMU noise {report.accel_noise:.2f} m/s^2 / "
            f"{report.gyro_noise:.3f} rad/s, resets {report.resets}"
        )
        if log.onboard is not None:
            c = compare_solutions(solution, log.onboard)
            print(
                f"  EKF vs {c.reference}: {c.h_rmse_m:.3f} m horizontal, {c.v_rmse_m:.3f} m vertical RMS "
                f"(constant offset removed), yaw {c.yaw_rmse_deg:.1f} deg RMS, n={c.n}"
            )
    return 0


def _plot(args: argparse.Namespace) -> int:
    import numpy as np

    from ..mav import run_ekf
    from ..mav.plots import save_flight_figures

    log = _read(args.log)
    solution = None
    if not args.no_ekf and len(log.imu) >= 2 and np.any(log.gnss.fix >= 3):
        solution, _ = run_ekf(log)
    paths = save_flight_figures(log, args.out, solution=solution, dpi=args.dpi)
    for path in paths.values():
        print(path)
    return 0


def _offset(text: str) -> float | Literal["estimate"]:
    if text == "estimate":
        return "estimate"
    try:
        return float(text)
    except ValueError:
        raise InputError(f"--offset: expected seconds or 'estimate', got {text!r}") from None


def _poses(args: argparse.Namespace) -> int:
    from ..mav.export import write_image_folder, write_poses
    from ..mav.frames import read_frames
    from ..mav.loops import loops_from_trajectory
    from ..mav.poses import poses_for_frames
    from ..mav.solutions import log_solution

    log = _read(args.log)
    solution = log_solution(log, args.source)
    if args.frames is None and args.times is None:
        if args.dataset is not None:
            raise InputError("--dataset needs camera frames (--frames and/or --times)")
        return _poses_at_rate(args, solution)
    frames = read_frames(args.frames, args.times, time_column=args.time_column)
    poses = poses_for_frames(
        frames, log, solution, clock=args.clock, offset=_offset(args.offset), mount=args.mount
    )
    n = write_poses(args.out, poses)
    print(
        f"{args.out}: {n} of {len(frames)} frames posed from {poses.source} "
        f"(clock offset {poses.offset:.3f} s)"
    )
    if args.dataset is not None:
        keep = poses.valid
        loops = loops_from_trajectory(
            poses.positions[keep],
            max_distance=args.max_distance,
            quaternions=poses.quaternions[keep],
            max_angle_deg=args.max_angle,
            times=poses.frame_times[keep],
            min_gap_s=args.min_gap_s if args.min_gap_s is not None else 20.0,
            min_gap_frames=args.min_gap_frames,
        )
        out = write_image_folder(args.dataset, frames, poses, loops=loops, calibration=args.calib)
        print(f"{out}: image-folder dataset, {int(keep.sum())} frames, {int(loops.sum())} loop pairs")
    return 0


def _poses_at_rate(args: argparse.Namespace, solution: NavSolution) -> int:
    """Body poses at ``--rate`` over the solution's span (no camera frames given)."""
    import numpy as np

    from ..geometry.rotations import matrix_to_quat
    from ..mav.geo import R_ENU_NED
    from ..mav.poses import pose_matrices
    from ..mav.solutions import resample_solution
    from ..trajectory import write_tum

    every = resample_solution(solution, args.rate)
    quat = every.quaternion
    if not solution.has_attitude:
        # no attitude in the source: a level, north-facing body (as poses_for_frames does)
        level_north = matrix_to_quat(R_ENU_NED)
        quat = np.where(np.isfinite(every.position).all(axis=1)[:, None], level_north, np.nan)
    origin = solution.origin
    n = write_tum(
        args.out,
        every.t,
        pose_matrices(every.position, quat),
        comments=(
            "stablecues mav poses: t (s since log start) x y z qx qy qz qw, body(FRD)-to-world",
            f"world: ENU metres about lat={origin[0]:.8f} lon={origin[1]:.8f} "
            f"alt={origin[2]:.3f} m; source: {solution.name}",
        ),
    )
    print(f"{args.out}: {n} poses at {args.rate:g} Hz from {solution.name}")
    return 0


def _gt(args: argparse.Namespace) -> int:
    import numpy as np

    from ..geometry.rotations import matrix_to_quat
    from ..mav.loops import loops_from_trajectory
    from ..mav.plots import loop_figure
    from ..outputs import check_output, output_file
    from ..trajectory import read_poses, read_times

    npy = args.npy or args.out.with_suffix(".npy")
    check_output(npy, "ground truth", make_folder=True)
    check_output(args.out, "figure", make_folder=True)

    times, poses = read_poses(args.poses)
    if times is None:  # KITTI poses carry no times: from --times, else gaps are in frames only
        if args.times is not None:
            times = read_times(args.times)
            if times.shape[0] != poses.shape[0]:
                raise InputError(
                    f"{args.times}: expected {poses.shape[0]} times (one per pose), found {times.shape[0]}"
                )
        elif args.min_gap_s:
            raise InputError(
                f"{args.poses}: KITTI poses carry no times; --min-gap-s needs --times TIMES_TXT "
                "(or use --min-gap-frames)"
            )
    min_gap_s = args.min_gap_s if args.min_gap_s is not None else (20.0 if times is not None else 0.0)
    positions = poses[:, :3, 3]
    gt = loops_from_trajectory(
        positions,
        max_distance=args.max_distance,
        quaternions=matrix_to_quat(poses[:, :3, :3]) if args.max_angle is not None else None,
        max_angle_deg=args.max_angle,
        times=times,
        min_gap_s=min_gap_s,
        min_gap_frames=args.min_gap_frames,
    )
    with output_file(npy, "ground truth") as tmp:
        np.save(tmp, gt)
    with output_file(args.out, "figure") as tmp:
        loop_figure(positions, gt).savefig(tmp, dpi=150)
    print(
        f"{npy}: {gt.shape[0]} frames, {int(gt.sum())} loop pairs ({int(gt.any(axis=1).sum())} query frames)"
    )
    print(args.out)
    return 0

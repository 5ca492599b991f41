"""``stablecues synth``: write a synthetic town drive in the image-folder format.

stablecues synth --out DIR [--frames N --seed S --width W --height H --loops L --clutter C ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .commands import summary


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "synth",
        help=summary("synth"),
        description="Render a drive through a procedural town that revisits its streets in another "
        "lane, the other way round and at other times of day, with other cars and people. Writes "
        "images/, right/, depth/ (16-bit PNG), labels/ (CamVid ids), times.txt, poses.txt (TUM), "
        "calib.yaml (ORB-SLAM settings), loops.npy and synthetic.json.",
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder to write")
    p.add_argument("--frames", type=int, default=300, metavar="N", help="frames (default 300)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--width", type=int, default=512, metavar="W", help="image width (default 512)")
    p.add_argument("--height", type=int, default=384, metavar="H", help="image height (default 384)")
    p.add_argument(
        "--loops", type=int, default=2, metavar="L", help="revisit laps after the first (default 2)"
    )
    p.add_argument(
        "--clutter", type=float, default=1.0, metavar="C", help="density of props, cars, people (default 1)"
    )
    p.add_argument(
        "--baseline", type=float, default=0.3, metavar="M", help="stereo baseline, metres (default 0.3)"
    )
    p.add_argument(
        "--fov", type=float, default=70.0, metavar="DEG", help="horizontal field of view (default 70)"
    )
    p.add_argument(
        "--step", type=float, default=2.0, metavar="M", help="wished metres between frames (default 2)"
    )
    p.add_argument(
        "--noise", type=float, default=2.0, metavar="SIGMA", help="sensor noise, grey levels (default 2)"
    )
    p.add_argument("--no-right", action="store_true", help="do not write right images")
    p.add_argument("--no-depth", action="store_true", help="do not write depth images")
    p.add_argument("--no-labels", action="store_true", help="do not write label images")
    g = p.add_argument_group("loop ground truth")
    g.add_argument("--gt-distance", type=float, default=6.0, metavar="M", help="loop distance (default 6 m)")
    g.add_argument(
        "--gt-angle", type=float, default=35.0, metavar="DEG", help="largest heading difference (default 35)"
    )
    g.add_argument("--gt-min-gap", type=int, default=20, metavar="N", help="smallest frame gap (default 20)")
    g.add_argument(
        "--opposite",
        choices=("never", "covisible", "always"),
        default="covisible",
        help="pairs beyond the heading limit count: never, when their views share matchable "
        "static surfaces (default), or always (distance only)",
    )
    p.add_argument("--overwrite", action="store_true", help="write into a folder that already holds images")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def run(args: argparse.Namespace) -> int:
    from ..synthetic import LoopTruthConfig, SyntheticTownConfig, write_sequence

    cfg = SyntheticTownConfig(
        frames=args.frames,
        width=args.width,
        height=args.height,
        fov_deg=args.fov,
        baseline=args.baseline,
        loops=args.loops,
        clutter=args.clutter,
        seed=args.seed,
        step=args.step,
        noise=args.noise,
    )
    truth = LoopTruthConfig(
        max_distance=args.gt_distance,
        max_angle_deg=args.gt_angle,
        min_gap_frames=args.gt_min_gap,
        opposite=args.opposite,
    )
    out = write_sequence(
        cfg,
        args.out,
        truth=truth,
        right=not args.no_right,
        depth=not args.no_depth,
        labels=not args.no_labels,
        progress=not args.quiet,
        overwrite=args.overwrite,
    )
    meta = json.loads((out / "synthetic.json").read_text())
    print(
        f"stablecues synth: {meta['frames']} frames {cfg.width}x{cfg.height}, {len(meta['laps'])} laps, "
        f"{meta['step_m']:.2f} m/frame, {meta['loop_queries']} loop queries ({meta['loop_pairs']} pairs) "
        f"-> {out} in {meta['total_s']:.1f} s"
    )
    return 0

"""``stablecues demo``: generate a synthetic town drive, detect loops, evaluate, report."""

from __future__ import annotations

import argparse
from pathlib import Path

from .commands import summary


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser("demo", help=summary("demo"))
    p.add_argument("--out", type=Path, default=Path("stablecues-demo"),
                   help="folder for the sequence, runs and report (default ./stablecues-demo)")
    p.add_argument("--frames", type=int, default=240, help="frames of the synthetic drive (default 240)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=384)
    p.add_argument("--height", type=int, default=288)
    p.add_argument("--no-progress", action="store_true")
    return p


def run(args: argparse.Namespace) -> int:
    from ..demo import run_demo

    res = run_demo(args.out, frames=args.frames, seed=args.seed, width=args.width, height=args.height,
                   progress=not args.no_progress)
    print()
    print(f"stablecues demo: {args.frames} synthetic frames in {res.sequence}")
    print(f"{res.semantic_note}")
    print(f"{'preset':10s} {'R@100P':>8s} {'loops':>6s} {'ms/frame':>9s}   (protocol: tolerance +-2 frames)")
    for name in res.runs:
        print(f"{name:10s} {res.r_at_100p[name]:8.3f} {res.loops[name]:6d} {res.ms_per_frame[name]:9.1f}")
    print(f"report: {res.report.resolve()}")
    print(f"done in {res.seconds:.0f} s")
    return 0

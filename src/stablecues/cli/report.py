"""``stablecues report``: a static, self-contained HTML page over one or more runs."""

from __future__ import annotations

import argparse
from pathlib import Path

from .commands import summary


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "report",
        help=summary("report"),
        description="PR curves of all runs (whole and zoomed), per run the loss funnel, the similarity "
        "matrix beside the ground truth, every accepted loop (thumbnails marked true / false with the "
        "verifier that ran; click to enlarge), decisions per status and timing tables. Plots are "
        "embedded; loop pictures go to OUT's folder <stem>_files/ beside it.",
    )
    p.add_argument("run_dirs", type=Path, nargs="+", metavar="RUN_DIR")
    p.add_argument("--out", type=Path, required=True, help="the HTML file to write")
    p.add_argument(
        "--protocol",
        choices=("exact", "tolerance", "ibow"),
        help="the evaluation to show (each run's eval_*.json); default: one every evaluated run has, "
        "exact first (the demo's report shows tolerance +-2). A run without it is listed as not "
        "evaluated, with a warning",
    )
    p.add_argument("--tolerance", type=int, help="tolerance of the evaluation to show (frames)")
    p.add_argument("--title", default="stablecues loop-closure evaluation")
    p.add_argument(
        "--max-loops",
        type=int,
        default=None,
        metavar="N",
        help="accepted loops per run that get a picture, spread over the run (default: all; every "
        "accepted loop is listed either way)",
    )
    return p


def run(args: argparse.Namespace) -> int:
    from ..evaluation.report import build_report
    from ..runs import load_run

    runs = [load_run(d) for d in args.run_dirs]
    out = build_report(
        runs,
        args.out,
        protocol=args.protocol,
        tolerance=args.tolerance,
        title=args.title,
        max_loops=args.max_loops,
    )
    print(f"written: {out}")
    return 0

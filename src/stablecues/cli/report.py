"""``stablecues report``: a static, self-contained HTML page over one or more runs."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "report",
        help="static HTML report of evaluated runs",
        description="PR curves of all runs on one plot, similarity matrix beside ground truth, timing "
        "tables, decisions per status and match pictures, images embedded.",
    )
    p.add_argument("run_dirs", type=Path, nargs="+", metavar="RUN_DIR")
    p.add_argument("--out", type=Path, required=True, help="the HTML file to write")
    p.add_argument(
        "--protocol", choices=("exact", "tolerance", "ibow"), help="evaluation to show (default exact)"
    )
    p.add_argument("--tolerance", type=int, help="tolerance of the evaluation to show")
    p.add_argument("--title", default="stablecues loop-closure evaluation")
    p.add_argument("--max-matches", type=int, default=6, help="match pictures per run (default 6)")
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
        max_matches=args.max_matches,
    )
    print(f"written: {out}")
    return 0

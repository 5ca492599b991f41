"""``stablecues results``: one table across runs, from their evaluation files."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any

from .commands import summary

COLUMNS = (
    "run",
    "preset",
    "protocol",
    "tolerance",
    "exclude",
    "gt_file",
    "gt_sha256",
    "queries",
    "positives",
    "tp",
    "fp",
    "fn",
    "recall_at_100p",
    "auc",
    "ms_per_frame",
)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "results",
        help=summary("results"),
        description="Collect the eval_*.json files of run directories into one table.",
    )
    p.add_argument("run_dirs", type=Path, nargs="+", metavar="RUN_DIR")
    p.add_argument("--protocol", choices=("exact", "tolerance", "ibow"), help="only this protocol")
    p.add_argument("--json", type=Path, metavar="OUT", help="also write the rows as JSON")
    p.add_argument("--csv", type=Path, metavar="OUT", help="also write the rows as CSV")
    return p


def collect_rows(run_dirs: list[Path], protocol: str | None = None) -> list[dict[str, Any]]:
    """One row per (run, evaluation file); a run without one gives a row with protocol None."""
    from ..evaluation.evaluate import run_evaluations
    from ..runs import load_run

    rows: list[dict[str, Any]] = []
    for d in run_dirs:
        run_ = load_run(d)
        total = (run_.timings().get("total") or {}).get("mean")
        evals = [
            e for e in run_evaluations(run_).values() if protocol is None or e.get("protocol") == protocol
        ]
        if not evals:
            rows.append(
                {c: None for c in COLUMNS}
                | {"run": str(d), "preset": run_.meta.get("preset"), "ms_per_frame": total}
            )
        for e in evals:
            row = {c: e.get(c) for c in COLUMNS}
            row.update(run=str(d), preset=run_.meta.get("preset"), ms_per_frame=total)
            rows.append(row)
    return rows


def format_rows(rows: list[dict[str, Any]]) -> str:
    """Fixed-width text table."""
    header = [
        "run",
        "preset",
        "protocol",
        "tol",
        "excl",
        "gt",
        "queries",
        "pos",
        "TP",
        "FP",
        "FN",
        "R@100P",
        "AUC",
        "ms/frame",
    ]
    table = [header]
    for r in rows:

        def f(v: Any, spec: str = "") -> str:
            return "-" if v is None else format(v, spec)

        table.append(
            [
                str(r["run"]),
                f(r["preset"]),
                f(r["protocol"]) if r["protocol"] else "not evaluated",
                f(r["tolerance"]),
                f(r["exclude"]),
                Path(r["gt_file"]).name if r["gt_file"] else "-",
                f(r["queries"]),
                f(r["positives"]),
                f(r["tp"]),
                f(r["fp"]),
                f(r["fn"]),
                "-" if r["recall_at_100p"] is None else f"{100 * r['recall_at_100p']:.2f}%",
                f(r["auc"], ".4f"),
                f(r["ms_per_frame"], ".2f"),
            ]
        )
    widths = [max(len(row[i]) for row in table) for i in range(len(header))]
    return "\n".join(
        "  ".join(
            c.ljust(w) if i < 3 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths, strict=True))
        )
        for row in table
    )


def run(args: argparse.Namespace) -> int:
    from ..outputs import check_output, output_file, write_output

    for path, what in ((args.json, "JSON table"), (args.csv, "CSV table")):
        if path:
            check_output(path, what)
    rows = collect_rows(list(args.run_dirs), args.protocol)
    print(format_rows(rows))
    if args.json:
        write_output(args.json, json.dumps(rows, indent=2) + "\n", "JSON table")
    if args.csv:
        with output_file(args.csv, "CSV table") as tmp, tmp.open("w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=list(COLUMNS))
            w.writeheader()
            w.writerows(rows)
    if any(r["protocol"] is None for r in rows):
        print(
            "(runs marked 'not evaluated' have no eval_*.json: run 'stablecues eval' on them)",
            file=sys.stderr,
        )
    return 0

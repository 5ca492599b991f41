"""``stablecues run``: the loop detector over a dataset, into a run directory."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    from ..detection import preset_names

    p = subparsers.add_parser("run", help="detect loops over a dataset and write a run directory")
    p.add_argument("dataset", type=Path, help="dataset folder")
    p.add_argument("--format", default="auto",
                   help="auto | folder | tum | kitti | euroc | fabmap | vprbench (default auto)")
    p.add_argument("--preset", default="default", choices=preset_names(), help="detector preset")
    p.add_argument("--out", type=Path, required=True, help="run directory to write")
    p.add_argument("--gt", type=Path, help="loop ground truth file to record with the run")
    p.add_argument("--db", type=Path, help="database file (default: RUN_DIR/map.sqlite)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the run already in --out (its own files only); without it an existing, "
                        "non-empty --out is refused")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--pictures", type=int, default=4, help="match pictures of accepted loops to save")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a setting, e.g. query.alpha=0.2 or verification.min_agree=3 "
                        "(VALUE is JSON; repeatable)")
    p.add_argument("--no-progress", action="store_true")
    return p


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["query.alpha=0.2", "masking.mode=\\"hard\\""]`` -> nested override dict."""
    from ..errors import ConfigError

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw  # bare strings
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def run(args: argparse.Namespace) -> int:
    from ..datasets import open_dataset
    from ..detection import preset
    from ..detection.run import run_dataset
    from ..errors import ConfigError

    if args.resume and args.overwrite:
        raise ConfigError("--resume continues the run in --out and --overwrite replaces it: give one")
    config = preset(args.preset, parse_overrides(args.set))
    dataset = open_dataset(args.dataset, format=args.format)
    gt = args.gt if args.gt is not None else dataset.ground_truth_path()
    described = dataset.describe() if hasattr(dataset, "describe") else {}
    meta = {**described, "dataset": str(args.dataset), "format": getattr(dataset, "format", args.format),
            "ground_truth": None if gt is None else str(gt), "overrides": args.set}
    summary = run_dataset(dataset, config, args.out, preset_name=args.preset, meta=meta,
                          database=args.db, resume=args.resume, overwrite=args.overwrite,
                          max_frames=args.max_frames, pictures=args.pictures, progress=not args.no_progress)
    statuses = ", ".join(f"{k} {v}" for k, v in sorted(summary.statuses.items()))
    if summary.already_complete:
        print(f"{summary.out_dir}: the run is already complete; nothing to resume")
    elif summary.resumed_from:
        print(f"resumed at frame {summary.resumed_from}")
    ms = summary.ms_per_frame
    speed = f"{ms:.1f} ms/frame" if ms == ms else "no frame timed"
    print(f"{summary.frames} frames, {summary.loops} loops accepted, {speed}; {statuses}")
    if summary.mask_fallbacks:
        print(f"semantic masking fell back to all features on {summary.mask_fallbacks} frames")
    print(f"run written to {summary.out_dir}" + (f" (ground truth: {gt})" if gt else ""))
    return 0

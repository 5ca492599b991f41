"""``stablecues sweep``: a grid of datasets x presets (x overrides) as tasks on a Dask cluster."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any

from .commands import summary


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    from ..detection import preset_names

    p = subparsers.add_parser(
        "sweep",
        help=summary("sweep"),
        description="Each cell is 'stablecues run' (then 'stablecues eval' when the dataset's ground truth "
        "is known) into OUT/<dataset>__<preset>[__<override-tag>]/; the merged table is OUT/sweep.csv and "
        "OUT/sweep.json. Runs on a local cluster of worker processes by default, on any cluster with "
        "--scheduler (workers must see the datasets and OUT at the same paths).",
    )
    p.add_argument("datasets", nargs="+", metavar="[NAME=]DATASET",
                   help="dataset folders, optionally named (default name: the folder's)")
    p.add_argument("--preset", action="append", choices=preset_names(), metavar="PRESET",
                   help=f"detector preset (repeatable; default: default). One of {', '.join(preset_names())}")
    p.add_argument("--out", "-o", type=Path, required=True, help="folder for the run folders and the table")
    p.add_argument("--format", default="auto", help="dataset format of every dataset (default auto)")
    p.add_argument("--gt", action="append", default=[], metavar="NAME=FILE",
                   help="loop ground truth of the dataset NAME (default: the dataset's own, if any)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a setting in every cell (VALUE is JSON; repeatable)")
    p.add_argument("--vary", action="append", default=[], metavar="KEY=[V1,V2,...]",
                   help="one cell per value (a JSON list); several --vary make their product")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler, e.g. tcp://host:8786")
    g.add_argument("--serial", action="store_true", help="no cluster: run the cells one after another here")
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="worker processes of the local cluster (default 2)")
    p.add_argument("--threads", type=int, default=1, metavar="N",
                   help="compute threads of each cell, OpenCV and the network (default 1: one core per "
                        "worker process)")
    m = p.add_mutually_exclusive_group()
    m.add_argument("--resume", action="store_true",
                   help="continue interrupted runs, re-evaluate complete ones")
    m.add_argument("--overwrite", action="store_true", help="replace the sweep's run folders")
    p.add_argument("--protocol", choices=("exact", "tolerance", "ibow"), default="exact")
    p.add_argument("--tolerance", type=int, default=0, metavar="N", help="+-N frames (tolerant protocols)")
    p.add_argument("--max-frames", type=int, help="stop each run after this many frames")
    p.add_argument("--pictures", type=int, default=0, help="match pictures per run (default 0)")
    p.add_argument("--timeout", type=float, metavar="S",
                   help="give up after S seconds waiting for the cluster (to connect, then for the results)")
    return p


def parse_dataset(text: str, fmt: str) -> Any:
    """``NAME=PATH`` or ``PATH`` -> a SweepDataset (a left part with a slash is a path)."""
    from ..distributed import SweepDataset

    name, sep, path = text.partition("=")
    if sep and path and name and "/" not in name:
        return SweepDataset(Path(path), name=name, format=fmt)
    return SweepDataset(Path(text), format=fmt)


def override_sets(set_items: list[str], vary_items: list[str]) -> list[dict[str, Any]]:
    """The product of every ``--vary`` list, each with the ``--set`` items."""
    from ..errors import ConfigError
    from ..limits import MAX_SWEEP_CELLS
    from .run import parse_overrides

    axes: list[list[str]] = []
    for item in vary_items:
        key, sep, raw = item.partition("=")
        try:
            values = json.loads(raw) if sep and key else None
        except json.JSONDecodeError:
            values = None
        if not isinstance(values, list) or not values:
            raise ConfigError(f"--vary {item!r}: expected KEY=[V1,V2,...] (a JSON list of one value or more)")
        axes.append([f"{key}={json.dumps(v)}" for v in values])
    cells = math.prod(len(a) for a in axes)
    if cells > MAX_SWEEP_CELLS:
        raise ConfigError(f"--vary: {' x '.join(str(len(a)) for a in axes)} = {cells} configurations; "
                          f"a sweep plans at most {MAX_SWEEP_CELLS} (vary fewer settings, or split it)")
    combos: list[list[str]] = [[]]
    for axis in axes:
        combos = [c + [v] for c in combos for v in axis]
    return [parse_overrides(set_items + c) for c in combos]


def _with_ground_truth(datasets: list[Any], items: list[str]) -> list[Any]:
    from dataclasses import replace

    from ..errors import ConfigError

    by_name = {d.name: d for d in datasets}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not path or name not in by_name:
            raise ConfigError(f"--gt {item!r}: expected NAME=FILE with NAME one of {', '.join(by_name)}")
        by_name[name] = replace(by_name[name], ground_truth=Path(path))
    return [by_name[d.name] for d in datasets]


def _progress(total: int) -> Any:
    done = [0]

    def show(row: dict[str, Any]) -> None:
        done[0] += 1
        name = Path(row["run"]).name
        if row.get("error"):
            print(f"[{done[0]}/{total}] {name}: FAILED: {row['error']}", flush=True)
            return
        r100 = row.get("recall_at_100p")
        score = "not evaluated" if r100 is None else f"R@100P {100 * r100:.2f} %"
        ms = row.get("ms_per_frame")
        speed = "-" if ms is None else f"{ms:.1f}"
        print(f"[{done[0]}/{total}] {name}: {row['frames']} frames, {row['loops']} loops, {score}, "
              f"{speed} ms/frame on {row['worker']}", flush=True)

    return show


def _quiet_dask(verbose: int) -> None:
    """Dask logs every scheduler and worker event at INFO: shown with -v only."""
    import distributed  # noqa: F401  (its logging setup runs at import; set the level after it)

    if not verbose:
        logging.getLogger("distributed").setLevel(logging.WARNING)


def run(args: argparse.Namespace) -> int:
    from ..distributed import SweepOptions, open_client, plan_sweep, run_sweep
    from ..distributed.cluster import CONNECT_TIMEOUT_S, check_timeout
    from ..distributed.sweep import Mode, check_out

    if args.timeout is not None:
        check_timeout(args.timeout, "--timeout")
    datasets = _with_ground_truth([parse_dataset(d, args.format) for d in args.datasets], args.gt)
    tasks = plan_sweep(datasets, args.preset or ["default"], override_sets(args.set, args.vary))
    mode: Mode = "resume" if args.resume else "overwrite" if args.overwrite else "new"
    options = SweepOptions(mode=mode, max_frames=args.max_frames, pictures=args.pictures,
                           protocol=args.protocol, tolerance=args.tolerance, threads=args.threads)
    check_out(tasks, args.out.absolute(), options)  # before a cluster starts
    show = _progress(len(tasks))
    if args.serial:
        print(f"stablecues sweep: {len(tasks)} tasks, serially", flush=True)
        result = run_sweep(tasks, args.out, options, on_row=show)
    else:
        _quiet_dask(args.verbose)
        connect = CONNECT_TIMEOUT_S if args.timeout is None else min(args.timeout, CONNECT_TIMEOUT_S)
        with open_client(args.scheduler, workers=args.workers, timeout_s=connect) as client:
            where = args.scheduler or f"a local cluster of {args.workers} worker processes"
            print(f"stablecues sweep: {len(tasks)} tasks on {where}", flush=True)
            result = run_sweep(tasks, args.out, options, client=client, timeout_s=args.timeout, on_row=show)
    print(f"{len(tasks)} tasks in {result.wall_s:.1f} s; table: {result.csv_path}, {result.json_path}")
    if result.failures:
        first = result.failures[0]
        print(f"stablecues sweep: {len(result.failures)} of {len(tasks)} tasks failed (see 'error' in the "
              f"table); first, {Path(first['run']).name}: {first['error']}", file=sys.stderr)
        return 1
    return 0

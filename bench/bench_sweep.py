"""Speed-up of ``stablecues sweep`` on a local Dask cluster of 2 worker processes over the same
grid run serially in one process.

Run as ``python bench/bench_sweep.py``; prints the figures and writes
``bench/results/sweep.json``. Goal (issue 13, part 5): ``sweep_speedup_2workers`` >= 1.7.

The grid: the CamVid revisit development sets (``val_drive``, ``train_drives``, with their
``gt.png``) and the Corridor set of ``../shared/data`` x the presets ``bow``, ``fast`` and
``default`` (9 tasks, 1707 frames). Without the shared data it falls back to three synthetic
drives (and says so in the JSON). The serial sweep runs first, in this process; then a
``LocalCluster(n_workers=2, processes=True, threads_per_worker=1)`` starts (timed apart) and
runs the same grid. ``sweep_speedup_2workers`` = serial wall time / cluster wall time from the
first task sent to the last row back; ``speedup_with_startup`` also counts the cluster's
start. Both sweeps must give the same table (all but the timing columns): checked and recorded.

The machine has 2 cores shared with other jobs: the 1-minute load average before each phase
is recorded beside the figure.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from stablecues.distributed import (
    VOLATILE_COLUMNS,
    SweepDataset,
    SweepTask,
    open_client,
    plan_sweep,
    run_sweep,
    worker_addresses,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("STABLECUES_SHARED_DATA", ROOT.parent / "shared" / "data"))
OUT = ROOT / "bench" / "results" / "sweep.json"
PRESETS = ("bow", "fast", "default")
GOAL = 1.7


def load() -> float:
    return round(os.getloadavg()[0], 2)


def datasets(work: Path) -> tuple[list[SweepDataset], str]:
    """The real grid when the shared data is there, else three synthetic drives."""
    dev = DATA / "camvid_revisit_dev"
    if dev.is_dir() and (DATA / "corridor").is_dir():
        sets = [SweepDataset(dev / name / "frames", name=name, format="folder",
                             ground_truth=dev / name / "gt.png") for name in ("val_drive", "train_drives")]
        sets.append(SweepDataset(DATA / "corridor", name="corridor", format="vprbench"))
        return sets, "camvid_revisit_dev val_drive + train_drives, corridor (real)"
    from stablecues.synthetic import SyntheticTownConfig, write_sequence

    sets = []
    for seed, frames in ((0, 120), (1, 200), (2, 80)):
        path = write_sequence(SyntheticTownConfig(frames=frames, width=384, height=288, seed=seed),
                              work / f"town{seed}", progress=False)
        sets.append(SweepDataset(path, name=f"town{seed}"))
    return sets, "synthetic towns (no shared data)"


def stable(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k not in VOLATILE_COLUMNS and k != "run"} for r in rows]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=list(PRESETS))
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="bench_sweep_"))
    try:
        sets, data = datasets(work)
        tasks: list[SweepTask] = plan_sweep(sets, args.presets)
        print(f"grid: {len(tasks)} tasks ({data}); presets {', '.join(args.presets)}", flush=True)

        load_serial = load()
        serial = run_sweep(tasks, work / "serial", on_row=lambda r: print(
            f"  serial {Path(r['run']).name}: {r['wall_s']:.1f} s", flush=True))
        print(f"serial: {serial.wall_s:.1f} s (load before {load_serial})", flush=True)

        load_dask = load()
        t0 = time.perf_counter()
        with open_client(workers=2, threads_per_worker=1) as client:
            worker_addresses(client, least=2)
            startup = time.perf_counter() - t0
            dist = run_sweep(tasks, work / "dask", client=client,
                             on_row=lambda r: print(f"  dask {Path(r['run']).name}: {r['wall_s']:.1f} s on "
                                                    f"{r['worker']}", flush=True))
        load_after = load()
        same = stable(serial.rows) == stable(dist.rows)
        speedup = serial.wall_s / dist.wall_s
        with_startup = serial.wall_s / (dist.wall_s + startup)
        print(f"LocalCluster 2 workers: {dist.wall_s:.1f} s + {startup:.1f} s start "
              f"(load before {load_dask})")
        print(f"sweep_speedup_2workers {speedup:.2f} (goal >= {GOAL}); with the cluster's start "
              f"{with_startup:.2f}; tables identical: {same}; load after {load_after}")
        frames = sum(r["frames"] or 0 for r in serial.rows)
        result = {
            "sweep_speedup_2workers": round(speedup, 3),
            "goal": GOAL,
            "speedup_with_startup": round(with_startup, 3),
            "serial_s": round(serial.wall_s, 2),
            "cluster_s": round(dist.wall_s, 2),
            "cluster_startup_s": round(startup, 2),
            "tables_identical": same,
            "failures": len(serial.failures) + len(dist.failures),
            "tasks": len(tasks),
            "frames": frames,
            "data": data,
            "presets": list(args.presets),
            "task_wall_s": {Path(r["run"]).name: r["wall_s"] for r in serial.rows},
            "load_1min": {"before_serial": load_serial, "before_cluster": load_dask, "after": load_after},
            "machine": f"{os.cpu_count()} cores, shared with other jobs; "
                       f"{platform.processor() or platform.machine()}",
            "cluster": "LocalCluster(n_workers=2, processes=True, threads_per_worker=1)",
            "rows": [{k: r[k] for k in ("run", "frames", "loops", "recall_at_100p", "auc", "ms_per_frame")}
                     | {"run": Path(r["run"]).name} for r in dist.rows],
        }
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
        print(f"written {args.out}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

"""The held-out report: CamVid ``test`` as a revisit sequence, measured once, never tuned on.

Builds a revisit set from CamVid ``test`` with ``scripts/make_revisit_set.py`` (the recipe of the
development sets ``../shared/data/camvid_revisit_dev``: first traversal = even moving frames,
second = odd moving frames under a changing appearance with distractor runs between its chunks,
ground truth from verified SIFT overlap of the original frames), and its "objects swapped"
variant (``bench_loops.make_swapped``: the second traversal's cars, people and cyclists replaced
by another frame's), both in a temporary folder (derived data never enters the repository). Then
the default, ``fast``, ``bow``, ``paper`` and a DBoW2-style top-1 retrieval with its raw score
swept, scored at the exact cell with no exclusion, as ``bench_loops.py`` scores the development
sets.

Run: ``python bench/bench_heldout.py`` (writes ``bench/results/heldout.json``). Every setting of
the detector was chosen on the development sets before this ran.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from bench_loops import (
    MAIN_PRESETS,
    SHARED,
    TOP1,
    _run_eval,
    eval_configs,
    make_swapped,
    network_available,
)
from stablecues.datasets import open_dataset
from stablecues.detection import preset
from stablecues.groundtruth import load_ground_truth

HERE = Path(__file__).resolve().parent
SCRIPT = HERE.parent / "scripts" / "make_revisit_set.py"
PRESETS = [p for p in MAIN_PRESETS if p != "bow-nogeom"]


def build(out: Path, seed: int) -> str:
    """The test revisit set in ``out``; returns the script's one-line summary."""
    cmd = [sys.executable, str(SCRIPT), "--split", "test", "--out", str(out), "--seed", str(seed)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"bench_heldout: building the test set failed: {done.stderr.strip()[-300:]}")
    return done.stdout.strip().splitlines()[-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0, help="seed of the test set's appearance changes")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "heldout.json")
    args = ap.parse_args()
    if not (SHARED / "camvid" / "test").is_dir():
        raise SystemExit(f"bench_heldout: {SHARED / 'camvid' / 'test'} is not here")
    network = network_available()
    results: dict[str, Any] = {"load_before": list(os.getloadavg()), "seed": args.seed,
                               "protocol": "exact cell, no exclusion, R@100P"}
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "test_revisit"
        results["set"] = build(base, args.seed)
        print(results["set"], flush=True)
        swapped = make_swapped(base, Path(tmp) / "swapped")
        sets = {"test_revisit": base, "test_revisit (objects swapped)": swapped}
        for name, root in sets.items():
            ds = open_dataset(root / "frames", format="folder")
            gt = load_ground_truth(root / "gt.png")
            rows = int(np.count_nonzero(gt.matrix.any(axis=1)))
            res: dict[str, Any] = {"frames": len(ds), "loop_rows": rows}
            tag = "swapped" if "swapped" in name else "test"
            res["dbow2 top-1, raw score swept"] = _run_eval(ds, gt, preset("bow-nogeom", TOP1), Path(tmp),
                                                            f"{tag}_top1", score="raw_score")
            res.update(eval_configs(ds, gt, {p: preset(p) for p in PRESETS}, Path(tmp), tag, network))
            results[name] = res
            for label, r in res.items():
                if isinstance(r, dict):
                    print(f"  {name:30s} {label:30s} R@100P {r['r_at_100p']:.3f} (TP {r['tp']} FP {r['fp']} "
                          f"of {r['positives']}) {r['ms_per_frame']} ms/frame "
                          f"{ {k: v for k, v in r['funnel'].items() if v} }", flush=True)
    results["load_after"] = list(os.getloadavg())
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()

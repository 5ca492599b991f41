#!/usr/bin/env python
"""The network's domain gate (issue 11, item 5: "where the network is not confident, the
weighting must fade out by itself rather than hurt").

Two parts, on the real data of ``../shared/data``:

``certainty``  the frame certainty (:meth:`SegmentationResult.frame_certainty`, the shipped
               network at T = 1) per data set: percentiles 0/10/50/90/100. These are the
               figures the gate's thresholds were read from (``WeightingConfig.domain``,
               ``MaskingConfig.min_frame_certainty``).
``loops``      R@100P of the default with the gate (the median certainty of the last 30 frames),
               the same with each frame gated alone (``domain_window = 1``), without any gate, and
               the ``fast`` preset (no network), on the CamVid revisit development sets (and their
               swapped-object variants, exact cell), the corridor (tolerance +-2 and exact, 20
               frames excluded, as ``bench_loops.py``) and desk_loop10 (is 10 -> 1 found?).

Prints tables and writes ``bench/results/domain.json``.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_loops as B  # noqa: E402
from stablecues.detection import preset  # noqa: E402
from stablecues.semantics.inference import SegmentationModel  # noqa: E402

DATA = B.SHARED
CERTAINTY_SETS: dict[str, tuple[str, int, int]] = {  # name -> (glob under DATA, step, limit)
    "camvid train drives": ("camvid_revisit_dev/train_drives/frames/*.jpg", 6, 60),
    "camvid val drive": ("camvid_revisit_dev/val_drive/frames/*.jpg", 3, 60),
    "corridor": ("corridor/*/*.jpg", 8, 60),
    "desk_loop10": ("desk_loop10/*.png", 1, 10),
    "kinect rgb-d": ("rgbd_kinect5/**/*.png", 1, 30),
    "tum": ("tum/**/*.png", 5, 30),
    "euroc": ("euroc/**/*.png", 3, 30),
    "kitti": ("kitti/**/*.png", 3, 30),
}
OFF = {"weighting": {"domain": None}, "masking": {"min_frame_certainty": 0.0}}
CONFIGS: dict[str, tuple[str, dict[str, Any]]] = {
    "default (gate: median of 30 frames)": ("default", {}),
    "default, each frame gated alone": ("default", {"domain_window": 1}),
    "default without the gate": ("default", OFF),
    "fast (no network)": ("fast", {}),
}


def certainty_table() -> dict[str, Any]:
    model = SegmentationModel.load(threads=1)
    out: dict[str, Any] = {}
    for name, (pattern, step, limit) in CERTAINTY_SETS.items():
        files = sorted(glob.glob(str(DATA / pattern), recursive=True))[::step][:limit]
        values = []
        for f in files:
            image = cv2.imread(f)
            if image is not None:
                values.append(model.predict(image, 1).frame_certainty())
        if not values:
            continue
        pct = np.percentile(values, [0, 10, 50, 90, 100]).round(3).tolist()
        out[name] = {"frames": len(values), "percentiles_0_10_50_90_100": pct}
        print(f"  {name:22s} {len(values):3d} frames  certainty p0 {pct[0]:.2f} p10 {pct[1]:.2f} "
              f"p50 {pct[2]:.2f} p90 {pct[3]:.2f} p100 {pct[4]:.2f}", flush=True)
    return out


def loops_table() -> dict[str, Any]:
    out: dict[str, Any] = {}
    dev = DATA / "camvid_revisit_dev"
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        sets = {n: (dev / n / "frames", dev / n / "gt.png") for n in B.REVISITS}
        for n in B.REVISITS:
            sw = B.make_swapped(dev / n, work / f"sw_{n}")
            sets[f"{n} (objects swapped)"] = (sw / "frames", sw / "gt.png")
        for set_name, (frames, gt_file) in sets.items():
            ds, gt = B.open_dataset(frames, format="folder"), B.load_ground_truth(gt_file)
            for label, (name, over) in CONFIGS.items():
                tag = f"{set_name}_{label}".replace(" ", "_").replace("(", "").replace(")", "")
                r = B._run_eval(ds, gt, preset(name, over), work, tag)
                out.setdefault(set_name, {})[label] = r
                print(f"  {set_name[:28]:28s} {label:38s} R@100P {r['r_at_100p']:.3f} (TP {r['tp']} "
                      f"FP {r['fp']} of {r['positives']})", flush=True)
        corridor = B.open_dataset(DATA / "corridor", format="vprbench")
        gt = corridor.ground_truth()
        for label, (name, over) in CONFIGS.items():
            run_dir = work / f"corridor_{len(out.get('corridor', {}))}"
            B.run_dataset(corridor, preset(name, over), run_dir, preset_name=name, progress=False, pictures=0)
            run = B.load_run(run_dir)
            res = {}
            for proto, tol in (("tolerance", 2), ("exact", 0)):
                ev, _ = B.evaluate_run(run, gt, protocol=proto, tolerance=tol, exclude=20)
                res[proto] = {"r_at_100p": round(ev.recall_at_100p, 4), "tp": ev.tp, "fp": ev.fp}
            out.setdefault("corridor", {})[label] = res
            print(f"  {'corridor':28s} {label:38s} R@100P tol+-2 {res['tolerance']['r_at_100p']:.3f} "
                  f"exact {res['exact']['r_at_100p']:.3f} (TP {res['tolerance']['tp']} "
                  f"FP {res['tolerance']['fp']})", flush=True)
        folder = DATA / "desk_loop10"
        frames = [B.Frame(index=i, name=f"{i + 1}.png", timestamp=float(i),
                          image=B.read_image(folder / f"{i + 1}.png")) for i in range(10)]
        for label, (name, over) in CONFIGS.items():
            det = B.LoopDetector(preset(name, {"query": {"exclude_recent": 3, "temporal_k": 1}, **over}))
            decisions = [det.process(f) for f in frames]
            det.close()
            loops = [[d.frame_index + 1, d.candidate_frame + 1] for d in decisions if d.accepted]
            found = [10, 1] in loops
            out.setdefault("desk_loop10", {})[label] = {"loops_1based": loops, "found_10_to_1": found}
            print(f"  {'desk_loop10':28s} {label:38s} loops {loops}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "domain.json")
    ap.add_argument("--sections", default="certainty,loops")
    args = ap.parse_args()
    if not DATA.exists():
        sys.exit(f"{DATA} is absent: this benchmark needs the real data")
    result: dict[str, Any] = {"load_before": list(os.getloadavg())}
    if "certainty" in args.sections:
        print("frame certainty (shipped network, T = 1):", flush=True)
        result["certainty"] = certainty_table()
    if "loops" in args.sections:
        print("R@100P with and without the domain gate:", flush=True)
        result["loops"] = loops_table()
    result["load_after"] = list(os.getloadavg())
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"written: {args.out}")


if __name__ == "__main__":
    main()

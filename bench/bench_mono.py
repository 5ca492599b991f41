#!/usr/bin/env python
"""What monocular 3D gives the triangle check on real sequences (issue 11, item 2).

Runs the ``mono-triangles`` preset (the default + monocular triangulation against a
neighbouring frame) on the CamVid revisit development sets and the corridor, and for every
candidate the detector verified counts:

* the frame's triangulated points (entries with any, points per entry);
* the loop's ratio-tested matches, and those with a point on *both* sides (what a triangle
  needs);
* the similar triangles that can be formed from them (``check_triangles`` with the verifier's
  own settings; a side must be 3 of its own sigmas long) and how many agree;
* the verifier that decided (``similar_triangles``, or ``fundamental`` when too few triangles
  could be formed); candidates left unchecked because they could not beat an accepted loop
  (``outranked``) are not counted.

Run: ``python bench/bench_mono.py`` (writes ``bench/results/mono.json``; needs ``../shared/data``
and the shipped network).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stablecues.datasets import open_dataset
from stablecues.detection import LoopDetector, preset
from stablecues.geometry.triangles import check_triangles
from stablecues.verification import Status

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared" / "data"
SETS = {
    "train_drives": (SHARED / "camvid_revisit_dev" / "train_drives" / "frames", "folder"),
    "val_drive": (SHARED / "camvid_revisit_dev" / "val_drive" / "frames", "folder"),
    "corridor": (SHARED / "corridor", "vprbench"),
}


def measure(path: Path, fmt: str) -> dict[str, Any]:
    ds = open_dataset(path, format=fmt)
    det = LoopDetector(preset("mono-triangles", {"similarity": False}))
    decisions = [det.process(ds[i]) for i in range(len(ds))]
    if any(d.entry_id != d.frame_index for d in decisions):
        raise SystemExit("bench_mono: every frame must be stored as the entry of its own index")
    # the verifier the detector used: the frames' calibration, or the one with a guessed focal
    size = det.db.entry(0).features.image_size
    calib, _ = det.preparer.camera_for(det.preparer.calibration_of(ds[0]), size)
    verifier = det.preparer.verifier(calib)
    similar = dataclasses.replace(verifier.config.triangle_config(), tolerance="similar")
    points = [int(np.isfinite(p).all(axis=1).sum()) if (p := det.db.entry(k).points3d) is not None else 0
              for k in range(len(det))]
    matches, both, formed, agree = [], [], [], []
    deciders: Counter[str] = Counter()
    for d in decisions:
        for checked in d.checked:
            v = checked.verification
            if v.status is Status.OUTRANKED:  # fewer matches than an accepted loop's inliers: not run
                continue
            deciders[str(v.method)] += 1
            q, c = det.db.entry(d.entry_id), det.db.entry(checked.frame)
            if q.points3d is None or c.points3d is None:
                continue
            qv, cv = verifier.view_of_entry(q), verifier.view_of_entry(c)
            assert qv.points is not None and cv.points is not None
            m = v.matches
            qp, cp = qv.points.subset(m.query), cv.points.subset(m.candidate)
            matches.append(len(m))
            both.append(int((qp.valid & cp.valid).sum()))
            tc = check_triangles(qp, cp, similar)
            formed.append(tc.n_checked)
            agree.append(tc.n_agree)
    det.close()

    def spread(x: list[int]) -> dict[str, float]:
        a = np.asarray(x if x else [0], float)
        return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)),
                "mean": round(float(a.mean()), 2)}

    return {
        "frames": len(ds),
        "entries_with_points": int(sum(p > 0 for p in points)),
        "points_per_entry": spread(points),
        "checks_run": int(sum(deciders.values())),
        "deciding_verifier": dict(deciders.most_common()),
        "checks_with_points_in_both_frames": len(matches),
        "their_matches": spread(matches),
        "their_matches_with_points_on_both_sides": spread(both),
        "forming_a_triangle": int(sum(f > 0 for f in formed)),
        "forming_two_triangles": int(sum(f >= 2 for f in formed)),
        "with_two_agreeing": int(sum(a >= 2 for a in agree)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "mono.json")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    missing = [name for name, (path, _) in SETS.items() if not path.exists()]
    if missing:
        sys.exit(f"bench_mono: {', '.join(missing)} not found under {SHARED}")
    out: dict[str, Any] = {"preset": "mono-triangles", "load_before": list(os.getloadavg())}
    for name, (path, fmt) in SETS.items():
        r = out[name] = measure(path, fmt)
        print(f"  {name:13s} entries with points {r['entries_with_points']}/{r['frames']} "
              f"(mean {r['points_per_entry']['mean']}); {r['checks_run']} checks run, decided by "
              f"{r['deciding_verifier']}; {r['checks_with_points_in_both_frames']} with points in both "
              f"frames: matches median {r['their_matches']['median']:.0f}, with points on both sides "
              f"median {r['their_matches_with_points_on_both_sides']['median']:.0f} (p90 "
              f"{r['their_matches_with_points_on_both_sides']['p90']:.0f}); forming a triangle "
              f"{r['forming_a_triangle']}, two {r['forming_two_triangles']}, two agreeing "
              f"{r['with_two_agreeing']}", flush=True)
    out["load_after"] = list(os.getloadavg())
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()

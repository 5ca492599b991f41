"""Speed of geometric verification: sparse stereo lifting, the triangle check, a full verification.

Run as ``python bench/bench_verification.py``; prints the figures and writes
``bench/results/verification.json``. Targets (issue 4, on a 2-core machine): stereo lifting of
1000 keypoints <= 5 ms, triangle check of one candidate <= 1 ms, full verification of one
candidate (matching through the direct index, triangles, PnP) <= 4 ms.

Uses the real EuRoC loop pair 0/1 of ``../shared/data/euroc/loop_pairs`` (rectified once;
lifting is timed on the rectified pair, as a SLAM front end would hand it over). Without the
shared data it falls back to a synthetic textured pair and says so in the JSON.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from stablecues.features import OrbConfig, OrbExtractor
from stablecues.geometry import (
    Calibration,
    PinholeCamera,
    StereoLifter,
    StereoRectifier,
    check_triangles,
    load_calibration,
)
from stablecues.verification import Verifier, View
from stablecues.vocabulary import default_vocabulary

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("STABLECUES_SHARED_DATA", ROOT.parent / "shared" / "data"))
OUT = ROOT / "bench" / "results" / "verification.json"


def timed(fn: Callable[[], object], repeats: int) -> dict[str, float]:
    """Milliseconds per call: median, min and 90th percentile over ``repeats`` calls (after warm-up)."""
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return {
        "median": statistics.median(times),
        "min": min(times),
        "p90": float(np.percentile(times, 90)),
        "repeats": repeats,
    }


def _synthetic() -> tuple[Calibration, list[tuple[np.ndarray, np.ndarray]]]:
    rng = np.random.default_rng(0)
    cam = PinholeCamera(436.0, 436.0, 376.0, 240.0, 752, 480)
    calib = Calibration.rectified_stereo(cam, 0.11)
    pairs = []
    for seed in (0, 0):
        img = cv2.GaussianBlur(rng.uniform(0, 255, (480, 752)).astype(np.float32), (0, 0), 2.0)
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
        m = np.array([[1.0, 0.0, 20.0 + seed], [0.0, 1.0, 0.0]])
        right = cv2.warpAffine(img, m, (752, 480), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        pairs.append((img, right))
    return calib, pairs


def main() -> int:
    folder = DATA / "euroc" / "loop_pairs"
    source = "euroc/loop_pairs 0-1"
    if folder.exists():
        rect = StereoRectifier(load_calibration(folder / "sensorLeft.yaml"))
        calib = rect.rectified
        pairs = [
            rect.rectify(
                cv2.imread(str(folder / f"left_img_{i}.png"), cv2.IMREAD_GRAYSCALE),
                cv2.imread(str(folder / f"right_img_{i}.png"), cv2.IMREAD_GRAYSCALE),
            )
            for i in (0, 1)
        ]
    else:
        source = "synthetic textured pair (../shared/data absent)"
        calib, pairs = _synthetic()

    extractor = OrbExtractor(OrbConfig(n_features=1000))
    vocab = default_vocabulary()
    lifter = StereoLifter(calib)
    feats = [extractor.extract(left) for left, _ in pairs]
    points = [lifter.lift(f, left, right) for f, (left, right) in zip(feats, pairs, strict=True)]
    direct_level = max(0, vocab.levels - 2)
    fvecs = [vocab.transform(f.descriptors, levels_up=direct_level)[1] for f in feats]
    fvecs_default = [vocab.transform(f.descriptors)[1] for f in feats]

    left0, right0 = pairs[0]
    lift = timed(lambda: lifter.lift(feats[0], left0, right0), 60)

    verifier = Verifier.from_calibration(calib)
    query = View(feats[1], fvecs[1], points[1])
    cand = View(feats[0], fvecs[0], points[0])
    result = verifier.verify(query, cand)
    m = result.matches
    pq, pc = points[1].subset(m.query), points[0].subset(m.candidate)
    tri_cfg = verifier.config.triangle_config()
    triangles = timed(lambda: check_triangles(pq, pc, tri_cfg), 200)
    verify = timed(lambda: verifier.verify(query, cand), 60)
    query_d = View(feats[1], fvecs_default[1], points[1])
    cand_d = View(feats[0], fvecs_default[0], points[0])
    verify_default = timed(lambda: verifier.verify(query_d, cand_d), 30)
    stages = {k: round(v, 3) for k, v in verifier.verify(query, cand).timings.items()}

    record = {
        "stereo_lift_ms": round(lift["median"], 3),
        "triangle_ms": round(triangles["median"], 3),
        "verify_ms": round(verify["median"], 3),
        "targets_ms": {"stereo_lift_ms": 5.0, "triangle_ms": 1.0, "verify_ms": 4.0},
        "details": {
            "data": source,
            "stereo_lift": {k: round(v, 3) for k, v in lift.items()},
            "triangles": {k: round(v, 3) for k, v in triangles.items()},
            "verify": {k: round(v, 3) for k, v in verify.items()},
            "verify_stage_ms_one_call": stages,
            "verify_with_vocabulary_default_direct_index_ms": round(verify_default["median"], 3),
            "vocabulary": {"k": vocab.k, "levels": vocab.levels, "default_levels_up": vocab.levels_up},
            "direct_index_levels_up": direct_level,
            "n_keypoints": [len(f) for f in feats],
            "n_lifted": [int(p.valid.sum()) for p in points],
            "max_disparity_px": round(lifter.max_disparity, 1),
            "n_matches": len(m),
            "triangles_agree": f"{result.n_triangles_agree}/{len(result.triangles)}",
            "pnp_inliers": result.n_inliers,
            "accepted": result.accepted,
            "machine": {
                "cpus": os.cpu_count(),
                "platform": platform.platform(),
                "python": sys.version.split()[0],
                "numpy": np.__version__,
                "opencv": cv2.__version__,
                "load_average": list(os.getloadavg()),
            },
            "note": "medians over repeats on a shared machine; min and p90 beside them",
        },
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(record, indent=1) + "\n")
    print(f"data: {source}")
    print(
        f"stereo lifting, {len(feats[0])} keypoints: {lift['median']:.2f} ms "
        f"(min {lift['min']:.2f}, p90 {lift['p90']:.2f}; target 5), {int(points[0].valid.sum())} lifted"
    )
    print(
        f"triangle check, T={tri_cfg.n_triangles}: {triangles['median']:.3f} ms "
        f"(min {triangles['min']:.3f}, p90 {triangles['p90']:.3f}; target 1)"
    )
    print(
        f"full verification: {verify['median']:.2f} ms (min {verify['min']:.2f}, p90 {verify['p90']:.2f}; "
        f"target 4); stages {stages}"
    )
    print(
        f"  with the vocabulary's default direct-index level "
        f"(levels_up={vocab.levels_up} of L={vocab.levels}): {verify_default['median']:.2f} ms"
    )
    agree = f"{result.n_triangles_agree}/{len(result.triangles)}"
    print(f"  {len(m)} matches, {agree} triangles agree, {result.n_inliers} PnP inliers")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

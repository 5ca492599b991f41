#!/usr/bin/env python
"""Per-class stability of ORB features across real revisits (issue 11, semantic weighting).

For every true loop pair of the CamVid revisit development set ``train_drives`` (CamVid
``train`` frames: the second traversal under a changed appearance, first traversal as stored,
ground truth from verified overlap), the features of the later frame are matched to the earlier
one (ratio 0.8 through the shipped vocabulary's direct index) and a fundamental matrix is fitted
(USAC). A feature *re-found* is one of the fundamental inliers. Its class is CamVid's own label at
the keypoint (oracle labels of the original frame). The stability of a class is its re-found
rate divided by the rate over all features: above 1, a class's features come back more often
than average when the place is revisited; below 1, less (cars parked elsewhere, sky, moving
people). ``val_drive`` stays out: it judges the network's masks on frames it never trained on.

Writes ``src/stablecues/data/class_stability.json`` (per-class stability, counts, provenance).
Run: ``python scripts/estimate_class_stability.py [--shared ../shared/data]``.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np

from stablecues.datasets import open_dataset
from stablecues.detection import FramePreparer, preset
from stablecues.geometry.pose import fundamental_ransac
from stablecues.groundtruth import load_ground_truth
from stablecues.imageio import read_labels
from stablecues.semantics.classes import CLASS_NAMES, VOID_ID
from stablecues.verification.matching import match_features
from stablecues.vocabulary import default_vocabulary

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "src" / "stablecues" / "data" / "class_stability.json"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    warnings.simplefilter("ignore", DeprecationWarning)
    root = args.shared / "camvid_revisit_dev" / "train_drives"
    ds = open_dataset(root / "frames", format="folder")
    gt = load_ground_truth(root / "gt.png").matrix
    labels = sorted((root / "labels").glob("*.png"))
    prep = FramePreparer(preset("bow"), default_vocabulary())
    prepared = {}

    def frame(i: int):  # noqa: ANN202 - a cache of prepared frames
        if i not in prepared:
            prepared[i] = prep.prepare(ds[i])
        return prepared[i]

    n_classes = VOID_ID + 1
    seen, refound = np.zeros(n_classes), np.zeros(n_classes)
    pairs = 0
    for i, j in zip(*np.nonzero(gt), strict=True):
        a, b = frame(int(i)), frame(int(j))
        m = match_features(a.features, b.features, a.fvec, b.fvec, ratio=0.8)
        if len(m) < 20:
            continue
        pq = a.features.keypoints[m.query].astype(np.float64)
        pc = b.features.keypoints[m.candidate].astype(np.float64)
        f, inl = fundamental_ransac(pq, pc, method="usac")
        if f is None or inl.sum() < 20:
            continue
        lab = read_labels(labels[int(i)])
        xy = np.clip(np.round(a.features.keypoints).astype(int), 0, [lab.shape[1] - 1, lab.shape[0] - 1])
        cls = lab[xy[:, 1], xy[:, 0]]
        seen += np.bincount(cls, minlength=n_classes)
        refound += np.bincount(cls[m.query[inl]], minlength=n_classes)
        pairs += 1
    rate = refound.sum() / seen.sum()
    names = [*CLASS_NAMES, "Unlabelled"][:n_classes]
    stability = {
        n: (round(float(r / s / rate), 3) if s >= 200 else 1.0)
        for n, r, s in zip(names, refound, seen, strict=True)
    }
    doc = {
        "stability": stability,
        "features_seen": {n: int(s) for n, s in zip(names, seen, strict=True)},
        "features_refound": {n: int(r) for n, r in zip(names, refound, strict=True)},
        "pairs": pairs,
        "made_by": "scripts/estimate_class_stability.py",
        "data": "camvid_revisit_dev/train_drives (CamVid train frames), its gt.png loop pairs, oracle labels",
        "method": "ORB 1000, ratio 0.8 via the shipped vocabulary's direct index, fundamental USAC inliers; "
                  "stability = class re-found rate / overall rate (classes with < 200 features: 1)",
    }
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    for n in names:
        k = names.index(n)
        print(f"{n:12s} stability {stability[n]:5.2f}  ({int(refound[k])} of {int(seen[k])})")
    print(f"{pairs} pairs; written {args.out}")


if __name__ == "__main__":
    main()

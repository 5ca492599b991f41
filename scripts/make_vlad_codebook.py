#!/usr/bin/env python
"""Remake the VLAD codebook shipped in ``src/stablecues/data/`` (``vlad_xfeat_k32.npy``).

How it was made: XFeat features (the shipped ONNX export, the best 1000 per image, detection
threshold 0.05) of exactly the development images the XFeat vocabulary was trained on
(``make_xfeat_vocabulary.py``: CamVid ``train`` + ``val``, EuRoC V1_01 both cameras and its loop
pairs, TUM fr2/desk, fr2 RGB-D pair, fr3/long_office; nothing of Gardens Point, the corridor,
desk_loop10 or CamVid ``test``), made unit vectors; ``--sample`` of them drawn at random (seed 0);
flat k-means (k-means++ seeds, Lloyd's iterations, ``stablecues.vocabulary.clustering.kmeans``)
into ``--k`` centres. Saved as a (K, 64) float32 ``.npy`` with its provenance beside it as JSON.

    python scripts/make_vlad_codebook.py [--data ../shared/data] [--k 32] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from make_vocabulary import camvid_train_val
from make_xfeat_vocabulary import indoor_images
from stablecues.features import XFeatConfig, make_extractor
from stablecues.imageio import read_image, to_grey
from stablecues.vocabulary.clustering import kmeans
from stablecues.vocabulary.vlad import DEFAULT_CODEBOOKS, VladCodebook

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path,
                    default=REPO / "src" / "stablecues" / "data" / DEFAULT_CODEBOOKS["xfeat"])
    ap.add_argument("--k", type=int, default=32)
    ap.add_argument("--sample", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    camvid = camvid_train_val(args.data)
    indoor, indoor_sources = indoor_images(args.data)
    images = camvid + indoor
    config = XFeatConfig()
    extractor = make_extractor(config)
    t0 = time.perf_counter()
    sets = [extractor.extract(to_grey(read_image(p))).descriptors for p in images]
    t1 = time.perf_counter()
    allx = np.concatenate(sets).astype(np.float32)
    allx /= np.maximum(np.linalg.norm(allx, axis=1, keepdims=True), 1e-12)
    rng = np.random.default_rng(args.seed)
    pick = rng.choice(allx.shape[0], size=min(args.sample, allx.shape[0]), replace=False)
    centres, labels = kmeans(np.ascontiguousarray(allx[np.sort(pick)]), args.k, rng, max_iter=50)
    t2 = time.perf_counter()
    book = VladCodebook(centres, str(args.out))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.save(args.out, book.centres)
    sizes = np.bincount(labels, minlength=book.k)
    meta = {
        "file": args.out.name, "images": len(images),
        "sources": [f"camvid/train + camvid/val ({len(camvid)})", *indoor_sources],
        "descriptors": int(allx.shape[0]), "sampled": int(pick.size), "k": book.k, "dim": book.dim,
        "vlad_dims": book.size, "cluster_sizes": {"min": int(sizes.min()), "max": int(sizes.max())},
        "seed": args.seed, "extract_seconds": round(t1 - t0, 1), "train_seconds": round(t2 - t1, 1),
        "fingerprint": book.fingerprint,
        "extractor": (f"XFeat (shipped ONNX), best {config.n_features}, "
                      f"threshold {config.detection_threshold}"),
        "command": "python scripts/make_vlad_codebook.py",
        "licence": "made by stablecues from XFeat descriptors (XFeat weights: Apache-2.0, LICENSE-xfeat.txt)",
    }
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n")
    print(json.dumps(meta, indent=2))


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()

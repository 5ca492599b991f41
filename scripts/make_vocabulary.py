#!/usr/bin/env python
"""Remake the vocabulary shipped in ``src/stablecues/data/``.

How it was made: ORB features (stablecues' default extractor: 1000 per image, quadtree
spread, 8 levels, scale 1.2) of the CamVid ``train`` and ``val`` frames in
``../shared/data/camvid`` (468 real urban images; the ``test`` split is kept out because the
loop benchmarks use it), clustered with k = 10, L = 5, seed 0, TF-IDF weighting, L1 scoring.

    python scripts/make_vocabulary.py [--data ../shared/data] [--out src/stablecues/data/vocab_orb_k10_L5.scv]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from stablecues.features import OrbConfig, make_extractor
from stablecues.imageio import list_images, read_image
from stablecues.vocabulary import DEFAULT_VOCABULARY, save_vocabulary, train_vocabulary

REPO = Path(__file__).resolve().parents[1]


def camvid_train_val(data: Path) -> list[Path]:
    """The CamVid ``train`` + ``val`` frames under ``data/camvid`` (never ``test``), in order."""
    camvid = data / "camvid"
    if not (camvid / "train").is_dir() or not (camvid / "val").is_dir():
        raise SystemExit(f"no CamVid train/val images under {camvid}")
    # natural order == sorted order for CamVid's zero-padded names
    images = [p for split in ("train", "val")
              for p in list_images(camvid / split, f"CamVid {split}", suffixes=(".jpg",), allow_empty=True)]
    if not images:
        raise SystemExit(f"no CamVid train/val images under {camvid}")
    return images


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=REPO / "src" / "stablecues" / "data" / DEFAULT_VOCABULARY)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--levels", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    images = camvid_train_val(args.data)
    extractor = make_extractor(OrbConfig())
    sets = [extractor.extract(read_image(p, "grey")).descriptors for p in tqdm(images, desc="ORB")]
    t0 = time.perf_counter()
    voc = train_vocabulary(sets, k=args.k, levels=args.levels, seed=args.seed)
    took = time.perf_counter() - t0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_vocabulary(voc, args.out)
    info = voc.info()
    meta = {
        "file": args.out.name, "images": len(images), "sources": ["camvid/train", "camvid/val"],
        "descriptors": int(sum(s.shape[0] for s in sets)), "k": info.k, "L": info.levels,
        "words": info.n_words, "nodes": info.n_nodes, "weighting": info.weighting,
        "scoring": info.scoring, "levels_up": voc.levels_up, "seed": args.seed,
        "train_seconds": round(took, 1),
        "fingerprint": info.fingerprint, "extractor": "ORB 1000, quadtree, 8 levels, scale 1.2",
        "command": "python scripts/make_vocabulary.py",
    }
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n")
    print(json.dumps(meta, indent=2))


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()

#!/usr/bin/env python
"""Remake the SIFT vocabulary shipped in ``src/stablecues/data/`` (``vocab_sift_k10_L4.scv``).

How it was made: SIFT features (stablecues' SIFT extractor, OpenCV's ``cv2.SIFT`` with its
default thresholds, the strongest 1000 per image) of the CamVid ``train`` and ``val`` frames in
``../shared/data/camvid`` (468 real urban images; the ``test`` split is kept out because the
loop benchmarks use it), clustered by hierarchical k-means (L2) with k = 10, L = 4, seed 0,
TF-IDF weighting, L1 scoring. Four levels (about 10^4 words, 5.8 MB) rather than ORB's five:
a float word is 512 bytes, 16 times an ORB word, and five levels would be about 55 MB.

    python scripts/make_sift_vocabulary.py [--data ../shared/data] [--out PATH] [--scheduler local]

``--scheduler`` (an address, or ``local``) extracts and clusters on a dask cluster; the file is
the same either way.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from make_vocabulary import camvid_train_val  # the same frames as the ORB vocabulary
from stablecues.cli.vocab import dask_client
from stablecues.features import ExtractorConfig, SiftConfig
from stablecues.vocabulary import DEFAULT_VOCABULARIES, save_vocabulary, train_vocabulary
from stablecues.vocabulary.distributed import extract_descriptor_sets

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path,
                    default=REPO / "src" / "stablecues" / "data" / DEFAULT_VOCABULARIES["sift"])
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--levels", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scheduler", default=None, help="dask scheduler address or 'local'")
    args = ap.parse_args()

    images = camvid_train_val(args.data)
    config = SiftConfig()
    train_and_save(args, images, ["camvid/train", "camvid/val"], config,
                   extractor=f"OpenCV SIFT, strongest {config.n_features}, contrast "
                             f"{config.contrast_threshold}, edge {config.edge_threshold}, "
                             f"sigma {config.sigma}",
                   command="python scripts/make_sift_vocabulary.py")


def train_and_save(args: argparse.Namespace, images: list[Path], sources: list[str], config: ExtractorConfig,
                   extractor: str, command: str) -> dict[str, Any]:
    """Extract ``config``'s features of ``images``, train the vocabulary (``args``: k, levels,
    seed, scheduler, out), save it to ``args.out`` and its provenance beside it as JSON."""
    t0 = time.perf_counter()
    with dask_client(args.scheduler) as client:
        sets = extract_descriptor_sets(images, config, client)
        t1 = time.perf_counter()
        voc = train_vocabulary(sets, k=args.k, levels=args.levels, seed=args.seed, client=client)
    t2 = time.perf_counter()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_vocabulary(voc, args.out)
    info = voc.info()
    meta = {
        "file": args.out.name, "images": len(images), "sources": sources,
        "descriptors": int(sum(s.shape[0] for s in sets)), "descriptor_kind": str(voc.descriptor_kind),
        "k": info.k, "L": info.levels, "words": info.n_words, "nodes": info.n_nodes,
        "weighting": info.weighting, "scoring": info.scoring, "levels_up": voc.levels_up,
        "seed": args.seed, "extract_seconds": round(t1 - t0, 1), "train_seconds": round(t2 - t1, 1),
        "scheduler": args.scheduler or "none (serial)",
        "fingerprint": info.fingerprint,
        "extractor": extractor,
        "command": command,
    }
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n")
    print(json.dumps(meta, indent=2))
    return meta


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()

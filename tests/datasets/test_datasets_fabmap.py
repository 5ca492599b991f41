"""stablecues.datasets.fabmap: interleaved left / right images and the ground truth of each view."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from stablecues.datasets import open_dataset


def _img(path: Path, value: int, shape: tuple[int, ...] = (6, 8)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full(shape, value, np.uint8))


def test_fabmap(tmp_path: Path) -> None:
    for k in range(1, 7):  # 0001 left, 0002 right, ...
        _img(tmp_path / "Images" / f"{k:04d}.jpg", 10 * k)
    full = np.zeros((6, 6), np.uint8)
    full[4, 0] = 1  # left image of pair 2 sees left image of pair 0
    full[5, 3] = 1  # right of pair 2 sees right of pair 1
    import scipy.io

    scipy.io.savemat(tmp_path / "TinyGroundTruth.mat", {"truth": full.T})  # stored upper-triangular
    left = open_dataset(tmp_path)
    assert left.format == "fabmap" and len(left) == 3
    assert [n.split("/")[-1] for n in left.names] == ["0001.jpg", "0003.jpg", "0005.jpg"]
    gt = left.ground_truth()
    assert gt is not None and gt.transposed and gt.view == "left"
    assert list(zip(*np.nonzero(gt.matrix), strict=True)) == [(2, 0)]
    right = open_dataset(tmp_path, view="right")
    assert right.names[0].endswith("0002.jpg")
    rgt = right.ground_truth()
    assert rgt is not None and list(zip(*np.nonzero(rgt.matrix), strict=True)) == [(2, 1)]
    every = open_dataset(tmp_path, view="all")
    egt = every.ground_truth()
    assert len(every) == 6 and egt is not None and egt.matrix.sum() == 2

"""stablecues.datasets.vprbench: a two-pass set as one sequence, queries marked in the ground truth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.datasets import open_dataset
from stablecues.errors import DatasetError


def _img(path: Path, value: int, shape: tuple[int, ...] = (6, 8)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full(shape, value, np.uint8))


def test_vprbench(tmp_path: Path) -> None:
    for k in range(3):
        _img(tmp_path / "ref" / f"{k:07d}.jpg", k)
    for k in range(2):
        _img(tmp_path / "query" / f"{k:07d}.jpg", 100 + k)
    table = np.empty((2, 2), dtype=object)
    table[0, 0], table[0, 1] = 0, [0, 1]
    table[1, 0], table[1, 1] = 1, [-1]
    np.save(tmp_path / "ground_truth_new.npy", table, allow_pickle=True)
    ds = open_dataset(tmp_path)
    assert ds.format == "vprbench" and len(ds) == 5
    assert ds.names == [f"ref/{k:07d}.jpg" for k in range(3)] + [f"query/{k:07d}.jpg" for k in range(2)]
    assert ds[3].image[0, 0] == 100
    assert [ds[k].session for k in range(5)] == [0, 0, 0, 1, 1]  # two passes, two sessions
    gt = ds.ground_truth()
    assert gt is not None and gt.query_mask is not None
    assert list(zip(*np.nonzero(gt.matrix), strict=True)) == [(3, 0), (3, 1)]
    assert gt.query_mask.tolist() == [False, False, False, True, True]
    (tmp_path / "query").rename(tmp_path / "q")
    with pytest.raises(DatasetError, match="query/"):
        open_dataset(tmp_path, format="vprbench")

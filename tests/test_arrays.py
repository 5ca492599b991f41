"""The array helpers of the add and query paths."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues._arrays import distinct


@pytest.mark.parametrize("n", [0, 1, 2, 7, 1000])
@pytest.mark.parametrize("dtype", [np.int32, np.int64, np.uint8, np.float64])
def test_distinct_gives_what_np_unique_gives(n: int, dtype: type) -> None:
    rng = np.random.default_rng(n)
    a = rng.integers(0, max(n // 3, 1), n).astype(dtype)
    kept = a.copy()
    got = distinct(a)
    assert got.dtype == a.dtype and np.array_equal(got, np.unique(a))
    assert np.array_equal(a, kept)  # the input is left as it was
    assert np.array_equal(distinct(np.sort(a), is_sorted=True), np.unique(a))

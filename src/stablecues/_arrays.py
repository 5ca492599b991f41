"""Array helpers for the paths that run inside an add or a query.

NumPy 2.4's ``np.unique(a)`` (without indices or counts) asks ``np.ma`` whether ``a`` is
masked, which imports :mod:`numpy.ma` the first time in a process: 8 ms of one add on this
project's machine, the slowest add of a 10^6-entry map after it reopened (``bench_scale.py``).
:func:`distinct` gives the same values without it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["distinct"]


def distinct(a: np.ndarray, is_sorted: bool = False) -> np.ndarray:
    """The sorted distinct values of a 1-D array (what ``np.unique(a)`` gives, NaN aside: each
    NaN counts once here).

    Args:
        a: (N,) values.
        is_sorted: ``a`` is already sorted ascending (skips the sort).
    """
    a = np.asarray(a).reshape(-1)
    if not is_sorted:
        a = np.sort(a)
    if a.size < 2:
        return a.copy()
    keep = np.empty(a.size, np.bool_)
    keep[0] = True
    np.not_equal(a[1:], a[:-1], out=keep[1:])
    return a[keep]

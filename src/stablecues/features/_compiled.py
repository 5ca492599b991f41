"""Compiled ORB keypoint spread (numba): the fast path of
:func:`stablecues.features.orb.select_keypoints`.

Imported only by :func:`stablecues.features.orb.quadtree_kernel`, never at package import
(importing it imports numba); compiled on first use and cached on disk as the vocabulary's
kernels are (:mod:`stablecues.vocabulary._compiled`). It picks what the NumPy path picks, in the
same order, ties included (``tests/features/test_features_orb.py`` checks it).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, boundscheck=False)
def _cell_keys(pts: np.ndarray, idx: np.ndarray, cell: np.float32, depth: int, keys: np.ndarray) -> int:
    """``keys[k] = cell_k * n + k`` sorted, for the quadtree cell of each point ``pts[idx[k]]``
    at ``depth`` (float32 arithmetic, as NumPy does for float32 points and a Python float
    cell): points by cell, then by position. Returns how many distinct cells."""
    n = idx.shape[0]
    for k in range(n):
        cx = np.int64(np.floor(pts[idx[k], 0] / cell))
        cy = np.int64(np.floor(pts[idx[k], 1] / cell))
        keys[k] = (cy * (np.int64(1) << depth) + cx) * n + k
    keys[:n].sort()
    distinct = 1 if n else 0
    for k in range(1, n):
        if keys[k] // n != keys[k - 1] // n:
            distinct += 1
    return distinct


@njit(cache=True, nogil=True, boundscheck=False)
def _strongest_first(rank: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """``pos`` ordered by ``rank[pos]`` ascending, ties kept in the given order (a stable
    argsort, by one sort of uint64 keys: the rank above, the position in ``pos`` below)."""
    m = pos.shape[0]
    keys = np.empty(m, np.uint64)
    for k in range(m):
        keys[k] = (rank[pos[k]] << np.uint64(32)) | np.uint64(k)
    keys.sort()
    out = np.empty(m, np.int64)
    for k in range(m):
        out[k] = pos[np.int64(keys[k] & np.uint64(0xFFFFFFFF))]
    return out


@njit(cache=True, nogil=True, boundscheck=False)
def _monotonic_rank(resp: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Sort ranks of ``-resp[idx]`` (float32): the float's bits made monotonic, as unsigned
    integers (-0.0 and +0.0 alike, as they compare equal; NaN after everything)."""
    n = idx.shape[0]
    r = np.empty(n, np.float32)
    for k in range(n):
        r[k] = -resp[idx[k]] + np.float32(0.0)  # -0.0 + 0.0 is +0.0
    rank = r.view(np.uint32).astype(np.uint64)
    sign = np.uint64(0x80000000)
    for k in range(n):
        u = rank[k]
        if r[k] != r[k]:  # NaN of either sign: last, as NumPy sorts it
            rank[k] = np.uint64(0xFFFFFFFF)
        else:
            rank[k] = (u ^ np.uint64(0xFFFFFFFF)) if u & sign else (u | sign)
    return rank


@njit(cache=True, nogil=True, boundscheck=False)
def _level_pick(pts: np.ndarray, resp: np.ndarray, idx: np.ndarray, quota: int, side: float,
                keys: np.ndarray) -> np.ndarray:
    """:func:`stablecues.features.orb.distribute_quadtree` of the points ``idx``: indices
    into the keypoints, strongest first."""
    count = idx.shape[0]
    if quota <= 0 or count == 0:
        return np.zeros(0, np.int64)
    rank = _monotonic_rank(resp, idx)
    if count <= quota:
        return idx[_strongest_first(rank, np.arange(count))]
    depth = 0
    while (1 << (2 * depth)) < quota and side / (1 << depth) >= 1.0:
        depth += 1
    while True:
        cell = side / (1 << depth)
        distinct = _cell_keys(pts, idx, np.float32(cell), depth, keys)
        if distinct >= quota or cell < 1.0:
            break
        depth += 1
    winners = np.empty(distinct, np.int64)  # positions in idx, by ascending cell
    w = -1
    for k in range(count):
        p = keys[k] % count
        if w < 0 or keys[k] // count != keys[k - 1] // count:
            w += 1
            winners[w] = p
        elif rank[p] < rank[winners[w]]:  # stronger; an equal one keeps the lower index
            winners[w] = p
    return idx[_strongest_first(rank, winners)[:quota]]


@njit(cache=True, nogil=True, boundscheck=False)
def quadtree_select(pts: np.ndarray, resp: np.ndarray, octv: np.ndarray, quotas: np.ndarray,
                    side: float) -> np.ndarray:
    """Every level's pick of :func:`stablecues.features.orb.distribute_quadtree`, levels in
    order, each level's unused quota handed down to the next: what ``OrbExtractor.extract``
    does per level in NumPy, with the same cells (float32 arithmetic) and the same ties
    (within a cell the lowest index; among winners of equal response the lower cell).

    Args:
        pts: (N, 2) float32 keypoints; resp: (N,) float32 responses; octv: (N,) int64 levels;
        quotas: (L,) int64 per-level quotas; side: the larger image side (>= 1).

    Returns:
        int64 indices into the keypoints, level by level, strongest first within a level.
    """
    out = np.empty(pts.shape[0], np.int64)
    keys = np.empty(pts.shape[0], np.int64)
    n_out = 0
    carry = 0
    for level in range(quotas.shape[0]):
        idx = np.flatnonzero(octv == level)
        quota = quotas[level] + carry
        chosen = _level_pick(pts, resp, idx, quota, side, keys)
        out[n_out : n_out + chosen.shape[0]] = chosen
        n_out += chosen.shape[0]
        carry = quota - chosen.shape[0]
    return out[:n_out].copy()

"""Kernels of the incremental vocabulary (:mod:`stablecues.vocabulary.incremental`).

Written in the subset of Python that numba compiles: :func:`kernels` returns them compiled
(``cache=True``, machine code kept on disk) when numba works here, and the same functions run as
plain Python otherwise (slow, identical results: ``tests/vocabulary/test_incremental.py`` checks
the two agree). Nothing here imports numba at module import.

**The word index** is a set of hash tables (locality-sensitive hashing): table ``t`` keys a
descriptor by some of its bits (binary) or by the signs of some projections (float). A bucket
holds its words' ids *and a copy of their descriptors*, in pages (a page of 2 slots, then
pages twice as large, up to :data:`MAX_PAGE`, newest first), so that scanning a bucket reads
memory in order instead of jumping to each word (a miss to main memory per candidate made a
descriptor's 60 candidates cost 3 ms per 1000 descriptors). A descriptor's candidates are the
words sharing a bucket with it in any table; its word is the nearest *live* one within the merge
threshold, ties to the lower id, so the answer does not depend on the order of the buckets.

The page pool (``state``: pages used, slots used) grows only; the caller makes room for the
worst case of a call (every insertion opening a page of :data:`MAX_PAGE` slots) beforehand and
rebuilds the pool from the live words after a purge (:func:`link` into an empty pool).
"""

from __future__ import annotations

from collections.abc import Callable
from types import FunctionType, SimpleNamespace
from typing import Any

import numpy as np

NONE = -1
MAX_PAGE = 32  # slots of the largest page
FIRST_PAGE = 2  # slots of a bucket's first page


def popcount64(x: Any) -> Any:
    """Set bits of one uint64 (SWAR, for the plain Python path; the compiled kernels use the
    popcount instruction)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


def put(t: int, key: int, wid: int, row: np.ndarray, head: np.ndarray, pg_next: np.ndarray,
        pg_start: np.ndarray, pg_cap: np.ndarray, pg_fill: np.ndarray, slot_ids: np.ndarray,
        slot_desc: np.ndarray, state: np.ndarray) -> None:
    """Word ``wid`` (descriptor ``row``) into bucket ``key`` of table ``t``."""
    p = head[t, key]
    if p == NONE or pg_fill[p] == pg_cap[p]:
        cap = FIRST_PAGE if p == NONE else min(2 * pg_cap[p], MAX_PAGE)
        q = state[0]
        state[0] += 1
        pg_start[q] = state[1]
        state[1] += cap
        pg_cap[q] = cap
        pg_fill[q] = 0
        pg_next[q] = p
        head[t, key] = q
        p = q
    s = pg_start[p] + pg_fill[p]
    slot_ids[s] = wid
    for j in range(row.shape[0]):
        slot_desc[s, j] = row[j]
    pg_fill[p] += 1


def assign_binary(keys: np.ndarray, q: np.ndarray, head: np.ndarray, pg_next: np.ndarray,
                  pg_start: np.ndarray, pg_cap: np.ndarray, pg_fill: np.ndarray, slot_ids: np.ndarray,
                  slot_desc: np.ndarray, state: np.ndarray, words: np.ndarray, alive: np.ndarray,
                  n_words: int, threshold: int, create: bool, limit: int, out: np.ndarray) -> int:
    """Each descriptor's word: the nearest live word within ``threshold`` bits among its
    candidates (ties to the lower id), or, with ``create``, a new word made of it (while
    ``n_words < limit``; -1 past it). Descriptors are taken in order, so a later one of the same
    image can join a word an earlier one made. Returns the new number of words.

    Args:
        keys: (N, T) int64 bucket of each descriptor in each table.
        q: (N, W) uint64 descriptors; words: (capacity, W) uint64, room for N more.
        head: (T, 2^bits) int32 newest page of each bucket; pg_*: the page pool; slot_ids,
            slot_desc: its slots; state: (2,) int64 pages and slots used.
        alive: (capacity,) uint8.
        out: (N,) int32 the answer.
    """
    n, w = q.shape
    tables = keys.shape[1]
    for i in range(n):
        best = NONE
        best_d = threshold + 1
        for t in range(tables):
            p = head[t, keys[i, t]]
            while p != NONE:
                s0 = pg_start[p]
                for s in range(s0, s0 + pg_fill[p]):
                    d = 0
                    for j in range(w):
                        d += popcount64(q[i, j] ^ slot_desc[s, j])
                    if d < best_d or (d == best_d and slot_ids[s] < best):
                        c = slot_ids[s]
                        if alive[c]:
                            best_d = d
                            best = c
                p = pg_next[p]
        if best == NONE and create and n_words < limit:
            best = n_words
            for j in range(w):
                words[best, j] = q[i, j]
            alive[best] = 1
            for t in range(tables):
                put(t, keys[i, t], best, q[i], head, pg_next, pg_start, pg_cap, pg_fill, slot_ids, slot_desc,
                    state)
            n_words += 1
        out[i] = best
    return n_words


def assign_float(keys: np.ndarray, q: np.ndarray, head: np.ndarray, pg_next: np.ndarray,
                 pg_start: np.ndarray, pg_cap: np.ndarray, pg_fill: np.ndarray, slot_ids: np.ndarray,
                 slot_desc: np.ndarray, state: np.ndarray, words: np.ndarray, alive: np.ndarray,
                 n_words: int, threshold: float, create: bool, limit: int, out: np.ndarray) -> int:
    """:func:`assign_binary` for float descriptors: squared Euclidean distance summed in
    float64 in dimension order, ``threshold`` a squared distance."""
    n, dims = q.shape
    tables = keys.shape[1]
    for i in range(n):
        best = NONE
        best_d = threshold
        for t in range(tables):
            p = head[t, keys[i, t]]
            while p != NONE:
                s0 = pg_start[p]
                for s in range(s0, s0 + pg_fill[p]):
                    d = 0.0
                    for j in range(dims):
                        e = np.float64(q[i, j]) - np.float64(slot_desc[s, j])
                        d += e * e
                    if d < best_d or (d == best_d and (best == NONE or slot_ids[s] < best)):
                        c = slot_ids[s]
                        if alive[c]:
                            best_d = d
                            best = c
                p = pg_next[p]
        if best == NONE and create and n_words < limit:
            best = n_words
            for j in range(dims):
                words[best, j] = q[i, j]
            alive[best] = 1
            for t in range(tables):
                put(t, keys[i, t], best, q[i], head, pg_next, pg_start, pg_cap, pg_fill, slot_ids, slot_desc,
                    state)
            n_words += 1
        out[i] = best
    return n_words


def link(keys: np.ndarray, ids: np.ndarray, rows: np.ndarray, head: np.ndarray, pg_next: np.ndarray,
         pg_start: np.ndarray, pg_cap: np.ndarray, pg_fill: np.ndarray, slot_ids: np.ndarray,
         slot_desc: np.ndarray, state: np.ndarray) -> None:
    """Put words ``ids`` (descriptors ``rows``, their keys ``keys``) into their buckets, in order
    (rebuilding the index after a purge or a load)."""
    tables = keys.shape[1]
    for i in range(ids.shape[0]):
        for t in range(tables):
            put(t, keys[i, t], ids[i], rows[i], head, pg_next, pg_start, pg_cap, pg_fill, slot_ids, slot_desc,
                state)


_NAMES = ("assign_binary", "assign_float", "link")
_compiled: list[SimpleNamespace | None] = []


def plain() -> SimpleNamespace:
    """The kernels as plain Python (the reference, and the path without numba)."""
    return SimpleNamespace(**{name: globals()[name] for name in _NAMES})


def kernels() -> SimpleNamespace:
    """The kernels compiled by numba (once per process, cached on disk), or :func:`plain` when
    numba is missing or fails here."""
    if not _compiled:
        from ..engine import load_compiled

        _compiled.append(load_compiled(_compile, "the incremental vocabulary"))
    got = _compiled[0]
    return got if got is not None else plain()


def _compile() -> SimpleNamespace:
    from numba import njit

    from . import _compiled  # its popcount: LLVM's ctpop, one instruction

    jit: Callable[[Any], Any] = njit(cache=True, nogil=True, boundscheck=False)
    g = dict(globals())
    g["popcount64"] = _compiled._popcount

    def rebind(name: str) -> Any:  # the function with its globals in ``g`` (the compiled helpers)
        fn = globals()[name]
        return jit(FunctionType(fn.__code__, g, name))

    g["put"] = rebind("put")
    ns = SimpleNamespace(**{name: rebind(name) for name in _NAMES})
    _warm(ns)
    return ns


def pool(tables: int, bits: int, pages: int, slots: int, width: int, dtype: Any) -> dict[str, np.ndarray]:
    """An empty page pool with room for ``pages`` pages and ``slots`` slots."""
    return {"head": np.full((tables, 1 << bits), NONE, np.int32), "pg_next": np.full(pages, NONE, np.int32),
            "pg_start": np.zeros(pages, np.int64), "pg_cap": np.zeros(pages, np.int32),
            "pg_fill": np.zeros(pages, np.int32), "slot_ids": np.zeros(slots, np.int32),
            "slot_desc": np.zeros((slots, width), dtype), "state": np.zeros(2, np.int64)}


POOL_ARGS = ("head", "pg_next", "pg_start", "pg_cap", "pg_fill", "slot_ids", "slot_desc", "state")


def _warm(ns: SimpleNamespace) -> None:
    """Compile (or load) every kernel on a tiny input, so a failure shows here, once."""
    keys = np.zeros((1, 1), np.int64)
    out = np.zeros(1, np.int32)
    for kernel, dtype, thr in ((ns.assign_binary, np.uint64, 8), (ns.assign_float, np.float32, 0.5)):
        pl = pool(1, 1, 8, 64, 2, dtype)
        kernel(keys, np.zeros((1, 2), dtype), *(pl[a] for a in POOL_ARGS), np.zeros((2, 2), dtype),
               np.zeros(2, np.uint8), 0, thr, True, 2, out)
        ns.link(keys, np.zeros(1, np.int32), np.zeros((1, 2), dtype), *(pl[a] for a in POOL_ARGS))

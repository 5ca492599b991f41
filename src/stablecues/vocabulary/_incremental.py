"""Kernels of the incremental vocabulary (:mod:`stablecues.vocabulary.incremental`).

Written in the subset of Python that numba compiles: :func:`kernels` returns them compiled
(``cache=True``, machine code kept on disk) when numba works here, and the same functions run as
plain Python otherwise (slow, identical results: ``tests/vocabulary/test_incremental.py`` checks
the two agree). Nothing here imports numba at module import.

**The word index** is a set of hash tables (locality-sensitive hashing): table ``t`` keys a
descriptor by some of its bits (binary) or by the signs of some projections (float). A bucket
holds its words' ids *and a copy of their descriptors*, in pages (a page of 2 slots, then
pages twice as large, up to :data:`MAX_PAGE`, newest first), so that scanning a bucket reads
its descriptors in order rather than each word's row elsewhere. A descriptor's candidates are the
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
    """Set bits of one uint64 (the plain Python path; the compiled kernels use the popcount
    instruction instead)."""
    return int(x).bit_count()


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
                  slot_desc: np.ndarray, state: np.ndarray, alive: np.ndarray, threshold: int,
                  out: np.ndarray) -> None:
    """Each descriptor's word: the nearest live word within ``threshold`` bits among its
    candidates (ties to the lower id), -1 when none.

    Args:
        keys: (N, T) int64 bucket of each descriptor in each table.
        q: (N, W) uint64 descriptors.
        head: (T, 2^bits) int32 newest page of each bucket; pg_*: the page pool; slot_ids,
            slot_desc: its slots; state: (2,) int64 pages and slots used (unchanged here).
        alive: (capacity,) uint8 live words.
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
        out[i] = best


def assign_float(keys: np.ndarray, q: np.ndarray, head: np.ndarray, pg_next: np.ndarray,
                 pg_start: np.ndarray, pg_cap: np.ndarray, pg_fill: np.ndarray, slot_ids: np.ndarray,
                 slot_desc: np.ndarray, state: np.ndarray, alive: np.ndarray, threshold: float,
                 out: np.ndarray) -> None:
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
                        if (j & 15) == 15 and d > best_d:  # already farther: it cannot win
                            break
                    if d < best_d or (d == best_d and (best == NONE or slot_ids[s] < best)):
                        c = slot_ids[s]
                        if alive[c]:
                            best_d = d
                            best = c
                p = pg_next[p]
        out[i] = best


def grow(todo: np.ndarray, keys: np.ndarray, q: np.ndarray, head: np.ndarray, pg_next: np.ndarray,
         pg_start: np.ndarray, pg_cap: np.ndarray, pg_fill: np.ndarray, slot_ids: np.ndarray,
         slot_desc: np.ndarray, state: np.ndarray, words: np.ndarray, alive: np.ndarray, n_words: int,
         limit: int, out: np.ndarray) -> int:
    """The second step of learning an image: each descriptor of ``todo`` (ascending), which
    joined no word, becomes a new word (while ``n_words < limit``; -1 past it), linked into the
    index. Returns the new number of words."""
    tables = keys.shape[1]
    for r in range(todo.shape[0]):
        i = todo[r]
        if n_words >= limit:
            out[i] = NONE
            continue
        wid = n_words
        for j in range(q.shape[1]):
            words[wid, j] = q[i, j]
        alive[wid] = 1
        for t in range(tables):
            put(t, keys[i, t], wid, q[i], head, pg_next, pg_start, pg_cap, pg_fill, slot_ids, slot_desc,
                state)
        out[i] = wid
        n_words += 1
    return n_words


def keys_binary(q: np.ndarray, positions: np.ndarray, out: np.ndarray) -> None:
    """Bucket of each descriptor in each table: bit ``b`` of table ``t``'s key is the
    descriptor's bit ``positions[t, b]`` (bit k of a descriptor: bit k % 64 of its word k // 64)."""
    n = q.shape[0]
    tables, bits = positions.shape
    for i in range(n):
        for t in range(tables):
            key = 0
            for b in range(bits):
                p = positions[t, b]
                key |= int((q[i, p >> 6] >> np.uint64(p & 63)) & np.uint64(1)) << b
            out[i, t] = key


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


_NAMES = ("assign_binary", "assign_float", "grow", "keys_binary", "link")
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
        kernel(keys, np.zeros((1, 2), dtype), *(pl[a] for a in POOL_ARGS), np.zeros(2, np.uint8), thr, out)
        ns.link(keys, np.zeros(1, np.int32), np.zeros((1, 2), dtype), *(pl[a] for a in POOL_ARGS))
    for dtype in (np.uint64, np.float32):
        pl = pool(1, 1, 8, 64, 2, dtype)
        ns.grow(np.zeros(1, np.int64), keys, np.zeros((1, 2), dtype), *(pl[a] for a in POOL_ARGS),
                np.zeros((2, 2), dtype), np.zeros(2, np.uint8), 0, 2, out)
    ns.keys_binary(np.zeros((1, 1), np.uint64), np.zeros((1, 1), np.int64), keys)

"""Kernels of the incremental vocabulary (:mod:`stablecues.vocabulary.incremental`).

Written in the subset of Python that numba compiles: :func:`kernels` returns them compiled
(``cache=True``, machine code kept on disk) when numba works here, and the same functions run as
plain Python otherwise (slow, identical results: ``tests/vocabulary/test_incremental.py`` checks
the two agree). Nothing here imports numba at module import.

**The word index** is a set of hash tables (locality-sensitive hashing): table ``t`` keys a
descriptor by some of its bits (binary) or by the signs of some projections (float). A bucket
holds its words' ids *and a copy of their descriptors*, so that scanning a bucket reads its
descriptors in order rather than each word's row elsewhere. A descriptor's candidates are the
words sharing a bucket with it in any table; its word is the nearest *live* one within the merge
threshold, ties to the lower id, so the answer depends neither on the order of the buckets nor
on how the index is laid out.

Each bucket has two parts:

* **runs**: every bucket of every table one contiguous run of slots with room to spare, built
  at once from the live words on a reopen (:func:`freeze`, a counting sort per table) and
  rebuilt from the index itself as words come and go (:func:`compact`). A scan reads a run in
  order: on 120,000 words about 8x faster than the pages below, whose slots lie all over the
  pool. A new word takes its bucket's next free slot in the run.
* **pages**: where a run is full, a bucket's new words go to pages (a page of 2 slots, then
  pages twice as large, up to :data:`MAX_PAGE`, newest first). The page pool (``state``: pages
  used, slots used) grows only; the caller makes room for the worst case of a call (every
  insertion opening a page of :data:`MAX_PAGE` slots) beforehand, and compacts the index
  (emptying the pool) once the paged words and the purged ones are a set share of those in
  the runs: amortised, each word is copied a bounded number of times.
"""

from __future__ import annotations

from collections.abc import Callable
from types import FunctionType, SimpleNamespace
from typing import Any

import numpy as np

NONE = -1
MAX_PAGE = 32  # slots of the largest page
FIRST_PAGE = 2  # slots of a bucket's first page
SLACK_SHIFT = 2  # a run's room to spare: a quarter of its words ...
SLACK_MIN = 2  # ... and at least this many slots


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


def same(desc: np.ndarray, s: int, words: np.ndarray, c: int) -> bool:
    """Whether slot ``s``'s copy is word ``c``'s descriptor."""
    for j in range(desc.shape[1]):  # noqa: SIM110 (numba: no generators)
        if desc[s, j] != words[c, j]:
            return False
    return True


def current(desc: np.ndarray, s: int, words: np.ndarray, c: int, alive: np.ndarray) -> bool:
    """Whether slot ``s`` holds word ``c`` as it is: alive, and its copy its descriptor (a slot
    left by a purged word whose id was given to a new word holds the old descriptor)."""
    return bool(alive[c]) and same(desc, s, words, c)


def scan_binary(q: np.ndarray, i: int, desc: np.ndarray, ids: np.ndarray, lo: int, hi: int,
                alive: np.ndarray, words: np.ndarray, best: int, best_d: int) -> tuple[int, int]:
    """The nearest current word (:func:`current`) among slots ``lo..hi`` of ``desc``/``ids``
    closer than ``best_d`` (or as close with a lower id) to descriptor ``q[i]``: ``(best,
    best_d)`` updated."""
    w = q.shape[1]
    for s in range(lo, hi):
        d = 0
        for j in range(w):
            d += popcount64(q[i, j] ^ desc[s, j])
        if d < best_d or (d == best_d and ids[s] < best):
            c = ids[s]
            if current(desc, s, words, c, alive):
                best_d = d
                best = c
    return best, best_d


def scan_float(q: np.ndarray, i: int, desc: np.ndarray, ids: np.ndarray, lo: int, hi: int,
               alive: np.ndarray, words: np.ndarray, best: int, best_d: float) -> tuple[int, float]:
    """:func:`scan_binary` for float descriptors: squared Euclidean distance summed in float64
    in dimension order."""
    dims = q.shape[1]
    for s in range(lo, hi):
        d = 0.0
        for j in range(dims):
            e = np.float64(q[i, j]) - np.float64(desc[s, j])
            d += e * e
            if (j & 15) == 15 and d > best_d:  # already farther: it cannot win
                break
        if d < best_d or (d == best_d and (best == NONE or ids[s] < best)):
            c = ids[s]
            if current(desc, s, words, c, alive):
                best_d = d
                best = c
    return best, best_d


scan = scan_binary  # what assign calls: each variant binds its own (:func:`_variant`)


def assign(keys: np.ndarray, q: np.ndarray, r_start: np.ndarray, r_fill: np.ndarray, r_ids: np.ndarray,
           r_desc: np.ndarray, head: np.ndarray, pg_next: np.ndarray, pg_start: np.ndarray,
           pg_cap: np.ndarray, pg_fill: np.ndarray, slot_ids: np.ndarray, slot_desc: np.ndarray,
           state: np.ndarray, alive: np.ndarray, words: np.ndarray, bound: Any, out: np.ndarray) -> None:
    """Each descriptor's word: the nearest live word closer than ``bound`` among its candidates
    (ties to the lower id), -1 when none. The template of :data:`assign_binary` (``scan`` is
    :func:`scan_binary`, ``bound`` the threshold in bits + 1) and :data:`assign_float`
    (:func:`scan_float`, the squared threshold).

    Args:
        keys: (N, T) int64 bucket of each descriptor in each table.
        q: (N, W) descriptors (uint64 words, or float32).
        r_start, r_fill, r_ids, r_desc: the runs (:func:`runs`).
        head: (T, 2^bits) int32 newest overflow page of each bucket; pg_*: the page pool;
            slot_ids, slot_desc: its slots; state: (2,) int64 pages and slots used (unchanged).
        alive: (capacity,) uint8 live words; words: (capacity, W) their descriptors.
        out: (N,) int32 the answer.
    """
    n = q.shape[0]
    tables, nb = head.shape
    best = np.full(n, NONE, np.int64)
    best_d = np.full(n, bound)
    for t in range(tables):
        # the descriptors in the order of their buckets: the runs are read front to back
        order = np.argsort(keys[:, t])
        for r in range(n):
            i = order[r]
            k = keys[i, t]
            lo = r_start[t * nb + k]
            b, bd = scan(q, i, r_desc, r_ids, lo, lo + r_fill[t * nb + k], alive, words, best[i], best_d[i])
            p = head[t, k]
            while p != NONE:
                b, bd = scan(q, i, slot_desc, slot_ids, pg_start[p], pg_start[p] + pg_fill[p], alive, words,
                             b, bd)
                p = pg_next[p]
            best[i] = b
            best_d[i] = bd
    for i in range(n):
        out[i] = best[i]


def _variant(name: str, scanner: Callable[..., Any], namespace: dict[str, Any]) -> Any:
    """:func:`assign` with ``scan`` bound to ``scanner`` (looked up in ``namespace``), named
    ``name`` (numba's on-disk cache tells the variants apart by it)."""
    fn = FunctionType(assign.__code__, {**namespace, "scan": scanner}, name)
    fn.__qualname__ = name
    return fn


assign_binary = _variant("assign_binary", scan_binary, globals())
assign_float = _variant("assign_float", scan_float, globals())


def freeze(ids: np.ndarray, keys: np.ndarray, rows: np.ndarray, r_start: np.ndarray, r_fill: np.ndarray,
           r_ids: np.ndarray, r_desc: np.ndarray) -> None:
    """Put words ``ids`` (ascending) into the empty runs :func:`runs` made for them: each
    bucket's words in id order at the start of its run. One table at a time: the rows read
    (gathered, a few MB) stay in cache while one table's runs are written.

    Args:
        ids: (L,) int32 the words; keys: (L, T) int32 their keys; rows: (L, W) their
            descriptors, gathered.
        r_start, r_fill (zeros), r_ids, r_desc: the runs, filled here.
    """
    tables = keys.shape[1]
    nb = r_fill.shape[0] // tables
    width = rows.shape[1]
    for t in range(tables):
        for r in range(ids.shape[0]):
            b = t * nb + keys[r, t]
            s = r_start[b] + r_fill[b]
            r_fill[b] += 1
            r_ids[s] = ids[r]
            for j in range(width):
                r_desc[s, j] = rows[r, j]


def compact(r_start: np.ndarray, r_fill: np.ndarray, r_ids: np.ndarray, r_desc: np.ndarray, head: np.ndarray,
            pg_next: np.ndarray, pg_start: np.ndarray, pg_cap: np.ndarray, pg_fill: np.ndarray,
            slot_ids: np.ndarray, slot_desc: np.ndarray, state: np.ndarray, keep: np.ndarray,
            check: np.ndarray, words: np.ndarray, n_start: np.ndarray, n_fill: np.ndarray,
            n_ids: np.ndarray, n_desc: np.ndarray, copy: bool) -> None:
    """The index rebuilt from itself: each bucket's run and then its pages read in order, the
    slots that stay copied into the bucket's new run. A slot of word ``c`` stays when bit ``c``
    of ``keep`` is set (a live word: its slots are its own) or bit ``c`` of ``check`` is and
    the slot holds its descriptor (a live word whose id was given to it after the word that had
    it was purged, since the index was last rebuilt: that word's slots are still in). The bits
    are little-endian bitmaps (:func:`numpy.packbits`): one lookup a slot, in 1/8 of the memory
    of a byte per id (at 2^22 ids a byte array left the cache: 240-350 ms a rebuild at 10^5
    entries of a patrol). Called twice: ``copy`` False counts the slots
    that stay per bucket into ``n_fill``, which :func:`runs` sizes the new runs by; ``copy``
    True fills those runs (``n_start``, zero ``n_fill``, ``n_ids``, ``n_desc``). Every slot is
    read once, in memory order, where :func:`freeze` scatters each word into every table; no
    key is computed and no row gathered. (One loop for runs and pages, no helper: numba counts
    references to every array passed to a call, about 0.5 us a call here.)"""
    tables, nb = head.shape
    width = r_desc.shape[1]
    for b in range(tables * nb):
        o = n_start[b] if copy else 0
        c = 0
        p = head[b // nb, b % nb]
        desc, ids, lo, hi = r_desc, r_ids, r_start[b], r_start[b] + r_fill[b]
        while True:
            for s in range(lo, hi):
                w = ids[s]
                byte, bit = w >> 3, w & 7
                if (keep[byte] >> bit) & 1 or ((check[byte] >> bit) & 1 and same(desc, s, words, w)):
                    if copy:
                        n_ids[o + c] = w
                        for j in range(width):
                            n_desc[o + c, j] = desc[s, j]
                    c += 1
            if p == NONE:
                break
            desc, ids, lo, hi = slot_desc, slot_ids, pg_start[p], pg_start[p] + pg_fill[p]
            p = pg_next[p]
        n_fill[b] = c


def grow(todo: np.ndarray, new_ids: np.ndarray, keys: np.ndarray, q: np.ndarray, r_start: np.ndarray,
         r_fill: np.ndarray, r_ids: np.ndarray, r_desc: np.ndarray, head: np.ndarray, pg_next: np.ndarray,
         pg_start: np.ndarray, pg_cap: np.ndarray, pg_fill: np.ndarray, slot_ids: np.ndarray,
         slot_desc: np.ndarray, state: np.ndarray, words: np.ndarray, alive: np.ndarray,
         out: np.ndarray) -> int:
    """The second step of learning an image: descriptor ``todo[r]`` (ascending), which joined no
    word, becomes word ``new_ids[r]`` (-1 past the ids given), put in its bucket's run in every
    table, or in an overflow page where the run is full. Returns the slots put in pages."""
    tables, nb = head.shape
    paged = 0
    for r in range(todo.shape[0]):
        i = todo[r]
        if r >= new_ids.shape[0]:
            out[i] = NONE
            continue
        wid = new_ids[r]
        for j in range(q.shape[1]):
            words[wid, j] = q[i, j]
        alive[wid] = 1
        for t in range(tables):
            k = keys[i, t]
            b = t * nb + k
            if r_fill[b] < r_start[b + 1] - r_start[b]:
                s = r_start[b] + r_fill[b]
                r_fill[b] += 1
                r_ids[s] = wid
                for j in range(q.shape[1]):
                    r_desc[s, j] = q[i, j]
            else:
                put(t, k, wid, q[i], head, pg_next, pg_start, pg_cap, pg_fill, slot_ids, slot_desc, state)
                paged += 1
        out[i] = wid
    return paged


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


_NAMES = ("assign_binary", "assign_float", "grow", "keys_binary", "freeze", "compact")
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

    def rebind(name: str, how: Callable[[Any], Any] = jit) -> Any:  # with its globals in ``g``
        fn = globals()[name]
        return how(FunctionType(fn.__code__, g, name))

    # the helpers inlined where they are called: a call of a compiled function counts references
    # to each array it is given, about 0.5 us a call with these arguments
    inline: Callable[[Any], Any] = njit(cache=True, nogil=True, boundscheck=False, inline="always")
    for helper in ("put", "same", "current", "scan_binary", "scan_float"):
        g[helper] = rebind(helper, inline)
    ns = SimpleNamespace(**{name: rebind(name) for name in _NAMES if not name.startswith("assign_")})
    ns.assign_binary = jit(_variant("assign_binary", g["scan_binary"], g))
    ns.assign_float = jit(_variant("assign_float", g["scan_float"], g))
    _warm(ns)
    return ns


def pool(tables: int, bits: int, pages: int, slots: int, width: int, dtype: Any) -> dict[str, np.ndarray]:
    """An empty page pool with room for ``pages`` pages and ``slots`` slots."""
    return {"head": np.full((tables, 1 << bits), NONE, np.int32), "pg_next": np.full(pages, NONE, np.int32),
            "pg_start": np.zeros(pages, np.int64), "pg_cap": np.zeros(pages, np.int32),
            "pg_fill": np.zeros(pages, np.int32), "slot_ids": np.zeros(slots, np.int32),
            "slot_desc": np.zeros((slots, width), dtype), "state": np.zeros(2, np.int64)}


def runs(tables: int, bits: int, counts: np.ndarray, width: int, dtype: Any,
         spare: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Empty runs for ``counts`` ((T, 2^bits) words per bucket), each with room to spare:
    ``counts / 2^SLACK_SHIFT`` slots, at least ``SLACK_MIN``.

    The slots are views of arrays with 1/8 more room, so that runs made later can reuse them:
    ``spare``, runs no longer in use, lends its arrays when they are large enough (their old
    slots are not cleared: only the first ``r_fill`` slots of a run are ever read). Fresh
    memory costs this virtual machine 1-17 us a page on first touch: a rebuild at 10^5 entries
    writes about 90 MB of runs."""
    counts = np.asarray(counts, np.int64).reshape(tables << bits)
    cap = counts + np.maximum(counts >> SLACK_SHIFT, SLACK_MIN)
    start = np.zeros(cap.size + 1, np.int64)
    np.cumsum(cap, out=start[1:])
    total = int(start[-1])
    fill = np.zeros(cap.size, np.int64)
    if spare is not None:
        ids, desc = held(spare["r_ids"]), held(spare["r_desc"])
        if ids.shape[0] >= total and desc.shape[1:] == (width,) and desc.dtype == dtype:
            return {"r_start": start, "r_fill": fill, "r_ids": ids[:total], "r_desc": desc[:total]}
    room = total + (total >> 3)
    return {"r_start": start, "r_fill": fill, "r_ids": np.zeros(room, np.int32)[:total],
            "r_desc": np.zeros((room, width), dtype)[:total]}


def held(a: np.ndarray) -> np.ndarray:
    """The array whose memory ``a`` (one of :func:`runs`'s slots, or any array) views."""
    return a if a.base is None else a.base


POOL_ARGS = ("head", "pg_next", "pg_start", "pg_cap", "pg_fill", "slot_ids", "slot_desc", "state")
RUN_ARGS = ("r_start", "r_fill", "r_ids", "r_desc")


def _warm(ns: SimpleNamespace) -> None:
    """Compile (or load) every kernel on a tiny input, so a failure shows here, once."""
    keys = np.zeros((1, 1), np.int64)
    out = np.zeros(1, np.int32)
    for kernel, dtype, thr in ((ns.assign_binary, np.uint64, 8), (ns.assign_float, np.float32, 0.5)):
        pl = pool(1, 1, 8, 64, 2, dtype)
        rn = runs(1, 1, np.array([1, 0]), 2, dtype)
        ns.freeze(np.zeros(1, np.int32), np.zeros((1, 1), np.int32), np.zeros((1, 2), dtype),
                  *(rn[a] for a in RUN_ARGS))
        kernel(keys, np.zeros((1, 2), dtype), *(rn[a] for a in RUN_ARGS), *(pl[a] for a in POOL_ARGS),
               np.zeros(2, np.uint8), np.zeros((2, 2), dtype), thr, out)
        ns.grow(np.zeros(1, np.int64), np.ones(1, np.int32), keys, np.zeros((1, 2), dtype),
                *(rn[a] for a in RUN_ARGS), *(pl[a] for a in POOL_ARGS), np.zeros((2, 2), dtype),
                np.zeros(2, np.uint8), out)
        again = runs(1, 1, np.array([1, 0]), 2, dtype)
        for copy in (False, True):
            ns.compact(*(rn[a] for a in RUN_ARGS), *(pl[a] for a in POOL_ARGS), np.ones(1, np.uint8),
                       np.zeros(1, np.uint8), np.zeros((2, 2), dtype), *(again[a] for a in RUN_ARGS), copy)
    ns.keys_binary(np.zeros((1, 1), np.uint64), np.zeros((1, 1), np.int64), keys)

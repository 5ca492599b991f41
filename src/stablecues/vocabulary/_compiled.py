"""Compiled transform kernels (numba), the fast path of :mod:`stablecues.vocabulary.engine`.

Imported only through :func:`stablecues.vocabulary.engine.compiled_kernels`, never at package
import: importing this module imports numba. The kernels are compiled on first use and cached on
disk (``cache=True``: next to this file, or numba's user cache directory when the package folder
is read-only), so later processes load machine code instead of compiling it.

The kernels compute exactly what the NumPy path computes (same greedy descent with ties to the
lowest child, same summation order per word), so their results are identical to the last bit;
``tests/vocabulary/test_vocab_engine.py`` checks it on real descriptors. Three descents:
:func:`descend` for ORB's 4-word binary descriptors (unrolled, in groups), :func:`descend_words`
for binary descriptors of any other width, :func:`descend_float` for float descriptors
(squared Euclidean distance summed in float64 in index order, as the NumPy path sums it;
``tests/vocabulary/test_vocab_float.py`` checks the two agree). One more kernel serves the
matcher: :func:`best_two_binary`, each query descriptor's nearest and second-nearest
candidate under its vocabulary node (``tests/verification/test_verification_matching.py``
checks it against NumPy); :func:`argmax_channels`, the class map of a segmentation; and
:func:`scatter_runs`, the copy at the heart of merging index segments, and
:func:`count_words` with :func:`scatter_words`, the counting sort that sorts and merges small
ones (``tests/database/test_database_segments.py`` checks them against NumPy).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

# Descriptors descend in groups: at each level every descriptor of the group picks its child
# before any goes one level deeper, so the memory loads of different descriptors overlap
# instead of waiting one after another (a tree of 10^5 words does not fit in the L2 cache).
GROUP = 16
_SHIFT = np.uint64(32)
_SLOT_MASK = np.uint64((1 << 32) - 1)
_NO_CHILD = np.uint64(1 << 62)


def _popcount_typer(typingctx: Any, x: Any) -> Any:
    """Bit count of a uint64 (LLVM's ctpop: one POPCNT instruction on x86-64)."""
    sig = types.uint64(types.uint64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.ctpop(args[0])

    return sig, codegen


_popcount: Any = intrinsic(_popcount_typer)


@njit(cache=True, nogil=True, boundscheck=False)
def descend(q: np.ndarray, blocks: np.ndarray, kids: np.ndarray, counts: np.ndarray,
            row: np.ndarray, out: np.ndarray) -> None:
    """Leaf reached by each descriptor (greedy descent, ties to the lowest child slot).

    Args:
        q: (N, 4) uint64 descriptors.
        blocks: (I, W * 4) uint64 children's centres of each internal node, side by side.
        kids: (I, W) int32 children of each internal node, -1 padded at the end.
        counts: (I,) int32 number of children of each internal node.
        row: (n,) int32 row of each node in ``blocks`` / ``kids``; -1 for leaves.
        out: (N,) int32, filled with the leaf node ids.
    """
    n = q.shape[0]
    rows = np.empty(GROUP, np.int64)
    for s in range(0, n, GROUP):
        m = min(GROUP, n - s)
        for g in range(m):
            rows[g] = row[0]
            out[s + g] = 0
        active = m if row[0] >= 0 else 0
        while active > 0:
            active = 0
            for g in range(m):
                r = rows[g]
                if r < 0:
                    continue
                i = s + g
                q0 = q[i, 0]
                q1 = q[i, 1]
                q2 = q[i, 2]
                q3 = q[i, 3]
                # (distance, slot) in one key: the smallest key is the nearest child and, among
                # equally near ones, the lowest slot; a branch-free min, as the distances are
                # too random for the branch predictor
                best = _NO_CHILD
                for c in range(counts[r]):
                    b = 4 * c
                    d = (_popcount(q0 ^ blocks[r, b]) + _popcount(q1 ^ blocks[r, b + 1])
                         + _popcount(q2 ^ blocks[r, b + 2]) + _popcount(q3 ^ blocks[r, b + 3]))
                    best = min(best, (d << _SHIFT) | np.uint64(c))
                chosen = kids[r, np.int64(best & _SLOT_MASK)]
                out[i] = chosen
                nxt = row[chosen]
                rows[g] = nxt
                if nxt >= 0:
                    active += 1


@njit(cache=True, nogil=True, boundscheck=False)
def descend_words(q: np.ndarray, blocks: np.ndarray, kids: np.ndarray, counts: np.ndarray,
                  row: np.ndarray, out: np.ndarray) -> None:
    """:func:`descend` for binary descriptors of any width: ``q`` is (N, W) uint64 and
    ``blocks`` (I, w * W) uint64, W words per descriptor (ORB's 4 words take :func:`descend`)."""
    n, words = q.shape
    for i in range(n):
        node = 0
        r = row[0]
        while r >= 0:
            best = _NO_CHILD
            for c in range(counts[r]):
                b = words * c
                d = np.uint64(0)
                for j in range(words):
                    d += _popcount(q[i, j] ^ blocks[r, b + j])
                best = min(best, (d << _SHIFT) | np.uint64(c))
            node = kids[r, np.int64(best & _SLOT_MASK)]
            r = row[node]
        out[i] = node


@njit(cache=True, nogil=True, boundscheck=False)
def descend_float(q: np.ndarray, blocks: np.ndarray, kids: np.ndarray, counts: np.ndarray,
                  row: np.ndarray, out: np.ndarray) -> None:
    """Leaf reached by each float descriptor (greedy descent by Euclidean distance, ties to the
    lowest child slot).

    The squared distance is summed dimension by dimension in float64, in index order: the
    NumPy path sums the same terms in the same order, so both choose the same children.

    Args:
        q: (N, D) float32 descriptors.
        blocks: (I, w * D) float32 children's centres of each internal node, side by side.
        kids, counts, row, out: as in :func:`descend`.
    """
    n, dim = q.shape
    for i in range(n):
        node = 0
        r = row[0]
        while r >= 0:
            best = np.inf
            slot = 0
            for c in range(counts[r]):
                b = dim * c
                acc = 0.0
                for j in range(dim):
                    diff = np.float64(blocks[r, b + j]) - np.float64(q[i, j])
                    acc += diff * diff
                if acc < best:
                    best = acc
                    slot = c
            node = kids[r, slot]
            r = row[node]
        out[i] = node


@njit(cache=True, nogil=True, boundscheck=False)
def assemble(leaves: np.ndarray, node_weight: np.ndarray, node_word: np.ndarray,
             di_table: np.ndarray, feature_weight: np.ndarray, weighted: bool,
             add: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """BoW words and values (before normalisation) and direct-index nodes of the leaves.

    Args:
        leaves: (N,) int32 leaf of each feature.
        node_weight: (n,) float64 weight of each node.
        node_word: (n,) int32 word id of each node (-1 for internal nodes).
        di_table: (n,) int32 direct-index node of each node.
        feature_weight: (N,) float64 weight of each feature (read only when ``weighted``).
        weighted: whether ``feature_weight`` applies.
        add: TF-IDF / TF (each feature adds its weight) rather than IDF / binary (each word
            once, scaled by the largest weight of its features).

    Returns:
        words (M,) int32 ascending, values (M,) float64, nodes (N,) int32 (-1: dropped).
    """
    n = leaves.shape[0]
    nodes = np.empty(n, np.int32)
    keys = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        leaf = leaves[i]
        ok = node_weight[leaf] > 0
        if weighted:
            ok = ok and feature_weight[i] > 0
        if ok:
            nodes[i] = di_table[leaf]
            keys[m] = np.int64(node_word[leaf]) * n + i  # word-major, features in order
            m += 1
        else:
            nodes[i] = -1
    keys = np.sort(keys[:m])
    words = np.empty(m, np.int32)
    values = np.empty(m, np.float64)
    top = np.empty(m, np.float64)  # IDF / binary: the largest feature weight of each word
    u = -1
    last = -1
    for j in range(m):
        word = keys[j] // n
        i = keys[j] - word * n
        ww = node_weight[leaves[i]]
        fw = feature_weight[i] if weighted else 1.0
        if word != last:
            u += 1
            last = word
            words[u] = word
            values[u] = 0.0 if add else ww
            top[u] = fw
        if add:
            # the same products, summed in the same order, as np.bincount over the features
            values[u] += ww * fw if weighted else ww
        elif fw > top[u]:
            top[u] = fw
    u += 1
    if weighted and not add:
        for j in range(u):
            values[j] = values[j] * top[j]
    return words[:u], values[:u], nodes


@njit(cache=True, nogil=True, boundscheck=False)
def transform(q: np.ndarray, blocks: np.ndarray, kids: np.ndarray, counts: np.ndarray,
              row: np.ndarray,
              node_weight: np.ndarray, node_word: np.ndarray, di_table: np.ndarray,
              feature_weight: np.ndarray, weighted: bool,
              add: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`descend` then :func:`assemble`, in one call (one dispatch from Python)."""
    leaves = np.empty(q.shape[0], np.int32)
    descend(q, blocks, kids, counts, row, leaves)
    return assemble(leaves, node_weight, node_word, di_table, feature_weight, weighted, add)


@njit(cache=True, nogil=True, boundscheck=False)
def best_two_binary(qw: np.ndarray, cw: np.ndarray, qnodes: np.ndarray, qorder: np.ndarray,
                    csorted: np.ndarray, corder: np.ndarray, none: int, best_j: np.ndarray,
                    best: np.ndarray, second: np.ndarray) -> None:
    """Nearest and second-nearest candidate of each query descriptor among those under its node.

    Queries are visited in node order (``qorder``) while a cursor walks the candidates sorted by
    node (``csorted``, ``corder``: a stable sort, so ascending indices within a node): one
    linear pass instead of a binary search per query. Ties go to the lower candidate index;
    with a single candidate the second distance is ``none``; without any (or ``qnodes[i] <
    0``) ``best_j`` is -1, ``best`` ``none + 1`` and ``second`` ``none``, as the NumPy path gives.

    Args:
        qw: (N, W) uint64 query descriptors; cw: (M, W) uint64 candidate descriptors.
        qnodes: (N,) vocabulary node of each query descriptor; qorder: (N,) its sorting order.
        csorted: (M,) candidate nodes sorted; corder: (M,) the sorting order.
        none: the distance standing for "no second candidate".
        best_j, best, second: (N,) int64 outputs.
    """
    n = qw.shape[0]
    m = csorted.shape[0]
    width = qw.shape[1]
    cursor = 0
    for t in range(n):
        i = qorder[t]
        node = qnodes[i]
        while cursor < m and csorted[cursor] < node:
            cursor += 1
        a = cursor
        b = cursor
        while b < m and csorted[b] == node:
            b += 1
        if node < 0 or b <= a:
            best_j[i] = -1
            best[i] = none + 1
            second[i] = none
            continue
        b1 = np.int64(1) << 40
        b2 = np.int64(1) << 40
        bj = np.int64(-1)
        for p in range(a, b):
            c = corder[p]
            d = np.int64(0)
            for k in range(width):
                d += np.int64(_popcount(qw[i, k] ^ cw[c, k]))
            if d < b1:
                b2 = b1
                b1 = d
                bj = c
            elif d < b2:
                b2 = d
        best_j[i] = bj
        best[i] = b1
        second[i] = b2 if b - a > 1 else none


@njit(cache=True, nogil=True, boundscheck=False)
def argmax_channels(hwc: np.ndarray, out: np.ndarray) -> None:
    """``out[i, j] = argmax(hwc[i, j, :])`` (the first of equal maxima, as ``np.argmax``), for a
    (H, W, C) float32 array of finite values; ``out`` is (H, W) uint8."""
    h, w, c = hwc.shape
    for i in range(h):
        for j in range(w):
            best = hwc[i, j, 0]
            k = 0
            for q in range(1, c):
                v = hwc[i, j, q]
                if v > best:
                    best = v
                    k = q
            out[i, j] = k


@njit(cache=True, nogil=True, boundscheck=False)
def scatter_runs(out: np.ndarray, postings: np.ndarray, counts: np.ndarray, dest: np.ndarray) -> None:
    """Copy consecutive runs of ``postings`` (``counts[w]`` of them for word ``w``) to
    ``out[dest[w] : dest[w] + counts[w]]``: one input's part of a merge of index segments
    (:func:`stablecues.database.segments.merge_runs`)."""
    src = 0
    for w in range(counts.shape[0]):
        c = counts[w]
        d = dest[w]
        for j in range(c):
            out[d + j] = postings[src + j]
        src += c


@njit(cache=True, nogil=True, boundscheck=False)
def count_words(counts: np.ndarray, words: np.ndarray, postings: np.ndarray, w0: int, lo: int,
                hi: int) -> int:
    """Add the postings of each word ``w0 + k`` to ``counts[k]``; returns how many postings
    have a word outside ``w0 .. w0 + len(counts) - 1`` or an entry id outside ``lo .. hi - 1``
    (left out: a corrupt segment). The first half of a counting sort of index postings by
    word (:func:`scatter_words` is the second)."""
    n = counts.shape[0]
    bad = 0
    for i in range(words.shape[0]):
        w = words[i] - w0
        e = postings[i] & 0xFFFFFFFF  # the entry id: the low half of a little-endian posting
        if w < 0 or w >= n or e < lo or e >= hi:
            bad += 1
        else:
            counts[w] += 1
    return bad


@njit(cache=True, nogil=True, boundscheck=False)
def scatter_words(out: np.ndarray, dest: np.ndarray, words: np.ndarray, postings: np.ndarray,
                  w0: int) -> None:
    """Write each posting to ``out[dest[word - w0]]`` and advance that word's ``dest``: the
    stable second half of a counting sort (inputs scattered oldest first keep entry ids
    ascending within every word). Postings :func:`count_words` left out are skipped."""
    n = dest.shape[0]
    m = out.shape[0]
    for i in range(words.shape[0]):
        w = words[i] - w0
        if 0 <= w < n:
            d = dest[w]
            if d < m:
                out[d] = postings[i]
                dest[w] = d + 1



@njit(cache=True, nogil=True, boundscheck=False)
def _radix_pass(src_w: np.ndarray, src_p: np.ndarray, dst_w: np.ndarray, dst_p: np.ndarray,
                shift: int, mask: int) -> None:
    start = np.zeros(mask + 2, np.int64)
    for i in range(src_w.shape[0]):
        start[((src_w[i] >> shift) & mask) + 1] += 1
    for d in range(1, mask + 2):
        start[d] += start[d - 1]
    for i in range(src_w.shape[0]):
        d = (src_w[i] >> shift) & mask
        j = start[d]
        start[d] = j + 1
        dst_w[j] = src_w[i]
        dst_p[j] = src_p[i]


@njit(cache=True, nogil=True, boundscheck=False)
def radix_words(words: np.ndarray, postings: np.ndarray, n_bits: int, out_w: np.ndarray,
                out_p: np.ndarray, tmp_w: np.ndarray, tmp_p: np.ndarray) -> None:
    """Sort (P,) int32 ``words`` in 0 .. 2**n_bits - 1, and their postings with them, stably
    into ``out_w`` / ``out_p`` (``tmp_*``: as large, scratch): least significant digit first,
    digits of at most 11 bits, so a 10^6-word vocabulary takes two passes of 1024 buckets
    (:func:`stablecues.database.segments.sort_blocks`). A digit is masked, so no word can
    index outside the buckets."""
    passes = max((n_bits + 10) // 11, 1)
    digit = (n_bits + passes - 1) // passes
    mask = (1 << digit) - 1
    for k in range(passes):
        to_out = (passes - 1 - k) % 2 == 0  # the last pass writes out_*
        if k == 0:
            if to_out:
                _radix_pass(words, postings, out_w, out_p, 0, mask)
            else:
                _radix_pass(words, postings, tmp_w, tmp_p, 0, mask)
        elif to_out:
            _radix_pass(tmp_w, tmp_p, out_w, out_p, k * digit, mask)
        else:
            _radix_pass(out_w, out_p, tmp_w, tmp_p, k * digit, mask)

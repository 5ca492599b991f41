"""The inverse index: word -> postings (entry id, weight), built for fast sparse queries.

Postings live in a few immutable segments sorted by word (a log-structured merge, like a
search engine's index) plus a small unsorted tail of the latest additions. A query finds each
query word's run in every segment with a binary search, gathers the postings with one
vectorised index computation, adds the tail's matching postings through a dense word lookup,
and accumulates the scoring's per-word terms per entry with ``np.bincount``: no Python loop
over words or entries. Tail flushes and segment merges keep O(log n) segments, and the cost of
an add stays amortised O(log n) per posting.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..vocabulary.scoring import Scoring, common_terms, finish, kl_missing_total

_INDPTR_MIN = 1 << 18  # segments at least this large get a word -> offset table


@dataclass
class _Segment:
    words: np.ndarray  # (P,) int32, sorted (stable: entry ids ascending within a word)
    entries: np.ndarray  # (P,) int32
    weights: np.ndarray  # (P,) float32
    indptr: np.ndarray | None = None  # (W + 1,) offsets of each word's run (large segments)

    @property
    def size(self) -> int:
        return int(self.words.shape[0])

    def with_table(self, n_words: int) -> _Segment:
        """Give a large segment its CSR table, so a query finds each word's run in O(1)."""
        if self.size >= _INDPTR_MIN and self.indptr is None:
            counts = np.bincount(self.words, minlength=n_words)
            dtype = np.int32 if self.size < 2**31 else np.int64
            self.indptr = np.zeros(n_words + 1, dtype)
            np.cumsum(counts, out=self.indptr[1:])
        return self

    def runs(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Start and end offsets of the runs of the given sorted query words."""
        if self.indptr is not None:
            return self.indptr[words].astype(np.int64), self.indptr[words + 1].astype(np.int64)
        return (np.searchsorted(self.words, words, "left"), np.searchsorted(self.words, words, "right"))


def _merge(a: _Segment, b: _Segment) -> _Segment:
    """Merge two word-sorted segments, ``a`` holding the older entries: a linear merge by
    binary search (no sort of the whole), keeping entry order within each word."""
    n = a.size + b.size
    # b's postings go after a's postings of the same word; a's before b's
    pos_b = np.searchsorted(a.words, b.words, side="right") + np.arange(b.size)
    pos_a = np.searchsorted(b.words, a.words, side="left") + np.arange(a.size)
    out = _Segment(np.empty(n, np.int32), np.empty(n, np.int32), np.empty(n, np.float32))
    for dst, src_a, src_b in ((out.words, a.words, b.words), (out.entries, a.entries, b.entries),
                              (out.weights, a.weights, b.weights)):
        dst[pos_a] = src_a
        dst[pos_b] = src_b
    return out


class InvertedIndex:
    """Inverse index over BoW vectors of entries numbered 0, 1, 2, ... in insertion order.

    Args:
        n_words: vocabulary size.
        scoring: how entries are scored against a query.
        tail_limit: postings kept unsorted before they are flushed into a segment.
    """

    def __init__(self, n_words: int, scoring: Scoring, tail_limit: int = 1 << 16) -> None:
        self.n_words = int(n_words)
        self.scoring = scoring
        self.tail_limit = int(tail_limit)
        self.n_entries = 0
        self._segments: list[_Segment] = []
        self._tail_words: list[np.ndarray] = []
        self._tail_entries: list[np.ndarray] = []
        self._tail_weights: list[np.ndarray] = []
        self._tail_size = 0
        self._tail_cache: _Segment | None = None
        self._lookup = np.zeros(self.n_words, np.float64)

    @property
    def n_postings(self) -> int:
        return sum(s.size for s in self._segments) + self._tail_size

    @property
    def nbytes(self) -> int:
        return sum(
            s.words.nbytes + s.entries.nbytes + s.weights.nbytes
            + (0 if s.indptr is None else s.indptr.nbytes)
            for s in self._segments
        ) + self._tail_size * 12

    def add(self, words: np.ndarray, weights: np.ndarray) -> int:
        """Append the next entry's BoW vector; returns its id."""
        entry = self.n_entries
        self._tail_words.append(np.asarray(words, np.int32))
        self._tail_entries.append(np.full(words.shape[0], entry, np.int32))
        self._tail_weights.append(np.asarray(weights, np.float32))
        self._tail_size += int(words.shape[0])
        self._tail_cache = None
        self.n_entries += 1
        if self._tail_size >= self.tail_limit:
            self.flush()
        return entry

    def add_many(self, words: np.ndarray, entries: np.ndarray, weights: np.ndarray, n_entries: int) -> None:
        """Bulk-load postings of entries ``n_entries`` ids (used when reopening a database)."""
        self.flush()
        order = np.argsort(words, kind="stable")
        self._push(_Segment(np.asarray(words, np.int32)[order], np.asarray(entries, np.int32)[order],
                            np.asarray(weights, np.float32)[order]))
        self.n_entries = max(self.n_entries, int(n_entries))

    def flush(self) -> None:
        """Sort the tail into a segment and merge segments of similar size."""
        if not self._tail_size:
            return
        tail = self._tail()
        self._tail_words, self._tail_entries, self._tail_weights = [], [], []
        self._tail_size = 0
        self._tail_cache = None
        order = np.argsort(tail.words, kind="stable")
        self._push(_Segment(tail.words[order], tail.entries[order], tail.weights[order]))

    def _push(self, seg: _Segment) -> None:
        self._segments.append(seg)
        # merge while the newer segment is at least half the size of the one before it
        while len(self._segments) > 1 and self._segments[-1].size * 2 >= self._segments[-2].size:
            b = self._segments.pop()
            a = self._segments.pop()
            self._segments.append(_merge(a, b))
        self._segments[-1].with_table(self.n_words)

    def _tail(self) -> _Segment:
        if self._tail_cache is None:
            if self._tail_size:
                self._tail_cache = _Segment(np.concatenate(self._tail_words),
                                            np.concatenate(self._tail_entries),
                                            np.concatenate(self._tail_weights))
            else:
                z = np.zeros(0, np.int32)
                self._tail_cache = _Segment(z, z, np.zeros(0, np.float32))
        return self._tail_cache

    def postings(self, words: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All postings of the given query words.

        Args:
            words: (M,) int32 sorted unique query words.
            values: (M,) float64 query weights.

        Returns:
            entries (P,) int32, entry weights (P,) float32 and the query weight of each
            posting's word (P,) float64.
        """
        ent_parts: list[np.ndarray] = []
        w_parts: list[np.ndarray] = []
        v_parts: list[np.ndarray] = []
        for seg in self._segments:
            lo, hi = seg.runs(words)
            counts = hi - lo
            nz = np.flatnonzero(counts)
            if not nz.size:
                continue
            # each word's postings are one contiguous run: copy runs (memcpy) rather than
            # gathering element by element
            bounds = list(zip(lo[nz].tolist(), hi[nz].tolist(), strict=True))
            ent_parts.append(np.concatenate([seg.entries[a:b] for a, b in bounds]))
            w_parts.append(np.concatenate([seg.weights[a:b] for a, b in bounds]))
            v_parts.append(np.repeat(values, counts))
        if self._tail_size:
            tail = self._tail()
            lookup = self._lookup
            lookup[words] = values
            v = lookup[tail.words]
            lookup[words] = 0.0
            hit = v != 0
            ent_parts.append(tail.entries[hit])
            w_parts.append(tail.weights[hit])
            v_parts.append(v[hit])
        if not ent_parts:
            return np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(0)
        return np.concatenate(ent_parts), np.concatenate(w_parts), np.concatenate(v_parts)

    def scores(
        self, words: np.ndarray, values: np.ndarray, max_id: int | None = None, min_id: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Score every entry sharing a word with the query.

        Args:
            words: (M,) int32 sorted unique query words.
            values: (M,) float64 query weights (normalised as the scoring needs).
            max_id: only entries with id < max_id (None: all).
            min_id: only entries with id >= min_id.

        Returns:
            entry ids (K,) int64 and their DBoW2 scores (K,) float64, in id order.
        """
        hi = self.n_entries if max_id is None else max(0, min(int(max_id), self.n_entries))
        if hi <= min_id or words.size == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        ent, w, v = self.postings(words, values)
        if ent.size == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        terms = common_terms(self.scoring, v, w)
        # accumulate over every entry, then keep the id range (cheaper than filtering postings)
        sums = np.bincount(ent, weights=terms, minlength=self.n_entries)[min_id:hi]
        if self.scoring == Scoring.KL or not (w.min() > 0 and v.min() > 0):
            present = np.bincount(ent, minlength=self.n_entries)[min_id:hi] > 0
        else:
            present = sums != 0  # every shared word adds a non-zero term when weights are > 0
        ids = np.flatnonzero(present)
        kl = kl_missing_total(values) if self.scoring == Scoring.KL else 0.0
        return ids + min_id, finish(self.scoring, sums[ids], kl)

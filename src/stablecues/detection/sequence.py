"""Sequence scores: SeqSLAM's diagonal search over the recent queries' database scores.

A single frame by night, or in a corridor of repeated doors, can score a wrong place as high as
the right one; the frames before it rarely repeat the same mistake in the same order. SeqSLAM
(Milford and Wyeth, ICRA 2012) scores a candidate ``c`` of the current query by the scores of the
previous queries along a line through the (query, map) similarity matrix: query ``t - i`` against
entry ``c - round(i * v)`` for ``i = 0 .. L - 1``, at the speed ``v`` (entries per frame) that
fits best, the map traversed at another pace than the query.

Here the matrix is never built: each recent query keeps its database results (the top
``max_results`` entries and their normalised scores capped at 1, what the query stage has
anyway; right after a cut a frame's own predecessor is another place and its normalised scores
run to 5 and more), an entry absent from them counts 0, and each step may land ``tolerance``
entries either side of the line (the best of them counts), which absorbs a pace that varies
within the window. The cost is
``L * len(speeds) * (2 * tolerance + 1)`` binary searches over at most ``max_results`` ids per
candidate, independent of the map's size.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

#: speeds searched (map entries per query frame): the map at half to twice the query's pace
DEFAULT_SPEEDS = (0.5, 0.7, 1.0, 1.4, 2.0)


@dataclass(frozen=True)
class Scored:
    """One query's database results: entry ids, sorted ascending, and their scores."""

    ids: np.ndarray
    scores: np.ndarray

    @classmethod
    def of(cls, ids: np.ndarray, scores: np.ndarray) -> Scored:
        ids = np.asarray(ids, np.int64)
        scores = np.asarray(scores, np.float64)
        order = np.argsort(ids, kind="stable")
        return cls(ids[order], scores[order])

    @classmethod
    def capped(cls, ids: np.ndarray, normalised: np.ndarray) -> Scored:
        """A query's results for the history: normalised scores capped at 1 (the frame against
        its own predecessor; right after a cut that predecessor is another place and normalised
        scores run to 5 and more, which would outweigh a line)."""
        return cls.of(ids, np.minimum(np.asarray(normalised, np.float64), 1.0))

    @classmethod
    def empty(cls) -> Scored:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.float64))

    def lookup(self, targets: np.ndarray) -> np.ndarray:
        """The score of each target entry id (0 where absent), same shape as ``targets``."""
        if self.ids.size == 0:
            return np.zeros(targets.shape)
        pos = np.searchsorted(self.ids, targets).clip(0, self.ids.size - 1)
        return np.where(self.ids[pos] == targets, self.scores[pos], 0.0)


def sequence_scores(
    candidates: np.ndarray,
    history: list[Scored],
    speeds: tuple[float, ...] = DEFAULT_SPEEDS,
    tolerance: int = 1,
) -> np.ndarray:
    """The sequence score of each candidate entry.

    Args:
        candidates: (K,) entry ids proposed for the current query.
        history: the current query's results first, then the previous queries', newest first
            (an empty :class:`Scored` where a query had none, so that positions stay frames).
        speeds: map entries per query frame tried; the best one counts, per candidate.
        tolerance: each step may land this many entries either side of the line.

    Returns:
        (K,) the mean, over the ``len(history)`` queries, of the best score within the
        tolerance along the best line (the current query's own score when the history holds
        it alone).
    """
    cand = np.asarray(candidates, np.int64)
    if not history or cand.size == 0:
        return np.zeros(cand.shape)
    deltas = np.arange(-tolerance, tolerance + 1)
    best = np.zeros(cand.shape)
    for v in speeds:
        total = history[0].lookup(cand)  # the current query: the candidate itself
        for i, past in enumerate(history[1:], start=1):
            line = cand - int(round(i * v))
            total = total + past.lookup(line[:, None] + deltas[None, :]).max(axis=1)
        best = np.maximum(best, total)
    return best / len(history)


class SequenceHistory:
    """The last ``length`` queries' results of one run of frames, newest first."""

    def __init__(self, length: int) -> None:
        self.length = length
        self._items: deque[Scored] = deque(maxlen=max(length, 1))
        self.run = -1  # the run (first entry) the history belongs to

    def __len__(self) -> int:
        return len(self._items)

    def start(self, run: int) -> None:
        """Forget the history when the frames start a new run (another place)."""
        if run != self.run:
            self._items.clear()
            self.run = run

    def window(self, current: Scored) -> list[Scored]:
        """The current query's results followed by the kept history (at most ``length`` in all)."""
        return [current, *list(self._items)[: self.length - 1]]

    def push(self, current: Scored) -> None:
        self._items.appendleft(current)

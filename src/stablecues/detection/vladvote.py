"""The second retrieval vote (``QueryConfig.vlad``): VLAD similarity fused with the BoW scores.

Each stored entry keeps the VLAD vector of its descriptors (float16, as the entry's extra array
``"vlad"``); while the map is open they are rows of one float32 matrix, so a query's VLAD
similarity to every entry is one matrix-vector product. A map made without the vote gets its
vectors computed from the stored descriptors when it is reopened with it.

Fusion (:meth:`VladVote.fuse`): the candidates are the BoW results and the ``max_results`` most
VLAD-similar entries; a candidate's score is ``(1 - w) * b + w * v`` with ``b`` the BoW score
normalised by the previous frame's (as DLoopDetector) and ``v = (s - m) / (s_prev - m)``: the VLAD
similarity ``s`` above the map's median ``m`` (the level of unrelated places), in units of the
previous frame's similarity above it, floored at 0. Both are then about 1 for the place the
camera is at and about 0 for unrelated ones, so the islands, ``alpha`` and the sequence stage
keep their meaning.
"""

from __future__ import annotations

import logging

import numpy as np

from ..database import Database
from ..errors import ConfigError, ModelError
from ..types import DescriptorKind
from ..vocabulary.vlad import VladCodebook, default_codebook, load_codebook
from .config import DetectorConfig

log = logging.getLogger(__name__)

__all__ = ["VladVote"]


class VladVote:
    """The VLAD vectors of a map's entries and the fusion of their similarity with BoW.

    Args:
        codebook: the VLAD codebook.
        weight: the vote's weight ``w`` in [0, 1].
        max_results: how many of the most VLAD-similar entries join the BoW candidates.
    """

    def __init__(self, codebook: VladCodebook, weight: float, max_results: int) -> None:
        self.codebook = codebook
        self.weight = float(weight)
        self.max_results = int(max_results)
        self._rows = np.zeros((0, codebook.size), np.float32)
        self._usable = np.zeros(0, bool)  # the entry has a vector (not removed, not empty)
        self._n = 0

    @classmethod
    def of(cls, config: DetectorConfig, descriptor_kind: DescriptorKind) -> VladVote | None:
        """The vote a configuration asks for (None when ``query.vlad`` is 0).

        Raises:
            ConfigError: binary descriptors, or a codebook of another dimension than theirs.
            ModelError: a codebook file that cannot be read.
        """
        q = config.query
        if q.vlad <= 0.0:
            return None
        if descriptor_kind.kind != "float":
            raise ConfigError(f"query.vlad needs float (learned) descriptors; {config.features.name!r} "
                              f"gives {descriptor_kind}")
        try:
            book = (default_codebook(config.features.name) if q.vlad_codebook == "default"
                    else load_codebook(q.vlad_codebook))
        except ModelError as exc:
            raise ConfigError(f"query.vlad_codebook: {exc}") from None
        if book.dim != descriptor_kind.size:
            raise ConfigError(f"query.vlad_codebook {book.source}: centres of {book.dim} dimensions, but "
                              f"{config.features.name!r} descriptors have {descriptor_kind.size}")
        return cls(book, q.vlad, q.max_results)

    def __len__(self) -> int:
        return self._n

    def row(self, entry: int) -> np.ndarray | None:
        """An entry's vector (None before the first entry)."""
        return self._rows[entry] if 0 <= entry < self._n else None

    @property
    def latest(self) -> np.ndarray | None:
        """The latest stored entry's vector (the previous frame's, for the next query)."""
        return self.row(self._n - 1)

    def encode(self, descriptors: np.ndarray) -> np.ndarray:
        """A frame's vector, rounded to float16 as the entry keeps it (so a reopened map scores
        exactly as the run that made it)."""
        return self.codebook.encode(descriptors).astype(np.float16).astype(np.float32)

    def append(self, vector: np.ndarray, entry: int | None = None) -> None:
        """The next entry's vector (zeros for a removed entry); with ``entry``, the rows of
        entries added to the map by other means before it are zeros (never VLAD candidates)."""
        while entry is not None and self._n < entry:
            self.append(np.zeros(self.codebook.size, np.float32))
        if self._n == self._rows.shape[0]:
            size = max(16, 2 * self._n)
            grown = np.zeros((size, self.codebook.size), np.float32)
            grown[: self._n] = self._rows[: self._n]
            usable = np.zeros(size, bool)
            usable[: self._n] = self._usable[: self._n]
            self._rows, self._usable = grown, usable
        self._rows[self._n] = vector
        self._usable[self._n] = bool(np.any(vector != 0))
        self._n += 1

    def restore(self, db: Database, present: np.ndarray) -> None:
        """The vectors of a reopened map's entries: stored ones read, missing ones (a map made
        without the vote) computed from the stored descriptors; removed entries are zeros."""
        alive = set(int(e) for e in present.tolist())
        computed = 0
        for e in range(len(db)):
            if e not in alive:
                self.append(np.zeros(self.codebook.size, np.float32))
                continue
            stored = db.extra_arrays(e).get("vlad")
            if stored is not None and stored.shape == (self.codebook.size,) and np.isfinite(stored).all():
                self.append(np.asarray(stored, np.float32))
            else:
                self.append(self.encode(db.entry(e).features.descriptors))
                computed += 1
        if computed:
            log.warning("%s: %d entries had no VLAD vector of this codebook; computed from their stored "
                        "descriptors", db.path if db.path is not None else "map", computed)

    def fuse(
        self, db: Database, ids: np.ndarray, raw: np.ndarray, ns: float, vector: np.ndarray,
        prev: np.ndarray | None, hi: int, scored: tuple[np.ndarray, np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fused candidates of a query (see the module docstring).

        Args:
            db: the map (which entries are removed).
            ids, raw: the BoW results (entry ids, raw scores), best first.
            ns: the BoW normaliser (the score with the previous frame; 1 without it).
            vector: the query's VLAD vector; prev: the previous frame's (None: BoW alone).
            hi: only entries with id < hi.
            scored: every entry sharing a word with the query and its raw score
                (:meth:`Database.scored`, the pass the BoW results came from): the BoW scores
                of the VLAD-only candidates.

        Returns:
            (ids, raw BoW scores, fused scores), best first, at most ``max_results`` long.
        """
        bow_norm = raw / ns
        hi = min(hi, self._n)
        if prev is None or hi <= 0:
            return ids, raw, bow_norm
        sims = self._rows[:hi] @ vector
        alive = db.index.alive()
        usable = self._usable[:hi].copy()
        if alive is not None:
            usable &= alive[:hi]
        if not usable.any():
            return ids, raw, bow_norm
        base = float(np.median(sims[usable]))
        spread = float(prev @ vector) - base
        if not spread > 1e-6:  # the previous frame is no nearer than the map's median: no scale
            return ids, raw, bow_norm
        v = np.maximum((sims - base) / spread, 0.0)
        v[~usable] = 0.0
        k = min(self.max_results, int(usable.sum()))
        top = np.flatnonzero(usable)[np.argpartition(-sims[usable], k - 1)[:k]]
        union = np.union1d(ids.astype(np.int64), top.astype(np.int64))
        every_ids, every_raw = scored
        inside = every_ids < hi
        raw_all = np.zeros(hi)  # 0: no word shared (as Database.scores gives it)
        raw_all[every_ids[inside]] = every_raw[inside]
        raw_u = raw_all[union]
        fused = (1.0 - self.weight) * (raw_u / ns) + self.weight * v[union]
        order = np.lexsort((union, -fused))[: self.max_results]
        return union[order], raw_u[order], fused[order]

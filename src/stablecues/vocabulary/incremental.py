"""A vocabulary that learns its words from the map it serves: no training set needed.

iBoW-LCD's idea (Garcia-Fidalgo and Ortiz, 2018) behind the interface of the trained
vocabulary (:class:`~stablecues.vocabulary.Vocabulary`): ``transform`` gives an image's BoW
vector, the map's inverse index and scoring are the same. The words are the map's own
descriptors:

* **Made and merged by distance.** When an image is added (:meth:`IncrementalVocabulary.learn`),
  each descriptor joins the nearest live word within the merge threshold (Hamming bits for binary
  descriptors, Euclidean distance for float ones); a descriptor that joins none becomes a new word
  (a *leader*: a word is the descriptor that made it, so a word never moves and a stored BoW
  vector keeps its meaning). Two descriptors of one image that join no older word make two words.
* **Found through an index kept as words arrive.** Locality-sensitive hash tables
  (:mod:`._incremental`): a descriptor's candidates are the words sharing a bucket with it. Each
  bucket is one contiguous run of slots with room to spare; a new word goes into its bucket's
  run in every table, O(tables), or into an overflow page where the run is full. The index is
  rebuilt from itself (its slots read in order, those of live words copied into new runs:
  O(slots)) once the words purged and those that overflowed since reach an eighth of those it
  was built with: amortised, a bounded number of copies per word. The layout changes how fast
  a word is found, never which.
* **Purged when they do not come back.** A word seen in a single image and not seen again for
  ``purge_after`` images is dropped (iBoW-LCD keeps the words that recur; a word made by noise
  or a passing object never does). The old image's posting of it stays, inert.
* **Weights kept current.** A word's IDF is ``log(1 + N / n_w)`` (N images learned, n_w of them
  with the word), computed at each transform: queries weigh words by the map as it is now;
  a stored vector keeps the weights of the moment it was added, as in iBoW-LCD.

Word ids run from 0 up to :attr:`IncrementalVocabulary.n_words`, a fixed id space (the map's
index is sized by it). Once every id has been used, new words take the ids of purged ones (in
id order, wrapping around): the one old image that held a purged word keeps its posting, which
now points at the new word (one feature's weight in that image; with ORB on a patrol of real
frames, the 2^22 ids last about 38,000 images).

The words live beside the map (``MAP.words``, :meth:`save`/:meth:`restore`): the live words,
written whole (atomically) on close and every ``save_every`` images, and brought up to date on reopen by
learning again the images added after it from the map's own entries, so that a writer killed
between two saves loses no acknowledged image and the words are the same as an uninterrupted
run's (learning is deterministic).
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import struct
import threading
import zlib
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import NamedTuple

import numpy as np

from .._arrays import distinct
from ..errors import ConfigError, InputError, VocabularyError
from ..types import BowVector, DescriptorKind, FeatureVector
from ..vocabulary.scoring import Scoring, Weighting, normalise
from .descriptors import as_words, check_descriptors

log = logging.getLogger(__name__)

__all__ = ["INCREMENTAL", "IncrementalInfo", "IncrementalVocabulary", "words_path"]

#: the name that selects it (``--vocab incremental``, ``vocabulary: incremental``)
INCREMENTAL = "incremental"

_MAGIC = b"SCVW"
_VERSION = 2  # 2: live words only in the file; ids of purged words reused once all are used
_HEADER = struct.Struct("<4sHBBIHHdQQQQQQQQ16sI")  # .. body CRC; the header's own CRC follows
_HEADER_SIZE = 128
_NONE = -1
#: the index is rebuilt once the words purged and those that overflowed their runs since are this
#: share (1/FREEZE_SHARE) of those it was built with, or FREEZE_MIN: each word is copied a bounded
#: number of times. Counting the purged words at a quarter halved the rebuilds but left their
#: slots in the runs: at 10^5 entries of the patrol queries took 46 ms against 37 and the median
#: add 1.69 ms against 1.41 (``incremental.json``, ``scale.patrol_ablation_purged_quarter``)
FREEZE_SHARE = 8
FREEZE_MIN = 4096


@dataclass(frozen=True)
class IncrementalInfo:
    """What an incremental vocabulary holds now."""

    kind: str
    images: int
    words_made: int
    words_live: int
    id_space: int
    threshold: float
    tables: int
    bits: int
    purge_after: int
    fingerprint: str


# Per kind: the merge threshold, the hash tables and their bits. Binary (ORB): the best mean
# R@100P of 9 settings over train_drives, the corridor and two Gardens Point pairings with
# ``fast`` (bench/bench_incremental.py, "grid"; thresholds 56/64/72 bits, 4x16, 8x16 and 16x12
# tables). Float (XFeat, unit vectors): the best of 0.6/0.7/0.8 with 16 tables of 12 bits over
# train_drives, the corridor and both Gardens Point night pairings with ``learned`` (the larger
# threshold won on every set: a coarse word survives a change of light).
DEFAULTS: dict[str, dict[str, float]] = {
    "binary": {"threshold": 64, "tables": 16, "bits": 12},
    "float": {"threshold": 0.8, "tables": 16, "bits": 12},
}


def words_path(map_path: str | Path) -> Path:
    """Where the words of the map at ``map_path`` live: ``MAP.words`` beside it."""
    p = Path(map_path)
    return p.with_name(p.name + ".words")


class IncrementalVocabulary:
    """Words made from the map's own descriptors as images are added (see the module).

    Args:
        kind: the descriptors' kind (``DescriptorKind("binary", 32)`` for ORB,
            ``DescriptorKind("float", 64)`` for XFeat).
        threshold: merge distance: Hamming bits (binary) or Euclidean distance (float); a
            descriptor joins the nearest word at most this far.
        tables: hash tables of the word index (more find more true neighbours, cost more).
        bits: bits of each table's key (more make smaller buckets and fewer candidates).
        id_space: word ids available (the map's index is sized by it).
        purge_after: images after which a word seen only once is dropped (0: never).
        save_every: images between two saves of the words file of a map.
        seed: of the hash functions (part of the identity: a map reopens with the same).

    Raises:
        ConfigError: a setting out of range.
    """

    k = 0
    levels = 0
    levels_up = 0
    weighting = Weighting.TF_IDF
    scoring = Scoring.L1
    engine = "compiled"

    def __init__(
        self,
        kind: DescriptorKind,
        threshold: float | None = None,
        tables: int | None = None,
        bits: int | None = None,
        id_space: int = 1 << 22,
        purge_after: int = 100,
        save_every: int = 1000,
        seed: int = 0,
    ) -> None:
        self.kind = kind
        d = DEFAULTS[kind.kind]
        self.threshold = float(d["threshold"] if threshold is None else threshold)
        self.tables = int(d["tables"] if tables is None else tables)
        self.bits = int(d["bits"] if bits is None else bits)
        self.id_space, self.purge_after = int(id_space), int(purge_after)
        self.save_every, self.seed = int(save_every), int(seed)
        width = 8 * kind.size if kind.kind == "binary" else None
        if not (math.isfinite(self.threshold) and self.threshold >= 0):
            raise ConfigError(f"incremental vocabulary: threshold {threshold!r} must be a finite number >= 0")
        if not 1 <= self.tables <= 64 or not 1 <= self.bits <= 24 or (width and self.bits > width):
            raise ConfigError(f"incremental vocabulary: {self.tables} tables of {self.bits} bits: "
                              "expected 1-64 tables of 1-24 bits")
        if self.tables << self.bits > 1 << 24:
            raise ConfigError(f"incremental vocabulary: {self.tables} tables of {self.bits} bits make "
                              f"{self.tables << self.bits} buckets; at most 2^24")
        space_ok = 1 <= self.id_space <= (1 << 31) // self.tables - 1  # page numbers are int32
        if not space_ok or self.purge_after < 0 or self.save_every < 1:
            raise ConfigError("incremental vocabulary: id_space must be 1..2^31 / tables - 1, "
                              "purge_after >= 0, save_every >= 1")
        if not 0 <= self.seed < 1 << 63:
            raise ConfigError(f"incremental vocabulary: seed {seed!r} must be in 0..2^63-1")
        if kind.size > 4096:
            raise ConfigError(f"incremental vocabulary: descriptors of {kind.size} bytes or dimensions; "
                              "at most 4096")
        rng = np.random.default_rng(self.seed)
        self._float = kind.kind == "float"
        if self._float:
            self._planes = rng.standard_normal((kind.size, self.tables * self.bits))
        else:
            self._positions = np.stack([rng.choice(width or 8, self.bits, replace=False)
                                        for _ in range(self.tables)]).astype(np.int64)
        self._pow2 = (1 << np.arange(self.bits, dtype=np.int64))
        self._lock = threading.RLock()
        self._owner: object | None = None
        self._reset()

    def _reset(self) -> None:
        self._made = 0  # word ids used so far (the high-water mark; ids below it are reused once it
        # reaches the id space)
        self._made_total = 0  # words ever made
        self._live = 0  # live words
        self._cursor = 0  # where the search for the next free id starts, once all were used
        self._images = 0  # images learned
        # (image, ids of the words it made): the words that may be purged, oldest first
        self._fifo: deque[tuple[int, np.ndarray]] = deque()
        self._alloc = 0
        width = self.kind.size if self._float else as_words(np.zeros((1, self.kind.size), np.uint8)).shape[1]
        self._dtype = np.float32 if self._float else np.uint64
        self._words = np.zeros((0, width), self._dtype)
        self._df = np.zeros(0, np.int32)
        self._last = np.zeros(0, np.int32)
        self._alive = np.zeros(0, np.uint8)
        # float descriptors: each word's keys as made when it was learned, which a freeze and a
        # reopen reuse, never recomputing a projection in another batch shape (BLAS may round it
        # otherwise); binary keys are bits of the word itself, taken again when needed
        self._wkeys = np.zeros((0, self.tables if self._float else 0), np.int32)
        self._id_space_said = False
        self._last_learned: np.ndarray | None = None
        mod = _kernel_module()
        self._pool = mod.pool(self.tables, self.bits, 1024, 4096, width, self._dtype)
        self._runs = mod.runs(self.tables, self.bits, np.zeros(self.tables << self.bits), width, self._dtype)
        # the runs before the last rebuild: the next rebuild writes into them where it fits
        self._spare: dict[str, np.ndarray] | None = None
        self._indexed = 0  # live words when the runs were made
        self._overflow = 0  # slots in overflow pages since
        self._dead_linked = 0  # purged words still in the index
        self._unlinked: list[np.ndarray] = []  # ids purged since the index was rebuilt (still in it)
        self._since_save = 0
        # float keys: signs of projections of the descriptors less this centre, the mean of the
        # first image learned (learned descriptors sit in a cone: planes through the origin put
        # most of them in a few buckets, 8x the candidates on Gardens Point XFeat)
        self._center: np.ndarray | None = None
        self._version = getattr(self, "_version", 0) + 1  # what was assigned before is stale
        self._cache: tuple[np.ndarray, int, np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ identity
    @property
    def n_words(self) -> int:
        """Size of the word id space (what the map's index is sized by)."""
        return self.id_space

    @property
    def descriptor_kind(self) -> DescriptorKind:
        return self.kind

    @property
    def is_float(self) -> bool:
        return self._float

    @property
    def fingerprint(self) -> str:
        """SHA-256 of what decides the words (kind, threshold, index, id space, purge, seed):
        a map records it and reopens only with the same."""
        text = (f"incremental {_VERSION} {self.kind.kind} {self.kind.size} {self.threshold!r} {self.tables} "
                f"{self.bits} {self.id_space} {self.purge_after} {self.seed}")
        return hashlib.sha256(text.encode()).hexdigest()

    @property
    def images(self) -> int:
        """Images learned so far."""
        return self._images

    @property
    def words_made(self) -> int:
        """Words made so far (purged ones included)."""
        return self._made_total

    @property
    def words_live(self) -> int:
        return self._live

    @property
    def nbytes(self) -> int:
        """Memory held: the words' rows, counts and keys, and the index (runs, the spare runs
        the next rebuild writes into, and pages)."""
        held = _kernel_module().held
        runs = [*self._runs.values(), *(self._spare or {}).values()]
        arrays = [self._words, self._df, self._last, self._alive, self._wkeys, *self._pool.values()]
        return sum(int(a.nbytes) for a in arrays) + sum(int(a.nbytes) for a in {id(held(r)): held(r)
                                                                                 for r in runs}.values())

    def info(self) -> IncrementalInfo:
        return IncrementalInfo(str(self.kind), self._images, self._made_total, self._live, self.id_space,
                               self.threshold, self.tables, self.bits, self.purge_after, self.fingerprint)

    def settings(self) -> str:
        """The settings that decide the words, in words (for messages)."""
        return (f"{self.kind}, threshold {self.threshold:g}, {self.tables}x{self.bits} bits, purge "
                f"{self.purge_after}, {self.id_space} ids, seed {self.seed}")

    def __repr__(self) -> str:
        return (f"IncrementalVocabulary({self.kind}, threshold={self.threshold:g}, images={self._images}, "
                f"words={self._live} live of {self._made_total} made)")

    def warm_up(self) -> str:
        """Load (or compile, the first time on a machine) the kernels now."""
        _kernels()
        return self.engine

    def bind(self, owner: object) -> None:
        """Tie the vocabulary to the one map it learns from.

        Raises:
            ConfigError: it already serves another map.
        """
        with self._lock:
            if self._owner is not None and self._owner is not owner:
                raise ConfigError("an incremental vocabulary learns from one map: make one per map")
            self._owner = owner

    def release(self, owner: object) -> None:
        with self._lock:
            if self._owner is owner:
                self._owner = None

    # ------------------------------------------------------------------ words
    def _keys(self, d: np.ndarray) -> np.ndarray:
        """(N, tables) int64 bucket of each descriptor in each table."""
        if self._float:
            x = np.asarray(d, np.float64)
            signs = ((x - self._center if self._center is not None else x) @ self._planes) > 0
            return signs.reshape(d.shape[0], self.tables, self.bits).astype(np.int64) @ self._pow2
        out = np.empty((d.shape[0], self.tables), np.int64)
        _kernels().keys_binary(as_words(d), self._positions, out)
        return out

    def _room(self, rows: int, words: int) -> None:
        """Room for ``words`` new words, ``rows`` of them with new ids: their rows, and the page
        pool's worst case (each of them opening a page of the largest size in every table)."""
        need = self._made + rows
        if need > self._alloc:
            alloc = min(max(need, 2 * self._alloc, 1024), self.id_space)
            self._words = _grow(self._words, (alloc, self._words.shape[1]))
            self._df = _grow(self._df, (alloc,))
            self._last = _grow(self._last, (alloc,))
            self._alive = _grow(self._alive, (alloc,))
            self._wkeys = _grow(self._wkeys, (alloc, self._wkeys.shape[1]))
            self._alloc = alloc
        pl = self._pool
        pages, slots = (int(v) for v in pl["state"])
        mod = _kernel_module()
        want_pages, want_slots = pages + self.tables * words, slots + self.tables * words * mod.MAX_PAGE
        if want_pages > pl["pg_next"].shape[0]:
            size = max(want_pages, 2 * pl["pg_next"].shape[0])
            for name, fill in (("pg_next", mod.NONE), ("pg_start", 0), ("pg_cap", 0), ("pg_fill", 0)):
                pl[name] = _grow(pl[name], (size,), fill)
        if want_slots > pl["slot_ids"].shape[0]:
            size = max(want_slots, 2 * pl["slot_ids"].shape[0])
            pl["slot_ids"] = _grow(pl["slot_ids"], (size,))
            pl["slot_desc"] = _grow(pl["slot_desc"], (size, pl["slot_desc"].shape[1]))

    def _new_ids(self, need: int) -> np.ndarray:
        """Ids for ``need`` new words: unused ones first, then (all used) the ids of purged
        words, in id order from where the last search stopped, wrapping around (fewer when
        fewer are free)."""
        fresh = min(need, self.id_space - self._made)
        parts = [np.arange(self._made, self._made + fresh, dtype=np.int32)]
        rest, n = need - fresh, self.id_space
        if rest and self._made >= n:
            c, scanned = self._cursor, 0
            while rest and scanned < n:
                hi = min(c + max(4 * rest, 4096), n, c + n - scanned)  # each id looked at once
                take = (np.flatnonzero(self._alive[c:hi] == 0)[:rest] + c).astype(np.int32)
                parts.append(take)
                rest -= int(take.size)
                scanned += hi - c
                c = int(take[-1]) + 1 if rest == 0 else hi
                if c >= n:
                    c = 0
            self._cursor = c
        return np.concatenate(parts)

    def _assign(self, d: np.ndarray) -> np.ndarray:
        """Each descriptor's word among the live ones (-1: none within the threshold); the last
        answer again when nothing was learned since and ``d`` holds the same descriptors (a
        binary image a detector queried with is the image it then adds; float descriptors are
        learned in their int8-stored form, so their add searches again)."""
        return self._assigned(d)[0]

    def _assigned(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_assign`'s words and the descriptors' keys."""
        cached = self._cache
        if cached is not None and cached[1] == self._version and np.array_equal(cached[0], d):
            return cached[2], cached[3]
        n = d.shape[0]
        out = np.full(n, _NONE, np.int32)
        keys = self._keys(d)
        if n and self._made:
            mod = _kernel_module()
            pl = [self._runs[a] for a in mod.RUN_ARGS] + [self._pool[a] for a in mod.POOL_ARGS]
            if self._float:
                q = np.ascontiguousarray(d, np.float32)
                _kernels().assign_float(keys, q, *pl, self._alive, self._words, self.threshold ** 2, out)
            else:  # within the threshold: closer than one bit more
                bound = int(self.threshold) + 1
                _kernels().assign_binary(keys, as_words(d), *pl, self._alive, self._words, bound, out)
        out.flags.writeable = False
        self._cache = (np.array(d), self._version, out, keys)  # a copy: the caller may reuse its array
        return out, keys

    def _grow_words(self, d: np.ndarray) -> np.ndarray:
        """Each descriptor's word, a new one for each that joined none (see :meth:`learn`)."""
        words, keys = self._assigned(d)
        todo = np.flatnonzero(words < 0)
        out = words.copy()
        if todo.size == 0:
            return out
        ids = self._new_ids(int(todo.size))
        fresh = int((ids >= self._made).sum())
        self._room(fresh, int(ids.size))
        mod = _kernel_module()
        pl = [self._runs[a] for a in mod.RUN_ARGS] + [self._pool[a] for a in mod.POOL_ARGS]
        q = np.ascontiguousarray(d, np.float32) if self._float else as_words(d)
        reused = ids.size - fresh
        self._overflow += _kernels().grow(todo, ids, keys, q, *pl, self._words, self._alive, out)
        if self._float:
            self._wkeys[ids] = keys[todo[: ids.size]]
        self._df[ids] = 0
        self._made += fresh
        self._made_total += int(ids.size)
        self._live += int(ids.size)
        if self.purge_after:  # the words that may be purged (none without a purge)
            self._fifo.append((self._images, ids))
        if (reused or ids.size < todo.size) and not self._id_space_said:
            self._id_space_said = True
            log.warning("incremental vocabulary: all %d word ids are used; the ids of purged words are given "
                        "to new words from now on (the one old image that held each keeps a posting of it)%s",
                        self.id_space, "" if ids.size == todo.size else
                        "; with none free, descriptors that join no word get none")
        return out

    def _vector(self, words: np.ndarray, fw: np.ndarray | None, images: int) -> BowVector:
        ok = words >= 0
        if fw is not None:
            ok &= fw > 0
        if not ok.any():
            return BowVector.empty()
        uniq, inverse = np.unique(words[ok], return_inverse=True)
        tf = np.bincount(inverse, weights=None if fw is None else fw[ok], minlength=uniq.size)
        idf = np.log1p(images / np.maximum(self._df[uniq], 1))
        return BowVector(uniq.astype(np.int32), normalise(tf * idf, self.scoring))

    def _check(self, descriptors: np.ndarray, weights: np.ndarray | None) -> np.ndarray | None:
        check_descriptors(descriptors, kind=self.kind)
        if weights is None:
            return None
        w = np.asarray(weights, np.float64)
        if w.shape != (descriptors.shape[0],) or not np.isfinite(w).all() or (w < 0).any():
            raise InputError(f"weights: expected ({descriptors.shape[0]},) finite values >= 0, "
                             f"got shape {w.shape}")
        return w

    def transform(self, descriptors: np.ndarray, levels_up: int | None = None,
                  weights: np.ndarray | None = None) -> tuple[BowVector, FeatureVector]:
        """BoW vector of an image against the words as they are (nothing learned): each
        descriptor's word, TF-IDF with the current IDF, L1-normalised. The direct index puts
        every feature in one group (node 0): verification matches all features of a pair.

        Raises:
            InputError: descriptors of another kind, or bad weights.
        """
        fw = self._check(descriptors, weights)
        with self._lock:
            words = self._assign(descriptors)
            bow = self._vector(words, fw, max(self._images, 1))
        return bow, self._direct(words)

    def learn(self, descriptors: np.ndarray, weights: np.ndarray | None = None
              ) -> tuple[BowVector, FeatureVector]:
        """Add one image's descriptors to the words (a new word for each that matches none) and
        give its BoW vector with the new words in it: what the map stores for the image.

        Raises:
            InputError: descriptors of another kind, or bad weights.
        """
        fw = self._check(descriptors, weights)
        with self._lock:
            words = self._learn(descriptors)
            bow = self._vector(words, fw, self._images)
        return bow, self._direct(words)

    @staticmethod
    def _direct(words: np.ndarray) -> FeatureVector:
        """The direct index: every feature under one node, so verification compares all the
        features of a pair (features grouped by their word kept 10 % fewer loops of
        train_drives at 100 % precision: a revisit's feature and its twin share a word less
        often than a trained tree's coarse node; ``bench_incremental.py``)."""
        return FeatureVector(np.zeros(words.shape[0], np.int32), 0)

    def learned_last(self, descriptors: np.ndarray) -> bool:
        """Whether ``descriptors`` are what the last :meth:`learn` took (a map checks that the
        image it stores is the image learned, in the form it stores)."""
        last = self._last_learned
        return last is not None and np.array_equal(last, descriptors)

    def _learn(self, descriptors: np.ndarray) -> np.ndarray:
        self._last_learned = np.array(descriptors)
        if self._float and self._center is None and descriptors.shape[0]:
            self._center = np.asarray(descriptors, np.float64).mean(axis=0)
            self._version += 1  # keys made before are stale
        words = self._grow_words(descriptors)
        self._version += 1
        seen = distinct(words[words >= 0])
        self._df[seen] += 1
        self._last[seen] = self._images
        self._images += 1
        self._since_save += 1
        if self.purge_after and self._images % 16 == 0:
            self._purge()
        if self._overflow // self.tables + self._dead_linked > max(self._indexed // FREEZE_SHARE, FREEZE_MIN):
            self._compact()
        return words

    def _purge(self) -> None:
        """Drop the words seen in one image only and not since ``purge_after`` images (they stay
        in the index, skipped, until the next freeze; their rows are cleared)."""
        cutoff = self._images - self.purge_after
        parts = []
        while self._fifo and self._fifo[0][0] < cutoff:
            image, ids = self._fifo.popleft()
            # still seen in that image only (a later image would have raised df; an id given
            # again since belongs to a younger word, with a later `last`)
            parts.append(ids[(self._alive[ids] == 1) & (self._df[ids] == 1) & (self._last[ids] == image)])
        gone = np.concatenate(parts) if parts else np.zeros(0, np.int32)
        if not gone.size:
            return
        self._alive[gone] = 0
        for arr in (self._words, self._df, self._last, self._wkeys):
            if arr.shape[-1]:
                arr[gone] = 0
        self._live -= int(gone.size)
        self._version += 1
        self._dead_linked += int(gone.size)
        self._unlinked.append(gone)

    def _compact(self) -> None:
        """Rebuild the word index from itself: each bucket one run with room to spare, no
        overflow page, no purged word (the words found do not change: only how fast). Reads
        the runs and pages in order and copies the slots of live words; no key is computed
        again (:meth:`_freeze` computes every word's keys and scatters it into every table).
        The new runs are written into those of the rebuild before (``_spare``) where they fit,
        whose pages are mapped already: on the patrol of ``bench_incremental.py`` at 10^5
        entries a rebuild took 31-57 ms so, 135-248 ms writing fresh memory (13-24 ms at 10^3
        and 10^4). Exploring at 10^4 entries (15.8M slots) a rebuild took 160 ms into mapped
        runs, 2.0 s into fresh ones: the index grows there, and each rebuild needs more."""
        mod = _kernel_module()
        # bit c of keep: word c is live, its slots its own; of check: word c is live and its id
        # was a word's purged since the last rebuild (whose slots are still in: a slot is the
        # live word's if it holds its descriptor)
        check = np.zeros(self._alive.shape[0], bool)
        if self._unlinked:
            gone = np.concatenate(self._unlinked)
            check[gone[self._alive[gone] != 0]] = True
        keep = np.packbits((self._alive != 0) & ~check, bitorder="little")
        check = np.packbits(check, bitorder="little")
        old = [self._runs[a] for a in mod.RUN_ARGS] + [self._pool[a] for a in mod.POOL_ARGS]
        counts = np.zeros(self.tables << self.bits, np.int64)
        k = _kernels()
        k.compact(*old, keep, check, self._words, counts, counts, old[2], old[3], False)
        width = self._words.shape[1]
        runs = mod.runs(self.tables, self.bits, counts, width, self._dtype, self._spare)
        k.compact(*old, keep, check, self._words, *(runs[a] for a in mod.RUN_ARGS), True)
        # the runs replaced are kept for the next rebuild if they would hold it, its slots
        # foreseen as the new runs' plus what they grew by: an index that keeps growing (a robot
        # exploring) writes fresh memory each time and keeps no spare
        was, now = self._runs["r_ids"].shape[0], runs["r_ids"].shape[0]
        fits = mod.held(self._runs["r_ids"]).shape[0] >= now + max(now - was, 0)
        self._runs, self._spare = runs, self._runs if fits else None
        self._pool = mod.pool(self.tables, self.bits, 1024, 4096, width, self._dtype)
        self._indexed, self._overflow, self._dead_linked = self._live, 0, 0
        self._unlinked = []

    def _freeze(self) -> None:
        """Build the word index from the live words (a restore): each bucket one run with room
        to spare, no overflow page."""
        mod = _kernel_module()
        ids = np.flatnonzero(self._alive[: self._made]).astype(np.int32)
        keys = self._word_keys(ids)
        flat = keys.astype(np.int64) + (np.arange(self.tables, dtype=np.int64) << self.bits)
        counts = np.bincount(flat.ravel(), minlength=self.tables << self.bits)
        width = self._words.shape[1]
        self._runs = mod.runs(self.tables, self.bits, counts, width, self._dtype)
        rows = np.ascontiguousarray(self._words[ids])
        _kernels().freeze(ids, keys, rows, *(self._runs[a] for a in mod.RUN_ARGS))
        self._pool = mod.pool(self.tables, self.bits, 1024, 4096, width, self._dtype)
        self._indexed, self._overflow, self._dead_linked = int(ids.size), 0, 0
        self._unlinked = []

    def _word_keys(self, ids: np.ndarray) -> np.ndarray:
        """(len(ids), tables) int32 the keys of words ``ids``: kept (float), or the words' bits."""
        if self._float:
            return np.ascontiguousarray(self._wkeys[ids])
        out = np.empty((ids.size, self.tables), np.int64)
        _kernels().keys_binary(np.ascontiguousarray(self._words[ids]), self._positions, out)
        return out.astype(np.int32)

    def _descriptors_of(self, ids: np.ndarray) -> np.ndarray:
        """The descriptors of words ``ids`` (in the form they were given)."""
        if self._float:
            return self._words[ids]
        return np.ascontiguousarray(self._words[ids]).view(np.uint8)[:, : self.kind.size]

    # ------------------------------------------------------------------ files
    def due(self) -> bool:
        """Whether ``save_every`` images were learned since the last save."""
        return self._since_save >= self.save_every

    @property
    def unsaved(self) -> bool:
        """Whether anything was learned since the last save or restore."""
        return self._since_save > 0

    def save(self, path: str | Path, map_id: bytes, images: int | None = None) -> bool:
        """Write the words to ``path`` atomically (a temporary file, fsynced, renamed over it).

        Args:
            map_id: the 16-byte id of the map they belong to (recorded and checked on restore).
            images: write only if exactly this many images are learned (the map's entries, checked
                under the vocabulary's lock: a frame learned by another thread meanwhile waits for
                the next save).

        Returns:
            whether the file was written.
        """
        p = Path(path)
        with self._lock:
            if images is not None and images != self._images:
                return False
            n = self._made
            ids = np.flatnonzero(self._alive[:n])  # the live words only: purged ones left no trace
            body = [ids.astype("<i4").tobytes(), np.ascontiguousarray(self._words[ids]).tobytes(),
                    self._df[ids].astype("<i4").tobytes(), self._last[ids].astype("<i4").tobytes(),
                    self._wkeys[ids].astype("<i4").tobytes()]  # float only: binary keys are bits of the words
            if self._float:  # the keys' centre (zeros until the first image)
                centre = self._center if self._center is not None else np.zeros(self.kind.size)
                body.append(centre.astype("<f8").tobytes())
            crc = 0
            for part in body:
                crc = zlib.crc32(part, crc)
            centred = int(self._center is not None)
            fields = _HEADER.pack(_MAGIC, _VERSION, int(self._float), centred, self.kind.size, self.tables,
                                  self.bits, self.threshold, self.id_space, self.purge_after, self.seed,
                                  n, self._images, int(ids.size), self._made_total, self._cursor, map_id,
                                  crc)
            header = fields + struct.pack("<I", zlib.crc32(fields))
            header += bytes(_HEADER_SIZE - len(header))
            tmp = p.with_name(p.name + ".tmp")
            with open(tmp, "wb") as f:
                f.write(header)
                for part in body:
                    f.write(part)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, p)
            _fsync_dir(p.parent)
            self._since_save = 0
            return True

    @classmethod
    def of_words_file(cls, path: str | Path) -> IncrementalVocabulary:
        """A new vocabulary with the settings a words file records (nothing learned: a map
        opened with it reads the words back).

        Raises:
            VocabularyError: not a words file, or settings out of range.
        """
        h = _read_header(Path(path))
        if not (1 <= h.tables <= 64 and 1 <= h.bits <= 24 and h.tables << h.bits <= 1 << 24):
            raise VocabularyError(f"{path}: {h.tables} tables of {h.bits} bits (corrupt file)")
        try:
            kind = DescriptorKind("float" if h.is_float else "binary", h.dim)
            return cls(kind, threshold=h.threshold, tables=h.tables, bits=h.bits, id_space=h.id_space,
                       purge_after=h.purge_after, seed=h.seed)
        except (ConfigError, InputError) as exc:
            raise VocabularyError(f"{path}: {exc}") from None

    @staticmethod
    def saved_images(path: str | Path) -> int:
        """The images a words file holds the words of (its header only).

        Raises:
            VocabularyError: not a readable words file.
        """
        return int(_read_header(Path(path)).images)

    def restore(self, path: str | Path, map_id: bytes) -> None:
        """Read the words saved at ``path`` for the map ``map_id`` (replacing what is here).

        Raises:
            VocabularyError: one line naming the file: not a words file, truncated, corrupt,
                made with other settings or for another map.
        """
        p = Path(path)
        h = _read_header(p)
        mine = (int(self._float), self.kind.size, self.tables, self.bits, self.threshold, self.id_space,
                self.purge_after, self.seed)
        if (h.is_float, h.dim, h.tables, h.bits, h.threshold, h.id_space, h.purge_after, h.seed) != mine:
            theirs = (f"{'float' if h.is_float else 'binary'} {h.dim}, threshold {h.threshold:g}, "
                      f"{h.tables}x{h.bits} bits, purge {h.purge_after}, {h.id_space} ids, seed {h.seed}")
            raise VocabularyError(f"{p}: made by an incremental vocabulary with other settings ({theirs}); "
                                  f"this one has {self.settings()}")
        if h.owner != map_id:
            raise VocabularyError(f"{p}: the words of another map (id {h.owner.hex()[:12]}..., this map is "
                                  f"{map_id.hex()[:12]}...)")
        n, live, dim, tables = h.n, h.live, h.dim, self.tables
        width = self._words.shape[1]
        item = 4 if self._float else 8
        if not (live <= n <= h.id_space and n <= h.made_total and h.cursor <= n):
            raise VocabularyError(f"{p}: {live} live words, ids used {n}, made {h.made_total}, next free id "
                                  f"searched from {h.cursor}, in an id space of {h.id_space} (corrupt file)")
        if h.has_centre not in (0, 1) or (h.has_centre and not h.is_float):
            raise VocabularyError(f"{p}: a centre flag of {h.has_centre} (corrupt file)")
        kt = tables if h.is_float else 0  # keys kept per word
        row = 4 + width * item + 8 + 4 * kt
        expected = _HEADER_SIZE + live * row + (8 * dim if h.is_float else 0)
        raw = _body(p, expected)
        if zlib.crc32(raw) != h.crc:
            raise VocabularyError(f"{p}: the words' checksum does not match (corrupt file)")
        ids = np.frombuffer(raw, "<i4", live, 0).astype(np.int64)
        o = 4 * live
        words = np.frombuffer(raw, self._dtype, live * width, o).reshape(live, width)
        o += live * width * item
        df = np.frombuffer(raw, "<i4", live, o)
        last = np.frombuffer(raw, "<i4", live, o + 4 * live)
        wkeys = np.frombuffer(raw, "<i4", live * kt, o + 8 * live).reshape(live, kt)
        o += 8 * live + 4 * live * kt
        if live and (int(ids[0]) < 0 or int(ids[-1]) >= n or (np.diff(ids) <= 0).any()):
            raise VocabularyError(f"{p}: word ids not ascending within 0..{n - 1} (corrupt file)")
        if live and (int(df.min()) < 1 or int(last.min()) < 0 or int(last.max()) >= h.images):
            raise VocabularyError(f"{p}: word counts below 1 or last images outside 0..{h.images - 1} "
                                  "(corrupt file)")
        if wkeys.size and (int(wkeys.min()) < 0 or int(wkeys.max()) >= 1 << self.bits):
            raise VocabularyError(f"{p}: word keys outside 0..2^{self.bits}-1 (corrupt file)")
        centre = np.frombuffer(raw, "<f8", dim, o).astype(np.float64) if h.has_centre else None
        if centre is not None and not np.isfinite(centre).all():
            raise VocabularyError(f"{p}: the keys' centre is not finite (corrupt file)")
        with self._lock:
            self._reset()
            self._room(n, 0)  # the index is made by the freeze below
            self._words[ids] = words
            self._df[ids] = df
            self._last[ids] = last
            self._alive[ids] = 1
            self._wkeys[ids] = wkeys
            self._center = centre
            self._made, self._images, self._live = n, int(h.images), live
            self._made_total, self._cursor = int(h.made_total), int(h.cursor)
            once = np.flatnonzero(df == 1)  # the words that may still be purged, by the image that made them
            order = once[np.argsort(last[once], kind="stable")]
            if order.size and self.purge_after:
                cuts = np.flatnonzero(np.diff(last[order])) + 1
                for part in np.split(order, cuts):
                    self._fifo.append((int(last[part[0]]), ids[part].astype(np.int32)))
            self._freeze()

    def forget(self) -> None:
        """Drop every word and image learned (to learn a map again from its first entry)."""
        with self._lock:
            self._reset()

    def replay(self, descriptors: np.ndarray) -> None:
        """Learn one stored image again (bringing restored words up to date)."""
        with self._lock:
            self._learn(descriptors)
            self._since_save = self.save_every  # what was replayed is saved at the next chance


class _Header(NamedTuple):
    version: int
    is_float: int
    has_centre: int
    dim: int
    tables: int
    bits: int
    threshold: float
    id_space: int
    purge_after: int
    seed: int
    n: int
    images: int
    live: int
    made_total: int
    cursor: int
    owner: bytes
    crc: int


def _read_header(p: Path) -> _Header:
    """A words file's header, its magic, checksum and version checked.

    Raises:
        VocabularyError: one line naming the file.
    """
    try:
        with open(p, "rb") as f:
            head = f.read(_HEADER_SIZE)
    except OSError as exc:
        raise VocabularyError(f"{p}: cannot read the words file ({exc.strerror or exc})") from None
    if len(head) < _HEADER_SIZE or head[:4] != _MAGIC:
        raise VocabularyError(f"{p}: not a stablecues words file (expected {_MAGIC!r} and a "
                              f"{_HEADER_SIZE}-byte header)")
    fields = head[: _HEADER.size]
    if struct.unpack_from("<I", head, _HEADER.size)[0] != zlib.crc32(fields):
        raise VocabularyError(f"{p}: the header's checksum does not match (corrupt file)")
    h = _Header(*_HEADER.unpack(fields)[1:])
    if h.version != _VERSION:
        raise VocabularyError(f"{p}: words file version {h.version}, expected {_VERSION}")
    if h.is_float not in (0, 1) or h.has_centre not in (0, 1) or not 1 <= h.dim <= 4096:
        raise VocabularyError(f"{p}: a header of kind {h.is_float}, centre flag {h.has_centre} and {h.dim} "
                              "bytes or dimensions (corrupt file)")
    return h


def _body(p: Path, expected: int) -> bytes:
    """A words file's bytes after the header, once its size is the ``expected`` one."""
    try:
        size = p.stat().st_size
        if size != expected:
            raise VocabularyError(f"{p}: {size} bytes, expected {expected} for the words its header "
                                  "counts (truncated or corrupt)")
        with open(p, "rb") as f:
            f.seek(_HEADER_SIZE)
            return f.read()
    except OSError as exc:
        raise VocabularyError(f"{p}: cannot read the words file ({exc.strerror or exc})") from None


def _grow(a: np.ndarray, shape: tuple[int, ...], fill: int = 0) -> np.ndarray:
    out = np.full(shape, fill, a.dtype) if fill else np.zeros(shape, a.dtype)
    out[: a.shape[0]] = a
    return out


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _kernels() -> SimpleNamespace:
    from . import _incremental

    return _incremental.kernels()


def _kernel_module() -> ModuleType:
    from . import _incremental

    return _incremental

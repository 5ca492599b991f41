"""The topological database: BoW vectors (inverse index), direct index, keypoints,
descriptors, 3D points and metadata per entry, persisted in an embedded SQLite file.

Durability: every :meth:`Database.add` is one SQLite transaction in WAL mode, so a process
killed in the middle of an add loses at most that entry and never earlier ones; reopening
rebuilds the in-memory inverse index from the stored BoW vectors and gives identical query
results. One writer and any number of readers may use a file at once (readers call
:meth:`Database.refresh` to see entries added since they opened it). The file records the
vocabulary's fingerprint and refuses to be used with another vocabulary.
"""

from __future__ import annotations

import json
import logging
import math
import sqlite3
import time
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import DatabaseError, InputError, check_array
from ..types import BowVector, Entry, Features, FeatureVector, QueryResult
from ..vocabulary import Vocabulary, higher_is_better
from .inverted import InvertedIndex
from .packing import pack_arrays, unpack_arrays

log = logging.getLogger(__name__)

FORMAT_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS entries (
    id INTEGER PRIMARY KEY,
    timestamp REAL,
    n_features INTEGER NOT NULL,
    bow BLOB NOT NULL,
    payload BLOB NOT NULL,
    meta TEXT NOT NULL
);
"""


@dataclass(frozen=True)
class DatabaseConfig:
    """Database settings.

    Attributes:
        durability: "normal" survives a killed process (SQLite WAL, synchronous=NORMAL);
            "full" also survives power loss (synchronous=FULL), at a cost per add.
        store_descriptors: keep keypoints and descriptors (needed by geometric verification).
        cache_entries: how many full entries to keep in memory for :meth:`Database.entry`.
        busy_timeout_s: how long to wait for a lock held by another process.
    """

    durability: Literal["normal", "full"] = "normal"
    store_descriptors: bool = True
    cache_entries: int = 256
    busy_timeout_s: float = 10.0


class Database:
    """DBoW2-style image database with inverse and direct indexes.

    Args:
        vocabulary: the vocabulary every stored BoW vector comes from.
        path: SQLite file (created when missing), or None for a database kept in memory.
        config: settings.
        readonly: open an existing file for reading only (a concurrent reader).
    """

    def __init__(
        self,
        vocabulary: Vocabulary,
        path: str | Path | None = None,
        config: DatabaseConfig | None = None,
        readonly: bool = False,
    ) -> None:
        self.vocabulary = vocabulary
        self.config = config or DatabaseConfig()
        self.path = None if path is None else Path(path)
        self.readonly = readonly
        self._higher_better = higher_is_better(vocabulary.scoring)
        self._index = InvertedIndex(vocabulary.n_words, vocabulary.scoring)
        self._cache: OrderedDict[int, Entry] = OrderedDict()
        self._conn = self._connect()
        self._check_or_write_meta()
        self.refresh()

    # ------------------------------------------------------------------ opening
    def _where(self) -> str:
        return str(self.path) if self.path is not None else "<memory database>"

    def _connect(self) -> sqlite3.Connection:
        where = self._where()
        if self.path is None:
            if self.readonly:
                raise DatabaseError("a memory database cannot be opened read-only")
            target = ":memory:"
            uri = False
        else:
            if self.readonly and not self.path.is_file():
                raise DatabaseError(f"{where}: database file not found")
            if self.path.exists() and not self.path.is_file():
                raise DatabaseError(f"{where}: not a file")
            if not self.readonly:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            # as_uri() percent-encodes '#', '?' and '%', which a raw "file:" URI would cut at
            target = f"{self.path.resolve().as_uri()}?mode={'ro' if self.readonly else 'rwc'}"
            uri = True
        try:
            conn = sqlite3.connect(target, uri=uri, timeout=self.config.busy_timeout_s,
                                   isolation_level=None, check_same_thread=False)
            if not self.readonly and self.path is not None:
                conn.execute("PRAGMA journal_mode=WAL")
            sync = "FULL" if self.config.durability == "full" else "NORMAL"
            conn.execute(f"PRAGMA synchronous={sync}")
            if not self.readonly:
                conn.executescript(_SCHEMA)
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{where}: not a stablecues database or corrupt ({exc})") from exc
        return conn

    def _check_or_write_meta(self) -> None:
        voc = self.vocabulary
        want = {
            "format_version": str(FORMAT_VERSION),
            "vocabulary_fingerprint": voc.fingerprint,
            "vocabulary": json.dumps({"k": voc.k, "L": voc.levels, "words": voc.n_words,
                                      "weighting": int(voc.weighting), "scoring": int(voc.scoring)}),
            "levels_up": str(voc.levels_up),
        }
        try:
            have = dict(self._conn.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{self._where()}: not a stablecues database or corrupt ({exc})") from exc
        if not have:
            if self.readonly:
                raise DatabaseError(f"{self._where()}: empty database (no metadata)")
            with self._write():
                self._conn.executemany("INSERT INTO meta VALUES (?, ?)", list(want.items()))
            return
        if have.get("format_version") != str(FORMAT_VERSION):
            raise DatabaseError(
                f"{self._where()}: database format {have.get('format_version')}, expected {FORMAT_VERSION}"
            )
        if have.get("vocabulary_fingerprint") != voc.fingerprint:
            theirs = str(have.get("vocabulary_fingerprint", "?"))[:12]
            raise DatabaseError(
                f"{self._where()}: made with vocabulary {theirs}..., not with this vocabulary "
                f"{voc.fingerprint[:12]}... (open it with the vocabulary it was built with)"
            )
        if have.get("levels_up") != str(voc.levels_up):
            raise DatabaseError(
                f"{self._where()}: direct index stored at levels_up={have.get('levels_up')}, "
                f"the vocabulary uses {voc.levels_up}"
            )

    @contextmanager
    def _write(self) -> Iterator[None]:
        if self.readonly:
            raise DatabaseError(f"{self._where()}: opened read-only")
        try:
            self._conn.execute("BEGIN IMMEDIATE")
        except sqlite3.OperationalError as exc:
            raise DatabaseError(f"{self._where()}: cannot write ({exc}; another writer?)") from exc
        try:
            yield
        except BaseException:
            self._conn.execute("ROLLBACK")
            raise
        else:
            self._conn.execute("COMMIT")

    def refresh(self) -> int:
        """Load entries added (by this or another process) since the last refresh.

        Returns:
            how many entries were loaded.
        """
        start = self._index.n_entries
        loaded = 0
        try:
            cursor = self._conn.execute("SELECT id, bow FROM entries WHERE id >= ? ORDER BY id", (start,))
            while True:
                rows = cursor.fetchmany(4096)  # bounded memory: one sorted segment per chunk
                if not rows:
                    break
                words_l, entries_l, weights_l = [], [], []
                for eid, blob in rows:
                    expect = start + loaded
                    if eid != expect:
                        raise DatabaseError(f"{self._where()}: entry ids are not contiguous at id {expect}")
                    arrays = unpack_arrays(blob, f"{self._where()}: entry {eid}")
                    words_l.append(arrays["words"])
                    weights_l.append(arrays["weights"])
                    entries_l.append(np.full(arrays["words"].shape[0], eid, np.int32))
                    loaded += 1
                self._index.add_many(np.concatenate(words_l), np.concatenate(entries_l),
                                     np.concatenate(weights_l), start + loaded)
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{self._where()}: cannot read entries ({exc})") from exc
        return loaded

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> Database:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return self._index.n_entries

    # ------------------------------------------------------------------ writing
    def add(
        self,
        bow: BowVector,
        fvec: FeatureVector,
        features: Features,
        points3d: np.ndarray | None = None,
        timestamp: float = math.nan,
        pose: np.ndarray | None = None,
        meta: dict[str, Any] | None = None,
        arrays: dict[str, np.ndarray] | None = None,
    ) -> int:
        """Store an entry atomically and index it.

        Args:
            bow: the image's BoW vector (from this database's vocabulary).
            fvec: its direct index, one node per feature.
            features: its keypoints and descriptors.
            points3d: optional (N, 3) float32 3D point per keypoint in the image's camera
                frame, NaN where unknown.
            timestamp: seconds (NaN when unknown).
            pose: optional (4, 4) camera-to-world pose.
            meta: JSON-serialisable metadata (image path, ...).
            arrays: extra named per-entry arrays to keep (e.g. 3D point uncertainties).

        Returns:
            the entry's id (0, 1, 2, ... in order).
        """
        n = len(features)
        if len(fvec) != n:
            raise InputError(f"feature vector has {len(fvec)} nodes for {n} features")
        if bow.words.size and (bow.words[0] < 0 or bow.words[-1] >= self.vocabulary.n_words):
            raise InputError(f"BoW word ids outside this vocabulary's 0..{self.vocabulary.n_words - 1}")
        if fvec.levels_up != self.vocabulary.levels_up:
            raise InputError(f"feature vector at levels_up={fvec.levels_up}, database uses "
                             f"{self.vocabulary.levels_up}")
        payload: dict[str, np.ndarray] = {"fvec": fvec.nodes}
        if self.config.store_descriptors:
            payload.update(keypoints=features.keypoints, descriptors=features.descriptors,
                           octaves=features.octaves, angles=features.angles,
                           responses=features.responses, sizes=features.sizes)
        payload["image_size"] = np.array(features.image_size, np.int32)
        if points3d is not None:
            check_array("points3d", points3d, shape=(n, 3))
            payload["points3d"] = np.asarray(points3d, np.float32)
        if pose is not None:
            check_array("pose", pose, shape=(4, 4))
            payload["pose"] = np.asarray(pose, np.float64)
        for name, arr in (arrays or {}).items():
            payload["x_" + name] = np.asarray(arr)
        try:
            meta_text = json.dumps(meta or {})
        except TypeError as exc:
            raise InputError(f"entry metadata is not JSON-serialisable: {exc}") from exc
        bow_blob = pack_arrays({"words": bow.words, "weights": bow.weights.astype(np.float32)})
        eid = self._index.n_entries
        try:
            with self._write():
                # another process may have added entries (ids are 0..n-1, so MAX(id) + 1 is the
                # count, read from the end of the rowid b-tree instead of scanning the table)
                (last,) = self._conn.execute("SELECT MAX(id) FROM entries").fetchone()
                count = 0 if last is None else int(last) + 1
                if count != eid:
                    raise DatabaseError(
                        f"{self._where()}: {count} entries on disk but {eid} loaded: "
                        "another writer is using this file"
                    )
                self._conn.execute(
                    "INSERT INTO entries (id, timestamp, n_features, bow, payload, meta) "
                    "VALUES (?, ?, ?, ?, ?, ?)",
                    (eid, float(timestamp), n, bow_blob, pack_arrays(payload), meta_text),
                )
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{self._where()}: cannot add entry ({exc})") from exc
        self._index.add(bow.words, bow.weights.astype(np.float32))
        return eid

    # ------------------------------------------------------------------ reading
    def query(
        self,
        bow: BowVector,
        max_results: int = 10,
        exclude_recent: int = 0,
        max_id: int | None = None,
        min_id: int = 0,
    ) -> list[QueryResult]:
        """Entries most similar to ``bow``, best first.

        Args:
            bow: query BoW vector.
            max_results: how many results at most (<= 0: all entries sharing a word).
            exclude_recent: leave out the latest ``exclude_recent`` entries.
            max_id: only entries with id < max_id.
            min_id: only entries with id >= min_id.

        Returns:
            list of QueryResult(entry_id, score); for KL scoring lower scores rank first.
        """
        hi = len(self) - max(int(exclude_recent), 0)
        if max_id is not None:
            hi = min(hi, int(max_id))
        ids, scores = self._index.scores(bow.words, bow.weights, max_id=hi, min_id=min_id)
        if ids.size == 0:
            return []
        key = -scores if self._higher_better else scores
        if 0 < max_results < ids.size:
            part = np.argpartition(key, max_results - 1)[:max_results]
            order = part[np.lexsort((ids[part], key[part]))]
        else:
            order = np.lexsort((ids, key))
        return [QueryResult(int(ids[i]), float(scores[i])) for i in order]

    def scores(self, bow: BowVector, max_id: int | None = None) -> np.ndarray:
        """Dense (len(self),) float64 scores of the query against every entry (0 when no word
        is shared; for KL, +inf)."""
        n = len(self)
        out = np.zeros(n) if self._higher_better else np.full(n, np.inf)
        ids, s = self._index.scores(bow.words, bow.weights, max_id=max_id)
        out[ids] = s
        return out

    def entry(self, entry_id: int) -> Entry:
        """Everything stored about one entry (cached)."""
        eid = int(entry_id)
        hit = self._cache.get(eid)
        if hit is not None:
            self._cache.move_to_end(eid)
            return hit
        if not 0 <= eid < len(self):
            raise InputError(f"entry id {eid} outside 0..{len(self) - 1}")
        try:
            row = self._conn.execute(
                "SELECT timestamp, bow, payload, meta FROM entries WHERE id = ?", (eid,)
            ).fetchone()
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{self._where()}: cannot read entry {eid} ({exc})") from exc
        if row is None:
            raise DatabaseError(f"{self._where()}: entry {eid} is missing")
        ts, bow_blob, payload_blob, meta_text = row
        what = f"{self._where()}: entry {eid}"
        b = unpack_arrays(bow_blob, what)
        p = unpack_arrays(payload_blob, what)
        size = tuple(int(x) for x in p["image_size"])
        n = int(p["fvec"].shape[0])
        if "descriptors" in p:
            feats = Features(p["keypoints"], p["descriptors"], p["octaves"], p["angles"],
                             p["responses"], p["sizes"], (size[0], size[1]))
        else:
            feats = Features.empty((size[0], size[1]))
        entry = Entry(
            entry_id=eid,
            bow=BowVector(b["words"], b["weights"].astype(np.float64)),
            fvec=FeatureVector(p["fvec"], self.vocabulary.levels_up),
            features=feats,
            points3d=p.get("points3d"),
            timestamp=float(ts) if ts is not None else math.nan,
            pose=p.get("pose"),
            meta=json.loads(meta_text),
        )
        if n and len(feats) and len(feats) != n:
            raise DatabaseError(f"{what}: {len(feats)} features but {n} direct-index nodes")
        self._cache[eid] = entry
        if len(self._cache) > self.config.cache_entries:
            self._cache.popitem(last=False)
        return entry

    def extra_arrays(self, entry_id: int) -> dict[str, np.ndarray]:
        """The extra arrays stored with an entry (``arrays=`` of :meth:`add`)."""
        row = self._conn.execute("SELECT payload FROM entries WHERE id = ?", (int(entry_id),)).fetchone()
        if row is None:
            raise InputError(f"entry id {entry_id} not in {self._where()}")
        p = unpack_arrays(row[0], f"{self._where()}: entry {entry_id}")
        return {k[2:]: v for k, v in p.items() if k.startswith("x_")}

    def column(self, name: str) -> list[Any]:
        """One scalar column of every entry in id order: "timestamp", "n_features" or "meta"
        (decoded from JSON)."""
        if name not in ("timestamp", "n_features", "meta"):
            raise InputError(f"unknown entry column {name!r}")
        try:
            rows = self._conn.execute(f"SELECT {name} FROM entries ORDER BY id").fetchall()
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{self._where()}: cannot read entries ({exc})") from exc
        values = [r[0] for r in rows[: len(self)]]
        if name == "meta":
            return [json.loads(v) for v in values]
        if name == "timestamp":
            return [math.nan if v is None else float(v) for v in values]
        return values

    def stats(self) -> dict[str, float]:
        """Sizes: entries, postings, index bytes in memory, file bytes on disk."""
        file_bytes = 0
        if self.path is not None:
            for suffix in ("", "-wal"):
                f = Path(str(self.path) + suffix)
                if f.exists():
                    file_bytes += f.stat().st_size
        return {"entries": len(self), "postings": self._index.n_postings,
                "index_bytes": self._index.nbytes, "file_bytes": file_bytes,
                "time": time.time()}

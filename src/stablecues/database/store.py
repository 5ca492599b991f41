"""The topological database: BoW vectors (inverse index), direct index, keypoints,
descriptors, 3D points and metadata per entry, persisted in an embedded SQLite file.

Durability: every :meth:`Database.add` to a file is one record appended to the file's entry
log (``<file>-entries``, see :mod:`.entrylog`) and put into SQLite (WAL mode) from a thread of
its own, so a process killed in the middle of an add loses at most that entry and never
earlier ones, and no add waits for SQLite's commits or syncs; the next writer puts whatever
the log holds beyond SQLite's entries into SQLite before anything else. The inverse index is
kept next to the file in ``<file>-index/`` as memory-mapped segment files named by a manifest
inside the database (see :mod:`.files`), so reopening a map maps a few files instead of
rebuilding the index entry by entry; only the latest additions (at most a few blocks of
``tail_postings``) are read back from the entries. Entries are the source of truth: a missing
or damaged index file is rebuilt from them. Index maintenance (sorting the latest additions,
merging segments) runs in bounded steps, at most one per add (or in a thread of its own), so
no add waits for a whole merge; the write-ahead log is copied into the file by a thread of its
own, so no add waits for the disk either. A database in memory
(no path) holds each entry's arrays as read-only NumPy copies instead of packed blobs: its
SQLite rows keep the scalars, and nothing is packed or unpacked per add or entry.

One writing Database object per file at a time, and any number of readers (other objects or
processes, ``readonly=True``; they call :meth:`Database.refresh` to see what the writer has
put into SQLite since: its adds within milliseconds, all of them once it calls
:meth:`Database.flush` or closes). One object may be shared by threads: queries from any
number of threads while one thread adds. The file records the vocabulary's fingerprint and
refuses to be used with another vocabulary.

Long-lived maps: every entry belongs to a session (an int; :meth:`Database.new_session`
starts one); queries can keep to some sessions or leave some out; entries can be removed by
id, session or time (:meth:`Database.remove`) and the space reclaimed
(:meth:`Database.compact`); :func:`stablecues.database.merge_maps` merges map files.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import json
import logging
import math
import sqlite3
import sys
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from .._arrays import distinct
from ..errors import ConfigError, DatabaseError, InputError, VocabularyError, check_array
from ..types import BowVector, Entry, Features, FeatureVector, QueryResult
from ..vocabulary import Vocabulary, higher_is_better
from ..vocabulary.incremental import IncrementalVocabulary, words_path
from .entrylog import EMPTY_BOW, EMPTY_PAYLOAD, INSERT_ENTRY, EntryWriter, Row, log_path, replay, row_values
from .files import (
    IndexFiles,
    LogCheckpointer,
    Manifest,
    WriterLock,
    index_dir,
    open_segments,
    stored_segments,
)
from .inverted import InvertedIndex
from .packing import pack_buffer, unpack_arrays
from .schema import (
    FORMAT_VERSION,
    MAX_SESSION,
    Schema,
    Sql,
    int_value,
    meta_value,
    prepare,
    timestamp_value,
)
from .segments import Segment, SegmentDamaged, empty_postings, pack_postings, sort_block, verify_segment

log = logging.getLogger(__name__)

__all__ = ["FORMAT_VERSION", "Database", "DatabaseConfig"]

_LOAD_BLOCK = 4096  # entries per segment when entries are read back from the database
_CHECKPOINT_PAGES = 256  # SQLite copies its log into the file every ~1 MB: short stalls
#: ... or every 2 MB, in the adding thread, when the thread of ours that does it falls behind
#: (adds back to back: it never drains a log that grows as fast as it copies). A 16 MB backstop
#: stalled 40 of 10,000 back-to-back adds of 57 kB entries for 36-55 ms each (the log copied
#: inside the commit); 2 MB: slowest add 7.4-9.3 ms, mean 0.28 -> 0.32 ms (README, engine)
_BACKSTOP_PAGES = 512
_EMPTY_BOW, _EMPTY_PAYLOAD = EMPTY_BOW, EMPTY_PAYLOAD
_EMPTY_BOW_ARRAYS = unpack_arrays(_EMPTY_BOW)  # a removed entry's vector in a memory database


@dataclass(frozen=True)
class DatabaseConfig:
    """Database settings.

    Attributes:
        durability: "normal" survives a killed process (an add is durable once its record is
            in the entry log; SQLite WAL, synchronous=NORMAL); "full" also survives power loss
            (each record synced, synchronous=FULL, index files synced), at a cost per add.
        store_descriptors: keep keypoints and descriptors (needed by geometric verification).
        cache_entries: how many full entries to keep in memory for :meth:`Database.entry`.
        busy_timeout_s: how long to wait for a lock held by another process.
        maintenance: "inline" sorts and merges index segments in the adding thread, one
            bounded step per add at most; "background" does it in a thread of its own (better
            where a core is free and the adding thread leaves the interpreter idle: on a
            busy 2-core machine the two threads slow each other down).
        tail_postings: postings of the latest additions kept unsorted before they are sealed
            (and sorted in groups of 4): every query reads them all (sealed blocks waiting for
            their sort are searched through a word-sorted view instead), so a map queried while
            it grows pays for them. 16,384 was measured too, before the views: the query on a
            233-frame CamVid map queried after every add fell from 0.86 to 0.64 ms, but at 10^6
            entries the maintenance fell behind the adds (952 entries/s built instead of 2,994,
            one add of 3 s, queries at 33 ms instead of 13; ``bench_scale.py --parts 1m``); with
            the views, 65,536 gives 0.55 ms there (``bench_engine.py --sections growing``).
        merge_chunk: postings merged per maintenance step (about).
        descriptor_storage: how float descriptors (SIFT, learned) are stored: "int8" keeps
            one int8 per dimension and one float32 scale per entry (64 bytes per 64-dim
            descriptor instead of 256; read back within half a step, ``max|d| / 254``, of
            the original), "float32" keeps them exactly. Binary descriptors are stored as
            they are either way, and every entry reads back as it was written, whatever the
            setting when it is read.
    """

    durability: Literal["normal", "full"] = "normal"
    store_descriptors: bool = True
    cache_entries: int = 256
    busy_timeout_s: float = 10.0
    maintenance: Literal["background", "inline"] = "inline"
    tail_postings: int = 1 << 16
    merge_chunk: int = 1 << 17
    descriptor_storage: Literal["float32", "int8"] = "int8"

    def __post_init__(self) -> None:
        if self.durability not in ("normal", "full"):
            raise InputError(f"durability must be 'normal' or 'full', not {self.durability!r}")
        if self.maintenance not in ("background", "inline"):
            raise InputError(f"maintenance must be 'background' or 'inline', not {self.maintenance!r}")
        if self.descriptor_storage not in ("float32", "int8"):
            raise InputError(f"descriptor_storage must be 'float32' or 'int8', "
                             f"not {self.descriptor_storage!r}")
        for name in ("cache_entries", "tail_postings", "merge_chunk"):
            value = getattr(self, name)
            least = 0 if name == "cache_entries" else 1
            if not isinstance(value, int) or isinstance(value, bool) or value < least:
                raise InputError(f"{name} must be a positive integer, not {value!r}")


def _refuse_a_new_map_over_old_files(path: Path) -> None:
    """A missing or empty (0-byte) SQLite file would start a new, empty map, and a new map
    deletes the segment files its manifest does not name: refuse while a map's index segments
    or entry log lie beside it (a truncated or deleted ``map.sqlite`` must not take them along).

    Raises:
        DatabaseError: naming what was found and what to do.
    """
    try:
        fresh = not path.exists() or (path.is_file() and path.stat().st_size == 0)
        log = log_path(path)
        logged = log.is_file() and log.stat().st_size > 0
    except OSError:
        return  # _connect names what is wrong with the path
    if not fresh:
        return
    segments = stored_segments(path)
    state = "missing" if not path.exists() else "empty (0 bytes)"
    words = words_path(path)
    if words.is_file():  # an incremental vocabulary's words of a map that is gone
        raise DatabaseError(f"{path}: the SQLite file is {state} but {words.name} of a map remains beside "
                            "it: refusing to start a new map over it (restore the file, or move the words "
                            "away)")
    if segments or logged:
        found = (f"{len(segments)} index segment file(s) in {index_dir(path)}" if segments else "")
        found += (" and " if segments and logged else "") + (f"the entry log {log}" if logged else "")
        raise DatabaseError(f"{path}: the SQLite file is {state} but {found} of a map remain: refusing to "
                            "start a new map over them (restore the file, or move them away to start anew)")


def _session_ids(value: int | Iterable[int], what: str) -> np.ndarray:
    ids = np.atleast_1d(np.asarray(list(value) if not isinstance(value, int | np.integer) else value))
    if ids.dtype.kind not in "iu":
        raise InputError(f"{what}: expected session ids (integers), got {ids.dtype}")
    return ids.astype(np.int64)


_OPEN: weakref.WeakSet[Database] = weakref.WeakSet()


def _track(db: Database) -> None:
    """Close the database at exit, while its threads can still run (registered on first use,
    not at import)."""
    if not _OPEN and not getattr(_track, "registered", False):
        atexit.register(_close_open_databases)
        _track.registered = True  # type: ignore[attr-defined]
    _OPEN.add(db)


def _close_open_databases() -> None:
    for db in list(_OPEN):
        with contextlib.suppress(Exception):
            db.close()


class Database:
    """DBoW2-style image database with inverse and direct indexes.

    Args:
        vocabulary: the vocabulary every stored BoW vector comes from.
        path: SQLite file (created when missing; its directory must exist), or None for a
            database kept in memory.
        config: settings.
        readonly: open an existing file for reading only (a concurrent reader).
        session: session of the entries added from now on (default: the latest session in
            the file, 0 for a new one).
    """

    def __init__(
        self,
        vocabulary: Vocabulary | IncrementalVocabulary,
        path: str | Path | None = None,
        config: DatabaseConfig | None = None,
        readonly: bool = False,
        *,
        session: int | None = None,
    ) -> None:
        self.vocabulary = vocabulary
        self.config = config or DatabaseConfig()
        self.path = None if path is None else Path(path)
        self.readonly = readonly
        self._higher_better = higher_is_better(vocabulary.scoring)
        self._cache: OrderedDict[int, Entry] = OrderedDict()
        # a memory database holds each entry's arrays (BoW vector included) as read-only copies;
        # its SQLite rows keep the scalars only, with placeholder blobs
        self._held: dict[int, _Held] | None = {} if self.path is None else None
        self._cache_lock = threading.Lock()
        self._add_lock = threading.RLock()
        self._writer: WriterLock | None = None
        self._checkpointer: LogCheckpointer | None = None
        self._entries: EntryWriter | None = None  # a file's write-behind (the writer's)
        self._files: IndexFiles | None = None
        self._index: InvertedIndex | None = None
        self._incremental: IncrementalVocabulary | None = None
        if self.path is not None and not readonly:
            _refuse_a_new_map_over_old_files(self.path)
        self._sql = Sql(self._connect(), self._where(), readonly)
        _track(self)
        try:
            self._schema: Schema = prepare(self._sql, vocabulary)  # refuses other files untouched
            if not readonly and self.path is not None:
                self._wal()
            persistent = self.path is not None and not readonly and self._schema.uuid is not None
            if persistent:
                self._take_writer_lock()
            background = self.config.maintenance == "background" and not readonly
            self._index = InvertedIndex(vocabulary.n_words, vocabulary.scoring, self.config.tail_postings,
                                        store=self._files, background=background,
                                        chunk=self.config.merge_chunk)
            self._load_index()
            self._open_words()
            latest = self._index.sessions()
            self.session = int(latest[-1]) if session is None and latest.size else int(session or 0)
            self._check_session(self.session)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ opening
    def _where(self) -> str:
        return str(self.path) if self.path is not None else "<memory database>"

    @property
    def index(self) -> InvertedIndex:
        if self._index is None:
            raise DatabaseError(f"{self._where()}: database is closed")
        return self._index

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
            if not self.path.parent.is_dir():
                raise DatabaseError(f"{where}: directory {self.path.parent} does not exist")
            # as_uri() percent-encodes '#', '?' and '%', which a raw "file:" URI would cut at
            target = f"{self.path.resolve().as_uri()}?mode={'ro' if self.readonly else 'rwc'}"
            uri = True
        try:
            conn = sqlite3.connect(target, uri=uri, timeout=self.config.busy_timeout_s,
                                   isolation_level=None, check_same_thread=False)
            sync = "FULL" if self.config.durability == "full" else "NORMAL"
            conn.execute(f"PRAGMA synchronous={sync}")
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{where}: not a stablecues database or corrupt ({exc})") from exc
        return conn

    def _wal(self) -> None:
        try:
            with self._sql.lock:
                self._sql.conn.execute("PRAGMA journal_mode=WAL")
                self._sql.conn.execute(f"PRAGMA wal_autocheckpoint={_CHECKPOINT_PAGES}")
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{self._where()}: cannot use a write-ahead log ({exc})") from exc

    def _take_writer_lock(self) -> bool:
        """Become the one writer of this file (and the keeper of its index directory)."""
        if self._writer is not None:
            return True
        assert self.path is not None and self._schema.uuid is not None
        directory = index_dir(self.path)
        if directory.exists() and (directory.is_symlink() or not directory.is_dir()):
            raise DatabaseError(f"{directory}: exists and is not the database's index directory")
        try:
            directory.mkdir(exist_ok=True)
            try:
                lock = WriterLock(directory)
            except BlockingIOError:
                gc.collect()  # a Database dropped without close() may still hold the lock
                lock = WriterLock(directory)
        except BlockingIOError:
            return False
        except OSError as exc:
            raise DatabaseError(f"{directory}: cannot use the index directory "
                                f"({exc.strerror or exc})") from exc
        self._writer = lock
        full = self.config.durability == "full"
        try:
            # entries a killed writer left in the entry log go into SQLite before anything reads it
            with self._sql.snapshot() as conn:
                n = self._count(conn)
            replay(log_path(self.path), self._schema.uuid, self._sql, n)
            # the log's checkpoints (which sync the file) run in a thread of their own; SQLite's
            # own stay, further apart, as a backstop
            self._checkpointer = LogCheckpointer(self.path, self._sql.lock, "FULL" if full else "NORMAL")
            with self._sql.lock:
                self._sql.conn.execute(f"PRAGMA wal_autocheckpoint={_BACKSTOP_PAGES}")
                self._sql.conn.execute(f"PRAGMA journal_size_limit={_BACKSTOP_PAGES * 4096}")
            entries = EntryWriter(log_path(self.path), self._schema.uuid, self._sql, full,
                                  self._checkpointer.wrote)
        except BaseException:
            self._writer = None
            lock.release()
            raise
        self._entries = entries
        manifest = Manifest.parse(self._schema.manifest, self._where())
        self._files = IndexFiles(
            directory, self._schema.uuid, self.vocabulary.n_words, full, entries.save_manifest,
            self._entries_segments, manifest.next_gen, after_commit=entries.after_commit,
        )
        return True

    def _drain(self) -> None:
        """Wait until every add so far is in SQLite (before reading entries there)."""
        if self._entries is not None:
            self._entries.drain()

    def _entries_segments(self, lo: int, hi: int) -> list[Segment]:
        self._drain()
        return _load_segments(self._sql, self._schema, self.vocabulary.n_words, lo, hi)

    def _count(self, conn: sqlite3.Connection) -> int:
        # one aggregate per statement: SQLite reads MAX or MIN alone off the end of the id
        # b-tree, but scans the whole table for both at once
        (last,) = conn.execute("SELECT MAX(id) FROM entries").fetchone()
        (first,) = conn.execute("SELECT MIN(id) FROM entries").fetchone()
        if last is None:
            return 0
        last, first = int_value(last, self._where(), -1, "id"), int_value(first, self._where(), -1, "id")
        if first != 0:
            raise DatabaseError(f"{self._where()}: entry ids start at {first}, not 0 (corrupt)")
        size = self.path.stat().st_size if self.path is not None else 0
        if self.path is not None and (last >= 2**31 - 1 or last > 64 + size // 8):
            raise DatabaseError(f"{self._where()}: entry ids up to {last} in a file of {size} bytes "
                                "(corrupt)")
        return last + 1

    def _read_state(self) -> tuple[int, str | None, np.ndarray]:
        try:
            with self._sql.snapshot() as conn:
                n = self._count(conn)
                row = conn.execute("SELECT value FROM meta WHERE key = 'index'").fetchone()
                removed = np.zeros(0, np.int64)
                if "removed" in self._schema.columns:
                    rows = conn.execute("SELECT id FROM entries WHERE removed != 0").fetchall()
                    removed = np.array([r[0] for r in rows if isinstance(r[0], int) and 0 <= r[0] < n],
                                       np.int64)
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{self._where()}: cannot read entries ({exc})") from exc
        return n, (row[0] if row is not None and isinstance(row[0], str) else None), removed

    def _load_index(self) -> None:
        """Map the index files the manifest names and read the entries they do not cover."""
        index = self.index
        current = index.segments
        for _ in range(5):
            n, text, removed = self._read_state()
            segments: list[Segment] = []
            missing = False
            if self.path is not None and self._schema.uuid is not None and index_dir(self.path).is_dir():
                manifest = Manifest.parse(text, self._where())
                if self._files is not None:
                    self._files.next_gen = max(self._files.next_gen, manifest.next_gen)
                    self._files.cleanup({r.file for r in manifest.segments})
                reuse = {s.name: s for s in current if s.name is not None}
                segments, missing = open_segments(index_dir(self.path), manifest, self._schema.uuid,
                                                  self.vocabulary.n_words, n, reuse)
            if not missing:
                break
        loaded = {(s.lo, s.hi): s for s in current if s.name is None}
        full: list[Segment] = []
        pos = 0
        for seg in [*segments, None]:
            end = n if seg is None else seg.lo
            if end > pos:
                full.extend(self._gap(pos, end, loaded))
            if seg is not None:
                full.append(seg)
                pos = seg.hi
        sessions = np.concatenate([np.asarray(s.sessions, np.int32) for s in full] or [np.zeros(0, np.int32)])
        index.reset(full, n, sessions, removed)

    def _gap(self, lo: int, hi: int, loaded: dict[tuple[int, int], Segment]) -> list[Segment]:
        out = []
        for a in range(lo, hi, _LOAD_BLOCK):
            b = min(a + _LOAD_BLOCK, hi)
            seg = loaded.get((a, b))
            out.extend([seg] if seg is not None else self._segments_of(a, b))
        return out

    def _segments_of(self, lo: int, hi: int) -> list[Segment]:
        """The index of entries ``lo .. hi - 1`` built from their BoW vectors."""
        self._drain()
        return _load_segments(self._sql, self._schema, self.vocabulary.n_words, lo, hi, self._held)

    def refresh(self) -> int:
        """Load entries added (by this or another process) since the last refresh, and follow
        the writer's index changes and removals.

        Returns:
            how many entries were loaded.
        """
        before = len(self)
        with self._add_lock:
            if self._writer is None:
                self._load_index()
                self._follow_words()
            else:
                self._load_new_entries()
        return len(self) - before

    def _follow_words(self) -> None:
        """A reader's incremental vocabulary brought up to the entries it now holds: the
        writer's newer words file when it saved one since, and the entries after it learned
        again, as a reopen does."""
        voc = self._incremental
        n = len(self)
        if voc is None or voc.images >= n or self.path is None or self._schema.uuid is None:
            return
        wp = words_path(self.path)
        try:
            saved = IncrementalVocabulary.saved_images(wp)
        except VocabularyError:
            saved = -1
        if saved > voc.images:
            self._catch_up(voc, n)
            return
        for eid in range(voc.images, n):
            d = self._stored_of(eid)
            voc.replay(d if d is not None else np.zeros((0, voc.kind.size), voc.kind.dtype))

    def _load_new_entries(self) -> None:
        index = self.index
        n = index.n_entries
        rows = self._sql.rows(f"SELECT id, bow, {self._schema.session_sql} FROM entries WHERE id >= ? "
                              "ORDER BY id", (n,))
        for eid, blob, session in rows:
            if eid != index.n_entries:
                raise DatabaseError(f"{self._where()}: entry ids are not contiguous at id {index.n_entries}")
            arrays = unpack_arrays(blob, f"{self._where()}: entry {eid}")
            index.add(_bow_words(arrays, eid, self._where(), self.vocabulary.n_words), arrays["weights"],
                      int_value(session, self._where(), eid, "session"))

    def close(self) -> None:
        """Stop the index maintenance, close the file and give up the writer lock."""
        if self._incremental is not None and self._index is not None:
            with contextlib.suppress(DatabaseError):  # reported by the save itself; entries are safe
                self._save_words(final=True)
        index, self._index = self._index, None
        if index is not None:
            index.close()
        files = getattr(self, "_files", None)
        if files is not None:
            files.close()
        held = getattr(self, "_held", None)
        if held is not None:
            held.clear()
        entries, self._entries = getattr(self, "_entries", None), None
        if entries is not None:  # what is queued goes into SQLite first
            entries.close()
        checkpointer, self._checkpointer = self._checkpointer, None
        if checkpointer is not None:
            checkpointer.close()
        sql = getattr(self, "_sql", None)
        if sql is not None:
            with sql.lock:
                sql.conn.close()
        if entries is not None:
            entries.remove_log()
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self._incremental is not None:
            self._incremental.release(self)

    # ------------------------------------------------------------------ an incremental vocabulary's words
    def _open_words(self) -> None:
        """Bind an incremental vocabulary to this map, read its words back (``MAP.words``) and
        learn again the entries added after they were saved (a writer killed in between)."""
        voc = self.vocabulary
        if not isinstance(voc, IncrementalVocabulary):
            return
        voc.bind(self)
        self._incremental = voc
        n = len(self)
        if self.path is None or self._schema.uuid is None:
            if voc.images != n:
                raise ConfigError(f"the incremental vocabulary has learned {voc.images} images, the map "
                                  f"holds {n}: give a new map a new vocabulary")
            return
        self._catch_up(voc, n)

    def _catch_up(self, voc: IncrementalVocabulary, n: int) -> None:
        """The saved words into ``voc``, then the entries added after them learned again."""
        assert self.path is not None
        wp = words_path(self.path)
        self._read_words(voc, wp, n)
        if voc.images > n:  # saved after entries a power cut took (entries not synced): learn all again
            log.warning("%s: learned %d images, the map holds %d: learning the map's entries again", wp,
                        voc.images, n)
            voc.forget()
        lost: list[int] = []
        for eid in range(voc.images, n):  # added after the last save: learn them again, in order
            d = self._stored_of(eid)
            if d is None:  # removed (or saved without descriptors): counted, its words are gone
                lost.append(eid)
                d = np.zeros((0, voc.kind.size), voc.kind.dtype)
            voc.replay(d)
        if lost:
            log.warning("%s: %d entries (first %d) keep no descriptors: the words are learned again without "
                        "theirs", wp, len(lost), lost[0])
        if not self.readonly:
            if voc.images == 0:
                wp.unlink(missing_ok=True)  # words ahead of an empty map: nothing to keep
            elif voc.due():
                self._save_words()

    def _read_words(self, voc: IncrementalVocabulary, wp: Path, n: int) -> None:
        """The saved words into ``voc`` (a new map, or one whose words file is gone: none)."""
        assert self._schema.uuid is not None
        try:
            if wp.exists():
                voc.restore(wp, self._schema.uuid)
            elif voc.images:
                raise ConfigError(f"the incremental vocabulary has learned {voc.images} images, the map "
                                  f"{self._where()} has no words: give a map a new vocabulary")
            elif n:
                log.warning("%s: missing; learning the words again from the map's %d entries", wp, n)
        except VocabularyError as exc:
            raise DatabaseError(str(exc)) from None

    def _stored_of(self, eid: int) -> np.ndarray | None:
        """Entry ``eid``'s descriptors as stored, or None (removed, missing, or kept without them)."""
        alive = self.index.alive()
        if alive is not None and not alive[eid]:
            return None
        what = f"{self._where()}: entry {eid}"
        try:
            return _stored_descriptors(unpack_arrays(self._row(eid, "payload")[0], what), what)
        except (DatabaseError, InputError):
            return None

    def resync_words(self) -> None:
        """Bring an incremental vocabulary back to this map's entries (after an add that failed
        once the vocabulary had learned its frame): the saved words, and the entries after them
        learned again."""
        voc = self._incremental
        if voc is None:
            return
        voc.forget()
        if self.path is not None and self._schema.uuid is not None:
            self._catch_up(voc, len(self))
            return
        for eid in range(len(self)):  # a memory map: its entries, as held
            try:
                feats = self.entry(eid).features
                d = feats.descriptors
            except (DatabaseError, InputError):
                d = np.zeros((0, voc.kind.size), voc.kind.dtype)
            voc.replay(d)

    def _save_words(self, final: bool = False) -> None:
        voc = self._incremental
        if (voc is None or self.readonly or self.path is None or self._schema.uuid is None
                or voc.images != len(self) or not (voc.due() or (final and voc.unsaved))):
            return
        try:
            voc.save(words_path(self.path), self._schema.uuid, images=len(self))
        except OSError as exc:
            log.error("%s: cannot save the incremental vocabulary's words (%s); they are learned again "
                      "from the entries at the next open", words_path(self.path), exc)
            raise DatabaseError(f"{words_path(self.path)}: cannot write ({exc})") from None

    def _check_learned(self, features: Features) -> None:
        """An incremental vocabulary's map stores exactly the image its vocabulary learned last.

        Raises:
            InputError: not learned once just before, or learned in another form than stored.
        """
        voc = self._incremental
        if voc is None:
            return
        if voc.images != len(self) + 1:
            raise InputError(f"the incremental vocabulary has learned {voc.images} images for entry "
                             f"{len(self)}: call its learn() once per entry, just before add()")
        if not voc.learned_last(self.stored_form(features.descriptors)):
            raise InputError("the incremental vocabulary learned other descriptors than those stored: learn "
                             "db.stored_form(descriptors), the form a reopened map learns them again from")

    def stored_form(self, descriptors: np.ndarray) -> np.ndarray:
        """``descriptors`` as an entry of this map gives them back (float ones through the
        int8 storage): what an incremental vocabulary learns from, so that learning them again
        after a reopen makes the same words."""
        if self.config.descriptor_storage == "int8" and descriptors.dtype == np.float32:
            q, scale = _quantised(descriptors)
            return q.astype(np.float32) * scale[0]
        return descriptors

    def __del__(self) -> None:
        if sys.is_finalizing():  # its threads cannot run any more; the OS releases the rest
            return
        with contextlib.suppress(Exception):  # nothing to report to at collection time
            self.close()

    def __enter__(self) -> Database:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        """Entry ids given out so far (the next entry's id); removed entries keep theirs."""
        return self.index.n_entries

    # ------------------------------------------------------------------ writing
    def _check_session(self, session: object) -> int:
        if (not isinstance(session, int | np.integer) or isinstance(session, bool)
                or not 0 <= session <= MAX_SESSION):
            raise InputError(f"session must be an integer in 0..{MAX_SESSION}, not {session!r}")
        return int(session)

    def _writable(self) -> None:
        if self.readonly:
            raise DatabaseError(f"{self._where()}: opened read-only")
        if self.path is None or self._writer is not None or self._schema.uuid is None:
            return
        if not self._take_writer_lock():
            raise DatabaseError(f"{self._where()}: another Database object or process is writing this "
                                "file (close it first, or open this one with readonly=True)")
        # another writer may have added entries or changed the index since this object opened
        self._load_index()
        self.index.set_store(self._files)

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
        *,
        session: int | None = None,
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
            session: the entry's session (default: :attr:`session`).

        Returns:
            the entry's id (0, 1, 2, ... in order).
        """
        n = len(features)
        if len(fvec) != n:
            raise InputError(f"feature vector has {len(fvec)} nodes for {n} features")
        self._check_learned(features)
        if bow.words.size and (bow.words[0] < 0 or bow.words[-1] >= self.vocabulary.n_words):
            raise InputError(f"BoW word ids outside this vocabulary's 0..{self.vocabulary.n_words - 1}")
        if fvec.levels_up != self.vocabulary.levels_up:
            raise InputError(f"feature vector at levels_up={fvec.levels_up}, database uses "
                             f"{self.vocabulary.levels_up}")
        sess = self.session if session is None else self._check_session(session)
        payload = self._payload(fvec, features, n, points3d, pose, arrays)
        try:
            meta_text = json.dumps(meta or {})
        except (TypeError, ValueError) as exc:
            raise InputError(f"entry metadata is not JSON-serialisable: {exc}") from exc
        weights = bow.weights.astype(np.float32)
        held = None
        if self._held is not None:  # the row keeps the scalars only
            bow_arrays = _frozen({"words": bow.words, "weights": weights})
            held = _Held(float(timestamp), bow_arrays, _frozen(payload), meta_text)
            bow_blob: bytes | bytearray = _EMPTY_BOW
            payload_blob: bytes | bytearray = _EMPTY_PAYLOAD
        else:
            bow_blob = pack_buffer({"words": bow.words, "weights": weights})
            payload_blob = pack_buffer(payload)
        with self._add_lock:
            self._writable()
            index = self.index
            eid = index.n_entries
            row = Row(eid, float(timestamp), n, bow_blob, payload_blob, meta_text, sess)
            entries = self._entries
            if entries is not None:  # a file: appended to its entry log, SQLite filled behind
                entries.add(row)
            else:
                try:
                    with self._sql.lock:  # one statement: its own transaction, atomic
                        self._sql.conn.execute(INSERT_ENTRY, tuple(row))
                except sqlite3.IntegrityError as exc:
                    raise DatabaseError(f"{self._where()}: entry {eid} already on disk: another writer "
                                        "is using this file") from exc
                except sqlite3.DatabaseError as exc:
                    raise DatabaseError(f"{self._where()}: cannot add entry ({exc})") from exc
            if self._held is not None and held is not None:
                self._held[eid] = held
            index.add(bow.words, weights, sess)
            if self._incremental is not None and self._incremental.due():
                with contextlib.suppress(DatabaseError):  # logged; the entry is stored, the words follow
                    self._save_words()
        return eid

    def _payload(
        self, fvec: FeatureVector, features: Features, n: int, points3d: np.ndarray | None,
        pose: np.ndarray | None, arrays: dict[str, np.ndarray] | None,
    ) -> dict[str, np.ndarray]:
        payload: dict[str, np.ndarray] = {"fvec": fvec.nodes}
        if self.config.store_descriptors:
            payload["keypoints"] = features.keypoints
            d = features.descriptors
            if self.config.descriptor_storage == "int8" and d.dtype == np.float32:
                # quantised here, so that a memory database holds what a file would give back
                payload["qdescriptors"], payload["qscale"] = _quantised(d)
            else:
                payload["descriptors"] = d
            payload.update(octaves=features.octaves, angles=features.angles,
                           responses=features.responses, sizes=features.sizes)
        payload["image_size"] = np.array(features.image_size, np.int32)
        if points3d is not None:
            check_array("points3d", points3d, shape=(n, 3))
            payload["points3d"] = np.asarray(points3d, np.float32)
        if pose is not None:
            check_array("pose", pose, shape=(4, 4))
            payload["pose"] = np.asarray(pose, np.float64)
        for name, arr in (arrays or {}).items():
            a = np.asarray(arr)
            if a.dtype.kind not in "biufc":
                raise InputError(f"extra array {name!r}: dtype {a.dtype} cannot be stored (numbers only)")
            payload["x_" + name] = a
        return payload

    def new_session(self) -> int:
        """Start a new session (one more than any session so far); returns its id."""
        sessions = self.index.sessions()
        latest = int(sessions.max()) if sessions.size else -1
        self.session = self._check_session(max(latest, self.session) + 1)
        return self.session

    def remove(
        self,
        ids: Iterable[int] | None = None,
        *,
        session: int | None = None,
        before: float | None = None,
        after: float | None = None,
    ) -> int:
        """Remove entries: those matching every filter given (at least one).

        A removed entry leaves every query at once; its id is never given out again, and
        :meth:`entry` refuses it. Its data stays in the file until :meth:`compact`.

        Args:
            ids: entry ids.
            session: entries of this session.
            before: entries with a timestamp < before.
            after: entries with a timestamp >= after.

        Returns:
            how many entries were removed (entries already removed do not count).
        """
        where, args = self._removal_filter(ids, session, before, after)
        with self._add_lock:
            self._writable()
            self._drain()
            self._save_words(final=True)  # the entries removed could not be learned again
            try:
                with self._sql.write() as conn:
                    rows = conn.execute(f"SELECT id FROM entries WHERE removed = 0 AND {where}",
                                        args).fetchall()
                    gone = np.array(sorted(r[0] for r in rows), np.int64)
                    conn.executemany(
                        "UPDATE entries SET removed = 1, n_features = 0, bow = ?, payload = ?, meta = 'null' "
                        "WHERE id = ?", [(_EMPTY_BOW, _EMPTY_PAYLOAD, int(i)) for i in gone])
            except sqlite3.DatabaseError as exc:
                raise DatabaseError(f"{self._where()}: cannot remove entries ({exc})") from exc
            if gone.size:
                self.index.remove(gone)
                with self._cache_lock:
                    for i in gone.tolist():
                        self._cache.pop(i, None)
                        if self._held is not None:
                            self._held.pop(i, None)
        return int(gone.size)

    def _removal_filter(
        self, ids: Iterable[int] | None, session: int | None, before: float | None, after: float | None
    ) -> tuple[str, list[Any]]:
        clauses: list[str] = []
        args: list[Any] = []
        if ids is not None:
            arr = distinct(np.asarray(list(ids), np.int64))
            arr = arr[(arr >= 0) & (arr < len(self))]
            clauses.append("id IN (SELECT value FROM json_each(?))")
            args.append(json.dumps(arr.tolist()))
        if session is not None:
            clauses.append("session = ?")
            args.append(self._check_session(session))
        for value, op in ((before, "<"), (after, ">=")):
            if value is not None:
                if not isinstance(value, int | float) or math.isnan(value):
                    raise InputError(f"time limits must be numbers, not {value!r}")
                clauses.append(f"timestamp {op} ?")
                args.append(float(value))
        if not clauses:
            raise InputError("remove() needs ids, a session or a time limit")
        return " AND ".join(clauses), args

    def compact(self, vacuum: bool = True) -> None:
        """Reclaim the space of removed entries: rewrite the index without their postings and
        (``vacuum``) the file without their data. Takes about as long as reading the map."""
        with self._add_lock:
            self._writable()
            self.index.compact()
            self._drain()
        if self._files is not None:  # the replaced segment files' space, back before returning
            self._files.wait_discarded()
        if vacuum:
            try:
                with self._sql.lock:
                    self._sql.conn.execute("VACUUM")
                    if self.path is not None:  # hand the space back now, not at the next checkpoint
                        self._truncate_log()
            except sqlite3.DatabaseError as exc:
                raise DatabaseError(f"{self._where()}: cannot compact the file ({exc})") from exc

    def _truncate_log(self, tries: int = 100) -> None:
        """Copy the whole log into the file and empty it. A checkpoint of the log-copying thread
        in progress makes SQLite answer busy (a row, not an error): try again until it is done."""
        for attempt in range(tries):
            busy = self._sql.conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()[0]
            if not busy:
                return
            time.sleep(0.001 * min(attempt + 1, 20))
        log.warning("%s: the log could not be emptied now (a reader holds it); it empties later",
                    self._where())

    def flush(self) -> None:
        """Finish the index maintenance now: sort the latest additions and merge segments
        (and, for a file, write them all, and every entry added so far into SQLite), so that
        a reopen reads nothing back and readers see every entry."""
        with self._add_lock:
            if not self.readonly:
                self._writable()
            self.index.flush()
            self._drain()
            self._save_words(final=True)

    # ------------------------------------------------------------------ reading
    def query(
        self,
        bow: BowVector,
        max_results: int = 10,
        exclude_recent: int = 0,
        max_id: int | None = None,
        min_id: int = 0,
        *,
        sessions: int | Iterable[int] | None = None,
        exclude_sessions: int | Iterable[int] | None = None,
    ) -> list[QueryResult]:
        """Entries most similar to ``bow``, best first.

        Args:
            bow: query BoW vector.
            max_results: how many results at most (<= 0: all entries sharing a word).
            exclude_recent: leave out the latest ``exclude_recent`` entries.
            max_id: only entries with id < max_id.
            min_id: only entries with id >= min_id.
            sessions: only entries of these sessions (None: every session).
            exclude_sessions: leave out entries of these sessions (e.g. the current one).

        Returns:
            list of QueryResult(entry_id, score); for KL scoring lower scores rank first.
        """
        hi = len(self) - max(int(exclude_recent), 0)
        if max_id is not None:
            hi = min(hi, int(max_id))
        ids, scores = self.scored(bow, max_id=hi, min_id=min_id, sessions=sessions,
                                  exclude_sessions=exclude_sessions)
        return self.best(ids, scores, max_results)

    def scored(
        self,
        bow: BowVector,
        max_id: int | None = None,
        min_id: int = 0,
        *,
        sessions: int | Iterable[int] | None = None,
        exclude_sessions: int | Iterable[int] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every entry sharing a word with ``bow`` (filters as :meth:`query`), in id order, and
        its score: what :meth:`query` ranks, for a caller that needs more than the best."""
        ids, scores = self._index_scores(bow, max_id=max_id, min_id=min_id)
        return self._in_sessions(ids, scores, sessions, exclude_sessions)

    def best(self, ids: np.ndarray, scores: np.ndarray, max_results: int) -> list[QueryResult]:
        """The ``max_results`` best of :meth:`scored`'s entries (<= 0: all), best first (ties:
        lower ids first), as :meth:`query` returns them."""
        if ids.size == 0:
            return []
        key = -scores if self._higher_better else scores
        if 0 < max_results < ids.size:
            part = np.argpartition(key, max_results - 1)[:max_results]
            order = part[np.lexsort((ids[part], key[part]))]
        else:
            order = np.lexsort((ids, key))
        return [QueryResult(int(ids[i]), float(scores[i])) for i in order]

    def _index_scores(
        self, bow: BowVector, max_id: int | None, min_id: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """The inverse index's scores; a persisted segment whose body fails its checksum on
        first use is rebuilt from the entries by the writer (with a warning naming it), and
        refused in one line by a reader."""
        for _ in range(len(self.index.segments) + 1):
            try:
                return self.index.scores(bow.words, bow.weights, max_id=max_id, min_id=min_id)
            except SegmentDamaged as exc:
                if self.readonly or self.path is None or self._writer is None:
                    raise
                log.warning("%s; rebuilding it from the entries", exc.problem)
                with self._add_lock:
                    if exc.segment in self.index.segments:
                        self._rebuild([exc.segment])
        return self.index.scores(bow.words, bow.weights, max_id=max_id, min_id=min_id)

    def _in_sessions(
        self, ids: np.ndarray, scores: np.ndarray, sessions: int | Iterable[int] | None,
        exclude: int | Iterable[int] | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        if (sessions is None and exclude is None) or ids.size == 0:
            return ids, scores
        of = self.index.sessions()[ids]
        keep = np.ones(ids.size, bool)
        if sessions is not None:
            keep &= np.isin(of, _session_ids(sessions, "sessions"))
        if exclude is not None:
            keep &= ~np.isin(of, _session_ids(exclude, "exclude_sessions"))
        return ids[keep], scores[keep]

    def scores(
        self,
        bow: BowVector,
        max_id: int | None = None,
        *,
        sessions: int | Iterable[int] | None = None,
        exclude_sessions: int | Iterable[int] | None = None,
    ) -> np.ndarray:
        """Dense (len(self),) float64 scores of the query against every entry (0 when no word
        is shared, or the entry is removed or left out by the session filters; for KL, +inf)."""
        ids, s = self.scored(bow, max_id=max_id, sessions=sessions, exclude_sessions=exclude_sessions)
        n = len(self)
        out = np.zeros(n) if self._higher_better else np.full(n, np.inf)
        out[ids] = s
        return out

    def _row(self, eid: int, columns: str) -> tuple[Any, ...]:
        if not 0 <= eid < len(self):
            raise InputError(f"entry id {eid} outside 0..{len(self) - 1}")
        entries = self._entries
        pending = entries.pending(eid) if entries is not None else None
        if pending is not None:  # added, not in SQLite yet (a pending entry is never removed)
            return row_values(pending, columns)
        rows = self._sql.rows(f"SELECT {columns}, {self._schema.removed_sql} FROM entries WHERE id = ?",
                              (eid,), f"entry {eid}")
        if not rows:
            raise DatabaseError(f"{self._where()}: entry {eid} is missing")
        if rows[0][-1]:
            raise InputError(f"entry {eid} was removed from {self._where()}")
        return tuple(rows[0][:-1])

    def entry(self, entry_id: int) -> Entry:
        """Everything stored about one entry (cached)."""
        eid = int(entry_id)
        with self._cache_lock:
            hit = self._cache.get(eid)
            if hit is not None:
                self._cache.move_to_end(eid)
                return hit
        where = self._where()
        what = f"{where}: entry {eid}"
        held = self._held_entry(eid)
        if held is not None:
            ts, b, p, meta_text = held
        else:
            ts, bow_blob, payload_blob, meta_text = self._row(eid, "timestamp, bow, payload, meta")
            b = unpack_arrays(bow_blob, what)
            p = unpack_arrays(payload_blob, what)
        feats, nodes = _features(p, what)
        meta = meta_value(meta_text, where, eid)
        words = _bow_words(b, eid, where, self.vocabulary.n_words)
        entry = Entry(
            entry_id=eid,
            bow=BowVector(words, np.asarray(b["weights"], np.float64)),
            fvec=FeatureVector(nodes, self.vocabulary.levels_up),
            features=feats,
            points3d=_optional(p, "points3d", (nodes.shape[0], 3), what),
            timestamp=timestamp_value(ts, where, eid),
            pose=_optional(p, "pose", (4, 4), what),
            meta=meta if meta is not None else {},
            arrays=_extras(p),
        )
        with self._cache_lock:
            self._cache[eid] = entry
            while len(self._cache) > self.config.cache_entries:
                self._cache.popitem(last=False)
        return entry

    def _held_entry(self, eid: int) -> _Held | None:
        """A memory database's entry ``eid`` (None: a file, or not a live id)."""
        return self._held.get(eid) if self._held is not None and 0 <= eid < len(self) else None

    def extra_arrays(self, entry_id: int) -> dict[str, np.ndarray]:
        """The extra arrays stored with an entry (``arrays=`` of :meth:`add`)."""
        eid = int(entry_id)
        held = self._held_entry(eid)
        if held is not None:
            p = held.payload
        else:
            (blob,) = self._row(eid, "payload")
            p = unpack_arrays(blob, f"{self._where()}: entry {eid}")
        return _extras(p)

    def column(self, name: str) -> list[Any]:
        """One scalar column of every entry id in order: "timestamp" (NaN when unknown),
        "n_features", "session" or "meta" (decoded from JSON). Removed entries read as NaN,
        0, their session and None."""
        sql_name = {"timestamp": "timestamp", "n_features": "n_features", "meta": "meta",
                    "session": self._schema.session_sql}.get(name)
        if sql_name is None:
            raise InputError(f"unknown entry column {name!r}; known: timestamp, n_features, session, meta")
        n = len(self)
        self._drain()
        rows = self._sql.rows(f"SELECT id, {sql_name}, {self._schema.removed_sql} FROM entries "
                              "WHERE id < ? ORDER BY id", (n,))
        where = self._where()
        if len(rows) != n:
            raise DatabaseError(f"{where}: {len(rows)} entries on disk, {n} expected (corrupt)")
        if name == "meta":
            return [meta_value(v, where, i) for i, v, _ in rows]
        if name == "timestamp":
            return [math.nan if gone else timestamp_value(v, where, i) for i, v, gone in rows]
        return [int_value(v, where, i, name) for i, v, _ in rows]

    def ids(self) -> np.ndarray:
        """(K,) int64 ids of the entries not removed."""
        alive = self.index.alive()
        n = len(self)
        return np.arange(n) if alive is None else np.flatnonzero(alive[:n])

    def sessions(self) -> dict[int, int]:
        """Entries (not removed) per session."""
        ids = self.ids()
        s, counts = np.unique(self.index.sessions()[ids], return_counts=True)
        return dict(zip(s.tolist(), counts.tolist(), strict=True))

    def check(self, repair: bool = False) -> list[str]:
        """Check the index files' checksums and entry ids, the rows against the entry ids (one
        row per id: a row deleted from the SQLite file leaves its id answering queries with
        nothing to read), and the file's integrity.

        Args:
            repair: rebuild index segments that fail from the entries; give every id without a
                row a removed entry's row (its data is lost; it leaves the queries).

        Returns:
            the problems found (empty: all good).
        """
        self._drain()  # every add in SQLite
        n = len(self)
        checked = [(s, verify_segment(s, n)) for s in self.index.segments]
        for s, p in checked:
            s.verified = s.verified or p is None
        bad = [(s, p) for s, p in checked if p is not None]
        problems = [p for _, p in bad]
        missing = self._missing_rows(n)
        if missing.size:
            shown = ", ".join(map(str, missing[:8].tolist())) + (", ..." if missing.size > 8 else "")
            problems.append(f"{self._where()}: {missing.size} of the entry ids 0..{n - 1} have no row in the "
                            f"SQLite file (ids {shown}): their entries are lost")
        rows = self._sql.rows("PRAGMA quick_check", what="the file's integrity")
        problems += [f"{self._where()}: {r[0]}" for r in rows if r[0] != "ok"]
        if repair and (bad or missing.size):
            with self._add_lock:
                self._writable()
                self._rebuild([s for s, _ in bad])
                self._fill_missing_rows(missing)
        return problems

    def _missing_rows(self, n: int) -> np.ndarray:
        """Entry ids below ``n`` without a row (a row count first: one read of the id b-tree)."""
        (count,) = self._sql.rows("SELECT COUNT(*) FROM entries", what="the entries")[0]
        if count >= n:
            return np.zeros(0, np.int64)
        have = np.zeros(n, bool)
        for (eid,) in self._sql.rows("SELECT id FROM entries", what="the entries"):
            if isinstance(eid, int) and 0 <= eid < n:
                have[eid] = True
        return np.flatnonzero(~have).astype(np.int64)

    def _fill_missing_rows(self, missing: np.ndarray) -> None:
        """A removed entry's row for every id in ``missing`` (its session kept from the index)."""
        if not missing.size:
            return
        sessions = self.index.sessions()
        try:
            with self._sql.write() as conn:
                conn.executemany(
                    "INSERT INTO entries (id, timestamp, n_features, bow, payload, meta, session, removed) "
                    "VALUES (?, NULL, 0, ?, ?, 'null', ?, 1)",
                    [(int(i), _EMPTY_BOW, _EMPTY_PAYLOAD, int(sessions[i]) if i < sessions.size else 0)
                     for i in missing])
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{self._where()}: cannot restore the rows of lost entries ({exc})") from exc
        self.index.remove(missing)
        with self._cache_lock:
            for i in missing.tolist():
                self._cache.pop(i, None)

    def _rebuild(self, segments: list[Segment]) -> None:
        for seg in segments:
            new = self._segments_of(seg.lo, seg.hi)
            self.index.replace(seg, new)

    def stats(self) -> dict[str, float]:
        """Sizes: entries, postings, segments, index bytes (mapped or in memory), file bytes on
        disk (database, its log and its index files)."""
        file_bytes = 0
        if self.path is not None:
            for suffix in ("", "-wal", "-entries"):
                f = Path(str(self.path) + suffix)
                if f.exists():
                    file_bytes += f.stat().st_size
            d = index_dir(self.path)
            if d.is_dir():
                file_bytes += sum(f.stat().st_size for f in d.glob("seg-*.sci"))
        index = self.index
        return {"entries": len(self), "live": int(self.ids().size), "postings": index.n_postings,
                "segments": len(index.segments), "index_bytes": index.nbytes, "file_bytes": file_bytes,
                "time": time.time()}


# ---------------------------------------------------------------------------- helpers
class _Held(NamedTuple):
    """An entry of a memory database as its SQLite row would give it back, unpacked."""

    timestamp: float
    bow: dict[str, np.ndarray]
    payload: dict[str, np.ndarray]
    meta: str


def _frozen(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Read-only contiguous copies, as unpacking a stored blob gives (the caller may reuse its
    arrays)."""
    # each copy is handed out as a view of a read-only array, so it cannot be made writable
    # again, as a blob's arrays cannot (0-d arrays come back 1-d, as packing gives them); one
    # copy, not the two of bytes and back (bench_scale.py, adds: about 20 us an entry less)
    out = {}
    for name, a in arrays.items():
        c = np.array(a.reshape(a.shape or (1,)), order="C", copy=True)  # owns its data
        c.flags.writeable = False
        out[name] = c.view()
    return out


def _bow_words(arrays: dict[str, np.ndarray], eid: int, where: str, n_words: int) -> np.ndarray:
    words, weights = arrays.get("words"), arrays.get("weights")
    if (words is None or weights is None or words.ndim != 1 or words.shape != weights.shape
            or words.dtype.kind not in "iu" or weights.dtype.kind != "f"):
        raise DatabaseError(f"{where}: entry {eid}: stored BoW vector is malformed")
    w = words.astype(np.int32, copy=False)
    if w.size and (int(w.min()) < 0 or int(w.max()) >= n_words or bool(np.any(w[1:] <= w[:-1]))):
        raise DatabaseError(f"{where}: entry {eid}: stored BoW words are not sorted ids below {n_words}")
    return w


def _features(p: dict[str, np.ndarray], what: str) -> tuple[Features, np.ndarray]:
    try:
        nodes = np.asarray(p["fvec"], np.int32)
        size = tuple(int(x) for x in p["image_size"])
        if nodes.ndim != 1 or len(size) != 2:
            raise ValueError("bad direct index or image size")
        descriptors = _stored_descriptors(p, what)
        if descriptors is not None:
            feats = Features(p["keypoints"], descriptors, p["octaves"], p["angles"],
                             p["responses"], p["sizes"], (size[0], size[1]))
        else:
            feats = Features.empty((size[0], size[1]))
    except (KeyError, ValueError, TypeError) as exc:
        raise DatabaseError(f"{what}: stored features are malformed ({str(exc)[:80]})") from None
    n = int(nodes.shape[0])
    if n and len(feats) and len(feats) != n:
        raise DatabaseError(f"{what}: {len(feats)} features but {n} direct-index nodes")
    return feats, nodes


def _quantised(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, D) float32 descriptors as ``q`` (N, D) int8 in -127..127 and ``scale`` (1,) float32
    with ``q * scale`` within ``scale / 2`` of ``d``: ``scale = max|d| / 127`` over the
    entry, 0 when every value is 0 (no descriptors included)."""
    top = float(np.abs(d).max()) if d.size else 0.0
    if not math.isfinite(top):
        raise InputError("descriptors: int8 storage needs finite values (NaN or inf found)")
    scale = np.float32(top / 127)
    if top > 0 and scale == 0:  # below float32's range: the smallest step there is
        scale = np.finfo(np.float32).smallest_subnormal
    if scale == 0:
        return np.zeros(d.shape, np.int8), np.zeros(1, np.float32)
    q = np.clip(np.rint(d / np.float64(scale)), -127, 127).astype(np.int8)
    return q, np.array([scale], np.float32)


def _stored_descriptors(p: dict[str, np.ndarray], what: str) -> np.ndarray | None:
    """A payload's descriptors: as stored ("descriptors"), dequantised to float32 (int8
    "qdescriptors" times "qscale"), or None when the entry keeps none."""
    if "qdescriptors" not in p and "qscale" not in p:
        return p.get("descriptors")
    q, s = p.get("qdescriptors"), p.get("qscale")
    if "descriptors" in p or q is None or s is None:
        found = ", ".join(k for k in ("descriptors", "qdescriptors", "qscale") if k in p)
        raise DatabaseError(f"{what}: stored descriptors are malformed (found {found}; expected "
                            "descriptors, or qdescriptors with qscale)")
    if q.dtype != np.int8 or q.ndim != 2 or q.shape[1] < 1:
        raise DatabaseError(f"{what}: stored qdescriptors are {q.dtype} of shape {q.shape}, "
                            "expected int8 (N, D) with D >= 1")
    if s.dtype != np.float32 or s.shape != (1,):
        raise DatabaseError(f"{what}: stored qscale is {s.dtype} of shape {s.shape}, expected float32 (1,)")
    scale = s[0]
    if not (math.isfinite(scale) and (scale > 0 or (scale == 0 and not q.any()))):
        raise DatabaseError(f"{what}: stored qscale is {float(scale)!r}, expected a finite positive "
                            "number (0 only when every qdescriptor is 0)")
    if q.size and int(q.min()) < -127:
        raise DatabaseError(f"{what}: stored qdescriptors hold -128, outside -127..127")
    out = q.astype(np.float32) * scale
    out.flags.writeable = False  # read-only, as stored arrays are
    return out


def _extras(p: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The extra arrays of an unpacked payload (``add(arrays=...)``), by their own names."""
    return {k[2:]: v for k, v in p.items() if k.startswith("x_")}


def _optional(p: dict[str, np.ndarray], name: str, shape: tuple[int, int], what: str) -> np.ndarray | None:
    a = p.get(name)
    if a is not None and a.shape != shape:
        raise DatabaseError(f"{what}: stored {name} has shape {a.shape}, expected {shape}")
    return a


def _load_segments(
    sql: Sql, schema: Schema, n_words: int, lo: int, hi: int, held: dict[int, _Held] | None = None
) -> list[Segment]:
    """In-memory segments of entries ``lo .. hi - 1`` read from the entries' BoW vectors
    (what the index files would hold), one per block of entries; a memory database's vectors
    come from ``held`` (removed entries: none there, an empty vector)."""
    out: list[Segment] = []
    damaged: list[str] = []
    for a in range(lo, hi, _LOAD_BLOCK):
        b = min(a + _LOAD_BLOCK, hi)
        rows = sql.rows(f"SELECT id, bow, {schema.session_sql} FROM entries WHERE id >= ? AND id < ? "
                        "ORDER BY id", (a, b))
        words_l, post_l, sessions = [], [], np.zeros(b - a, np.int32)
        for k, (eid, blob, session) in enumerate(rows):
            if eid != a + k:
                raise DatabaseError(f"{sql.where}: entry ids are not contiguous at id {a + k}")
            if held is not None:
                h = held.get(eid)
                arrays = h.bow if h is not None else _EMPTY_BOW_ARRAYS
            else:
                try:
                    arrays = unpack_arrays(blob, f"entry {eid}")
                    _bow_words(arrays, eid, sql.where, n_words)
                except DatabaseError as exc:  # one damaged vector must not lock the map away
                    damaged.append(str(exc).removeprefix(f"{sql.where}: "))
                    arrays = _EMPTY_BOW_ARRAYS
            words = _bow_words(arrays, eid, sql.where, n_words)
            words_l.append(words)
            post_l.append(pack_postings(np.full(words.shape[0], eid, np.int32), arrays["weights"]))
            s = int_value(session, sql.where, eid, "session")
            if not 0 <= s <= MAX_SESSION:
                raise DatabaseError(f"{sql.where}: entry {eid}: session {s} outside 0..{MAX_SESSION}")
            sessions[k] = s
        if len(rows) != b - a:
            raise DatabaseError(f"{sql.where}: entry ids are not contiguous at id {a + len(rows)}")
        words = np.concatenate(words_l) if words_l else np.zeros(0, np.int32)
        post = np.concatenate(post_l) if post_l else empty_postings()
        out.append(sort_block(words, post, a, b, sessions, n_words))
    if damaged:
        log.warning("%s: %d entr%s with a corrupt BoW vector left out of every query (%s%s); the "
                    "rest of the map is intact: remove them (Database.remove) or restore the file",
                    sql.where, len(damaged), "y" if len(damaged) == 1 else "ies", "; ".join(damaged[:3]),
                    "; ..." if len(damaged) > 3 else "")
    return out


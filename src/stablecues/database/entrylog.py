"""Write-behind for a map file: an add is durable once it is appended to the entry log, and
SQLite is filled from a thread of its own.

Why: SQLite syncs its write-ahead log's header in whichever connection writes first after the
log starts over (``synchronous=NORMAL`` included; SQLite ticket ff5be73dee), about every 8
back-to-back adds once the log-copying thread keeps the log drained. On a virtual disk such a
sync waits for every block the filesystem has still to allocate (segment files being written),
and single adds of large maps stalled for 50-225 ms inside the INSERT. An append to a file of
our own never syncs (``durability="normal"``), so the adding thread never waits for the disk.

``map.sqlite-entries`` (the *entry log*): a 32-byte header (magic, the database's uuid), then
one record per add::

    b"SCE1" | u32 body length | u32 CRC-32 of the body | body
    body = i64 id | f64 timestamp | i64 n_features | i64 session
           | u32 len(bow) | u32 len(payload) | u32 len(meta) | bow | payload | meta (UTF-8)

Records are written in id order from the end of the header; once every entry in the log is in
SQLite the next record is written at the header again (no truncation, no sync), so stale records
may follow the live ones. Reading back (at open, by the next writer) takes records in order and
skips those whose id SQLite already holds: stale records always carry smaller ids than live ones.
A record that is damaged (a flipped byte, a wrong length) does not end the reading: the rest of
the file is searched for the next intact record (its magic, a CRC that holds) with a later id,
every intact record is recovered, and the ids in between are kept as removed entries with a
warning naming them. With no later record behind it, a bad record is the torn last one.

A process killed at any point loses at most the entry whose record was being written (a torn
record fails its CRC, and nothing follows it but stale records); the entries in the log are put
into SQLite before the index is loaded, so index and entries agree as before. Manifests (the
index's list of segment files) go through the same queue after the entries they cover, and
replaced segment files are deleted only after the manifest that drops them is committed.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import mmap
import os
import sqlite3
import struct
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..errors import DatabaseError
from .packing import pack_arrays
from .schema import MAX_SESSION, Sql

log = logging.getLogger(__name__)

LOG_SUFFIX = "-entries"
_MAGIC = b"STABLECUES-ELOG\x01"
HEADER_SIZE = len(_MAGIC) + 16
_REC = struct.Struct("<4sII")
_REC_MAGIC = b"SCE1"
_BODY = struct.Struct("<qdqqIII")
_MAX_RECORD = 1 << 31  # a record longer than this is not one this code wrote
_WINDOW = 16 << 20  # bytes searched for a record's magic at a time after damage
_SEEK_DATA: int | None = getattr(os, "SEEK_DATA", None)
#: entries and bytes per SQLite transaction at most: larger ones grow SQLite's log past its
#: 2 MB backstop (16 MB batches left a 16 MB log), smaller ones commit (and sync) more often
_BATCH_ENTRIES = 64
_BATCH_BYTES = 1 << 20
#: the adding thread waits for SQLite when this much is waiting for it (a disk far slower
#: than the adds): the entries waiting are held in memory as well as in the log
MAX_BEHIND_BYTES = 256 << 20

INSERT_ENTRY = ("INSERT INTO entries (id, timestamp, n_features, bow, payload, meta, session) "
           "VALUES (?, ?, ?, ?, ?, ?, ?)")
INSERT_REMOVED = ("INSERT INTO entries (id, timestamp, n_features, bow, payload, meta, session, removed) "
                  "VALUES (?, ?, ?, ?, ?, ?, ?, 1)")
#: a removed entry's blobs: no words, no features
EMPTY_BOW = pack_arrays({"words": np.zeros(0, np.int32), "weights": np.zeros(0, np.float32)})
EMPTY_PAYLOAD = pack_arrays({"fvec": np.zeros(0, np.int32), "image_size": np.zeros(2, np.int32)})


def log_path(db_path: Path) -> Path:
    """The entry log of a database file."""
    return Path(str(db_path) + LOG_SUFFIX)


class Row(NamedTuple):
    """One entry as its SQLite row holds it."""

    id: int
    timestamp: float
    n_features: int
    bow: bytes | bytearray
    payload: bytes | bytearray
    meta: str
    session: int

    @property
    def nbytes(self) -> int:
        return len(self.bow) + len(self.payload) + len(self.meta)


def record_parts(row: Row) -> list[bytes | bytearray]:
    """One record as the pieces written with one ``pwritev`` (no joined copy of the blobs)."""
    meta = row.meta.encode()
    fixed = _BODY.pack(row.id, row.timestamp, row.n_features, row.session, len(row.bow),
                       len(row.payload), len(meta))
    crc = zlib.crc32(meta, zlib.crc32(row.payload, zlib.crc32(row.bow, zlib.crc32(fixed))))
    length = len(fixed) + len(row.bow) + len(row.payload) + len(meta)
    return [_REC.pack(_REC_MAGIC, length, crc) + fixed, row.bow, row.payload, meta]


def encode(row: Row) -> bytes:
    """One record as bytes."""
    return b"".join(record_parts(row))


class LogContents(NamedTuple):
    """What :func:`read_log` found: the intact records from the first id asked on, the ids lost
    to damaged records between them (the map keeps them as removed entries), and a note on the
    damage for a warning (None: none)."""

    rows: list[Row]
    lost: list[int]
    note: str | None


def _record_at(data: mmap.mmap, view: memoryview, pos: int) -> tuple[Row, int] | str | None:
    """The record at ``pos``: (its row, the offset after it); a string naming what is wrong
    with a record whose CRC holds but whose contents do not (not one this code wrote); None
    where there is no intact record (torn, damaged, stale bytes or the end)."""
    if pos + _REC.size > len(data):
        return None
    _, length, crc = _REC.unpack_from(data, pos)
    room = min(_MAX_RECORD, len(data) - pos - _REC.size)
    if length < _BODY.size or length > room:
        return None
    body = view[pos + _REC.size: pos + _REC.size + length]
    if zlib.crc32(body) != crc:  # the CRC decides, not the magic: a damaged magic loses nothing
        if length > _WINDOW:  # a garbage length: the pages read for its CRC are let go
            _let_go(data, pos, pos + _REC.size + length)
        return None
    eid, ts, n, session, lb, lp, lm = _BODY.unpack_from(body)
    if _BODY.size + lb + lp + lm != length:
        return f"record of entry {eid} has inconsistent lengths"
    if n < 0 or not 0 <= session <= MAX_SESSION or eid < 0:
        return f"record of entry {eid} has a bad id, feature count or session"
    a = _BODY.size
    try:
        meta = bytes(body[a + lb + lp: a + lb + lp + lm]).decode()
    except UnicodeDecodeError:
        return f"record of entry {eid} has metadata that is not UTF-8"
    row = Row(eid, ts, n, bytes(body[a: a + lb]), bytes(body[a + lb: a + lb + lp]), meta, session)
    return row, pos + _REC.size + length


def _next_record(
    data: mmap.mmap, view: memoryview, pos: int, expected: int, fd: int
) -> tuple[Row, int] | None:
    """The first intact record from ``pos`` on that carries ``expected`` or a later id (a live
    record after damage), skipping stale ones: their ids are always smaller. Holes of a sparse
    file are skipped (``SEEK_DATA``) and the pages searched are let go a window at a time, so a
    huge or sparse log costs neither memory nor time for what it does not hold."""
    while pos < len(data):
        if _SEEK_DATA is not None:
            try:
                pos = os.lseek(fd, pos, _SEEK_DATA)  # the next byte that is not in a hole
            except OSError as exc:
                if exc.errno == errno.ENXIO:
                    return None  # nothing but holes after pos
                # a file system that cannot tell holes: search every byte
        end = min(pos + _WINDOW, len(data))
        hit = data.find(_REC_MAGIC, pos, min(end + len(_REC_MAGIC) - 1, len(data)))
        if hit < 0:
            _let_go(data, pos, end)
            pos = end
            continue
        found = _record_at(data, view, hit)
        if isinstance(found, tuple) and found[0].id >= expected:
            return found
        pos = hit + 1
    return None


def _let_go(data: mmap.mmap, start: int, end: int) -> None:
    """Drop the mapped pages of ``[start, end)`` from this process (they stay in the page cache)."""
    first = start - start % mmap.PAGESIZE
    with contextlib.suppress(AttributeError, OSError, ValueError):
        data.madvise(mmap.MADV_DONTNEED, first, end - first)


def _scan(
    path: Path, data: mmap.mmap, fd: int, uuid: bytes, first_id: int
) -> tuple[list[Row], list[int], list[str], str | None]:
    """:func:`read_log`'s walk over the mapped file: (rows, lost ids, damage notes, a note on
    a torn or damaged last record)."""
    if data[: len(_MAGIC)] != _MAGIC:
        raise DatabaseError(f"{path}: not a stablecues entry log (bad header)")
    if data[len(_MAGIC):HEADER_SIZE] != uuid:
        raise DatabaseError(f"{path}: entry log of another database (its id differs)")
    rows: list[Row] = []
    lost: list[int] = []
    damage: list[str] = []
    last = None
    pos, expected = HEADER_SIZE, first_id
    view = memoryview(data)
    try:
        while pos < len(data):
            found = _record_at(data, view, pos)
            if not isinstance(found, tuple):
                nxt = _next_record(data, view, pos + 1, expected, fd)
                if nxt is None:  # the end of what was written last (a torn record, stale bytes)
                    if pos + _REC.size + 8 <= len(data) and int.from_bytes(
                            data[pos + _REC.size: pos + _REC.size + 8], "little", signed=True) == expected:
                        last = (f"the last record (entry {expected}) is torn or damaged and not recovered "
                                "(a kill while it was written, never acknowledged, or damage)")
                    break
                damage.append(found or f"damaged record at byte {pos}")
                found = nxt
            row, end = found
            if row.id < expected:  # already in the database (or a stale record)
                pos = end
                continue
            if row.id > expected:  # records lost to damage before this one
                lost.extend(range(expected, row.id))
            rows.append(row)
            expected, pos = row.id + 1, end
    finally:
        view.release()
    return rows, lost, damage, last


def read_log(path: Path, uuid: bytes, first_id: int) -> LogContents:
    """The records of ``path`` from id ``first_id`` on, in order.

    A record that is damaged (its CRC fails, its length or magic is wrong, its contents are not
    ones this code writes) does not end the reading: the rest of the file is searched for the
    next intact record with a later id (records are framed by a magic and a CRC, and stale
    records carry smaller ids than live ones), so every intact record after the damage is
    recovered and only the ids in between are lost. Where no later record follows, what was
    there is the torn last record or the stale bytes behind the live ones: nothing is lost.
    """
    try:
        with path.open("rb") as fh:
            if os.fstat(fh.fileno()).st_size < HEADER_SIZE:
                raise DatabaseError(f"{path}: not a stablecues entry log (bad header)")
            # mapped, not read: a sparse or huge file costs no memory until a record is taken
            with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
                rows, lost, damage, last = _scan(path, data, fh.fileno(), uuid, first_id)
    except OSError as exc:
        raise DatabaseError(f"{path}: cannot read the entry log ({exc.strerror or exc})") from None
    note = None
    if lost:
        shown = ", ".join(map(str, lost[:10])) + (", ..." if len(lost) > 10 else "")
        note = (f"{len(lost)} entr{'y' if len(lost) == 1 else 'ies'} lost to damaged records "
                f"(ids {shown}; kept as removed entries); {damage[0]}; the {len(rows)} intact "
                "records around them recovered")
    if last is not None:
        note = last if note is None else f"{note}; {last}"
    return LogContents(rows, lost, note)


class _Call(NamedTuple):
    fn: Callable[[], None]


class _Manifest(NamedTuple):
    text: str


class EntryWriter:
    """Appends entries to the entry log and puts them (and index manifests) into SQLite from
    a thread of its own, in the order they came.

    Args:
        path: the entry log (created; an existing one must have been read back first).
        uuid: the database's id.
        sql: the writer's connection.
        fsync: sync every record (``durability="full"``).
        committed: called with the bytes of every transaction committed (wakes the log
            copier).
    """

    def __init__(self, path: Path, uuid: bytes, sql: Sql, fsync: bool,
                 committed: Callable[[int], None] | None = None) -> None:
        self.path = path
        self.sql = sql
        self.fsync = fsync
        self._committed = committed
        try:
            self.fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except OSError as exc:
            raise DatabaseError(f"{path}: cannot open the entry log ({exc.strerror or exc})") from exc
        try:
            self._write_all(_MAGIC + uuid, 0)
            if fsync:
                os.fsync(self.fd)
        except DatabaseError:
            os.close(self.fd)
            raise
        self._offset = HEADER_SIZE
        self._cond = threading.Condition()
        self._queue: deque[Row | _Manifest | _Call] = deque()
        self._pending: dict[int, Row] = {}
        self._behind = 0  # bytes of pending entries
        self._busy = False
        self._stop = False
        self.error: DatabaseError | None = None
        self._thread = threading.Thread(target=self._run, name="stablecues-entries", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the adding side
    def _write_all(self, data: bytes, offset: int) -> None:
        view = memoryview(data)
        try:
            while view:
                n = os.pwrite(self.fd, view, offset)
                view, offset = view[n:], offset + n
        except OSError as exc:
            raise DatabaseError(f"{self.path}: cannot write the entry log ({exc.strerror or exc})") from exc

    def _write_parts(self, parts: list[bytes | bytearray], offset: int) -> int:
        """Write a record's pieces at ``offset``; returns its length."""
        total = sum(len(p) for p in parts)
        pwritev = getattr(os, "pwritev", None)
        if pwritev is None:
            self._write_all(b"".join(parts), offset)
            return total
        try:
            n = pwritev(self.fd, parts, offset)
        except OSError as exc:
            raise DatabaseError(f"{self.path}: cannot write the entry log ({exc.strerror or exc})") from exc
        if n < total:  # a short write (a full disk, a signal): the rest as one piece
            self._write_all(b"".join(parts)[n:], offset + n)
        return total

    def _check(self) -> None:
        if self.error is not None:
            raise self.error
        if self._stop:
            raise DatabaseError(f"{self.path}: entry log is closed")

    def add(self, row: Row) -> None:
        """Append one entry to the log (durable when this returns) and queue it for SQLite."""
        parts = record_parts(row)
        with self._cond:
            self._check()
            while self._behind > MAX_BEHIND_BYTES and self.error is None:
                self._cond.wait(0.1)
            self._check()
            size = self._write_parts(parts, self._offset)
            if self.fsync:
                os.fdatasync(self.fd)
            self._offset += size
            self._pending[row.id] = row
            self._behind += row.nbytes
            self._queue.append(row)
            self._cond.notify_all()

    def save_manifest(self, text: str) -> None:
        """Queue the index manifest; it is committed after every entry queued before it."""
        with self._cond:
            self._check()
            self._queue.append(_Manifest(text))
            self._cond.notify_all()

    def after_commit(self, fn: Callable[[], None]) -> bool:
        """Run ``fn`` (in the writer thread) once everything queued so far is committed;
        False (and never run) when the writer has stopped."""
        with self._cond:
            if self.error is not None or self._stop:
                return False  # what it would delete may still be named on disk
            self._queue.append(_Call(fn))
            self._cond.notify_all()
            return True

    def pending(self, eid: int) -> Row | None:
        """Entry ``eid`` when it is not in SQLite yet."""
        with self._cond:
            return self._pending.get(eid)

    def drain(self) -> None:
        """Wait until everything queued so far is in SQLite."""
        if threading.current_thread() is self._thread:
            return
        with self._cond:
            while (self._queue or self._busy) and self.error is None and self._thread.is_alive():
                self._cond.wait(0.1)
            if self.error is not None:
                raise self.error

    def close(self) -> None:
        """Put what is queued into SQLite and stop."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join()
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = -1

    def remove_log(self) -> None:
        """Delete the log when everything in it is in SQLite."""
        if self.error is None and not self._pending:
            with contextlib.suppress(OSError):
                self.path.unlink()

    # ------------------------------------------------------------------ the writer thread
    def _take(self) -> tuple[list[Row | _Manifest], _Call | None]:
        batch: list[Row | _Manifest] = []
        size = 0
        while self._queue and len(batch) < _BATCH_ENTRIES and size < _BATCH_BYTES:
            item = self._queue[0]
            if isinstance(item, _Call):
                if not batch:
                    self._queue.popleft()
                    return batch, item
                break
            self._queue.popleft()
            batch.append(item)
            size += item.nbytes if isinstance(item, Row) else len(item.text)
        return batch, None

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    self._cond.wait()
                if not self._queue:
                    break
                batch, call = self._take()
                self._busy = True
            try:
                if call is not None:
                    call.fn()
                else:
                    nbytes = self._commit(batch)
                    if self._committed is not None:
                        self._committed(nbytes)
            except Exception as exc:  # kept for the adding thread; the log keeps the entries
                what = exc if isinstance(exc, DatabaseError) else DatabaseError(
                    f"{self.sql.where}: cannot add entries ({exc}); they stay in {self.path} and are "
                    "written when the map is opened again")
                with self._cond:
                    self.error = what
                    self._busy = False
                    self._cond.notify_all()
                log.error("%s", what)
                return
            with self._cond:
                for item in batch:
                    if isinstance(item, Row):
                        self._pending.pop(item.id, None)
                        self._behind -= item.nbytes
                if not self._pending:
                    self._offset = HEADER_SIZE  # everything in the log is in SQLite
                self._busy = False
                self._cond.notify_all()

    def _commit(self, batch: list[Row | _Manifest]) -> int:
        rows = [r for r in batch if isinstance(r, Row)]
        manifests = [m for m in batch if isinstance(m, _Manifest)]
        try:  # a reader's lock is waited for by the connection's busy timeout
            with self.sql.write() as conn:
                if rows:
                    conn.executemany(INSERT_ENTRY, [tuple(r) for r in rows])
                if manifests:  # the last one queued is the one that counts
                    conn.execute("INSERT OR REPLACE INTO meta VALUES ('index', ?)", (manifests[-1].text,))
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{self.sql.where}: cannot add entries {rows[0].id if rows else ''}.. "
                                f"({exc}); they stay in {self.path} and are written when the map is "
                                "opened again") from exc
        return sum(r.nbytes for r in rows)


def replay(path: Path, uuid: bytes, sql: Sql, first_id: int) -> int:
    """Put the entries of an existing log from id ``first_id`` on into SQLite (a writer that
    was killed left them there); returns how many. A log that is not this database's is moved
    aside, with a warning, and nothing is read from it."""
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise DatabaseError(f"{path}: exists and is not an entry log (a link or not a file)")
    if not path.exists():
        return 0
    try:
        contents = read_log(path, uuid, first_id)
    except DatabaseError as exc:
        aside = path.with_name(path.name + f".unread-{int(time.time())}")
        try:
            path.rename(aside)
        except OSError as err:
            raise DatabaseError(f"{exc}; cannot move it aside ({err.strerror or err})") from exc
        log.warning("%s: moved to %s, nothing read from it", exc, aside.name)
        return 0
    if contents.note:
        log.warning("%s: %s", path, contents.note)
    rows = contents.rows
    if rows or contents.lost:
        holes = _holes(rows, contents.lost)
        try:
            with sql.write() as conn:
                conn.executemany(INSERT_ENTRY, [tuple(r) for r in rows])
                conn.executemany(INSERT_REMOVED, holes)
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{path}: cannot put its {len(rows)} entries into the database "
                                f"({exc})") from exc
        log.info("%s: %d entries put into the database", path, len(rows))
    return len(rows) + len(contents.lost)


def _holes(rows: list[Row], lost: list[int]) -> list[tuple[Any, ...]]:
    """SQL values of the lost ids as removed entries, each with the timestamp and session of the
    record before it (after it for the first), so that time order and sessions stay."""
    out = []
    for eid in lost:
        before = [r for r in rows if r.id < eid]
        near = before[-1] if before else next((r for r in rows if r.id > eid), None)
        ts, session = (near.timestamp, near.session) if near is not None else (0.0, 0)
        out.append((eid, ts, 0, EMPTY_BOW, EMPTY_PAYLOAD, "null", session))
    return out


def row_values(row: Row, columns: str) -> tuple[Any, ...]:
    """A pending entry's values of SQL ``columns`` ("timestamp, bow, ..."), as a row gives them."""
    values = row._asdict()
    # read-only bytes, as SQLite gives a blob back (unpacked arrays are then read-only too)
    return tuple(bytes(v) if isinstance(v, bytearray) else v
                 for v in (values[c.strip()] for c in columns.split(",")))

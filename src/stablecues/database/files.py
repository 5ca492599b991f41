"""The index directory next to a database file: segment files, the writer lock, the manifest.

``map.sqlite`` keeps its inverse index in ``map.sqlite-index/``: one file per segment
(``seg-00000042.sci``, see :mod:`.segments`) and ``writer.lock``. Which files make up the
index is recorded in the database itself (the ``index`` row of its ``meta`` table, the
*manifest*), so a change of segments is one SQLite transaction:

1. a job writes its new segment file completely (and, with ``durability="full"``, syncs it
   and the directory);
2. one transaction replaces the manifest;
3. the files it no longer names are deleted.

A process killed anywhere in between leaves either the old manifest with an unused new file
or the new manifest with unused old files; the next writer deletes the files the manifest
does not name. Entries the manifest does not cover (the latest additions, or a segment file
that is missing or corrupt) are read back from the database's entries when it is opened.
Only files named like segments are ever deleted, and only inside the index directory.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import re
import sqlite3
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import DatabaseError
from .segments import ChunkReader, FileSink, Segment, SegmentReplaced, SegmentWriter, map_segment

log = logging.getLogger(__name__)

INDEX_SUFFIX = "-index"
MANIFEST_VERSION = 1
_SEGMENT_NAME = re.compile(r"seg-(\d{8,12})\.sci")
_MAX_SEGMENTS = 4096  # a manifest naming more is not one this code wrote


def index_dir(db_path: Path) -> Path:
    """The index directory of a database file."""
    return Path(str(db_path) + INDEX_SUFFIX)


def stored_segments(db_path: Path) -> list[str]:
    """The segment files in a database file's index directory (names, sorted; [] without one)."""
    d = index_dir(db_path)
    if not d.is_dir() or d.is_symlink():
        return []
    with contextlib.suppress(OSError):
        return sorted(f.name for f in d.iterdir() if _SEGMENT_NAME.fullmatch(f.name))
    return []


def remove_database(db_path: str | Path) -> None:
    """Delete a database file, its SQLite side files and its index directory (only the files
    stablecues writes there)."""
    path = Path(db_path)
    for suffix in ("", "-wal", "-shm", "-journal", "-entries", ".words", ".words.tmp"):
        Path(str(path) + suffix).unlink(missing_ok=True)
    d = index_dir(path)
    if d.is_dir() and not d.is_symlink():
        for f in d.iterdir():
            if _SEGMENT_NAME.fullmatch(f.name) or f.name in ("writer.lock",) or f.name.endswith(".tmp"):
                f.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            d.rmdir()


@dataclass
class SegmentRecord:
    file: str
    lo: int
    hi: int
    postings: int
    crc: int


@dataclass
class Manifest:
    """Which segment files make up the index, in entry order."""

    next_gen: int = 0
    segments: list[SegmentRecord] = field(default_factory=list)

    def dumps(self) -> str:
        return json.dumps({"version": MANIFEST_VERSION, "next_gen": self.next_gen,
                           "segments": [[s.file, s.lo, s.hi, s.postings, s.crc] for s in self.segments]},
                          separators=(",", ":"))

    @staticmethod
    def parse(text: str | None, where: str) -> Manifest:
        """Read a manifest; one that does not parse or validate is treated as empty (the
        index is then rebuilt from the entries), with a warning."""
        if text is None:
            return Manifest()
        try:
            return Manifest._parse(text)
        except (ValueError, TypeError, KeyError, RecursionError) as exc:
            log.warning("%s: index manifest is corrupt (%s); rebuilding the index from the entries",
                        where, exc)
            return Manifest()

    @staticmethod
    def _parse(text: str) -> Manifest:
        if len(text) > 64 * _MAX_SEGMENTS:
            raise ValueError("manifest too long")
        data = json.loads(text)
        if not isinstance(data, dict) or data.get("version") != MANIFEST_VERSION:
            raise ValueError("unknown manifest version")
        gen = data["next_gen"]
        rows = data["segments"]
        if not isinstance(gen, int) or not 0 <= gen < 10**12 or not isinstance(rows, list):
            raise ValueError("bad fields")
        if len(rows) > _MAX_SEGMENTS:
            raise ValueError(f"{len(rows)} segments")
        out = Manifest(gen)
        pos = 0
        for row in rows:
            if not (isinstance(row, list) and len(row) == 5 and isinstance(row[0], str)
                    and all(isinstance(x, int) and not isinstance(x, bool) for x in row[1:])):
                raise ValueError(f"bad segment record {row!r:.80}")
            name, lo, hi, postings, crc = row
            if not _SEGMENT_NAME.fullmatch(name):
                raise ValueError(f"bad segment file name {name!r:.80}")
            if not (pos <= lo <= hi < 2**31 and 0 <= postings < 2**40 and 0 <= crc < 2**32):
                raise ValueError(f"bad segment range {lo}..{hi}")
            pos = hi
            out.segments.append(SegmentRecord(name, lo, hi, postings, crc))
        return out


class WriterLock:
    """An exclusive lock on the index directory, held by the one writing Database object."""

    def __init__(self, directory: Path) -> None:
        self.fd = os.open(directory / "writer.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self.fd)
            raise

    def release(self) -> None:
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = -1


def _unlink(paths: list[Path], segments: list[Segment] | None = None, step: int = 64 << 20) -> None:
    """Delete files, a large one a slice at a time: freeing gigabytes at once (and, on a disk
    mounted with ``discard``, trimming them) makes every sync on the disk wait meanwhile.
    ``segments``: the replaced segments themselves, let go here first, so that unmapping a
    large file (tearing down the page tables of gigabytes) happens in this thread, not in the
    one that replaced them: in an instrumented 10^6 build, steps that replaced segments took
    13-28 ms, 2-6 ms of it CPU, outside every part that was timed, where the last references
    to the replaced segments were dropped.

    A file is shortened only while this thread holds its ``flock`` exclusively: every mapping
    of a segment file holds it shared (:func:`.segments.map_segment`), and a query still
    running on the replaced segments, here or in a reader process, would be killed by SIGBUS
    at the next page it reads past the new end. A file still mapped is only unlinked (the
    kernel frees it when the last mapping goes); the lock, held until it is unlinked, also
    keeps a reader from mapping it meanwhile."""
    if segments is not None:
        segments.clear()
    for path in paths:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_NOFOLLOW)
        except OSError:
            with contextlib.suppress(OSError):
                path.unlink()
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                size = os.fstat(fd).st_size
            except OSError:
                size = 0  # mapped somewhere: deleted, not shortened
            with contextlib.suppress(OSError):
                while size > step:
                    size -= step
                    os.ftruncate(fd, size)
                    time.sleep(0.002)
            with contextlib.suppress(OSError):
                path.unlink()
        finally:
            os.close(fd)


class IndexFiles:
    """Segment files of one database (the inverse index's store).

    Args:
        directory: the index directory (exists).
        uuid: the database's 16-byte id, written into every segment file.
        n_words: vocabulary size.
        fsync: sync files and the directory before a manifest names them.
        save_manifest: writes the manifest into the database (one transaction).
        rebuild: segments of entries ``lo .. hi - 1`` built from the database's entries.
        next_gen: first free file number.
        after_commit: runs a function once the manifests saved so far are committed (a
            manifest saved behind the adds); False when it never will (default: at once).
    """

    def __init__(
        self, directory: Path, uuid: bytes, n_words: int, fsync: bool,
        save_manifest: Callable[[str], None], rebuild: Callable[[int, int], list[Segment]],
        next_gen: int, after_commit: Callable[[Callable[[], None]], bool] | None = None,
    ) -> None:
        self.directory = directory
        self.uuid = uuid
        self.n_words = n_words
        self.fsync = fsync
        self._save = save_manifest
        self._rebuild = rebuild
        self.next_gen = next_gen
        self._after_commit = after_commit
        self.writer = SegmentWriter()  # the files' writes, off the thread that runs the steps
        self.reader = ChunkReader()  # and the merges' reads, ahead of the steps
        self._discarding: list[threading.Thread] = []

    def sink(self, lo: int, hi: int, csr: bool, total: int) -> FileSink:
        path = self.directory / f"seg-{self.next_gen:08d}.sci"
        self.next_gen += 1
        return FileSink(path, self.uuid, lo, hi, csr, self.n_words, self.fsync, total, self.writer)

    def close(self) -> None:
        """Stop the files' reader and writer threads (after the index's jobs are stopped)."""
        self.reader.close()
        self.writer.close()

    def commit(self, segments: Sequence[Segment]) -> None:
        if self.fsync:
            fd = os.open(self.directory, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        records = [SegmentRecord(s.name, s.lo, s.hi, s.size, s.crc) for s in segments if s.name is not None]
        self._save(Manifest(self.next_gen, records).dumps())

    def discard(self, segments: Sequence[Segment]) -> None:
        """Delete replaced segment files, in a thread of its own: freeing a large file's blocks
        takes a while (a disk mounted with ``discard`` trims them first), and no add should
        wait for it. A file left by a process that ended meanwhile is deleted at the next open."""
        paths = [self.directory / s.name for s in segments
                 if s.name is not None and _SEGMENT_NAME.fullmatch(s.name)]
        if not paths:
            return
        thread = threading.Thread(target=_unlink, args=(paths, list(segments)), name="stablecues-discard",
                                  daemon=True)
        self._discarding = [t for t in self._discarding if t.is_alive() or not t.ident] + [thread]
        # only once the manifest that no longer names them is committed
        if self._after_commit is not None:
            if not self._after_commit(thread.start):  # never committed: the next open deletes them
                self._discarding.remove(thread)
        else:
            thread.start()

    def wait_discarded(self, timeout: float = 60.0) -> None:
        """Wait until the replaced files handed to :meth:`discard` so far are deleted (a
        compaction hands their space back before it returns)."""
        deadline = time.monotonic() + timeout
        for thread in list(self._discarding):
            while not thread.ident and time.monotonic() < deadline:  # not started yet
                time.sleep(0.001)
            if thread.ident:
                thread.join(max(deadline - time.monotonic(), 0.0))

    def rebuild(self, lo: int, hi: int) -> list[Segment]:
        return self._rebuild(lo, hi)

    def cleanup(self, keep: set[str]) -> None:
        """Delete segment files the manifest does not name (left by a killed process)."""
        for f in self.directory.iterdir():
            m = _SEGMENT_NAME.fullmatch(f.name)
            if m:
                self.next_gen = max(self.next_gen, int(m.group(1)) + 1)
            if (m and f.name not in keep) or (f.name.startswith("seg-") and f.name.endswith(".tmp")):
                with contextlib.suppress(OSError):
                    f.unlink()


class LogCheckpointer:
    """Copies the database's write-ahead log into the file from a thread of its own, so that
    no add waits for a checkpoint (SQLite's automatic one runs in the committing thread and
    syncs the file, stalling that add for as long as the disk takes).

    SQLite starts the log over only when a write begins after everything in it has been
    copied; with a writer that never pauses, that moment would never come and the log would
    grow. So the bulk is copied while the writer goes on, and the few pages added meanwhile
    (at most ``locked_pages``) are copied while ``lock`` holds the writer's next transaction
    back (the entry log's thread: adds themselves never take it).

    Args:
        db_path: the database file.
        lock: the lock every write on the writer's connection holds.
        synchronous: the writer's ``PRAGMA synchronous`` (the checkpoint syncs as it does).
        every_s: how often to look at the log.
        locked_pages: most log pages copied while adds wait.
        slow_s: no copying while the writer waits after a checkpoint that took this long.
        wake_bytes: :meth:`wrote` wakes the thread once this much was written since its last
            round, so that it keeps up with adds back to back (57-75 kB entries at 500 a
            second fill SQLite's backstop within one ``every_s``: the backstop then ran in
            the adding thread for most of the log, with its syncs, every ~10 adds).
    """

    def __init__(
        self, db_path: Path, lock: threading.RLock, synchronous: str, every_s: float = 0.05,
        locked_pages: int = 256, slow_s: float = 0.02, wake_bytes: int = 512 * 1024,
    ) -> None:
        self.uri = f"{db_path.resolve().as_uri()}?mode=rw"
        self.lock = lock
        self.synchronous = synchronous
        self.every_s = every_s
        self.locked_pages = locked_pages
        self.slow_s = slow_s
        self.wake_bytes = wake_bytes
        self._written = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stablecues-checkpoint", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            conn = sqlite3.connect(self.uri, uri=True, timeout=1.0, isolation_level=None,
                                   check_same_thread=False)
        except sqlite3.Error as exc:  # SQLite's own checkpoints carry on
            log.warning("log checkpoints stay in the adding thread: %s", exc)
            return
        try:
            conn.execute(f"PRAGMA synchronous={self.synchronous}")
            while True:
                self._wake.wait(self.every_s)
                if self._stop.is_set():
                    break
                self._wake.clear()
                self._written = 0
                self.checkpoint(conn)
        except sqlite3.Error as exc:
            log.warning("log checkpoints stay in the adding thread: %s", exc)
        finally:
            conn.close()

    def checkpoint(self, conn: sqlite3.Connection) -> tuple[int, int]:
        """One round; returns the log's pages and those copied."""
        frames = copied = 0
        took = 0.0
        for attempt in range(8):
            t = time.perf_counter()
            busy, frames, copied = conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
            took = time.perf_counter() - t
            if busy:  # the writer was committing: SQLite could not read the log's header
                time.sleep(0.002 * (attempt + 1))
                continue
            if frames - copied <= self.locked_pages:
                break
        # the last few pages while the writer waits, unless the disk is slow to sync just now
        # (the log then grows a little until a later round); also when all was copied: a
        # writer that began its transaction while this one copied does not start the log
        # over, and one that never pauses (the entry log's thread) would always have
        if frames > 0 and frames - copied <= self.locked_pages and took < self.slow_s:
            with self.lock:
                busy, frames, copied = conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
        return frames, copied

    def wrote(self, nbytes: int) -> None:
        """Called by the writer after a commit of about ``nbytes``: wakes the thread early
        when enough was written since its last round."""
        self._written += nbytes
        if self._written >= self.wake_bytes and not self._wake.is_set():
            self._wake.set()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=60)


def open_segments(
    directory: Path, manifest: Manifest, uuid: bytes, n_words: int, n_entries: int,
    reuse: dict[str, Segment] | None = None,
) -> tuple[list[Segment], bool]:
    """Map the manifest's segment files; a corrupt or mismatched file is left out (with a
    warning), and the entries it covered are then read from the database.

    Args:
        reuse: segments already mapped, by file name.

    Returns:
        the segments, and whether a file was missing (a writer may have replaced it since
        the manifest was read: read the manifest again).
    """
    out: list[Segment] = []
    missing = False
    for rec in manifest.segments:
        path = directory / rec.file
        old = (reuse or {}).get(rec.file)
        if old is not None and (old.lo, old.hi, old.size, old.crc) == (rec.lo, rec.hi, rec.postings, rec.crc):
            out.append(old)
            continue
        try:
            if rec.hi > n_entries:
                raise DatabaseError(f"{path}: covers entries up to {rec.hi - 1}, the database has "
                                    f"{n_entries}")
            if not path.is_file():
                missing = True
                raise DatabaseError(f"{path}: index file is missing")
            try:
                seg = map_segment(path, uuid, n_words)
            except SegmentReplaced:
                missing = True
                raise
            if (seg.lo, seg.hi, seg.size, seg.crc) != (rec.lo, rec.hi, rec.postings, rec.crc):
                raise DatabaseError(f"{path}: index file does not match the manifest")
        except DatabaseError as exc:
            log.warning("%s; its entries are read from the database instead", exc)
            continue
        out.append(seg)
    return out, missing

"""Segments of the inverse index: immutable runs of postings sorted by word.

A posting is one (entry id, weight) pair of 8 bytes (:data:`POSTING`), moved around as one
int64 (:func:`pack_postings`, :func:`split`: NumPy copies 8-byte items far faster than a
structured dtype). A segment holds the
postings of the entries ``lo .. hi - 1``, sorted by word and, within a word, by entry id, plus
the session id of every entry it covers. Small segments keep the word of every posting
(``words``, binary search per query word); large ones keep a CSR table instead (``indptr``,
one offset per word), so a query finds each word's run in O(1) and no word array is stored.

A segment lives in memory or in a file of the index directory, memory-mapped read-only:

=========  ==========================================================================
offset     content
=========  ==========================================================================
0          header, 128 bytes: ``b"SCIX"``, version, form (0 words, 1 CSR), database
           id (16 bytes), words in the vocabulary, lo, hi, postings, CRC-32 of the
           body, CRC-32 of the header fields
128        postings, (P,) little-endian (int32 entry, float32 weight)
..         words (P,) int32, or indptr (W + 1,) int64
..         sessions (hi - lo,) int32
=========  ==========================================================================

Every size follows from the header, and the file's length must match it exactly before
anything is mapped, so a hostile or truncated file is refused without allocating.
:class:`MergeJob` merges adjacent segments (and drops removed entries) one bounded step at a
time, so that no step of index maintenance stalls the thread that runs it.
"""

from __future__ import annotations

import contextlib
import fcntl
import mmap
import os
import struct
import threading
import weakref
import zlib
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol

import numpy as np
from numpy.typing import DTypeLike

from .._arrays import distinct
from ..engine import requested
from ..errors import DatabaseError
from ..vocabulary.engine import compiled_kernels, loaded_kernels, resolve

POSTING = np.dtype([("entry", "<i4"), ("weight", "<f4")])
SEGMENT_MAGIC = b"SCIX"
SEGMENT_VERSION = 1
HEADER_SIZE = 128
_HEADER = struct.Struct("<4sHBx16sQQQQI")  # magic .. body CRC; the header CRC follows
FORM_WORDS, FORM_CSR = 0, 1
CSR_MIN = 1 << 18  # segments with at least max(CSR_MIN, 2 * n_words) postings get a CSR table


def csr_threshold(n_words: int) -> int:
    """Postings from which a segment keeps a CSR table (its indptr then costs at most half
    of what its postings take)."""
    return max(CSR_MIN, 2 * int(n_words))


def split(postings64: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P,) int32 entry ids and (P,) float32 weights (strided views) of postings held as int64."""
    return postings64.view("<i4")[0::2], postings64.view("<f4")[1::2]


def gather_runs(
    p64: np.ndarray, lo: np.ndarray, hi: np.ndarray, values: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The postings ``p64[lo[i]:hi[i]]`` of every query word i, in word order, and the query
    weight of each (None when every run is empty)."""
    counts = hi - lo
    nz = np.flatnonzero(counts)
    if not nz.size:
        return None
    counts = counts[nz]
    lo = lo[nz]
    total = int(counts.sum())
    if nz.size * 32 < total:
        # long runs: copy each run whole
        got = np.concatenate([p64[a:b] for a, b in zip(lo.tolist(), (lo + counts).tolist(), strict=True)])
    else:
        # many short runs: one vectorised gather of every posting of every run
        starts = np.cumsum(counts) - counts
        got = p64[np.repeat(lo - starts, counts) + np.arange(total)]
    return got, np.repeat(values[nz], counts)


def empty_postings(n: int = 0) -> np.ndarray:
    return np.zeros(n, "<i8")


def pack_postings(entries: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(P,) postings (as int64) from (P,) entry ids and (P,) weights (rounded to float32)."""
    out = np.empty((entries.shape[0], 2), "<i4")
    out[:, 0] = entries
    out.view("<f4")[:, 1] = weights
    return out.view("<i8").reshape(-1)


@dataclass(eq=False)
class Segment:
    """Postings of entries ``lo .. hi - 1``, sorted by word (entry ids ascending within a word).

    Attributes:
        lo, hi: the entry ids covered.
        postings: (P,) postings as int64 (:func:`split` gives entry ids and weights).
        words: (P,) int32 sorted word of every posting (small segments), or None.
        indptr: (W + 1,) int64 offsets of every word's run (large segments), or None.
        sessions: (hi - lo,) int32 session id of every covered entry.
        name: file name in the index directory when the segment is persisted, else None.
        crc: CRC-32 of the file body (persisted segments).
        path: the file, for a persisted segment.
        verified: the file's body was checked against ``crc`` (or this process wrote it); an
            unverified one is checked before it first answers a query or is merged
            (:func:`ensure_verified`).
    """

    lo: int
    hi: int
    postings: np.ndarray
    words: np.ndarray | None
    indptr: np.ndarray | None
    sessions: np.ndarray
    name: str | None = None
    crc: int = 0
    path: Path | None = None
    verified: bool = False

    @property
    def size(self) -> int:
        return int(self.postings.shape[0])

    @property
    def nbytes(self) -> int:
        table = self.words if self.words is not None else self.indptr
        return int(self.postings.nbytes + (0 if table is None else table.nbytes) + self.sessions.nbytes)

    def runs(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M,) int64 start and end offsets of the runs of the sorted query words."""
        if self.indptr is not None:
            return self.indptr[words].astype(np.int64), self.indptr[words + 1].astype(np.int64)
        assert self.words is not None
        return (np.searchsorted(self.words, words, "left").astype(np.int64),
                np.searchsorted(self.words, words, "right").astype(np.int64))

    def gather(self, words: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Postings of the query words, and the query weight of each, in word order.

        Args:
            words: (M,) int32 sorted unique query words.
            values: (M,) float64 their query weights.

        Returns:
            (K,) postings as int64 (see :func:`split`) and (K,) float64 query weights, or
            None when no word is shared.
        """
        lo, hi = self.runs(words)
        return gather_runs(self.postings, lo, hi, values)

    def word_at(self, positions: np.ndarray) -> np.ndarray:
        """Word of the postings at the given offsets."""
        if self.indptr is not None:
            return np.searchsorted(self.indptr, positions, "right") - 1
        assert self.words is not None
        return self.words[positions].astype(np.int64)


def _pread(path: Path, offset: int, count: int, dtype: str = "<i8") -> np.ndarray:
    out = np.empty(count, dtype)
    view = out.data.cast("B")
    fd = os.open(path, os.O_RDONLY)
    try:
        done = 0
        while done < out.nbytes:
            n = os.preadv(fd, [view[done:]], offset + done)
            if n <= 0:
                raise DatabaseError(f"{path}: index file shorter than its header says")
            done += n
    finally:
        os.close(fd)
    return out


def sort_block(
    words: np.ndarray, postings: np.ndarray, lo: int, hi: int, sessions: np.ndarray, n_words: int,
    engine: str = "auto",
) -> Segment:
    """An in-memory segment from unsorted postings (the latest additions)."""
    return sort_blocks([(words, postings)], lo, hi, sessions, n_words, engine)


def sort_blocks(
    blocks: Sequence[tuple[np.ndarray, np.ndarray]], lo: int, hi: int, sessions: np.ndarray,
    n_words: int, engine: str = "auto", scratch: dict[str, np.ndarray] | None = None,
) -> Segment:
    """An in-memory segment from consecutive blocks of unsorted postings (words, postings),
    oldest first, of the entries ``lo .. hi - 1``.

    ``scratch``: the sort's working arrays, kept in this dict from one call to the next (one
    caller at a time): fresh ones cost the sort its page faults, 2.8 ms against 0.9 for a group
    of 262k postings at 10^6 words by radix; a counting sort of 264k postings at 96,618 words
    touched about 894 fresh pages without them and 704 with (the segment's own), and a fresh page
    cost this virtual machine 1-17 us (2.3-13 ms for the sort).

    The compiled engine sorts by counting, O(P + W): sorting several blocks at once costs
    about what one costs (the per-word passes dominate a small block), so the latest
    additions are sorted FAN_IN blocks at a time. NumPy sorts unique (word, position) keys.
    Both orders are stable (entry ids ascending within a word): the segments are identical.
    """
    total = sum(int(w.shape[0]) for w, _ in blocks)
    csr = total >= csr_threshold(n_words)
    # only a CSR segment is counted: a small one (the entries a reopen reads back) never loads
    # the compiled kernels (numba's import and cache, about a second in a fresh process)
    kernels = compiled_kernels() if csr and resolve(engine) == "compiled" else None
    if kernels is None or not csr:
        # a table of words per posting: the sort gives it, a counting sort would expand it
        words = np.concatenate([w for w, _ in blocks]) if len(blocks) > 1 else blocks[0][0]
        postings = np.concatenate([p for _, p in blocks]) if len(blocks) > 1 else blocks[0][1]
        sw, sp = _by_word(words, postings, n_words, engine, scratch)
        if csr:
            return Segment(lo, hi, sp, None, _indptr(sw, n_words), sessions)
        return Segment(lo, hi, sp, sw, None, sessions)
    parts = [(np.ascontiguousarray(w, np.int32), np.ascontiguousarray(p, "<i8"), lo, hi) for w, p in blocks]
    # counted straight into the segment's table, each word's run advanced in a kept array: the
    # only fresh pages are the segment's own
    indptr = np.zeros(n_words + 1, "<i8")
    dest = _work(scratch, "dest", n_words, "<i8")
    _, out = _counting_sort(kernels, parts, 0, n_words, lambda _: ValueError(
        f"postings to index hold words outside 0..{n_words - 1} or entries outside {lo}..{hi - 1}"),
        counts=indptr[1:], dest=dest)
    indptr[1:] = dest  # every run advanced to its end: the running total of the counts
    return Segment(lo, hi, out, None, indptr, sessions)


def _work(scratch: dict[str, np.ndarray] | None, key: str, n: int, dtype: DTypeLike) -> np.ndarray:
    """A working array of ``n`` elements: part of the one kept under ``key`` in ``scratch``
    (replaced by a larger one when too small), or a fresh one without ``scratch``."""
    have = None if scratch is None else scratch.get(key)
    if have is None or have.shape[0] < n:
        have = np.empty(n, dtype)
        if scratch is not None:
            scratch[key] = have
    return have[:n]


def _by_word(words: np.ndarray, postings: np.ndarray, n_words: int, engine: str,
             scratch: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(P,) words in ``0 .. n_words - 1`` and their postings, sorted stably by word: by radix
    when the compiled kernels are loaded anyway (never loaded for this: at 10^6 words a group
    of 262k postings took 6-7 ms to sort by keys in a 10^6 build, 1-2 by radix), else by
    :func:`word_order`."""
    n = words.shape[0]
    radix = loaded_kernels() if requested(engine) != "numpy" and n > 4096 else None
    if radix is None:
        order = word_order(words, n_words)
        return np.ascontiguousarray(words[order], np.int32), postings[order]
    if int(words.min()) < 0 or int(words.max()) >= n_words:  # a digit is masked: the order would be wrong
        raise ValueError(f"postings to index hold words outside 0..{n_words - 1}")
    sw, sp = np.empty(n, np.int32), np.empty(n, "<i8")
    radix.radix_words(np.ascontiguousarray(words, np.int32), np.ascontiguousarray(postings, "<i8"),
                      max(int(n_words - 1).bit_length(), 1), sw, sp,
                      _work(scratch, "words", n, np.int32), _work(scratch, "postings", n, "<i8"))
    return sw, sp


def word_order(words: np.ndarray, n_words: int) -> np.ndarray:
    """Stable order of (P,) word ids: an unstable sort of unique int64 keys (word, position),
    which NumPy runs with its vectorised quicksort, about 3x faster than a stable argsort
    or a radix sort on 16-bit halves of a tail's many short runs."""
    del n_words  # any int32 word id fits in the key's high half
    pos_bits = max(int(words.shape[0]).bit_length(), 1)
    keys = (words.astype(np.int64) << pos_bits) | np.arange(words.shape[0], dtype=np.int64)
    keys.sort()
    return keys & ((1 << pos_bits) - 1)


def _indptr(words: np.ndarray, n_words: int) -> np.ndarray:
    indptr = np.zeros(n_words + 1, np.int64)
    np.cumsum(np.bincount(words, minlength=n_words), out=indptr[1:])
    return indptr


# ---------------------------------------------------------------------------- sinks
class Sink(Protocol):
    """Where a merge writes its output, chunk by chunk in word order."""

    def append(self, w0: int, counts: np.ndarray, postings: np.ndarray) -> None:
        """Postings of words ``w0 .. w0 + len(counts) - 1``, ``counts[i]`` of word ``w0 + i``;
        each append's words follow the previous one's."""

    def append_table(self, words: np.ndarray, postings: np.ndarray) -> None:
        """Postings with the word of each, in word order (a word-form segment only)."""

    def finish(self, sessions: np.ndarray) -> Segment: ...

    def abort(self) -> None: ...


def _table(counts: np.ndarray, csr: bool, w0: int = 0) -> np.ndarray:
    """A segment's word table from the (W,) count of postings of every word: the CSR indptr
    (W + 1,) int64, or the (P,) int32 word of every posting (the words counted from ``w0``:
    a chunk's part of the table)."""
    if csr:
        indptr = np.zeros(counts.shape[0] + 1, "<i8")
        np.cumsum(counts, out=indptr[1:])
        return indptr
    return np.repeat(np.arange(w0, w0 + counts.shape[0], dtype="<i4"), counts)


class MemorySink:
    """Builds an in-memory segment."""

    def __init__(self, lo: int, hi: int, csr: bool, n_words: int, capacity: int) -> None:
        self.lo, self.hi, self.csr, self.n_words = lo, hi, csr, n_words
        self.postings = np.empty(capacity, "<i8")
        # a CSR table counts every word; a word-form one is the word of each posting, filled as
        # they arrive (nothing the size of the vocabulary: an incremental vocabulary's id space
        # is 2^22 words, and a table expanded from its counts cost every merge ~10 ms)
        self.counts: np.ndarray | None = np.zeros(n_words, np.int64) if csr else None
        self.words: np.ndarray | None = None if csr else np.empty(capacity, "<i4")
        self.size = 0

    def append(self, w0: int, counts: np.ndarray, postings: np.ndarray) -> None:
        n = postings.shape[0]
        self.postings[self.size : self.size + n] = postings
        self.placed(w0, counts, n)

    def append_table(self, words: np.ndarray, postings: np.ndarray) -> None:
        """Postings with the word of each (word form only; each append's words follow the
        previous one's)."""
        n = postings.shape[0]
        assert self.words is not None
        self.words[self.size : self.size + n] = words
        self.postings[self.size : self.size + n] = postings
        self.size += n

    def reserve(self, n: int) -> np.ndarray:
        """Where the next ``n`` postings go, for a merge to write them in place (then
        :meth:`placed`): one pass over fresh memory instead of two."""
        return self.postings[self.size : self.size + n]

    def placed(self, w0: int, counts: np.ndarray, n: int) -> None:
        """``n`` postings of words ``w0 ..`` written in place at :meth:`reserve`'s view."""
        if self.counts is not None:
            self.counts[w0 : w0 + counts.shape[0]] += counts
        else:
            assert self.words is not None
            self.words[self.size : self.size + n] = _table(counts, False, w0)
        self.size += n

    def finish(self, sessions: np.ndarray) -> Segment:
        post = self.postings[: self.size]
        if self.size < self.postings.shape[0] // 2:
            post = post.copy()
        if self.counts is not None:
            return Segment(self.lo, self.hi, post, None, _table(self.counts, True), sessions)
        assert self.words is not None
        words = self.words[: self.size]
        if self.size < self.words.shape[0] // 2:
            words = words.copy()
        return Segment(self.lo, self.hi, post, words, None, sessions)

    def abort(self) -> None:
        pass


def header_bytes(form: int, uuid: bytes, n_words: int, lo: int, hi: int, n_postings: int, crc: int) -> bytes:
    fields = _HEADER.pack(SEGMENT_MAGIC, SEGMENT_VERSION, form, uuid, n_words, lo, hi, n_postings, crc)
    head = fields + struct.pack("<I", zlib.crc32(fields))
    return head + bytes(HEADER_SIZE - len(head))


def _layout(seg: Segment, n_words: int) -> tuple[int, int]:
    """File offsets of a persisted segment's word table and of its sessions."""
    table = HEADER_SIZE + 8 * seg.size
    return table, table + (8 * (n_words + 1) if seg.indptr is not None else 4 * seg.size)


def expected_size(form: int, n_words: int, lo: int, hi: int, n_postings: int) -> int:
    table = 8 * (n_words + 1) if form == FORM_CSR else 4 * n_postings
    return HEADER_SIZE + 8 * n_postings + table + 4 * (hi - lo)


#: a segment file written by a :class:`SegmentWriter` is synced every this many bytes: a merge
#: of the 10^6-entry map writes 2.4 GB, and left to the kernel its dirty pages crossed the
#: dirty limit, at which the kernel pauses every thread that writes, the adding thread's
#: 6.5 kB entry-log appends included (bursts of 10-69 ms adds, with 0.2 ms of CPU each, in an
#: instrumented 10^6 build); smaller files (most are merged away soon) are never synced
SYNC_EVERY = 32 << 20


class SegmentWriter:
    """Does the file work of :class:`FileSink` objects (create, write, header, sync, close) in
    a thread of its own, in the order it was asked for, so that a maintenance step run by the
    adding thread never waits in a write: at 10^6 entries one 1 MB write of a merge blocked
    for 47 ms (the kernel throttling a process that dirties pages faster than the disk
    takes them), and the add with it.

    Args:
        max_behind: bytes queued at most; a sink asking for more waits (a disk far slower
            than the maintenance).
    """

    def __init__(self, max_behind: int = 64 << 20) -> None:
        self.max_behind = max_behind
        self._cond = threading.Condition()
        self._queue: deque[tuple[FileSink, str, Any]] = deque()
        self._behind = 0
        self._thread: threading.Thread | None = None
        self._stop = False

    def put(self, sink: FileSink, op: str, data: Any = None) -> None:
        n = data.nbytes if isinstance(data, np.ndarray) else 0
        with self._cond:
            while self._behind > self.max_behind and self._thread is not None and self._thread.is_alive():
                self._cond.wait(0.05)
            if self._stop:
                raise DatabaseError(f"{sink.path}: index file writer is closed")
            self._queue.append((sink, op, data))
            self._behind += n
            sink.queued += 1
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="stablecues-segments", daemon=True)
                self._thread.start()
            self._cond.notify_all()

    @property
    def full(self) -> bool:
        """More than ``max_behind`` bytes queued: a maintenance step that would queue more
        does nothing instead of waiting (the disk sets the pace, not the adding thread)."""
        thread = self._thread
        return self._behind > self.max_behind and thread is not None and thread.is_alive()

    def wait(self, sink: FileSink, timeout: float) -> None:
        """Wait up to ``timeout`` for the sink's queued work to be done."""
        with self._cond:
            if sink.queued:
                self._cond.wait_for(lambda: not sink.queued, timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    self._cond.wait()
                if not self._queue:
                    return
                sink, op, data = self._queue.popleft()
            with sink.io_lock:
                if not sink.aborted and sink.error is None:
                    try:
                        sink.do(op, data)
                    except OSError as exc:
                        sink.error = exc
            with self._cond:
                self._behind -= data.nbytes if isinstance(data, np.ndarray) else 0
                sink.queued -= 1
                self._cond.notify_all()

    def close(self) -> None:
        """Do what is queued, then stop the thread."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=60)


class ChunkReader:
    """Reads what merge steps are about to merge, in a thread of its own, a few chunks ahead.

    At 10^6 entries the inputs of a large merge are old files whose pages the kernel has
    let go: a maintenance step that read them itself waited 10-30 ms for the disk (and its
    add with it), in instrumented 10^6 builds. With a reader, a step merges only what is
    already in memory; when its chunk has not arrived yet it does nothing (the add goes on,
    the step runs at a later add). Everything is read with ``pread``, which lets the
    interpreter go while it waits, never through a segment's mapping (a page fault there
    would hold the interpreter lock, and so the adding thread, for as long as the disk takes).

    Args:
        ahead: chunks of a merge read before the step that needs them.
    """

    def __init__(self, ahead: int = 4) -> None:
        self.ahead = ahead
        self._cond = threading.Condition()
        self._queue: deque[tuple[MergeJob, int]] = deque()
        self._thread: threading.Thread | None = None
        self._stop = False

    def request(self, job: MergeJob, task: int) -> None:
        with self._cond:
            if not self._stop:
                self._queue.append((job, task))
                if self._thread is None or not self._thread.is_alive():
                    self._thread = threading.Thread(target=self._run, name="stablecues-reader", daemon=True)
                    self._thread.start()
                self._cond.notify_all()
                return
        self._do(job, task)  # closed (the map is closing): read in the caller's thread

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    self._cond.wait()
                if not self._queue:
                    return
                job, task = self._queue.popleft()
            self._do(job, task)

    @staticmethod
    def _do(job: MergeJob, task: int) -> None:
        if job.aborted:
            return
        try:
            result: Any = job.read_task(task)
        except Exception as exc:  # noqa: BLE001 - handed to the step that needs it
            result = exc
        job.deliver(task, result)

    def close(self) -> None:
        """Drop what is queued and stop the thread."""
        with self._cond:
            self._stop = True
            self._queue.clear()
            self._cond.notify_all()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=60)


class FileSink:
    """Writes a segment file in chunks (postings streamed, tables at the end, header last).

    Finishing takes bounded steps: a word-form table (the word of each posting) is filled chunk
    by chunk as the postings arrive, not expanded from the counts at the end (at 2M postings and
    10^6 words that expansion and the copy after it took 18-27 ms of one add, ``bench_scale.py``);
    a CSR table is one cumulative sum over the counts, in a step of its own; the tables are then
    written ``budget`` bytes a step. With a ``writer``, the file itself is created, written and
    closed by its thread: the steps only compute (CRC included) and queue, and the last one
    waits (returns None, :attr:`waiting`) until the file is complete.
    """

    def __init__(
        self, path: Path, uuid: bytes, lo: int, hi: int, csr: bool, n_words: int, fsync: bool,
        total: int = 0, writer: SegmentWriter | None = None,
    ) -> None:
        self.path, self.uuid, self.lo, self.hi, self.csr = path, uuid, lo, hi, csr
        self.n_words, self.fsync = n_words, fsync
        self.writer = writer
        self.io_lock = threading.Lock()
        self.queued = 0  # operations queued with the writer and not done yet
        self.aborted = False
        self.error: OSError | None = None
        self._closing = False
        self._unsynced = 0  # bytes written by the writer's thread since its last sync
        self.f: Any = None
        if writer is None:
            self.do("open", None)
        else:
            writer.put(self, "open")
        self.crc = 0
        self.size = 0
        # the table, filled chunk by chunk as postings arrive in word order: the CSR offsets of
        # the words up to ``_filled`` (the rest of the zeroed pages untouched until their chunk:
        # made whole at the end, a fresh 8 MB table at 10^6 words took one step 15 ms of CPU in
        # page faults, early in a 10^6 build), or the word of every posting so far (word form;
        # ``total``: the postings expected)
        self._indptr: np.ndarray | None = np.zeros(n_words + 1, "<i8") if csr else None
        self._filled = 0
        self._words: np.ndarray | None = None if csr else np.empty(max(int(total), 0), "<i4")
        self._parts: list[np.ndarray] | None = None  # the tables and sessions as bytes, once made
        self._part = 0
        self._pos = 0

    def do(self, op: str, data: Any) -> None:
        """One piece of file work (the writer's thread, or the caller's without a writer)."""
        if op == "open":
            self.f = open(self.path, "wb")  # noqa: SIM115 - closed by "close" or abort
            self.f.write(bytes(HEADER_SIZE))
        elif op == "write":
            self.f.write(data.data.cast("B"))
            if self.writer is not None:
                self._unsynced += data.nbytes
                if self._unsynced >= SYNC_EVERY:  # in the writer's thread: no add waits for it
                    self.f.flush()
                    os.fdatasync(self.f.fileno())
                    self._unsynced = 0
        else:  # "close": the header last, then the file is complete
            self.f.seek(0)
            self.f.write(data)
            self.f.flush()
            if self.fsync:
                os.fsync(self.f.fileno())
            self.f.close()

    @property
    def waiting(self) -> bool:
        """Finishing, with the writer's work on the file not done yet, or the writer too far
        behind to queue more."""
        return (self._closing and self.queued > 0) or self.backlogged

    @property
    def backlogged(self) -> bool:
        return self.writer is not None and self.writer.full

    def _check(self) -> None:
        if self.error is not None:
            raise DatabaseError(f"{self.path}: cannot write index file ({self.error.strerror or self.error})")

    def _write(self, data: np.ndarray) -> None:
        arr = np.ascontiguousarray(data)
        self.crc = zlib.crc32(arr.data.cast("B"), self.crc)
        if self.writer is None:
            self.do("write", arr)
        else:
            self._check()
            self.writer.put(self, "write", arr)  # the array stays alive in the queue

    def append(self, w0: int, counts: np.ndarray, postings: np.ndarray) -> None:
        n = postings.shape[0]
        if self._words is not None and n:
            if self.size + n > self._words.shape[0]:  # more than announced
                grown = np.empty(max(2 * self._words.shape[0], self.size + n), "<i4")
                grown[: self.size] = self._words[: self.size]
                self._words = grown
            self._words[self.size : self.size + n] = _table(counts, False, w0)
        if self._indptr is not None:
            if w0 < self._filled:
                raise ValueError(f"postings of word {w0} appended after word {self._filled - 1}'s")
            w1 = w0 + counts.shape[0]
            self._indptr[self._filled + 1 : w0 + 1] = self.size  # words without postings
            np.cumsum(counts, out=self._indptr[w0 + 1 : w1 + 1])
            self._indptr[w0 + 1 : w1 + 1] += self.size
            self._filled = w1
        self._write(postings)
        self.size += n

    def append_table(self, words: np.ndarray, postings: np.ndarray) -> None:
        """Postings with the word of each (word form only; each append's words follow the
        previous one's)."""
        n = postings.shape[0]
        assert self._words is not None
        if self.size + n > self._words.shape[0]:  # more than announced
            grown = np.empty(max(2 * self._words.shape[0], self.size + n), "<i4")
            grown[: self.size] = self._words[: self.size]
            self._words = grown
        self._words[self.size : self.size + n] = words
        self._write(postings)
        self.size += n

    def finish(self, sessions: np.ndarray) -> Segment:
        while True:
            done = self.finish_step(sessions)
            if done is not None:
                return done

    def finish_step(self, sessions: np.ndarray, budget: int = 1 << 20) -> Segment | None:
        """Write the tables a slice of ``budget`` bytes at a time (a 10^6-word table is 8 MB);
        returns the segment once the file is complete, else None."""
        if self._parts is None:
            if self._indptr is not None:
                self._indptr[self._filled + 1 :] = self.size
                table = self._indptr
            else:
                assert self._words is not None
                table = self._words[: self.size]
            self._parts = [table.view(np.uint8), np.asarray(sessions, "<i4").view(np.uint8)]
            self._words = None
            return None
        while self._part < len(self._parts):
            part = self._parts[self._part]
            if self._pos < part.shape[0]:
                self._write(part[self._pos : self._pos + budget])
                self._pos += budget
                return None
            self._part, self._pos = self._part + 1, 0
        if not self._closing:
            form = FORM_CSR if self.csr else FORM_WORDS
            head = header_bytes(form, self.uuid, self.n_words, self.lo, self.hi, self.size, self.crc)
            self._closing = True
            if self.writer is not None:
                self.writer.put(self, "close", head)
                return None
            self.do("close", head)
        if self.queued:
            return None  # the writer has not finished the file yet
        self._check()
        return map_segment(self.path, self.uuid, self.n_words, trusted=True)

    def abort(self) -> None:
        with self.io_lock:  # the writer skips whatever is still queued for this sink
            self.aborted = True
            try:
                if self.f is not None:
                    with contextlib.suppress(OSError):
                        self.f.close()
            finally:
                self.path.unlink(missing_ok=True)


# ---------------------------------------------------------------------------- files
def read_header(
    path: Path, uuid: bytes, n_words: int, fd: int | None = None
) -> tuple[int, int, int, int, int]:
    """Check a segment file's header against the database and the file's length (``fd``: the
    file already open, else it is opened by ``path``).

    Returns:
        form, lo, hi, postings, body CRC.
    """
    try:
        if fd is None:
            with open(path, "rb") as f:
                head = f.read(HEADER_SIZE)
                size = os.fstat(f.fileno()).st_size
        else:
            head = os.pread(fd, HEADER_SIZE, 0)
            size = os.fstat(fd).st_size
    except OSError as exc:
        raise DatabaseError(f"{path}: cannot read index file ({exc.strerror or exc})") from exc
    if len(head) < HEADER_SIZE or head[:4] != SEGMENT_MAGIC:
        raise DatabaseError(f"{path}: not an index segment file (bad magic or shorter than its header)")
    fields = head[: _HEADER.size]
    (crc_h,) = struct.unpack_from("<I", head, _HEADER.size)
    if zlib.crc32(fields) != crc_h:
        raise DatabaseError(f"{path}: index file header is corrupt (checksum mismatch)")
    _, version, form, file_uuid, words, lo, hi, n_post, crc = _HEADER.unpack(fields)
    if version != SEGMENT_VERSION or form not in (FORM_WORDS, FORM_CSR):
        raise DatabaseError(f"{path}: index file version {version} form {form}, expected "
                            f"version {SEGMENT_VERSION}")
    if file_uuid != uuid:
        raise DatabaseError(f"{path}: index file belongs to another database")
    if words != n_words:
        raise DatabaseError(f"{path}: index file made for {words} words, the vocabulary has {n_words}")
    if lo > hi or hi >= 2**31:
        raise DatabaseError(f"{path}: index file covers entries {lo}..{hi}, not a valid range")
    if n_post > (hi - lo) * words:  # an entry has at most one posting per word
        raise DatabaseError(f"{path}: index file claims {n_post} postings for {hi - lo} entries of at most "
                            f"{words} words each (corrupt)")
    want = expected_size(form, words, lo, hi, n_post)
    if want != size:
        raise DatabaseError(f"{path}: index file is {size} bytes, its header says {want} "
                            "(truncated or corrupt)")
    return form, lo, hi, n_post, crc


class SegmentReplaced(DatabaseError):
    """A segment file that is being deleted (a newer manifest no longer names it)."""


class _Mapping(mmap.mmap):
    """A segment file's mapping, holding a shared ``flock`` on the file for as long as any
    array made from it lives: the thread that deletes replaced files shortens a large file
    step by step only when it gets the lock exclusively, i.e. when no process maps it (a
    mapping whose file is shortened under it raises SIGBUS at the next read of a lost page)."""


def _sorted(values: np.ndarray, block: int = 1 << 22) -> bool:
    """Whether ``values`` never decreases, checked a block at a time (the temporaries of a
    check of a whole large table would cost as much memory as the table)."""
    for a in range(0, max(values.shape[0] - 1, 0), block):
        b = min(a + block, values.shape[0] - 1)
        if bool(np.any(values[a + 1 : b + 1] < values[a:b])):
            return False
    return True


def map_segment(path: Path, uuid: bytes, n_words: int, trusted: bool = False) -> Segment:
    """Memory-map a segment file after checking its header, length and the ends of its word
    table (O(1): the body's checksum and the order of its tables are checked by
    :func:`verify_segment`, before the file first answers a query or is merged; reading every
    table at open made a cold reopen of a 10^6-entry map read 80 MB); ``trusted`` skips even
    the ends (a file this process has just written).

    Raises:
        SegmentReplaced: the file is being deleted (read the manifest again).
        DatabaseError: the file is missing, corrupt or not this database's.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError as exc:
        raise DatabaseError(f"{path}: cannot read index file ({exc.strerror or exc})") from exc
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError as exc:
            raise SegmentReplaced(f"{path}: index file is being deleted (replaced by a newer one)") from exc
        except OSError:
            pass  # a file system without flock: mapped unlocked (the deleting thread cannot lock it either)
        form, lo, hi, n_post, crc = read_header(path, uuid, n_words, fd)
        mm = _Mapping(fd, 0, access=mmap.ACCESS_READ)
    except BaseException:
        os.close(fd)
        raise
    weakref.finalize(mm, os.close, fd)  # the lock goes with the last array made from the mapping
    off = HEADER_SIZE
    postings = np.frombuffer(mm, "<i8", n_post, off)
    off += 8 * n_post
    words = indptr = None
    if form == FORM_CSR:
        indptr = np.frombuffer(mm, "<i8", n_words + 1, off)
        off += 8 * (n_words + 1)
        if not trusted and (indptr[0] != 0 or indptr[-1] != n_post):
            raise DatabaseError(f"{path}: index file's word table is corrupt")
    else:
        words = np.frombuffer(mm, "<i4", n_post, off)
        off += 4 * n_post
        if not trusted and n_post and (words[0] < 0 or words[-1] >= n_words):
            raise DatabaseError(f"{path}: index file's words are corrupt")
    sessions = np.frombuffer(mm, "<i4", hi - lo, off)
    return Segment(lo, hi, postings, words, indptr, sessions, name=path.name, crc=crc, path=path,
                   verified=trusted)


_VERIFYING = threading.Lock()


class SegmentDamaged(DatabaseError):
    """A persisted segment whose body fails its checksum (``segment``: which one; ``problem``:
    what :func:`verify_segment` found)."""

    def __init__(self, problem: str, segment: Segment) -> None:
        super().__init__(f"{problem}: refusing to answer from it (`stablecues map repair` on its map "
                         "rebuilds it from the entries)")
        self.problem = problem
        self.segment = segment


def ensure_verified(seg: Segment, n_entries: int) -> None:
    """Check a persisted segment's body once, before it first answers a query or is merged
    (opening a map checks headers and tables only, so that a map of 10^6 entries reopens in
    milliseconds; the body's checksum costs one read of the file).

    Raises:
        DatabaseError: the body does not match its checksum or holds foreign entry ids, naming
            the file and the repair.
    """
    if seg.verified or seg.path is None:
        return
    with _VERIFYING:
        if seg.verified:
            return
        problem = verify_segment(seg, n_entries)
        if problem is not None:
            raise SegmentDamaged(problem, seg)
        seg.verified = True


def ensure_all_verified(segs: Sequence[Segment], n_entries: int) -> None:
    """:func:`ensure_verified` for several segments at once, their files read in parallel (one
    thread per core: zlib's CRC releases the GIL), so that the first query of a large map
    waits for its largest file rather than for the sum of them.

    Raises:
        DatabaseError: as :func:`ensure_verified`, for the first damaged segment in order.
    """
    todo = [s for s in segs if not s.verified and s.path is not None]
    if len(todo) < 2:
        for seg in todo:
            ensure_verified(seg, n_entries)
        return
    from concurrent.futures import ThreadPoolExecutor

    with _VERIFYING:
        todo = [s for s in todo if not s.verified]  # another thread may have checked them meanwhile
        if len(todo) < 2:
            problems = [verify_segment(seg, n_entries) for seg in todo]
        else:
            workers = min(len(todo), os.cpu_count() or 1)
            with ThreadPoolExecutor(workers, thread_name_prefix="stablecues-verify") as pool:
                problems = list(pool.map(lambda seg: verify_segment(seg, n_entries), todo))
        for seg, problem in zip(todo, problems, strict=True):
            if problem is not None:
                raise SegmentDamaged(problem, seg)
            seg.verified = True


def verify_segment(seg: Segment, n_entries: int, block: int = 1 << 24) -> str | None:
    """Check a persisted segment's body checksum and entry ids; returns the problem or None.
    The body is read through a memory map of the file, ``block`` bytes at a time (no copy)."""
    if seg.path is None:
        return None
    crc = 0
    try:
        with open(seg.path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size > HEADER_SIZE:
                with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
                    view = memoryview(mapped)
                    try:
                        for start in range(HEADER_SIZE, size, block):
                            crc = zlib.crc32(view[start : start + block], crc)
                    finally:
                        view.release()
    except (OSError, ValueError) as exc:
        return f"{seg.path}: cannot read index file ({getattr(exc, 'strerror', None) or exc})"
    if crc != seg.crc:
        return f"{seg.path}: index file body is corrupt (checksum mismatch)"
    if seg.indptr is not None and not _sorted(seg.indptr):
        return f"{seg.path}: index file's word table is corrupt"
    if seg.words is not None and not _sorted(seg.words):
        return f"{seg.path}: index file's words are corrupt"
    ent = split(seg.postings)[0]
    if ent.size and (int(ent.min()) < seg.lo or int(ent.max()) >= min(seg.hi, n_entries)):
        return f"{seg.path}: index file holds entry ids outside {seg.lo}..{seg.hi - 1}"
    return None


# ---------------------------------------------------------------------------- merging
_PREPARE = -1  # a reader's first task of a merge: its chunk bounds and small inputs' word tables
_NOT_READY = object()


class MergeJob:
    """Merge adjacent segments (oldest first) into one, a bounded chunk of words per step.

    Args:
        inputs: adjacent segments, ordered by entry ids.
        sink: where the merged segment goes.
        n_words: vocabulary size.
        chunk: postings per step (about).
        alive: (n,) bool, False for removed entries whose postings are dropped, or None.
        shift: added to every entry id (copying segments into another map).
        session_shift: added to every session id.
        engine: ``"auto"``, ``"compiled"`` or ``"numpy"``: how postings are merged (the same
            segment either way).
        reader: reads the persisted inputs a few chunks ahead of the steps (a step whose
            chunk has not arrived does nothing, :attr:`waiting`), or None: each step reads
            what it merges. The same segment either way.
    """

    def __init__(
        self, inputs: Sequence[Segment], sink_factory: Callable[[int, int, bool, int], Sink],
        n_words: int, chunk: int = 1 << 18, alive: np.ndarray | None = None,
        shift: int = 0, session_shift: int = 0, engine: str = "auto", reader: ChunkReader | None = None,
    ) -> None:
        for a, b in zip(inputs, inputs[1:], strict=False):
            if a.hi != b.lo:
                raise ValueError("merge inputs must be adjacent")
        self.inputs = list(inputs)
        self.n_words = n_words
        self.alive = alive
        self.shift, self.session_shift = int(shift), int(session_shift)
        self.engine = engine
        self.lo, self.hi = self.inputs[0].lo, self.inputs[-1].hi
        self.total = sum(s.size for s in self.inputs)
        self.csr = self.total >= csr_threshold(n_words)
        self.sink_factory = sink_factory
        self.sink: Sink | None = None
        self.chunk = chunk
        # only files are read ahead: inputs in memory are merged from where they are
        self.reader = reader if any(s.path is not None for s in self.inputs) else None
        self.aborted = False
        self._lock = threading.Lock()
        self._ready: dict[int, Any] = {}  # the reader's results, by task
        self._asked = _PREPARE - 1  # the last task handed to the reader
        self._tables: list[np.ndarray | None] | None = None  # word-form inputs' word tables
        self.bounds: list[int] | None = None if self.reader is not None else self._bounds(chunk)
        self.next = 0
        self._sessions: np.ndarray | None = None
        self.result: Segment | None = None
        self._ask()  # reading starts now, not at the job's first step

    def _bounds(self, chunk: int, word_at: Callable[[np.ndarray], np.ndarray] | None = None) -> list[int]:
        n_chunks = -(-self.total // max(chunk, 1))
        if n_chunks <= 1:
            return [0, self.n_words]
        big = max(self.inputs, key=lambda s: s.size)
        pos = (np.arange(1, n_chunks) * big.size) // n_chunks
        # the words at ascending offsets of a segment sorted by word ascend too
        inner = distinct((word_at or big.word_at)(pos.astype(np.int64)), is_sorted=True)
        inner = inner[(inner > 0) & (inner < self.n_words)]
        return [0, *inner.tolist(), self.n_words]

    @property
    def waiting(self) -> bool:
        """A step now does nothing: the chunk it needs is still being read, or the merge is
        finished but for the file work a writer thread still does."""
        want = self._want()
        if want is not None:
            with self._lock:
                if want not in self._ready:
                    return True
        return bool(getattr(self.sink, "waiting", False))

    @property
    def remaining(self) -> int:
        """About how many postings are still to merge."""
        if self.bounds is None:
            return self.total
        return self.total * (len(self.bounds) - 1 - self.next) // max(len(self.bounds) - 1, 1)

    # ------------------------------------------------------------------ reading ahead
    def _want(self) -> int | None:
        """The reader's task the next step needs (None: nothing, or no reader)."""
        if self.reader is None:
            return None
        if self.bounds is None:
            return _PREPARE
        if self.next < len(self.bounds) - 1:
            return self.next
        return len(self.bounds) - 1 if self._sessions is None else None  # the sessions last

    def _ask(self) -> None:
        """Hand the reader every task up to ``ahead`` past the one the next step needs."""
        want = self._want()
        if want is None or self.reader is None:
            return
        last = want if self.bounds is None else min(want + self.reader.ahead, len(self.bounds) - 1)
        while self._asked < last:
            self._asked += 1
            self.reader.request(self, self._asked)

    def _take(self) -> Any:
        """The result of the task the next step needs, or _NOT_READY; a task that failed
        raises its error here."""
        want = self._want()
        self._ask()
        with self._lock:
            if want not in self._ready:
                return _NOT_READY
            got = self._ready.pop(want)
        if isinstance(got, Exception):
            raise got
        return got

    def deliver(self, task: int, result: Any) -> None:
        with self._lock:
            if not self.aborted:
                self._ready[task] = result

    def read_task(self, task: int) -> Any:
        """What task ``task`` needs (in the reader's thread): the chunk bounds and the small
        inputs' word tables (_PREPARE), a chunk's parts, or the sessions (the last task)."""
        if task == _PREPARE:
            tables = [_pread(s.path, _layout(s, self.n_words)[0], s.size, "<i4")
                      if s.path is not None and s.words is not None else s.words for s in self.inputs]
            i = max(range(len(self.inputs)), key=lambda k: self.inputs[k].size)
            big, table = self.inputs[i], tables[i]
            word_at: Callable[[np.ndarray], np.ndarray] = big.word_at
            if big.path is not None and big.indptr is not None:
                indptr = _pread(big.path, _layout(big, self.n_words)[0], self.n_words + 1)
                word_at = lambda pos: np.searchsorted(indptr, pos, "right") - 1  # noqa: E731
            elif table is not None:
                word_at = lambda pos: table[pos].astype(np.int64)  # noqa: E731
            return self._bounds(self.chunk, word_at), tables
        assert self.bounds is not None
        if task < len(self.bounds) - 1:
            return self._parts(self.bounds[task], self.bounds[task + 1], self._tables)
        return np.concatenate([_pread(s.path, _layout(s, self.n_words)[1], s.hi - s.lo, "<i4")
                               if s.path is not None else np.asarray(s.sessions, np.int32)
                               for s in self.inputs])

    def _parts(
        self, w0: int, w1: int, tables: Sequence[np.ndarray | None] | None = None,
    ) -> list[tuple[Segment, np.ndarray, np.ndarray]]:
        """(segment, table, postings) of every input holding words ``w0 .. w1 - 1``: the
        table is the word of each posting (word form) or each word's count (CSR). With the
        inputs' ``tables`` (the reader's), files are read with ``pread`` only."""
        parts = []
        for i, seg in enumerate(self.inputs):
            path = seg.path if tables is not None else None  # read ahead: files by pread only
            if seg.indptr is not None:
                ip = (seg.indptr[w0 : w1 + 1] if path is None
                      else _pread(path, _layout(seg, self.n_words)[0] + 8 * w0, w1 - w0 + 1))
                a, b = int(ip[0]), int(ip[-1])
                table = np.diff(ip).astype(np.int64, copy=False)
            else:
                words = seg.words if path is None or tables is None else tables[i]
                assert words is not None
                # the bounds as the table's own type: a Python int made NumPy 2.4 cast the whole table (7 ms
                # for 5M words)
                a = int(np.searchsorted(words, words.dtype.type(w0), "left"))
                b = int(np.searchsorted(words, words.dtype.type(w1), "left"))
                table = words[a:b]
            if b > a:
                post = seg.postings[a:b] if seg.path is None else _pread(seg.path, HEADER_SIZE + 8 * a, b - a)
                parts.append((seg, table, post))
        return parts

    # ------------------------------------------------------------------ merging
    def step(self) -> bool:
        """Merge the next chunk of words; returns True once the merged segment is ready."""
        if self.sink is None:
            self.sink = self.sink_factory(self.lo + self.shift, self.hi + self.shift, self.csr, self.total)
        if getattr(self.sink, "backlogged", False):
            return False  # its writer is behind (a slow disk): a later step goes on
        if self.bounds is None:
            got = self._take()
            if got is not _NOT_READY:
                self.bounds, self._tables = got
                self._ask()  # the first chunks
            return False
        if self.next < len(self.bounds) - 1:
            parts = None if self.reader is None else self._take()
            if parts is not _NOT_READY:
                self._merge_next(self.sink, self.bounds, parts)
            return False
        if self._sessions is None:
            if self.reader is None:
                sessions = np.concatenate([np.asarray(s.sessions, np.int32) for s in self.inputs])
            elif (sessions := self._take()) is _NOT_READY:
                return False
            if self.session_shift:
                sessions = (sessions.astype(np.int64) + self.session_shift).astype(np.int32)
            self._sessions = sessions
        finish_step = getattr(self.sink, "finish_step", None)
        if finish_step is None:
            self.result = self.sink.finish(self._sessions)
        else:
            self.result = finish_step(self._sessions)
        return self.result is not None

    def _merge_next(self, sink: Sink, bounds: list[int], parts: Any) -> None:
        w0, w1 = bounds[self.next], bounds[self.next + 1]
        self.next += 1
        if not self.csr:
            got = self._sparse(w0, w1, parts)
            if got is not None:
                sink.append_table(*got)
                return
        # a memory sink takes the merge in place unless postings are dropped or renumbered
        reserve = getattr(sink, "reserve", None) if self.alive is None and not self.shift else None
        w0, counts, post = self._chunk(w0, w1, reserve, parts)
        if reserve is not None:
            sink.placed(w0, counts, post.shape[0])  # type: ignore[attr-defined]
        else:
            sink.append(w0, counts, post)

    def _sparse(
        self, w0: int, w1: int, parts: list[tuple[Segment, np.ndarray, np.ndarray]] | None,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Words ``w0 .. w1 - 1`` of word-form inputs merged by a stable sort of their word
        tables, in O(P) whatever the span of words: (the word of each posting, postings), or
        None where the span is small enough for counting (:meth:`_chunk`). An incremental
        vocabulary's words span its whole id space (2^22): counted over it, one merge of a few
        thousand postings cost ~10 ms."""
        if parts is None:
            parts = self._parts(w0, w1)
        if not parts:
            return np.zeros(0, "<i4"), empty_postings()
        n = sum(p.shape[0] for _, _, p in parts)
        if w1 - w0 <= 2 * n or any(seg.words is None for seg, _, _ in parts):
            return None
        for seg, table, p in parts:
            ent = split(p)[0]
            if (int(table[0]) < w0 or int(table[-1]) >= w1 or int(ent.min()) < seg.lo
                    or int(ent.max()) >= seg.hi or table.shape[0] != p.shape[0]):
                raise DatabaseError(f"{_name(seg)}: holds words or entry ids out of place (corrupt)")
        if len(parts) == 1:
            words, post = np.asarray(parts[0][1], "<i4"), np.asarray(parts[0][2], "<i8")
        else:
            # the inputs oldest first, each sorted by word: a stable sort by word keeps every
            # word's postings in entry order, as the counting merge does
            words = np.concatenate([t for _, t, _ in parts]).astype("<i4", copy=False)
            post = np.concatenate([p for _, _, p in parts]).astype("<i8", copy=False)
            words, post = _by_word(words - np.int32(w0), post, w1 - w0, self.engine)
            words += np.int32(w0)
        if self.alive is not None:
            keep = self.alive[split(post)[0]]
            if not keep.all():
                words, post = words[keep], post[keep]
        if self.shift:
            ent, weights = split(post)
            post = pack_postings(ent.astype(np.int64) + self.shift, weights)
        return words, post

    def _chunk(
        self, w0: int, w1: int, reserve: Callable[[int], np.ndarray] | None = None,
        parts: list[tuple[Segment, np.ndarray, np.ndarray]] | None = None,
    ) -> tuple[int, np.ndarray, np.ndarray]:
        """Words ``w0 .. w1 - 1`` of every input merged: (w0, per-word counts, postings); with
        ``reserve``, the postings are written to ``reserve(n)`` (no removal or shift then).
        ``parts``: what :meth:`_parts` gives for these words (read ahead), or None."""
        if parts is None:
            parts = self._parts(w0, w1)
        if not parts:
            return w0, np.zeros(w1 - w0, np.int64), empty_postings()
        kernels = compiled_kernels() if resolve(self.engine) == "compiled" else None
        if kernels is not None and all(seg.words is not None for seg, _, _ in parts):
            # small inputs merged by counting: one pass to count each word's postings, one to
            # scatter them, oldest input first; O(P + (w1 - w0)), not the per-input passes
            # over every word that merge_runs makes, and the same result (tests check it)
            counts, post = _counting_sort(
                kernels, [(table, p, seg.lo, seg.hi) for seg, table, p in parts], w0, w1 - w0,
                lambda i: DatabaseError(
                    f"{_name(parts[i][0])}: holds words or entry ids out of place (corrupt)"), reserve)
        else:
            counts_l, post_l = [], []
            for seg, table, p in parts:
                c = (table if seg.words is None
                     else np.bincount(table - w0, minlength=w1 - w0).astype(np.int64, copy=False))
                ent = split(p)[0]
                if int(ent.min()) < seg.lo or int(ent.max()) >= seg.hi:
                    raise DatabaseError(
                        f"{_name(seg)}: holds entry ids outside {seg.lo}..{seg.hi - 1} (corrupt)")
                counts_l.append(c)
                post_l.append(p)
            out = None if reserve is None else reserve(sum(p.shape[0] for p in post_l))
            counts, post = merge_runs(counts_l, post_l, engine=self.engine, out=out)
        if reserve is not None:
            return w0, counts, post
        if self.alive is not None:
            keep = self.alive[split(post)[0]]
            if not keep.all():
                words = np.repeat(np.arange(w1 - w0, dtype=np.int64), counts)
                counts = np.bincount(words[keep], minlength=w1 - w0).astype(np.int64, copy=False)
                post = post[keep]
        if self.shift:
            ent, weights = split(post)
            post = pack_postings(ent.astype(np.int64) + self.shift, weights)
        return w0, counts, post

    def abort(self) -> None:
        with self._lock:
            self.aborted = True
            self._ready.clear()
        if self.sink is not None and self.result is None:
            self.sink.abort()


def _name(seg: Segment) -> str:
    return str(seg.path) if seg.path is not None else "an index segment"


def _counting_sort(
    kernels: ModuleType, parts: Sequence[tuple[np.ndarray, np.ndarray, int, int]], w0: int, n: int,
    refuse: Callable[[int], Exception], reserve: Callable[[int], np.ndarray] | None = None,
    counts: np.ndarray | None = None, dest: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Postings of words ``w0 .. w0 + n - 1`` from parts (words, postings, lo, hi), oldest first,
    sorted stably by word: the (n,) count of each word and the postings (in ``reserve(P)``
    when given). Every word and entry id (within the part's ``lo .. hi - 1``) is checked before
    anything is written: ``refuse(i)`` is raised for the first part that fails.

    ``counts`` (n,) int64 zeros and ``dest`` (n,) int64: arrays to count in and to advance each
    word's run in (fresh ones without them); ``dest`` ends as the running total of the counts."""
    counts = np.zeros(n, np.int64) if counts is None else counts
    for i, (words, post, lo, hi) in enumerate(parts):
        if kernels.count_words(counts, words, post, w0, lo, hi):
            raise refuse(i)
    total = int(counts.sum())
    out = np.empty(total, "<i8") if reserve is None else reserve(total)
    # where each word's run starts; advanced by the scatter
    dest = np.cumsum(counts, out=dest)
    dest -= counts
    for words, post, _, _ in parts:
        kernels.scatter_words(out, dest, words, post, w0)
    return counts, out


def merge_runs(counts: Sequence[np.ndarray], postings: Sequence[np.ndarray],
               engine: str = "auto", out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Merge word-sorted runs of postings of adjacent segments, oldest first.

    Args:
        counts: per input, (W,) int64 postings of each of W consecutive words.
        postings: per input, its postings (int64) in word order.
        engine: ``"auto"``, ``"compiled"`` or ``"numpy"`` (as for the vocabulary).
        out: where to write the merged postings (as many as the inputs hold), or None.

    Returns:
        (W,) int64 counts of the merge and its postings: every word's run is the runs of that
        word in input order, so entry ids stay ascending within a word (exactly what a stable
        sort of the inputs' concatenation by word gives, in O(P + W) instead of O(P log P)).
    """
    for c, p in zip(counts, postings, strict=True):
        if int(c.sum()) != p.shape[0] or (c.size and int(c.min()) < 0):
            # the compiled copy trusts its bounds: a mismatch must never reach it
            raise DatabaseError(f"an index segment's word table counts {int(c.sum())} postings where "
                                f"{p.shape[0]} are stored (corrupt)")
    total = counts[0].copy()
    for c in counts[1:]:
        total += c
    n = int(total.sum())
    if out is None:
        if len(postings) == 1:
            return total, postings[0]
        out = np.empty(n, "<i8")
    elif out.shape[0] != n:
        raise ValueError(f"merge output holds {out.shape[0]} postings, the inputs {n}")
    if len(postings) == 1:
        out[:] = postings[0]
        return total, out
    dest = np.cumsum(total) - total  # where each word's run starts in the output
    kernels = compiled_kernels() if resolve(engine) == "compiled" else None
    for c, p in zip(counts, postings, strict=True):
        if kernels is not None:
            kernels.scatter_runs(out, np.ascontiguousarray(p, "<i8"), c, dest)
        elif p.shape[0]:
            starts = np.cumsum(c) - c  # where each word's run starts in this input
            out[np.repeat(dest - starts, c) + np.arange(p.shape[0])] = p
        dest += c
    return total, out

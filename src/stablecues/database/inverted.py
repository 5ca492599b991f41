"""The inverse index: word -> postings (entry id, weight), built for fast sparse queries.

Postings live in a few immutable segments sorted by word (a log-structured merge, like a
search engine's index; see :mod:`.segments`) plus unsorted blocks of the latest additions.
A query finds each query word's run in every segment (a CSR table or a binary search),
gathers the postings with one vectorised index computation, adds the unsorted blocks'
matching postings through a dense word lookup, and accumulates the scoring's per-word terms
per entry with ``np.bincount``: no Python loop over words or entries. Every entry's terms are
summed in word order whatever the segments look like, so scores do not depend on when
segments were merged.

Maintenance never stalls an add: when the latest additions reach ``tail_limit`` postings they
are sealed into a block (O(1)); sorting ``FAN_IN`` blocks together into a segment (a group:
one counting sort, O(P + W), with the compiled engine) and merging ``MERGE_FAN_IN`` adjacent
segments of one size class are jobs done one bounded step at a time (a chunk of words), by
the adding thread, one step per add at most (``background=False``), or by a background thread
(``background=True``). Segments stay O(log n), and each posting is merged about
log_MERGE_FAN_IN(n / group) times. With a ``store`` the segments are files: a finished job
writes its segment file first and then commits the list of files (the manifest) through the
store, so the files on disk and the manifest never disagree.

Thread safety: queries work on an immutable snapshot taken under a lock and may run in any
number of threads while one thread adds.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..errors import DatabaseError
from ..vocabulary.scoring import Scoring, common_terms, finish, kl_missing_total
from .segments import (
    MemorySink,
    MergeJob,
    Segment,
    SegmentDamaged,
    Sink,
    empty_postings,
    ensure_all_verified,
    ensure_verified,
    gather_runs,
    pack_postings,
    sort_blocks,
    split,
)

log = logging.getLogger(__name__)

FAN_IN = 4  # sealed blocks sorted together into one segment (a group)
# segments of one size class merged together. 8 was measured too (bench_scale.py): it saves
# the adds at 10k about 0.01-0.02 ms of merging, but rebuilt maps then held 15 segments where
# 4 leaves 9-10, and their queries took 16.9-22.5 ms at 10^5 entries (4: 15.7) and 23.7-27.7 ms
# p50, 28.6-35.3 p90 at 10^6 (4: 23.9 / 28.7)
MERGE_FAN_IN = 4
MAX_BLOCKS = 2 * FAN_IN  # sealed blocks waiting to be sorted before an add helps the maintenance
MAX_SEGMENTS = 48  # beyond this many segments an add helps the background maintenance


class SegmentStore(Protocol):
    """Where segments are persisted (see :class:`stablecues.database.files.IndexFiles`)."""

    def sink(self, lo: int, hi: int, csr: bool, total: int) -> Sink: ...

    def commit(self, segments: Sequence[Segment]) -> None: ...

    def discard(self, segments: Sequence[Segment]) -> None: ...

    def rebuild(self, lo: int, hi: int) -> list[Segment]: ...


@dataclass(eq=False)
class _Block:
    """Unsorted postings of entries ``lo .. hi - 1`` (sealed additions)."""

    lo: int
    hi: int
    words: np.ndarray
    postings: np.ndarray
    sessions: np.ndarray
    _view: tuple[np.ndarray, np.ndarray] | None = None

    def view(self) -> tuple[np.ndarray, np.ndarray]:
        """Its words and postings in word order (a stable sort: entries ascending within a
        word, as a segment keeps them), made once, by the first query that needs it: a query
        then finds each of its words by binary search instead of reading every posting."""
        view = self._view
        if view is None:
            order = np.argsort(self.words, kind="stable")
            view = self._view = (self.words[order], self.postings[order])
        return view


@dataclass(eq=False)
class _Job:
    inputs: list[Segment]
    blocks: list[_Block] = field(default_factory=list)  # oldest sealed blocks, sorted together
    merge: MergeJob | None = None
    claimed: bool = False
    dropped: bool = False  # the index was reset while the job ran: its result is thrown away

    @property
    def waiting(self) -> bool:
        return self.merge is not None and self.merge.waiting

    @property
    def remaining(self) -> int:
        if self.blocks:
            return -1  # flushes first
        assert self.merge is not None
        return self.merge.remaining


@dataclass(frozen=True)
class _Snapshot:
    segments: tuple[Segment, ...]
    blocks: tuple[_Block, ...]  # sealed: searched through their word-sorted view
    unsorted: tuple[tuple[np.ndarray, np.ndarray], ...]  # the tail: read whole
    n_entries: int
    alive: np.ndarray | None


@dataclass
class _Tail:
    """The latest additions, entries ``lo .. lo + len(sessions) - 1``: their words and postings
    appended to buffers that grow by doubling, so that a query's snapshot takes the first k
    entries as views (appends only write past them; a grown buffer leaves the old one to the
    views that hold it) instead of joining every entry's arrays again after each add."""

    lo: int = 0
    sessions: list[int] = field(default_factory=list)
    size: int = 0
    _ends: list[int] = field(default_factory=list)  # postings after each entry
    _words: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    _postings: np.ndarray = field(default_factory=empty_postings)

    def append(self, words: np.ndarray, weights: np.ndarray, session: int) -> None:
        n = int(words.shape[0])
        end = self.size + n
        if end > self._words.shape[0]:
            cap = max(2 * self._words.shape[0], end, 1024)
            grown_w, grown_p = np.empty(cap, np.int32), empty_postings(cap)
            grown_w[: self.size], grown_p[: self.size] = self._words[: self.size], self._postings[: self.size]
            self._words, self._postings = grown_w, grown_p
        entry = self.lo + len(self.sessions)
        self._words[self.size : end] = words
        self._postings[self.size : end] = pack_postings(np.full(n, entry, np.int32), weights)
        self.sessions.append(int(session))
        self._ends.append(end)
        self.size = end

    def arrays(self, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Words and postings of the first ``k`` entries (all by default), as views."""
        k = len(self._ends) if k is None else k
        if k <= 0:
            return np.zeros(0, np.int32), empty_postings()
        end = self._ends[k - 1]
        return self._words[:end], self._postings[:end]


class InvertedIndex:
    """Inverse index over BoW vectors of entries numbered 0, 1, 2, ... in insertion order.

    Args:
        n_words: vocabulary size.
        scoring: how entries are scored against a query.
        tail_limit: postings kept unsorted before they are sealed for sorting.
        store: where segments are persisted (None: in memory only).
        background: run the maintenance in a background thread (else one bounded step per
            add in the adding thread).
        chunk: postings merged per maintenance step (about).
    """

    def __init__(
        self, n_words: int, scoring: Scoring, tail_limit: int = 1 << 16, *,
        store: SegmentStore | None = None, background: bool = False, chunk: int = 1 << 17,
    ) -> None:
        self.n_words = int(n_words)
        self.scoring = scoring
        self.tail_limit = int(tail_limit)
        self.chunk = int(chunk)
        self.store = store
        self.n_entries = 0
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._segments: list[Segment] = []
        self._blocks: list[_Block] = []
        self._jobs: list[_Job] = []
        self._busy: set[int] = set()  # id() of segments in a job
        self._tail = _Tail()
        self._scratch: dict[str, np.ndarray] = {}  # the sort's working arrays (one sort job at a time)
        self._sessions = np.zeros(1024, np.int32)
        self._alive: np.ndarray | None = None
        self._snap: _Snapshot | None = None
        self._local = threading.local()
        self._credit = 0
        self._flushing = 0  # flush() is waiting: sort blocks even when fewer than FAN_IN
        self._idle = False  # nothing to do until the segments change (inline maintenance)
        self._broken: BaseException | None = None
        self._stop = False
        self._thread: threading.Thread | None = None
        if background:
            self._thread = threading.Thread(target=self._run, name="stablecues-index", daemon=True)
            self._thread.start()

    # ------------------------------------------------------------------ sizes
    @property
    def n_postings(self) -> int:
        with self._lock:
            return (sum(s.size for s in self._segments) + sum(b.postings.shape[0] for b in self._blocks)
                    + self._tail.size)

    @property
    def nbytes(self) -> int:
        """Bytes of postings and tables (resident or mapped)."""
        with self._lock:
            return (sum(s.nbytes for s in self._segments)
                    + sum(b.postings.nbytes + b.words.nbytes for b in self._blocks) + self._tail.size * 12)

    @property
    def segments(self) -> tuple[Segment, ...]:
        with self._lock:
            return tuple(self._segments)

    def sessions(self) -> np.ndarray:
        """(n_entries,) int32 session of every entry (a read-only view)."""
        with self._lock:
            view = self._sessions[: self.n_entries]
        view = view.view()
        view.flags.writeable = False
        return view

    def alive(self) -> np.ndarray | None:
        """(>= n_entries,) bool, False for removed entries, or None when none was removed."""
        return self._alive

    # ------------------------------------------------------------------ loading
    def reset(
        self, segments: Sequence[Segment], n_entries: int, sessions: np.ndarray,
        removed: np.ndarray | None = None,
    ) -> None:
        """Replace the whole content (opening or refreshing a database).

        Args:
            segments: segments covering entries ``0 .. n_entries - 1`` contiguously.
            n_entries: number of entry ids.
            sessions: (n_entries,) int32 session of every entry.
            removed: ids of removed entries, or None.
        """
        pos = 0
        for seg in segments:
            if seg.lo != pos:
                raise DatabaseError(f"index segments are not contiguous at entry {pos}")
            pos = seg.hi
        if pos != n_entries:
            raise DatabaseError(f"index segments cover {pos} entries, the database has {n_entries}")
        with self._lock:
            for job in self._jobs:
                job.dropped = True
                if job.merge is not None and not job.claimed:
                    job.merge.abort()
            self._jobs, self._busy = [], set()
            self._idle = False
            self._segments = list(segments)
            self._blocks = []
            self._tail = _Tail(lo=n_entries)
            self.n_entries = n_entries
            cap = max(1024, 1 << int(n_entries).bit_length())
            self._sessions = np.zeros(cap, np.int32)
            self._sessions[:n_entries] = sessions
            self._alive = None
            if removed is not None and removed.size:
                self._alive = np.ones(cap, bool)
                self._alive[removed] = False
            self._snap = None
            self._changed.notify_all()

    # ------------------------------------------------------------------ adding
    def add(self, words: np.ndarray, weights: np.ndarray, session: int = 0) -> int:
        """Append the next entry's BoW vector; returns its id."""
        w = np.asarray(words, np.int32)
        with self._lock:
            entry = self.n_entries
            t = self._tail
            t.append(w, np.asarray(weights, np.float32), session)
            if entry >= self._sessions.shape[0]:
                self._grow(2 * self._sessions.shape[0])
            self._sessions[entry] = session
            self.n_entries = entry + 1
            self._snap = None
            if t.size >= self.tail_limit:
                self._seal()
        self._after_add(int(w.shape[0]))
        return entry

    def _grow(self, cap: int) -> None:
        sessions = np.zeros(cap, np.int32)
        sessions[: self._sessions.shape[0]] = self._sessions
        self._sessions = sessions
        if self._alive is not None:
            alive = np.ones(cap, bool)
            alive[: self._alive.shape[0]] = self._alive
            self._alive = alive

    def _seal(self) -> None:
        t = self._tail
        if not t.sessions:
            return
        words, postings = t.arrays()  # copied out of the tail's buffers, which keep spare room
        block = _Block(t.lo, t.lo + len(t.sessions), words.copy(), postings.copy(),
                       np.array(t.sessions, np.int32))
        self._blocks.append(block)
        self._tail = _Tail(lo=block.hi)
        self._changed.notify_all()

    def _after_add(self, n_postings: int) -> None:
        if self._thread is None:
            # inline maintenance: at most one bounded step per add, paid for by the postings
            # added (each posting is merged about log2(n) times)
            self._credit += 32 * n_postings
            if len(self._blocks) >= FAN_IN or (self._credit >= self.chunk and not self._idle):
                done = self.step()
                if done is None:
                    self._idle, self._credit = True, 0
                else:
                    self._credit = max(self._credit - max(done, 0), 0)
            return
        if len(self._blocks) > MAX_BLOCKS or len(self._segments) > MAX_SEGMENTS:
            self.step()  # the background thread falls behind (a busy machine): one step of help
        if len(self._blocks) > 2 * MAX_BLOCKS:  # the hard limit on unsorted postings
            with self._lock:
                deadline = time.monotonic() + 60
                while len(self._blocks) > 2 * MAX_BLOCKS and self._broken is None and not self._stop:
                    if not self._changed.wait(timeout=max(deadline - time.monotonic(), 0.01)):
                        break

    def remove(self, ids: np.ndarray) -> None:
        """Leave these entries out of every query from now on (their postings stay until
        :meth:`compact`)."""
        with self._lock:
            alive = np.ones(self._sessions.shape[0], bool) if self._alive is None else self._alive.copy()
            alive[np.asarray(ids, np.int64)] = False
            self._alive = alive  # copy on write: snapshots keep the mask they were taken with
            self._snap = None

    # ------------------------------------------------------------------ maintenance
    def step(self) -> int | None:
        """Run one bounded maintenance step; returns the postings it handled (None: idle)."""
        with self._lock:
            if self._broken is not None:
                return None
            job = self._claim()
            if job is None:
                return None
        try:
            done, work = self._advance(job)
        except Exception as exc:  # noqa: BLE001 - a failed job must not take the index down
            self._failed(job, exc)
            return 0
        with self._lock:
            job.claimed = False
            if job.dropped:
                if job.merge is not None:
                    job.merge.abort()
                if done and job.merge is not None and job.merge.result is not None:
                    self._discard([job.merge.result])
                return work
            old = self._install(job) if done else []
            self._changed.notify_all()
        self._discard(old)
        return work

    def _advance(self, job: _Job) -> tuple[bool, int]:
        if job.blocks:
            bs = job.blocks
            # in memory first: with a store, the next job writes it to a file in bounded steps
            seg = sort_blocks([(b.words, b.postings) for b in bs], bs[0].lo, bs[-1].hi,
                              np.concatenate([b.sessions for b in bs]), self.n_words, scratch=self._scratch)
            job.inputs = [seg]
            return True, seg.size
        assert job.merge is not None
        before = job.merge.remaining
        done = job.merge.step()
        if not done and job.merge.waiting:
            return False, 0  # its file is being written: nothing was done
        return done, max(before - job.merge.remaining, 1)

    def _claim(self) -> _Job | None:
        self._plan()
        free = [j for j in self._jobs if not j.claimed]
        if not free:
            return None
        free = [j for j in free if not j.waiting] or free  # one whose file is being written: last
        job = min(free, key=lambda j: j.remaining)
        job.claimed = True
        return job

    def _plan(self) -> None:
        """Start the jobs the index needs: sort the oldest FAN_IN sealed blocks (fewer when
        flushing), persist segments kept in memory, merge adjacent segments of similar size."""
        if ((len(self._blocks) >= FAN_IN or (self._flushing and self._blocks))
                and not any(j.blocks for j in self._jobs)):
            self._jobs.append(_Job([], blocks=self._blocks[:FAN_IN]))
        segs = self._segments
        free = [s for s in segs if id(s) not in self._busy]
        if self.store is not None:
            for s in free:
                if s.name is None:
                    self._start([s])
                    return
        run = self._mergeable(segs)
        if run and self._sound(run):
            self._start(run)

    def _mergeable(self, segs: list[Segment]) -> list[Segment]:
        """The oldest MERGE_FAN_IN adjacent free segments of one size class, newest classes
        first (tiered merging: each posting is merged about log_MERGE_FAN_IN(n / group) times)."""
        # the unit is a sorted group of FAN_IN blocks: smaller segments (a group flushed early, the
        # entries a reopen read back) share its class, so they merge with groups, not strand
        base = FAN_IN * self.tail_limit
        # a file of a reopened map is merged only once its body was checked (by a query, which
        # checks them all in parallel, or by compact): checking it here would stall the add that
        # plans the merge for as long as reading the file takes (2.8 s at 10^6 entries)
        level = [-1 if id(s) in self._busy or (s.path is not None and not s.verified)
                 else _size_class(s.size, base) for s in segs]
        i = len(segs)
        while i > 0:
            j = i - 1
            while j > 0 and level[j - 1] == level[i - 1]:
                j -= 1
            if level[i - 1] >= 0 and i - j >= MERGE_FAN_IN:
                return segs[j : j + MERGE_FAN_IN]
            i = j
        return []

    def _sound(self, inputs: list[Segment]) -> bool:
        """Check the bodies of segments about to be merged (a damaged file merged would come out
        under a fresh checksum). A damaged one is rebuilt from the entries when the index has a
        store (the writer; a warning names it) and False returned: plan again. Without a store
        the damage is raised."""
        for seg in inputs:
            try:
                ensure_verified(seg, self.n_entries)
            except SegmentDamaged as exc:
                if self.store is None:
                    raise
                log.warning("%s; rebuilding it from the entries", exc.problem)
                try:
                    self._replace_from_store([seg])
                except Exception as exc2:  # noqa: BLE001 - queries then refuse the segment in one line
                    log.error("index maintenance stopped: %s", exc2)
                    self._broken = exc2
                    self._changed.notify_all()
                return False
        return True

    def _start(self, inputs: list[Segment], alive: np.ndarray | None = None) -> _Job:
        factory = self.store.sink if self.store is not None else self._memory_sink
        job = _Job(inputs, merge=MergeJob(inputs, factory, self.n_words, self.chunk, alive,
                                          reader=getattr(self.store, "reader", None)))
        self._busy.update(id(s) for s in inputs)
        self._jobs.append(job)
        return job

    def _memory_sink(self, lo: int, hi: int, csr: bool, total: int) -> Sink:
        return MemorySink(lo, hi, csr, self.n_words, total)

    def _install(self, job: _Job) -> list[Segment]:
        """Put a finished job's segment in place and commit the manifest; returns the replaced
        segments whose files are to be deleted."""
        self._jobs.remove(job)
        self._idle = False
        if job.blocks:
            k = len(job.blocks)
            assert all(a is b for a, b in zip(self._blocks[:k], job.blocks, strict=True))
            del self._blocks[:k]
            new = job.inputs[0]
            self._segments.append(new)
            old: list[Segment] = []
        else:
            assert job.merge is not None and job.merge.result is not None
            new = job.merge.result
            old = job.inputs
            i = next(k for k, s in enumerate(self._segments) if s is old[0])
            self._segments[i : i + len(old)] = [new]
            self._busy.difference_update(id(s) for s in old)
        self._snap = None
        if self.store is None:
            return []
        self.store.commit(self._segments)
        return [s for s in old if s.name is not None and s.name != new.name]

    def _discard(self, old: list[Segment]) -> None:
        """Delete replaced segment files, outside the lock (unlinking a large file takes a while)."""
        if old and self.store is not None:
            self.store.discard(old)

    def _failed(self, job: _Job, exc: Exception) -> None:
        with self._lock:
            if job.merge is not None:
                job.merge.abort()
            if job.dropped:
                return
            self._jobs.remove(job)
            self._busy.difference_update(id(s) for s in job.inputs)
            if isinstance(exc, DatabaseError) and self.store is not None and job.merge is not None:
                log.warning("%s; rebuilding entries %d..%d of the index from the database",
                            exc, job.merge.lo, job.merge.hi - 1)
                try:
                    self._replace_from_store(job.inputs)
                    return
                except Exception as exc2:  # noqa: BLE001
                    exc = exc2
            log.error("index maintenance stopped: %s", exc)
            self._broken = exc
            self._changed.notify_all()

    def _replace_from_store(self, inputs: list[Segment]) -> None:
        assert self.store is not None
        for seg in inputs:
            if seg.path is not None:
                self.replace(seg, self.store.rebuild(seg.lo, seg.hi))

    def replace(self, old: Segment, new: Sequence[Segment]) -> None:
        """Put segments covering the same entries in place of one (a repair)."""
        with self._lock:
            if id(old) in self._busy:
                raise DatabaseError("cannot replace a segment that is being merged")
            if new[0].lo != old.lo or new[-1].hi != old.hi:
                raise ValueError("replacement segments must cover the same entries")
            i = next(k for k, s in enumerate(self._segments) if s is old)
            self._segments[i : i + 1] = list(new)
            self._snap = None
            self._idle = False
            if self.store is not None:
                self.store.commit(self._segments)
            self._changed.notify_all()

    def set_store(self, store: SegmentStore | None) -> None:
        """Persist segments from now on (the database became the file's writer)."""
        with self._lock:
            self.store = store
            self._idle = False
            self._changed.notify_all()

    def _run(self) -> None:
        while True:
            with self._lock:
                while not self._stop and (self._broken is not None or not self._has_work()):
                    self._changed.wait()
                if self._stop:
                    return
            if self.step() == 0:  # only a file being written: let its thread get on with it
                with self._lock:
                    self._changed.wait(0.002)

    def _has_work(self) -> bool:
        if any(not j.claimed for j in self._jobs):
            return True
        self._plan()
        return any(not j.claimed for j in self._jobs)

    def flush(self) -> None:
        """Seal the latest additions and finish every maintenance job (persisting everything
        when the index has a store)."""
        with self._lock:
            self._seal()
            self._flushing += 1
            self._idle = False
            self._changed.notify_all()
        try:
            while True:
                if self._broken is not None:
                    raise DatabaseError(f"index maintenance failed: {self._broken}")
                work = self.step()
                if work is None:
                    with self._lock:
                        if not self._jobs and not self._blocks and self._has_no_pending_plan():
                            return
                        self._changed.wait(timeout=0.05)
                elif work == 0:  # only a file being written
                    with self._lock:
                        self._changed.wait(timeout=0.002)
        finally:
            with self._lock:
                self._flushing -= 1

    def _has_no_pending_plan(self) -> bool:
        self._plan()
        return not self._jobs

    def compact(self) -> None:
        """Rewrite every segment without the postings of removed entries."""
        while True:
            self.flush()
            with self._lock:
                if self._jobs:  # the background thread started a merge meanwhile
                    continue
                if self._alive is None or not self._segments:
                    return
                if not self._sound(list(self._segments)):
                    continue
                job = self._start(list(self._segments), self._alive)
                job.claimed = True
                break
        try:
            while True:
                done, work = self._advance(job)
                if done:
                    break
                if work == 0:  # only its file being written
                    time.sleep(0.001)
        except Exception as exc:
            self._failed(job, exc)
            raise
        with self._lock:
            job.claimed = False
            old = self._install(job)
        self._discard(old)

    def close(self) -> None:
        """Stop the maintenance (unfinished jobs are dropped; their inputs stay valid)."""
        with self._lock:
            self._stop = True
            self._changed.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=60)  # a step is short; never hang a closing program
        with self._lock:
            for job in self._jobs:
                if job.merge is not None:
                    job.merge.abort()
            self._jobs = []
            self._busy = set()

    # ------------------------------------------------------------------ querying
    def _snapshot(self) -> _Snapshot:
        with self._lock:
            snap = self._snap
            if snap is not None:
                return snap
            tail, k = self._tail, len(self._tail.sessions)
            blocks = tuple(self._blocks)
            segments = tuple(self._segments)
            n, alive = self.n_entries, self._alive
        # the tail's lists only grow: its first k entries stay
        unsorted = (tail.arrays(k),) if k else ()
        snap = _Snapshot(segments, blocks, unsorted, n, alive)
        with self._lock:
            if self.n_entries == n and self._snap is None and self._segments == list(segments):
                self._snap = snap
        return snap

    def _lookup(self) -> np.ndarray:
        lookup: np.ndarray | None = getattr(self._local, "lookup", None)
        if lookup is None:
            lookup = self._local.lookup = np.zeros(self.n_words, np.float64)
        return lookup

    def postings(self, words: np.ndarray, values: np.ndarray, snap: _Snapshot | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All postings of the given query words.

        Args:
            words: (M,) int32 sorted unique query words.
            values: (M,) float64 query weights.

        Returns:
            entries (P,) int32, entry weights (P,) float32 and the query weight of each
            posting's word (P,) float64.
        """
        snap = snap or self._snapshot()
        post_parts: list[np.ndarray] = []
        v_parts: list[np.ndarray] = []
        ensure_all_verified(snap.segments, snap.n_entries)  # the files of a reopened map, in parallel
        for seg in snap.segments:
            got = seg.gather(words, values)
            if got is not None:
                post_parts.append(got[0])
                v_parts.append(got[1])
        for block in snap.blocks:  # sealed, waiting to be sorted into a segment: by their view
            sw, sp = block.view()
            got = gather_runs(sp, np.searchsorted(sw, words, "left"), np.searchsorted(sw, words, "right"),
                              values)
            if got is not None:
                post_parts.append(got[0])
                v_parts.append(got[1])
        if snap.unsorted:
            lookup = self._lookup()
            lookup[words] = values
            try:
                for bw, bp in snap.unsorted:
                    v = lookup[bw]
                    hit = v != 0
                    post_parts.append(bp[hit])
                    v_parts.append(v[hit])
            finally:
                lookup[words] = 0.0
        if not post_parts:
            return np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(0)
        post = np.concatenate(post_parts) if len(post_parts) > 1 else post_parts[0]
        entries, weights = split(post)
        return entries, weights, np.concatenate(v_parts) if len(v_parts) > 1 else v_parts[0]

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
            entry ids (K,) int64 and their DBoW2 scores (K,) float64, in id order; removed
            entries are left out.
        """
        snap = self._snapshot()
        n = snap.n_entries
        hi = n if max_id is None else max(0, min(int(max_id), n))
        min_id = max(int(min_id), 0)
        if hi <= min_id or words.size == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        ent, w, v = self.postings(words, values, snap)
        if ent.size == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        terms = common_terms(self.scoring, v, w)
        # accumulate over every entry, then keep the id range (cheaper than filtering postings)
        try:
            sums = np.bincount(ent, weights=terms, minlength=n)
        except ValueError as exc:  # negative ids: only a corrupt index file holds them
            raise DatabaseError(f"the inverse index holds invalid entry ids ({exc})") from exc
        if sums.shape[0] != n:
            raise DatabaseError(f"the inverse index holds entry ids beyond the {n} entries")
        sums = sums[min_id:hi]
        if self.scoring == Scoring.KL or not terms.min() > 0:
            present = np.bincount(ent, minlength=n)[min_id:hi] > 0
        else:
            present = sums != 0  # a sum of positive terms is never 0
        if snap.alive is not None:
            present &= snap.alive[min_id:hi]
        ids = np.flatnonzero(present)
        kl = kl_missing_total(values) if self.scoring == Scoring.KL else 0.0
        return ids + min_id, finish(self.scoring, sums[ids], kl)


def _size_class(size: int, base: int) -> int:
    """0 below MERGE_FAN_IN * base postings, then one more per factor MERGE_FAN_IN."""
    c = 0
    limit = base * MERGE_FAN_IN
    while size >= limit:
        c += 1
        limit *= MERGE_FAN_IN
    return c


def empty_segment(lo: int = 0) -> Segment:
    return Segment(lo, lo, empty_postings(), np.zeros(0, np.int32), None, np.zeros(0, np.int32))


OnCommit = Callable[[Sequence[Segment]], None]

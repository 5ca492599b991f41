"""Segment files: round trip, and every damaged or hostile file refused with one line naming
it, before anything is mapped or allocated."""

from __future__ import annotations

import os
import struct
import threading
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

import stablecues.database.segments as segments
from stablecues.database.segments import (
    HEADER_SIZE,
    ChunkReader,
    FileSink,
    MergeJob,
    Segment,
    SegmentWriter,
    header_bytes,
    map_segment,
    pack_postings,
    sort_block,
    sort_blocks,
    split,
    verify_segment,
)
from stablecues.errors import DatabaseError

UUID = bytes(range(16))
N_WORDS = 300


def random_segment(n_entries: int = 50, seed: int = 0, lo: int = 0) -> Segment:
    rng = np.random.default_rng(seed)
    words, post = [], []
    for e in range(lo, lo + n_entries):
        w = np.unique(rng.integers(0, N_WORDS, 30)).astype(np.int32)
        words.append(w)
        post.append(pack_postings(np.full(w.size, e, np.int32), rng.random(w.size)))
    sessions = rng.integers(0, 5, n_entries).astype(np.int32)
    return sort_block(np.concatenate(words), np.concatenate(post), lo, lo + n_entries, sessions, N_WORDS)


def write(seg: Segment, path: Path, csr: bool) -> Segment:
    job = MergeJob([seg], lambda lo, hi, c, t: FileSink(path, UUID, lo, hi, csr, N_WORDS, fsync=False),
                   N_WORDS, chunk=200)
    job.csr = csr
    while not job.step():
        pass
    assert job.result is not None
    return job.result


@pytest.mark.parametrize("csr", [False, True])
def test_round_trip_and_queries(csr: bool, tmp_path: Path) -> None:
    seg = random_segment()
    f = write(seg, tmp_path / "seg-00000001.sci", csr)
    assert (f.indptr is not None) == csr and f.name == "seg-00000001.sci"
    assert np.array_equal(f.postings, seg.postings) and np.array_equal(f.sessions, seg.sessions)
    q = np.array([3, 17, 150, 299], np.int32)
    a, b = seg.gather(q, np.ones(4)), f.gather(q, np.ones(4))
    assert a is not None and b is not None and np.array_equal(a[0], b[0])
    assert verify_segment(f, 50) is None
    again = map_segment(f.path, UUID, N_WORDS)  # type: ignore[arg-type]
    assert np.array_equal(again.postings, seg.postings)


@pytest.mark.parametrize("csr", [False, True])
def test_files_do_not_depend_on_the_announced_size_or_the_step_budget(csr: bool, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The word table is filled chunk by chunk (growing past an announced total that was too
    small) and the tables are written a budget at a time: the file is the same either way."""
    seg = random_segment(80, seed=3)
    files = []
    real = FileSink.finish_step
    for k, (total, budget) in enumerate([(0, 1 << 20), (seg.size, 1 << 20), (7, 64), (seg.size, 1)]):
        path = tmp_path / f"seg-{k:08d}.sci"
        monkeypatch.setattr(FileSink, "finish_step", lambda self, sessions, b=budget: real(self, sessions, b))
        job = MergeJob([seg], lambda lo, hi, c, t, p=path, n=total: FileSink(p, UUID, lo, hi, csr, N_WORDS,
                                                                           fsync=False, total=n),
                       N_WORDS, chunk=100)
        job.csr = csr
        while not job.step():
            pass
        assert job.result is not None and np.array_equal(job.result.postings, seg.postings)
        if not csr:
            assert np.array_equal(job.result.words, seg.words)
        files.append(path.read_bytes())
    assert all(f == files[0] for f in files[1:])


def test_a_csr_table_is_filled_as_postings_arrive(tmp_path: Path) -> None:
    """A CSR file's offsets are written chunk by chunk (words without postings between and
    after the appended ones included), the same table as counting at the end; postings of an
    earlier word after a later one's are refused."""
    sink = FileSink(tmp_path / "seg-00000001.sci", UUID, 0, 3, True, N_WORDS, fsync=False)
    counts = np.zeros(N_WORDS, np.int64)
    for w0, c in ((5, [2, 0, 1]), (8, [0]), (20, [1, 4]), (299, [2])):
        c = np.array(c, np.int64)
        counts[w0 : w0 + c.size] = c
        sink.append(w0, c, pack_postings(np.zeros(int(c.sum()), np.int32), np.ones(int(c.sum()))))
    with pytest.raises(ValueError, match="postings of word 30 appended after word 299's"):
        sink.append(30, np.ones(1, np.int64), pack_postings(np.zeros(1, np.int32), np.ones(1)))
    seg = sink.finish(np.zeros(3, np.int32))
    assert seg.indptr is not None and np.array_equal(seg.indptr, np.concatenate([[0], np.cumsum(counts)]))
    assert np.array_equal(map_segment(tmp_path / "seg-00000001.sci", UUID, N_WORDS).indptr, seg.indptr)


def corrupt(path: Path, offset: int, data: bytes) -> None:
    raw = bytearray(path.read_bytes())
    raw[offset : offset + len(data)] = data
    path.write_bytes(bytes(raw))


def rewrite_header(path: Path, **fields: int) -> None:
    """A header with valid checksums but hostile fields."""
    raw = path.read_bytes()
    names = ["magic", "version", "form", "uuid", "n_words", "lo", "hi", "postings", "crc"]
    values = dict(zip(names, struct.unpack_from("<4sHBx16sQQQQI", raw), strict=True))
    values.update(fields)
    packed = struct.pack("<4sHBx16sQQQQI", *(values[k] for k in names))
    head = packed + struct.pack("<I", zlib.crc32(packed))
    path.write_bytes(head + raw[len(head) :])


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda p: p.write_bytes(b""), "not an index segment file"),
        (lambda p: corrupt(p, 0, b"JUNK"), "not an index segment file"),
        (lambda p: corrupt(p, 30, b"\xff"), "header is corrupt"),
        (lambda p: p.write_bytes(p.read_bytes()[:-7]), "truncated or corrupt"),
        (lambda p: p.write_bytes(p.read_bytes() + b"\0" * 8), "truncated or corrupt"),
        (lambda p: rewrite_header(p, postings=10**15), "claims 1000000000000000 postings"),  # 8 PB
        (lambda p: rewrite_header(p, postings=2**28), "claims 268435456 postings"),  # issue 34: 1.3 GB
        (lambda p: rewrite_header(p, n_words=10**12), "made for"),
        (lambda p: rewrite_header(p, hi=2**40), "not a valid range"),
        (lambda p: rewrite_header(p, lo=60, hi=50), "not a valid range"),
        (lambda p: rewrite_header(p, uuid=bytes(16)), "another database"),
        (lambda p: rewrite_header(p, version=9), "version 9"),
    ],
)
def test_damaged_or_hostile_files_are_refused(damage, message: str, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "seg-00000001.sci"
    write(random_segment(), path, csr=True)
    damage(path)
    with pytest.raises(DatabaseError, match=message) as err:
        map_segment(path, UUID, N_WORDS)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("csr", [False, True])
def test_corrupt_tables_are_refused_and_bodies_found_by_the_checksum(csr: bool, tmp_path: Path) -> None:
    path = tmp_path / "seg-00000001.sci"
    seg = write(random_segment(), path, csr)
    table_at = HEADER_SIZE + 8 * seg.size
    # the ends of the table are checked at open (O(1)) ...
    end_at = table_at + (8 * N_WORDS if csr else 4 * (seg.size - 1))
    corrupt(path, end_at, struct.pack("<q", -5) if csr else struct.pack("<i", 10**6))
    with pytest.raises(DatabaseError, match="corrupt"):
        map_segment(path, UUID, N_WORDS)
    # ... the rest before the file first answers: a table out of order under a checksum made
    # to fit it (a hostile file) is refused by the body's check, naming the file
    hostile = tmp_path / "seg-00000003.sci"
    made = write(random_segment(), hostile, csr)
    corrupt(hostile, table_at + 8, struct.pack("<q", 10**6) if csr else struct.pack("<i", N_WORDS - 1))
    body = hostile.read_bytes()[HEADER_SIZE:]
    form = segments.FORM_CSR if csr else segments.FORM_WORDS
    corrupt(hostile, 0, header_bytes(form, UUID, N_WORDS, made.lo, made.hi, made.size, zlib.crc32(body)))
    problem = verify_segment(map_segment(hostile, UUID, N_WORDS), 50)
    assert problem is not None and "corrupt" in problem and str(hostile) in problem
    path2 = tmp_path / "seg-00000002.sci"
    write(random_segment(), path2, csr)
    corrupt(path2, HEADER_SIZE + 8 * 10 + 4, b"\x7f\xc0\x00\x00")  # a NaN weight in the body
    mapped = map_segment(path2, UUID, N_WORDS)  # the header and tables are fine
    problem = verify_segment(mapped, 50)
    assert problem is not None and "checksum" in problem and str(path2) in problem


def test_merge_of_many_inputs_keeps_entry_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(segments, "CSR_MIN", 100)
    parts = [random_segment(20, seed=s, lo=20 * s) for s in range(4)]
    job = MergeJob(parts, lambda lo, hi, c, t: FileSink(tmp_path / "seg-00000009.sci", UUID, lo, hi, c,
                                                        N_WORDS, fsync=False), N_WORDS, chunk=150)
    while not job.step():
        pass
    out = job.result
    assert out is not None and out.indptr is not None and (out.lo, out.hi) == (0, 80)
    ent, _ = split(out.postings)
    words = np.repeat(np.arange(N_WORDS), np.diff(out.indptr))
    order = np.lexsort((ent, words))
    assert np.array_equal(order, np.arange(order.size))  # sorted by word, then entry
    assert sorted(zip(words.tolist(), ent.tolist(), strict=True)) == sorted(
        (int(w), int(e)) for p in parts for w, e in zip(p.words.tolist(), split(p.postings)[0].tolist(),  # type: ignore[union-attr]
                                                        strict=True))


def _merge(inputs: list[Segment], path: Path, reader: ChunkReader | None, engine: str = "auto",
           alive: np.ndarray | None = None) -> tuple[Segment, int]:
    """Merge into a file (steps until done; with a reader, waiting for what it reads)."""
    job = MergeJob(inputs, lambda lo, hi, c, t: FileSink(path, UUID, lo, hi, c, N_WORDS, fsync=False),
                   N_WORDS, chunk=150, engine=engine, alive=alive, reader=reader)
    idle = 0
    while not job.step():
        if job.waiting:
            idle += 1
            threading.Event().wait(0.001)
            assert idle < 20_000
    assert job.result is not None
    return job.result, idle


@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_a_reader_gives_the_same_merge(engine: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Inputs read ahead by a ChunkReader (files in CSR and word form, one input in memory,
    removed entries dropped) merge into the same file as inputs read by each step."""
    if engine == "compiled":
        pytest.importorskip("numba")
    monkeypatch.setattr(segments, "CSR_MIN", 400)
    alive = np.ones(100, bool)
    alive[[3, 41, 77]] = False
    for drop in (None, alive):
        # a large input in CSR form, two in word form, one in memory
        parts = [random_segment(40, seed=1), *(random_segment(20, seed=s, lo=20 * s) for s in (2, 3, 4))]
        for k in range(3):
            parts[k] = write(parts[k], tmp_path / f"seg-0000000{k + 1}.sci", k == 0)
        assert parts[0].indptr is not None and parts[1].words is not None and parts[3].path is None
        plain, _ = _merge(parts, tmp_path / "seg-00000010.sci", None, engine, drop)
        reader = ChunkReader(ahead=2)
        try:
            ahead, _ = _merge(parts, tmp_path / "seg-00000011.sci", reader, engine, drop)
        finally:
            reader.close()
        assert (tmp_path / "seg-00000010.sci").read_bytes() == (tmp_path / "seg-00000011.sci").read_bytes()
        assert np.array_equal(plain.postings, ahead.postings)
        assert np.array_equal(plain.sessions, ahead.sessions)
        for f in tmp_path.glob("seg-0000001*.sci"):
            f.unlink()


def test_a_step_whose_chunk_is_not_read_yet_does_nothing(tmp_path: Path) -> None:
    """With a reader, a step never reads a file itself: while the reader's thread is held
    back, steps return at once having merged nothing (the job says it is waiting)."""
    seg = write(random_segment(80, seed=6), tmp_path / "seg-00000001.sci", True)
    gate = threading.Event()
    real = MergeJob.read_task
    read_by: set[str] = set()

    def held(self: MergeJob, task: int) -> object:
        gate.wait(30)
        read_by.add(threading.current_thread().name)
        return real(self, task)

    reader = ChunkReader(ahead=3)
    try:
        MergeJob.read_task = held  # type: ignore[method-assign]
        job = MergeJob([seg], lambda lo, hi, c, t: FileSink(tmp_path / "seg-00000002.sci", UUID, lo, hi, c,
                                                            N_WORDS, fsync=False), N_WORDS, chunk=150,
                       reader=reader)
        for _ in range(5):
            assert not job.step()
            assert job.waiting and job.bounds is None and job.next == 0
        gate.set()
        idle = 0
        while not job.step():
            idle += 1
            threading.Event().wait(0.001)
            assert idle < 20_000
    finally:
        MergeJob.read_task = real  # type: ignore[method-assign]
        gate.set()
        reader.close()
    assert job.result is not None and np.array_equal(job.result.postings, seg.postings)
    assert read_by == {"stablecues-reader"}


def test_a_read_ahead_failure_fails_the_step_that_needs_it(tmp_path: Path) -> None:
    """An input file cut short after it was mapped: the reader's error is raised by the step
    that needs the chunk (and the job can be aborted cleanly)."""
    seg = write(random_segment(80, seed=7), tmp_path / "seg-00000001.sci", True)
    assert seg.path is not None
    with open(seg.path, "r+b") as f:
        f.truncate(HEADER_SIZE + 8)
    reader = ChunkReader()
    job = MergeJob([seg], lambda lo, hi, c, t: FileSink(tmp_path / "seg-00000002.sci", UUID, lo, hi, c,
                                                        N_WORDS, fsync=False),
                   N_WORDS, chunk=150, reader=reader)
    try:
        with pytest.raises(DatabaseError, match="seg-00000001.sci: index file shorter than its header says"):
            for _ in range(20_000):
                job.step()
                threading.Event().wait(0.001)
    finally:
        job.abort()
        reader.close()
    assert not (tmp_path / "seg-00000002.sci").exists()


def test_header_checksum_covers_every_field() -> None:
    head = header_bytes(1, UUID, 10, 0, 5, 7, 123)
    fields = head[: struct.calcsize("<4sHBx16sQQQQI")]
    (crc,) = struct.unpack_from("<I", head, len(fields))
    assert crc == zlib.crc32(fields) and len(head) == HEADER_SIZE


def _merge_by_stable_sort(counts: list[np.ndarray], posts: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The reference merge: a stable sort of the inputs' concatenation by word."""
    words = np.concatenate([np.repeat(np.arange(c.size), c) for c in counts])
    order = np.argsort(words, kind="stable")
    return np.bincount(words, minlength=counts[0].size), np.concatenate(posts)[order]


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_merge_runs_is_a_stable_merge_by_word(engine: str) -> None:
    if engine == "compiled":
        pytest.importorskip("numba")
    rng = np.random.default_rng(3)
    for trial in range(20):
        n_words = int(rng.integers(1, 40))
        k = int(rng.integers(1, 6))
        counts = [rng.integers(0, 4, n_words) * (rng.random(n_words) < 0.6) for _ in range(k)]
        if trial % 5 == 0:
            counts[0][:] = 0  # an input with nothing in this chunk
        counts = [c.astype(np.int64) for c in counts]
        posts = [rng.integers(-(2**62), 2**62, int(c.sum())).astype("<i8") for c in counts]
        want = _merge_by_stable_sort(counts, posts)
        got = segments.merge_runs(counts, posts, engine=engine)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        buf = np.full(want[1].size + 2, 7, "<i8")  # in place, into a sink's buffer
        got = segments.merge_runs(counts, posts, engine=engine, out=buf[1:-1])
        assert np.array_equal(got[1], want[1]) and (got[1].size == 0 or np.shares_memory(got[1], buf))
        assert buf[0] == 7 and buf[-1] == 7
    with pytest.raises(ValueError, match="holds 3 postings"):
        segments.merge_runs([np.ones(2, np.int64)], [np.zeros(2, "<i8")], out=np.zeros(3, "<i8"))


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
@pytest.mark.parametrize("csr", [False, True])
@pytest.mark.parametrize("drop", [False, True])
def test_merge_in_memory_drops_removed_entries_and_shifts_ids(
    engine: str, csr: bool, drop: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without removals or shift the merge is written in place into the sink's buffer. The
    inputs keep a word per posting: the compiled engine merges them by counting."""
    if engine == "compiled":
        pytest.importorskip("numba")
    monkeypatch.setattr(segments, "CSR_MIN", 100 if csr else 1 << 30)
    parts = [random_segment(20, seed=s, lo=20 * s) for s in range(3)]
    alive = np.ones(60, bool)
    if drop:
        alive[[0, 7, 21, 59]] = False
    shift = 1000 if drop else 0
    assert all(p.words is not None for p in parts)
    job = MergeJob(parts, lambda lo, hi, c, t: segments.MemorySink(lo, hi, c, N_WORDS, t), N_WORDS,
                   chunk=97, alive=alive if drop else None, shift=shift, engine=engine)
    while not job.step():
        pass
    out = job.result
    assert out is not None and (out.indptr is not None) == csr and (out.lo, out.hi) == (shift, shift + 60)
    words = np.repeat(np.arange(N_WORDS), np.diff(out.indptr)) if out.indptr is not None else out.words
    ent, weights = split(out.postings)
    # the reference: every posting of a living entry, sorted by word then entry, ids shifted
    all_words = np.concatenate([p.words for p in parts])  # type: ignore[misc]
    all_ent, all_w = split(np.concatenate([p.postings for p in parts]))
    keep = alive[all_ent]
    order = np.lexsort((all_ent[keep], all_words[keep]))
    assert np.array_equal(words, all_words[keep][order])
    assert np.array_equal(ent, all_ent[keep][order] + shift)
    assert np.array_equal(weights, all_w[keep][order])


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
@pytest.mark.parametrize("drop", [False, True])
@pytest.mark.parametrize("to_file", [False, True])
def test_merge_of_words_spread_over_a_large_id_space_is_sorted_not_counted(
    engine: str, drop: bool, to_file: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Word ids spread over a space far larger than the postings (an incremental vocabulary's
    2^22 ids) are merged by a stable sort of the word tables, never by arrays the size of the
    space, and give the segment a merge by counting gives."""
    if engine == "compiled":
        pytest.importorskip("numba")
    spread, n_words = 3001, N_WORDS * 3001
    monkeypatch.setattr(segments, "CSR_MIN", 1 << 30)
    parts = [random_segment(20 + 10 * s, seed=s, lo=sum(20 + 10 * k for k in range(s))) for s in range(3)]
    n = parts[-1].hi
    wide = [Segment(p.lo, p.hi, p.postings, (p.words * spread).astype(np.int32), None, p.sessions)
            for p in parts]  # type: ignore[operator]
    alive = np.ones(n, bool)
    if drop:
        alive[[0, 7, 21, n - 1]] = False
    shift = 1000 if drop else 0

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("counted over the id space")

    monkeypatch.setattr(segments, "_counting_sort", refuse)
    monkeypatch.setattr(segments, "merge_runs", refuse)

    def sink(lo: int, hi: int, c: bool, t: int) -> segments.Sink:
        if to_file:
            return FileSink(tmp_path / "m.seg", UUID, lo, hi, c, n_words, fsync=False, total=t)
        return segments.MemorySink(lo, hi, c, n_words, t)

    for chunk in (50, 1 << 20):  # many chunks, and one spanning every word
        job = MergeJob(wide, sink, n_words, chunk=chunk, alive=alive if drop else None, shift=shift,
                       engine=engine)
        while not job.step():
            pass
        out = job.result
        assert out is not None and out.words is not None and (out.lo, out.hi) == (shift, shift + n)
        all_words = np.concatenate([p.words for p in wide])  # type: ignore[misc]
        all_ent, all_w = split(np.concatenate([p.postings for p in wide]))
        keep = alive[all_ent]
        order = np.lexsort((all_ent[keep], all_words[keep]))
        assert np.array_equal(out.words, all_words[keep][order])
        ent, weights = split(out.postings)
        assert np.array_equal(ent, all_ent[keep][order] + shift)
        assert np.array_equal(weights, all_w[keep][order])


def test_merge_runs_refuses_counts_that_do_not_match_the_postings() -> None:
    """A corrupt word table never reaches the compiled copy (which trusts its bounds)."""
    with pytest.raises(DatabaseError, match="counts 4 postings where 1 are stored"):
        segments.merge_runs([np.array([3, 1]), np.array([1, 0])], [np.zeros(1, "<i8"), np.zeros(1, "<i8")])
    with pytest.raises(DatabaseError, match="corrupt"):
        segments.merge_runs([np.array([2, -1])], [np.zeros(1, "<i8")])


def random_blocks(n_blocks: int, per_block: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Unsorted blocks of postings as the index seals them: each entry's words in order."""
    rng = np.random.default_rng(seed)
    out, e = [], 0
    for _ in range(n_blocks):
        words, post = [], []
        for _ in range(per_block):
            w = np.unique(rng.integers(0, N_WORDS, int(rng.integers(0, 40)))).astype(np.int32)
            words.append(w)
            post.append(pack_postings(np.full(w.size, e, np.int32), rng.random(w.size)))
            e += 1
        out.append((np.concatenate(words), np.concatenate(post)))
    return out


@pytest.mark.parametrize("csr", [False, True])
def test_sort_blocks_counting_sort_is_the_numpy_sort(csr: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """Blocks sorted together by counting (compiled) give the segment NumPy's sort gives, and
    that of one block holding them all: by word, then entry."""
    pytest.importorskip("numba")
    monkeypatch.setattr(segments, "CSR_MIN", 100 if csr else 1 << 30)
    blocks = random_blocks(4, 15, seed=11)
    sessions = np.arange(60, dtype=np.int32) % 3
    a = sort_blocks(blocks, 0, 60, sessions, N_WORDS, engine="numpy")
    b = sort_blocks(blocks, 0, 60, sessions, N_WORDS, engine="compiled")
    one = sort_block(np.concatenate([w for w, _ in blocks]), np.concatenate([p for _, p in blocks]), 0, 60,
                     sessions, N_WORDS, engine="compiled")
    for seg in (b, one):
        assert np.array_equal(seg.postings, a.postings) and (seg.indptr is not None) == csr
        assert np.array_equal(seg.indptr if csr else seg.words, a.indptr if csr else a.words)
    # the working arrays kept from call to call (the index's): groups one after another sort
    # into the same ones and give the segments a fresh sort gives, the last one's untouched
    scratch: dict[str, np.ndarray] = {}
    kept = None
    sorted_: list[tuple[Segment, Segment]] = []
    for k in (4, 2, 3):
        want = sort_blocks(blocks[:k], 0, 15 * k, sessions[: 15 * k], N_WORDS, engine="numpy")
        got = sort_blocks(blocks[:k], 0, 15 * k, sessions[: 15 * k], N_WORDS, engine="compiled",
                          scratch=scratch)
        sorted_.append((want, got))
        for w, g in sorted_:  # this one right, and the ones before it untouched by its sort
            assert np.array_equal(w.postings, g.postings)
            assert np.array_equal(w.indptr if csr else w.words, g.indptr if csr else g.words)
        if csr:
            assert kept is None or scratch["dest"] is kept
            kept = scratch["dest"]
            assert not np.shares_memory(got.indptr, kept)  # type: ignore[arg-type]
    words = np.repeat(np.arange(N_WORDS), np.diff(a.indptr)) if csr else a.words
    ent = split(a.postings)[0]
    assert np.array_equal(np.lexsort((ent, words)), np.arange(ent.size))
    if csr:  # the counting sort checks every word and entry id before it writes anything
        bad = [*blocks[:3], (blocks[3][0] + N_WORDS, blocks[3][1])]
        with pytest.raises(ValueError, match="words outside 0..299"):
            sort_blocks(bad, 0, 60, sessions, N_WORDS, engine="compiled")
        with pytest.raises(ValueError, match="entries outside 0..44"):
            sort_blocks(blocks, 0, 45, sessions, N_WORDS, engine="compiled")


@pytest.mark.parametrize("n_words", [300, 2048, 10**6])
def test_sort_blocks_radix_sort_is_the_numpy_sort(n_words: int) -> None:
    """Word-form blocks sorted by radix (the compiled kernels once loaded: one pass up to 2^11
    words, two for 10^6) give the segment NumPy's key sort gives; a word outside the
    vocabulary is refused before anything is sorted."""
    pytest.importorskip("numba")
    from stablecues.vocabulary.engine import compiled_kernels

    assert compiled_kernels() is not None
    rng = np.random.default_rng(12)
    blocks = []
    for b in range(4):  # many postings per word (stability shows), the extreme words present
        w = rng.integers(0, min(n_words, 700), 2000).astype(np.int32)
        w[:2] = [0, n_words - 1]
        blocks.append((w, pack_postings(np.repeat(np.arange(100 * b, 100 * b + 100, dtype=np.int32), 20),
                                        rng.random(2000))))
    sessions = np.zeros(400, np.int32)
    a = sort_blocks(blocks, 0, 400, sessions, n_words, engine="numpy")
    b = sort_blocks(blocks, 0, 400, sessions, n_words, engine="compiled")
    assert a.words is not None and b.indptr is None
    assert np.array_equal(a.words, b.words) and np.array_equal(a.postings, b.postings)
    # the working arrays kept from call to call (the index's): a smaller group after a larger
    # one sorts in part of them, a larger one replaces them; the same segments every time
    scratch: dict[str, np.ndarray] = {}
    for k in (4, 2, 4, 1):
        want = sort_blocks(blocks[:k], 0, 100 * k, sessions[: 100 * k], n_words, engine="numpy")
        got = sort_blocks(blocks[:k], 0, 100 * k, sessions[: 100 * k], n_words, engine="compiled",
                          scratch=scratch)
        assert np.array_equal(want.words, got.words) and np.array_equal(want.postings, got.postings)
        assert scratch["words"].shape[0] == scratch["postings"].shape[0] == 8000
    ent = split(b.postings)[0]
    assert np.array_equal(np.lexsort((ent, b.words)), np.arange(ent.size))  # type: ignore[arg-type]
    for bad in (-1, n_words):
        w = blocks[2][0].copy()
        w[5] = bad
        with pytest.raises(ValueError, match=f"words outside 0..{n_words - 1}"):
            sort_blocks([*blocks[:2], (w, blocks[2][1])], 0, 300, sessions, n_words, engine="compiled")


def test_a_small_block_never_loads_the_compiled_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    """Sorting fewer postings than a CSR table is worth (what a reopen reads back from the
    entries) is NumPy's job: it does not import numba and load its cache (about a second in a
    fresh process), which is what a reopen used to spend there."""
    monkeypatch.setattr(segments, "CSR_MIN", 1 << 30)

    def loading() -> None:
        raise AssertionError("the compiled kernels were loaded")

    monkeypatch.setattr(segments, "compiled_kernels", loading)
    blocks = random_blocks(2, 10, seed=4)
    seg = sort_blocks(blocks, 0, 20, np.zeros(20, np.int32), N_WORDS)
    assert seg.words is not None and seg.indptr is None
    monkeypatch.setattr(segments, "CSR_MIN", 100)
    big = random_blocks(4, 15, seed=11)
    assert sum(w.size for w, _ in big) >= segments.csr_threshold(N_WORDS)
    with pytest.raises(AssertionError, match="were loaded"):  # a CSR segment is counted
        sort_blocks(big, 0, 60, np.zeros(60, np.int32), N_WORDS)


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_merge_refuses_entry_ids_out_of_place(engine: str) -> None:
    """A small segment holding an entry id outside its range (corrupt) stops the merge with a
    DatabaseError, whichever engine merges."""
    if engine == "compiled":
        pytest.importorskip("numba")
    parts = [random_segment(20, seed=s, lo=20 * s) for s in range(2)]
    ent, _ = split(parts[1].postings)
    post = parts[1].postings.copy()
    post.view("<i4")[0] = 3  # an entry of the first segment
    parts[1] = Segment(20, 40, post, parts[1].words, None, parts[1].sessions)
    job = MergeJob(parts, lambda lo, hi, c, t: segments.MemorySink(lo, hi, c, N_WORDS, t), N_WORDS,
                   engine=engine)
    with pytest.raises(DatabaseError, match="corrupt"):
        while not job.step():
            pass


@pytest.mark.parametrize("csr", [False, True])
def test_a_writer_thread_writes_the_same_file(csr: bool, tmp_path: Path) -> None:
    """File work done by a SegmentWriter's thread (the index files' way) gives the file the
    caller's own writes give, and the job waits (doing nothing) until the file is complete."""
    seg = random_segment(80, seed=4)
    plain = write(seg, tmp_path / "seg-00000001.sci", csr)
    writer = SegmentWriter()
    gate = threading.Event()
    real_do = FileSink.do

    def slow_do(self: FileSink, op: str, data: object) -> None:
        gate.wait(30)
        real_do(self, op, data)

    path = tmp_path / "seg-00000002.sci"
    try:
        FileSink.do = slow_do  # type: ignore[method-assign]
        job = MergeJob([seg], lambda lo, hi, c, t: FileSink(path, UUID, lo, hi, csr, N_WORDS, fsync=False,
                                                            writer=writer), N_WORDS, chunk=100)
        job.csr = csr
        steps = 0
        while not job.waiting:  # every chunk and table queued: only the file work is left
            assert not job.step()
            steps += 1
            assert steps < 1000
        assert not path.exists() and not job.step() and job.waiting
        gate.set()
        while not job.step():
            writer.wait(job.sink, 1.0)  # type: ignore[arg-type]
    finally:
        FileSink.do = real_do  # type: ignore[method-assign]
        gate.set()
        writer.close()
    assert job.result is not None and np.array_equal(job.result.postings, seg.postings)
    assert path.read_bytes() == Path(plain.path).read_bytes()  # type: ignore[arg-type]


def test_a_step_never_waits_for_a_writer_far_behind(tmp_path: Path) -> None:
    """Once more than max_behind bytes wait for the writer's thread (a slow disk), steps do
    nothing and return at once instead of queueing more; the file is the same in the end."""
    seg = random_segment(200, seed=8)
    plain = write(seg, tmp_path / "seg-00000001.sci", True)
    writer = SegmentWriter(max_behind=1000)
    gate = threading.Event()
    real_do = FileSink.do

    def slow_do(self: FileSink, op: str, data: object) -> None:
        gate.wait(30)
        real_do(self, op, data)

    path = tmp_path / "seg-00000002.sci"
    try:
        FileSink.do = slow_do  # type: ignore[method-assign]
        job = MergeJob([seg], lambda lo, hi, c, t: FileSink(path, UUID, lo, hi, c, N_WORDS, fsync=False,
                                                            writer=writer), N_WORDS, chunk=100)
        job.csr = True
        steps = 0
        while not job.waiting:
            assert not job.step()
            steps += 1
            assert steps < 1000
        at = job.next
        assert at < len(job.bounds) - 1  # type: ignore[arg-type]
        for _ in range(20):  # the writer is held (30 s): a step that queued more would wait for it
            assert not job.step() and job.waiting and job.next == at
        gate.set()
        while not job.step():
            writer.wait(job.sink, 1.0)  # type: ignore[arg-type]
    finally:
        FileSink.do = real_do  # type: ignore[method-assign]
        gate.set()
        writer.close()
    assert path.read_bytes() == Path(plain.path).read_bytes()  # type: ignore[arg-type]


def test_a_writer_threads_failure_fails_the_job_and_abort_leaves_no_file(tmp_path: Path) -> None:
    seg = random_segment(60, seed=5)
    writer = SegmentWriter()
    path = tmp_path / "seg-00000003.sci"
    real_do = FileSink.do

    def failing(self: FileSink, op: str, data: object) -> None:
        if op == "write":
            raise OSError(28, "No space left on device")
        real_do(self, op, data)

    try:
        FileSink.do = failing  # type: ignore[method-assign]
        job = MergeJob([seg], lambda lo, hi, c, t: FileSink(path, UUID, lo, hi, False, N_WORDS, fsync=False,
                                                            writer=writer), N_WORDS, chunk=50)
        with pytest.raises(DatabaseError, match=r"seg-00000003\.sci: cannot write index file \(No space"):
            for _ in range(1000):
                if job.step():
                    break
                writer.wait(job.sink, 1.0)  # type: ignore[arg-type]
        job.abort()
    finally:
        FileSink.do = real_do  # type: ignore[method-assign]
        writer.close()
    assert not path.exists()


def test_a_writer_thread_syncs_large_files_as_it_goes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file past SYNC_EVERY bytes is synced by the writer's thread as it is written (its dirty
    pages stay bounded), and it is the same file."""
    seg = random_segment(80, seed=6)
    plain = write(seg, tmp_path / "seg-00000001.sci", False)
    synced: list[str] = []
    real = os.fdatasync
    monkeypatch.setattr(segments, "SYNC_EVERY", 2000)
    monkeypatch.setattr(os, "fdatasync",
                        lambda fd: (synced.append(threading.current_thread().name), real(fd)))
    writer = SegmentWriter()
    path = tmp_path / "seg-00000002.sci"
    try:
        job = MergeJob([seg], lambda lo, hi, c, t: FileSink(path, UUID, lo, hi, False, N_WORDS, fsync=False,
                                                            writer=writer), N_WORDS, chunk=100)
        while not job.step():
            writer.wait(job.sink, 1.0)  # type: ignore[arg-type]
    finally:
        writer.close()
    assert synced and set(synced) == {"stablecues-segments"}
    assert path.read_bytes() == Path(plain.path).read_bytes()  # type: ignore[arg-type]


def test_replaced_segments_are_let_go_by_the_discarding_thread(tmp_path: Path) -> None:
    """The thread that deletes replaced segment files holds the last references to their
    mappings (so unmapping them happens there), until it runs."""
    import gc
    import weakref

    from stablecues.database.files import IndexFiles

    d = tmp_path / "map.sqlite-index"
    d.mkdir()
    files = IndexFiles(d, UUID, N_WORDS, False, lambda text: None, lambda lo, hi: [], 0)
    seg = write(random_segment(40, seed=7), d / "seg-00000001.sci", False)
    ref = weakref.ref(seg)
    start: list[Callable[[], None]] = []
    files._after_commit = lambda fn: (start.append(fn), True)[1]  # the manifest "commits" below
    files.discard([seg])
    del seg
    gc.collect()
    assert ref() is not None and (d / "seg-00000001.sci").exists()  # held by the waiting thread
    start[0]()
    files.wait_discarded()
    gc.collect()
    assert ref() is None and not (d / "seg-00000001.sci").exists()


def _mapped_sum(seg: Segment) -> int:
    return int(np.asarray(seg.postings, np.int64).sum()) + int(np.asarray(seg.sessions, np.int64).sum())


def test_a_mapped_segment_file_is_deleted_but_never_shortened(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A replaced file that a query's snapshot still maps is unlinked whole: shortening it (to
    free a large file's blocks step by step) would kill the process with SIGBUS at the next
    page read past the new end. A file nobody maps is shortened step by step as before."""
    from stablecues.database import files

    cut: list[int] = []
    real = os.ftruncate
    monkeypatch.setattr(os, "ftruncate", lambda fd, n: (cut.append(n), real(fd, n))[1])
    mapped = write(random_segment(400, seed=8), tmp_path / "seg-00000001.sci", True)
    want = _mapped_sum(mapped)
    files._unlink([tmp_path / "seg-00000001.sci"], step=512)
    assert not (tmp_path / "seg-00000001.sci").exists() and not cut
    assert _mapped_sum(mapped) == want  # every page still readable
    path = tmp_path / "seg-00000002.sci"
    write(random_segment(400, seed=9), path, True)
    import gc

    gc.collect()  # the write's own mapping is gone: nobody maps this file
    files._unlink([path], step=512)
    assert not path.exists() and len(cut) > 3


def test_a_reader_process_mapping_a_replaced_file_survives_its_deletion(tmp_path: Path) -> None:
    """The same across processes: a reader maps a segment file, the writer's discarding thread
    deletes it meanwhile, and the reader still reads every page (exit code 0, not SIGBUS)."""
    import subprocess
    import sys

    from stablecues.database import files

    path = tmp_path / "seg-00000001.sci"
    want = _mapped_sum(write(random_segment(400, seed=8), path, True))
    code = (
        "import sys, numpy as np\n"
        "from pathlib import Path\n"
        "from stablecues.database.segments import map_segment\n"
        f"seg = map_segment(Path({str(path)!r}), bytes(range(16)), {N_WORDS})\n"
        "print('mapped', flush=True)\n"
        "sys.stdin.readline()\n"
        "print(int(np.asarray(seg.postings, np.int64).sum())\n"
        "      + int(np.asarray(seg.sessions, np.int64).sum()))\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "mapped"
        files._unlink([path], step=512)
        assert not path.exists()
        out, _ = proc.communicate("go\n", timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0 and int(out.strip()) == want


def test_a_file_being_deleted_is_not_mapped(tmp_path: Path) -> None:
    """While the discarding thread holds a file (between its lock and the unlink), mapping it
    is refused as replaced, and ``open_segments`` asks for the manifest to be read again."""
    import fcntl

    from stablecues.database.files import Manifest, SegmentRecord, open_segments
    from stablecues.database.segments import SegmentReplaced

    seg = write(random_segment(40, seed=7), tmp_path / "seg-00000001.sci", False)
    record = SegmentRecord("seg-00000001.sci", seg.lo, seg.hi, seg.size, seg.crc)
    del seg
    import gc

    gc.collect()
    fd = os.open(tmp_path / "seg-00000001.sci", os.O_WRONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(SegmentReplaced, match="seg-00000001.sci: index file is being deleted"):
            map_segment(tmp_path / "seg-00000001.sci", UUID, N_WORDS)
        got, missing = open_segments(tmp_path, Manifest(2, [record]), UUID, N_WORDS, 40)
        assert got == [] and missing
    finally:
        os.close(fd)
    got, missing = open_segments(tmp_path, Manifest(2, [record]), UUID, N_WORDS, 40)
    assert len(got) == 1 and not missing

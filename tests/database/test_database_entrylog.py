"""The entry log (write-behind): adds acknowledged before SQLite holds them survive a SIGKILL,
torn and stale records are never read as entries, a log of another file or of random bytes is
moved aside, a failing SQLite keeps the adds in the log, readers see adds without a flush."""

from __future__ import annotations

import logging
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from test_database_crash import check_consistent

from dbkit import fake_features, fill
from stablecues.database import Database, DatabaseConfig, entrylog
from stablecues.database.entrylog import HEADER_SIZE, Row, log_path, read_log
from stablecues.errors import DatabaseError, InputError
from stablecues.vocabulary import Vocabulary, save_vocabulary

SMALL = DatabaseConfig(tail_postings=250, merge_chunk=120)

# A writer whose SQLite thread never commits after the first ``commits`` batches: every later
# add is acknowledged from the entry log alone, then the process is killed.
STUCK_WRITER = textwrap.dedent(
    """
    import sys, threading, numpy as np
    sys.path.insert(0, {tests!r})
    from dbkit import fake_features
    from stablecues.database import Database, DatabaseConfig
    from stablecues.database import entrylog
    from stablecues.vocabulary import load_vocabulary
    voc = load_vocabulary({voc!r}, levels_up=2)
    db = Database(voc, {db!r}, DatabaseConfig(tail_postings=250, merge_chunk=120))
    first = len(db)
    rng = np.random.default_rng(first)
    for i in range(first, first + {committed}):
        d = rng.integers(0, 256, (100, 32), dtype=np.uint8)
        db.add(*voc.transform(d), fake_features(d), meta={{"i": i}})
    db.flush()  # these are in SQLite; the log starts over at its header
    real = entrylog.EntryWriter._commit
    stuck = threading.Event()
    def commit(self, batch):
        stuck.wait()  # never
        return real(self, batch)
    entrylog.EntryWriter._commit = commit
    for i in range(first + {committed}, first + {committed} + {stuck}):
        d = rng.integers(0, 256, (60, 32), dtype=np.uint8)  # shorter records than the first ones
        db.add(*voc.transform(d), fake_features(d), meta={{"i": i}})
        print("A", i, flush=True)
    print("done", flush=True)
    threading.Event().wait()
    """
)


def run_stuck_writer(voc: Vocabulary, tmp_path: Path, committed: int, stuck: int) -> int:
    voc_path, db_path = tmp_path / "v.scv", tmp_path / "db.sqlite"
    if not voc_path.exists():
        save_vocabulary(voc, voc_path)
    script = STUCK_WRITER.format(tests=str(Path(__file__).parents[1]), voc=str(voc_path), db=str(db_path),
                                 committed=committed, stuck=stuck)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    acked = -1
    try:
        for line in proc.stdout:
            if line.startswith("A"):
                acked = int(line.split()[1])
            if line.startswith("done"):
                break
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    return acked + 1


def test_adds_acknowledged_from_the_log_alone_survive_a_kill(voc: Vocabulary, tmp_path: Path) -> None:
    db_path = tmp_path / "db.sqlite"
    acked = run_stuck_writer(voc, tmp_path, committed=30, stuck=25)
    assert acked == 55
    with sqlite3.connect(db_path) as conn:  # SQLite itself holds only the first 30
        assert conn.execute("SELECT COUNT(*) FROM entries").fetchone()[0] == 30
    assert log_path(db_path).stat().st_size > HEADER_SIZE
    with Database(voc, db_path) as db:  # the log's 25 go into SQLite before the index loads
        assert len(db) == 55
        check_consistent(db, 55, set())
        assert [m["i"] for m in db.column("meta")] == list(range(55))
    assert not log_path(db_path).exists()  # closed with everything in SQLite
    # a second round on the same file: the log's stale records (ids 30..54, longer) lie behind
    # the new ones and are never read as entries
    acked = run_stuck_writer(voc, tmp_path, committed=3, stuck=10)
    assert acked == 55 + 13
    with Database(voc, db_path) as db:
        assert len(db) == 68
        check_consistent(db, 68, set())


def test_a_torn_last_record_loses_that_entry_only(voc: Vocabulary, tmp_path: Path) -> None:
    db_path = tmp_path / "db.sqlite"
    acked = run_stuck_writer(voc, tmp_path, committed=5, stuck=8)
    log = log_path(db_path)
    data = log.read_bytes()
    rows, lost, note = read_log(log, _uuid(db_path), 5)
    assert [r.id for r in rows] == list(range(5, 13)) and not lost and note is None
    end = HEADER_SIZE + sum(len(entrylog.encode(r)) for r in rows)
    # stale records follow when the writer had started the log over by then (most runs; under
    # load the first commit can come late and the log holds the live records alone)
    assert len(data) >= end
    log.write_bytes(data[: end - 7])  # the last add was cut short by the kill
    with Database(voc, db_path) as db:
        assert len(db) == acked - 1
        check_consistent(db, acked - 1, set())


@pytest.mark.parametrize("where", ["body", "length", "magic"])
def test_damage_to_one_record_loses_that_entry_only(
    where: str, voc: Vocabulary, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """30 adds acknowledged from the log alone: one byte damaged in each record in turn (its
    body, its length field, its magic), and every other acknowledged entry survives the reopen
    with its own data; the damaged one is kept as a removed entry and named in a warning; the
    map then takes adds as usual, after all of them."""
    src = tmp_path / "src"
    src.mkdir()
    acked = run_stuck_writer(voc, src, committed=4, stuck=30)
    assert acked == 34
    log_data = log_path(src / "db.sqlite").read_bytes()
    rows, lost, note = read_log(log_path(src / "db.sqlite"), _uuid(src / "db.sqlite"), 4)
    assert [r.id for r in rows] == list(range(4, 34)) and not lost and note is None
    starts = np.cumsum([HEADER_SIZE] + [len(entrylog.encode(r)) for r in rows])[:-1]
    offset = {"body": 40, "length": 5, "magic": 1}[where]
    for k, start in enumerate(starts.tolist()):
        case = tmp_path / f"case{k}"
        shutil.copytree(src, case)
        data = bytearray(log_data)
        data[start + offset] ^= 0x5A
        log_path(case / "db.sqlite").write_bytes(bytes(data))
        damaged = 4 + k
        # a damaged magic loses nothing (the CRC decides); the last record damaged cannot be told
        # from one torn by a kill (never acknowledged): it is not recovered, and named
        gone = [] if where == "magic" else [damaged]
        n = 33 if gone and damaged == 33 else 34
        caplog.clear()
        with caplog.at_level(logging.WARNING), Database(voc, case / "db.sqlite") as db:
            assert len(db) == n  # ids stay: a damaged one inside the log is a removed entry
            kept = [int(i) for i in db.ids()]
            assert kept == [i for i in range(n) if i not in gone]
            assert [m["i"] for m in db.column("meta") if isinstance(m, dict)] == kept
            if gone and n == 34:
                with pytest.raises(InputError, match="removed"):
                    db.entry(damaged)
            d = np.random.default_rng(k).integers(0, 256, (80, 32), dtype=np.uint8)
            assert db.add(*voc.transform(d), fake_features(d), meta={"i": n}) == n
        messages = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        if not gone:
            assert not messages
        elif n == 34:
            assert any(f"ids {damaged};" in m and "1 entry lost" in m for m in messages), messages
        else:
            assert any("the last record (entry 33) is torn or damaged" in m for m in messages), messages
        with Database(voc, case / "db.sqlite") as db:
            assert len(db) == n + 1 and db.ids().tolist()[-1] == n
        shutil.rmtree(case)


def _uuid(db_path: Path) -> bytes:
    with sqlite3.connect(db_path) as conn:
        (value,) = conn.execute("SELECT value FROM meta WHERE key = 'uuid'").fetchone()
    return bytes.fromhex(value) if isinstance(value, str) else bytes(value)


@pytest.mark.parametrize("content", ["random", "other_database", "huge_length"])
def test_a_log_that_is_not_this_maps_is_moved_aside(
    content: str, voc: Vocabulary, images: list[np.ndarray], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    db_path = tmp_path / "map.sqlite"
    with Database(voc, db_path) as db:
        fill(db, voc, images[:4])
    log = log_path(db_path)
    rng = np.random.default_rng(0)
    if content == "random":
        log.write_bytes(rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
    elif content == "other_database":  # a well-formed log with one entry, of another map's id
        row = Row(4, 0.0, 0, b"", b"", "{}", 0)
        log.write_bytes(entrylog._MAGIC + os.urandom(16) + entrylog.encode(row))
    else:  # this map's header, then a record claiming 2 GB
        header = entrylog._MAGIC + _uuid(db_path)
        log.write_bytes(header + b"SCE1" + (2**31 - 1).to_bytes(4, "little") + b"\0" * 40)
    with caplog.at_level(logging.WARNING), Database(voc, db_path) as db:
        assert len(db) == 4 and [m["i"] for m in db.column("meta")] == [0, 1, 2, 3]
        fill(db, voc, images[4:6], start=4)
    if content == "huge_length":  # this map's log, nothing valid in it: read and left
        assert not any("moved" in r.getMessage() for r in caplog.records)
    else:
        aside = [p.name for p in tmp_path.iterdir() if ".unread-" in p.name]
        assert len(aside) == 1 and any("moved to" in r.getMessage() for r in caplog.records)
    with Database(voc, db_path) as db:
        assert len(db) == 6


def test_sqlite_failing_keeps_the_adds_in_the_log(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    db_path = tmp_path / "map.sqlite"
    db = Database(voc, db_path)
    fill(db, voc, images[:3])
    db.flush()
    entries = db._entries
    assert entries is not None

    def fail(batch: object) -> int:
        raise sqlite3.OperationalError("disk I/O error")

    entries._commit = fail  # type: ignore[method-assign]
    fill(db, voc, images[3:4], start=3)  # acknowledged from the log
    with pytest.raises(DatabaseError, match=r"disk I/O error.*stay in .*map\.sqlite-entries"):
        db.flush()
    with pytest.raises(DatabaseError, match="disk I/O error"):
        fill(db, voc, images[4:5], start=4)
    assert db.entry(3).meta == {"i": 3}  # still served from memory
    db.close()
    assert log_path(db_path).exists()  # kept: SQLite does not hold entry 3
    with Database(voc, db_path) as again:
        assert len(again) == 4 and again.entry(3).meta == {"i": 3}
        check_consistent(again, 4, set())


def test_a_reader_sees_adds_without_a_flush(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "map.sqlite"
    with Database(voc, path) as writer:
        fill(writer, voc, images[:8])
        with Database(voc, path, readonly=True) as reader:
            deadline = time.monotonic() + 30
            while len(reader) < 8 and time.monotonic() < deadline:
                time.sleep(0.01)
                reader.refresh()
            assert len(reader) == 8
            bow = writer.entry(5).bow
            assert reader.query(bow, 1)[0].entry_id == 5


def test_pending_entries_read_as_stored_ones(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    """An entry read while only the log holds it is the entry SQLite gives back later."""
    path = tmp_path / "map.sqlite"
    d = images[0]
    with Database(voc, path) as db:
        entries = db._entries
        assert entries is not None
        real = entries._commit
        gate = threading.Event()

        def slow(batch: list) -> int:  # type: ignore[type-arg]
            gate.wait(30)
            return real(batch)

        entries._commit = slow  # type: ignore[method-assign]
        bow, fvec = voc.transform(d)
        feats = fake_features(d)
        pts = np.arange(3 * len(feats), dtype=np.float32).reshape(-1, 3)
        db.add(bow, fvec, feats, points3d=pts, timestamp=2.5, meta={"k": "v"}, arrays={"u": np.ones(3)})
        assert entries.pending(0) is not None
        before = db.entry(0)
        extra = db.extra_arrays(0)
        gate.set()
        db.flush()
        db._cache.clear()
        after = db.entry(0)
    assert before.meta == after.meta == {"k": "v"} and before.timestamp == after.timestamp == 2.5
    for a, b in ((before.points3d, after.points3d), (before.features.descriptors, after.features.descriptors),
                 (before.bow.words, after.bow.words), (extra["u"], after.arrays["u"])):
        assert a is not None and b is not None
        assert np.array_equal(a, b) and a.flags.writeable == b.flags.writeable


def test_a_link_or_folder_in_place_of_the_log_is_refused(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    db_path = tmp_path / "map.sqlite"
    with Database(voc, db_path) as db:
        fill(db, voc, images[:2])
    target = tmp_path / "elsewhere.txt"
    target.write_text("keep me")
    log_path(db_path).symlink_to(target)
    with pytest.raises(DatabaseError, match=r"map\.sqlite-entries: exists and is not an entry log"):
        Database(voc, db_path)
    assert target.read_text() == "keep me"
    log_path(db_path).unlink()
    log_path(db_path).mkdir()
    with pytest.raises(DatabaseError, match="is not an entry log"):
        Database(voc, db_path)
    log_path(db_path).rmdir()
    with Database(voc, db_path) as db:  # the entries were never touched
        assert len(db) == 2 and db.entry(1).meta == {"i": 1}


def test_a_huge_sparse_log_is_mapped_not_read(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    """A 2 GiB sparse entry log (a header, then holes) was read whole on open (2.1 GB, issue 34):
    it is mapped, scanned without allocating it, and the map opens with its entries."""
    db_path = tmp_path / "db.sqlite"
    with Database(voc, db_path) as db:
        fill(db, voc, images[:3])
    uuid = _uuid(db_path)
    with log_path(db_path).open("wb") as fh:
        fh.write(entrylog._MAGIC + uuid)
        fh.truncate(2 << 30)
    script = textwrap.dedent(f"""
        import resource, sys
        sys.path.insert(0, {str(Path(__file__).parents[1])!r})
        from stablecues.database import Database
        from stablecues.vocabulary import load_vocabulary
        voc = load_vocabulary({str(tmp_path / "v.scv")!r}, levels_up=2)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        with Database(voc, {str(db_path)!r}) as db:
            print(len(db), (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) // 1024)
        """)
    save_vocabulary(voc, tmp_path / "v.scv")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    n, grown_mb = map(int, out.stdout.split())
    assert n == 3 and grown_mb < 200, out.stdout

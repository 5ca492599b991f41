"""Database: add/query, exclusion, persistence, vocabulary check, crash safety, readers."""

from __future__ import annotations

import os
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

import dbkit
from dbkit import fake_features, fill
from stablecues.database import Database, InvertedIndex
from stablecues.database.files import LogCheckpointer
from stablecues.errors import DatabaseError, InputError
from stablecues.types import Features
from stablecues.vocabulary import Scoring, Vocabulary, save_vocabulary, score, train_vocabulary

N_IMAGES = dbkit.N_IMAGES


def test_image_queried_against_database_comes_first(voc: Vocabulary, images: list[np.ndarray]) -> None:
    db = Database(voc)
    fill(db, voc, images)
    for i in (0, 7, N_IMAGES - 1):
        bow, _ = voc.transform(images[i])
        res = db.query(bow, max_results=5)
        assert res[0].entry_id == i and res[0].score == pytest.approx(1.0)
        assert [r.score for r in res] == sorted((r.score for r in res), reverse=True)
        # scores equal the pairwise DBoW2 score
        other = voc.transform(images[res[1].entry_id])[0]
        assert res[1].score == pytest.approx(score(bow, other, voc.scoring))


def test_noisy_copy_finds_its_original(voc: Vocabulary, images: list[np.ndarray]) -> None:
    db = Database(voc)
    fill(db, voc, images)
    rng = np.random.default_rng(3)
    d = images[12].copy()
    bits = np.unpackbits(d, axis=1)
    bits[rng.random(bits.shape) < 0.02] ^= 1
    bow, _ = voc.transform(np.packbits(bits, axis=1))
    assert db.query(bow, 3)[0].entry_id == 12


def test_exclusion_by_count_and_by_id(voc: Vocabulary, images: list[np.ndarray]) -> None:
    db = Database(voc)
    fill(db, voc, images)
    bow, _ = voc.transform(images[-1])
    res = db.query(bow, max_results=0, exclude_recent=5)
    assert res and max(r.entry_id for r in res) < N_IMAGES - 5
    res = db.query(bow, max_results=0, max_id=10)
    assert res and max(r.entry_id for r in res) < 10
    res = db.query(bow, max_results=0, min_id=20)
    assert res and min(r.entry_id for r in res) >= 20
    assert db.query(bow, max_results=3, exclude_recent=N_IMAGES) == []


def test_entry_round_trip(voc: Vocabulary, images: list[np.ndarray]) -> None:
    db = Database(voc)
    fill(db, voc, images, with_3d=True)
    e = db.entry(4)
    bow, fvec = voc.transform(images[4])
    np.testing.assert_array_equal(e.bow.words, bow.words)
    np.testing.assert_array_equal(e.fvec.nodes, fvec.nodes)
    np.testing.assert_array_equal(e.features.descriptors, images[4])
    assert e.points3d is not None and e.points3d.shape == (images[4].shape[0], 3)
    assert e.timestamp == 4.0 and e.meta == {"i": 4}
    with pytest.raises(InputError):
        db.entry(999)


def test_memory_entries_equal_stored_ones_and_keep_their_own_copy(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    """A memory database holds its entries' arrays unpacked: what it gives back is what a file
    gives back (values, dtypes, read-only), whatever the caller does to its arrays afterwards."""
    mem, disk = Database(voc), Database(voc, tmp_path / "db.sqlite")
    feats = fake_features(images[3].copy())
    pts = np.full((feats.keypoints.shape[0], 3), 2.0, np.float32)
    for db in (mem, disk):
        fill(db, voc, images[:3], with_3d=True)
        bow, fvec = voc.transform(feats.descriptors)
        db.add(bow, fvec, feats, points3d=pts, timestamp=float("nan"), pose=np.eye(4),
               arrays={"sigma": np.arange(feats.keypoints.shape[0], dtype=np.float64)})
    feats.descriptors[:] = 0  # the caller reuses its buffers
    feats.keypoints[:] = -1
    pts[:] = 0
    for i in range(4):
        a, b = mem.entry(i), disk.entry(i)
        for get in (lambda e: e.bow.words, lambda e: e.bow.weights, lambda e: e.fvec.nodes,
                    lambda e: e.features.keypoints, lambda e: e.features.descriptors,
                    lambda e: e.features.octaves, lambda e: e.features.angles,
                    lambda e: e.features.responses, lambda e: e.features.sizes, lambda e: e.points3d,
                    lambda e: e.pose):
            x, y = get(a), get(b)
            if y is None:
                assert x is None
                continue
            assert x.dtype == y.dtype and x.flags.writeable == y.flags.writeable
            np.testing.assert_array_equal(x, y)
        assert a.features.image_size == b.features.image_size and a.meta == b.meta
        assert a.timestamp == b.timestamp or (np.isnan(a.timestamp) and np.isnan(b.timestamp))
    np.testing.assert_array_equal(mem.entry(3).features.descriptors, images[3])
    for db in (mem, disk):  # nor can the stored arrays be made writable again
        with pytest.raises(ValueError):
            db.entry(3).features.descriptors.flags.writeable = True
    assert float(mem.entry(3).points3d.max()) == 2.0  # type: ignore[union-attr]
    np.testing.assert_array_equal(mem.extra_arrays(3)["sigma"], disk.extra_arrays(3)["sigma"])
    assert mem.column("meta") == disk.column("meta")
    # removed entries leave both alike
    for db in (mem, disk):
        assert db.remove([1]) == 1
        with pytest.raises(InputError, match="removed"):
            db.entry(1)
        with pytest.raises(InputError, match="removed"):
            db.extra_arrays(1)
    disk.close()
    mem.close()


def test_memory_index_rebuilt_from_its_entries(voc: Vocabulary, images: list[np.ndarray]) -> None:
    """A memory database's SQLite rows hold no BoW vectors: its index is rebuilt (refresh,
    repair) from the vectors it holds, removed entries left out."""
    db = Database(voc)
    fill(db, voc, images)
    db.remove([2, 5])
    queries = [voc.transform(d)[0] for d in images]
    before = [db.scores(q) for q in queries]
    db.refresh()
    db._rebuild(list(db.index.segments))
    for q, b in zip(queries, before, strict=True):
        np.testing.assert_array_equal(db.scores(q), b)
    assert db.scores(queries[2])[2] == 0 and db.query(queries[7], 1)[0].entry_id == 7
    db.close()


def test_persistence_gives_identical_queries(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "db.sqlite"
    with Database(voc, path) as db:
        fill(db, voc, images[:20])
        before = [db.query(voc.transform(d)[0], 5, exclude_recent=2) for d in images]
    with Database(voc, path) as db:
        assert len(db) == 20
        after = [db.query(voc.transform(d)[0], 5, exclude_recent=2) for d in images]
        assert after == before
        fill(db, voc, images[20:])  # continues where it stopped
        assert len(db) == N_IMAGES and db.entry(25).meta == {"i": 5}


def test_refuses_another_vocabulary(voc: Vocabulary, images: list[np.ndarray], tmp_path: Path) -> None:
    path = tmp_path / "db.sqlite"
    Database(voc, path).close()
    other = train_vocabulary(images, k=6, levels=4, seed=1, levels_up=2, progress=False)
    with pytest.raises(DatabaseError, match="not with this vocabulary"):
        Database(other, path)


def test_corrupt_and_truncated_files(voc: Vocabulary, images: list[np.ndarray], tmp_path: Path) -> None:
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(DatabaseError, match="junk.db"):
        Database(voc, junk)
    assert junk.read_bytes() == b"this is not sqlite" * 100  # nothing overwritten
    good = tmp_path / "good.db"
    with Database(voc, good) as db:
        fill(db, voc, images)
    with sqlite3.connect(good) as conn:
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    data = good.read_bytes()
    cut = tmp_path / "cut.db"
    cut.write_bytes(data[: len(data) // 3])
    with pytest.raises(DatabaseError, match="cut.db"):
        db2 = Database(voc, cut)
        for i in range(len(db2)):
            db2.entry(i)
    with pytest.raises(DatabaseError, match="not found"):
        Database(voc, tmp_path / "missing.db", readonly=True)


def test_empty_features_are_stored_and_queried(voc: Vocabulary, images: list[np.ndarray]) -> None:
    db = Database(voc)
    bow, fvec = voc.transform(np.zeros((0, 32), np.uint8))
    eid = db.add(bow, fvec, Features.empty((64, 48)))
    assert db.entry(eid).features.descriptors.shape == (0, 32)
    assert db.query(bow, 5) == []
    fill(db, voc, images[:3])
    assert db.query(bow, 5) == []
    assert db.query(voc.transform(images[1])[0], 1)[0].entry_id == 2


@pytest.mark.parametrize("table_from", [1 << 30, 64])  # binary search / CSR word tables
def test_inverted_index_segments_equal_brute_force(table_from: int, monkeypatch: pytest.MonkeyPatch) -> None:
    import stablecues.database.segments as segments

    monkeypatch.setattr(segments, "CSR_MIN", table_from)
    rng = np.random.default_rng(0)
    n_words = 500
    idx = InvertedIndex(n_words, Scoring.L1, tail_limit=300, chunk=500)
    vectors = []
    for _ in range(200):
        w = np.unique(rng.integers(0, n_words, 40)).astype(np.int32)
        v = rng.random(w.size)
        v /= v.sum()
        vectors.append((w, v))
        idx.add(w, v.astype(np.float32))
    assert len(idx.segments) <= 10  # merged logarithmically
    assert any(seg.indptr is not None for seg in idx.segments) == (table_from == 64)
    qw, qv = vectors[17]
    ids, s = idx.scores(qw, qv, max_id=150)
    brute = {}
    for e, (w, v) in enumerate(vectors[:150]):
        common, iq, ie = np.intersect1d(qw, w, return_indices=True)
        if common.size:
            v32 = v.astype(np.float32).astype(np.float64)
            brute[e] = -0.5 * np.sum(np.abs(qv[iq] - v32[ie]) - np.abs(qv[iq]) - np.abs(v32[ie]))
    assert ids.tolist() == sorted(brute)
    np.testing.assert_allclose(s, [brute[e] for e in ids.tolist()], rtol=1e-9)


WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    sys.path.insert(0, {tests!r})
    from dbkit import fake_features
    from stablecues.database import Database
    from stablecues.vocabulary import load_vocabulary
    voc = load_vocabulary({voc!r}, levels_up=2)
    db = Database(voc, {db!r})
    rng = np.random.default_rng(0)
    i = len(db)
    while True:
        d = rng.integers(0, 256, (400, 32), dtype=np.uint8)
        bow, fvec = voc.transform(d)
        db.add(bow, fvec, fake_features(d), meta={{"i": i}})
        print(i, flush=True)
        i += 1
    """
)


def test_killed_writer_loses_at_most_the_entry_in_progress(voc: Vocabulary, tmp_path: Path) -> None:
    voc_path, db_path = tmp_path / "v.scv", tmp_path / "db.sqlite"
    save_vocabulary(voc, voc_path)
    script = WRITER.format(tests=str(Path(__file__).parents[1]), voc=str(voc_path), db=str(db_path))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    done = -1
    deadline = time.time() + 60
    while done < 40 and time.time() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        done = int(line)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert done >= 40, "writer did not start"
    with Database(voc, db_path) as db:
        n = len(db)
        assert n >= done + 1  # every acknowledged add survived
        assert [db.entry(i).meta["i"] for i in range(n)] == list(range(n))
        bow = db.entry(n - 1).bow
        assert db.query(bow, 1)[0].entry_id == n - 1
        with sqlite3.connect(db_path) as conn:
            assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"


def test_concurrent_reader_sees_new_entries_after_refresh(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "db.sqlite"
    writer = Database(voc, path)
    fill(writer, voc, images[:10])
    writer.flush()  # every add in SQLite, where readers look
    reader = Database(voc, path, readonly=True)
    assert len(reader) == 10
    fill(writer, voc, images[10:15])
    writer.flush()
    assert len(reader) == 10
    assert reader.refresh() == 5 and len(reader) == 15
    bow, _ = voc.transform(images[12])
    assert reader.query(bow, 1)[0].entry_id == 12
    with pytest.raises(DatabaseError, match="read-only"):
        reader.add(bow, voc.transform(images[12])[1], fake_features(images[12]))
    reader.close()
    writer.close()


def test_paths_with_uri_characters_are_used_as_given(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "my#map?v=1%.sqlite"
    with Database(voc, path) as db:
        fill(db, voc, images[:3])
    assert path.is_file() and sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".sqlite") == [
        path.name
    ]
    with Database(voc, path) as db:
        assert len(db) == 3


def test_adds_wake_the_log_copying_thread(tmp_path: Path) -> None:
    """The log-copying thread copies as soon as the adding thread has written ``wake_bytes``,
    not only every ``every_s`` (adds back to back would fill SQLite's backstop meanwhile)."""
    path = tmp_path / "log.sqlite"
    conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA wal_autocheckpoint=0")
    conn.execute("CREATE TABLE t (x BLOB)")
    rounds: list[tuple[int, int]] = []
    copied = threading.Event()

    class Counting(LogCheckpointer):
        def checkpoint(self, c: sqlite3.Connection) -> tuple[int, int]:
            res = super().checkpoint(c)
            rounds.append(res)
            if res[0] and res[1] == res[0]:
                copied.set()
            return res

    ck = Counting(path, threading.RLock(), "NORMAL", every_s=3600, wake_bytes=100_000)
    try:
        for _ in range(3):
            conn.execute("INSERT INTO t VALUES (?)", (os.urandom(20_000),))
            ck.wrote(20_000)
        time.sleep(0.3)
        assert rounds == []  # 60 kB written: still asleep
        for _ in range(2):  # no write after the wake: a round racing one copies part of the log
            conn.execute("INSERT INTO t VALUES (?)", (os.urandom(20_000),))
            ck.wrote(20_000)
        assert copied.wait(30)  # 100 kB: woken, the whole log copied into the file
    finally:
        ck.close()
        conn.close()


def test_the_log_stays_short_when_adds_come_back_to_back(voc: Vocabulary, tmp_path: Path) -> None:
    """Entries of ~40 kB added as fast as possible (the log-copying thread cannot drain the log
    then): SQLite's backstop checkpoint keeps the log near 2 MB, not growing with the map."""
    rng = np.random.default_rng(5)
    descs = [rng.integers(0, 256, (1000, 32), dtype=np.uint8) for _ in range(8)]
    prepared = [(*voc.transform(d), fake_features(d)) for d in descs]
    path = tmp_path / "map.sqlite"
    log = Path(str(path) + "-wal")
    largest = 0
    with Database(voc, path) as db:
        for i in range(1500):  # about 60 MB of entries
            bow, fvec, feats = prepared[i % len(prepared)]
            db.add(bow, fvec, feats, timestamp=float(i))
            if log.exists():
                largest = max(largest, log.stat().st_size)
        assert len(db) == 1500
    assert 0 < largest < 8 * 2**20
    with Database(voc, path, readonly=True) as db:
        assert len(db) == 1500 and db.entry(1499).features.descriptors.shape == (1000, 32)


# A SLAM loop on a file map: query, then add, frame after frame. After the first frame nothing
# may be imported: a module's first import inside an add stalls it (NumPy's ``np.unique``
# imported ``numpy.ma`` at the first merge of a reopened map: 8 ms of one add, bench_scale.py).
LOOP_IMPORTS = textwrap.dedent(
    """
    import sys, numpy as np
    sys.path.insert(0, {tests!r})
    from dbkit import fake_features, make_images
    from stablecues.database import Database, DatabaseConfig
    from stablecues.vocabulary import load_vocabulary
    if {incremental}:
        from stablecues.types import DescriptorKind
        from stablecues.vocabulary.incremental import IncrementalVocabulary
        voc = IncrementalVocabulary(DescriptorKind("binary", 32), save_every=7, purge_after=5)
        to_bow = voc.learn
    else:
        voc = load_vocabulary({voc!r}, levels_up=2)
        to_bow = voc.transform
    images = make_images(240, seed=1)
    db = Database(voc, {db!r}, DatabaseConfig(tail_postings=400, merge_chunk=300))
    def frame(k):
        bow, fvec = to_bow(images[k])
        db.query(bow, max_results=5, exclude_recent=3)
        db.add(bow, fvec, fake_features(images[k]))
    frame(0)
    before = set(sys.modules)
    for k in range(1, len(images)):
        frame(k)
    segments = len(db.index._segments)
    db.close()
    print(segments, *sorted(set(sys.modules) - before))
    """
)


@pytest.mark.parametrize("incremental", [False, True], ids=["trained", "incremental"])
def test_a_slam_loop_on_a_file_map_imports_nothing_after_its_first_frame(
    voc: Vocabulary, tmp_path: Path, incremental: bool
) -> None:
    voc_path = tmp_path / "v.scv"
    save_vocabulary(voc, voc_path)
    script = LOOP_IMPORTS.format(tests=str(Path(__file__).parents[1]), voc=str(voc_path),
                                 db=str(tmp_path / "db.sqlite"), incremental=incremental)
    # the NumPy engine: the compiled one imports numba in a thread of its own, beside the adds
    env = dict(os.environ, STABLECUES_ENGINE="numpy")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    segments, *imported = out.stdout.split()
    assert int(segments) >= 2  # the index sorted, persisted and merged segments meanwhile
    assert imported == []

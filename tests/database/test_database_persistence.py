"""The persisted inverse index: reopening maps it (only the latest additions are read back
from the entries), damaged index files are rebuilt from the entries, a format-1 file still
opens, readers follow the writer, one writer at a time."""

from __future__ import annotations

import gc
import json
import logging
import sqlite3
from pathlib import Path

import numpy as np
import pytest

import stablecues.database.store as store
from dbkit import fake_features, fill
from stablecues.database import Database, DatabaseConfig, remove_database
from stablecues.database.files import index_dir
from stablecues.database.packing import pack_arrays
from stablecues.errors import DatabaseError
from stablecues.vocabulary import Vocabulary

SMALL = DatabaseConfig(tail_postings=400, merge_chunk=300)


@pytest.fixture
def loads(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, int]]:
    """Ranges of entries read back from the database to build index segments."""
    seen: list[tuple[int, int]] = []
    real = store._load_segments

    def spy(sql, schema, n_words, lo, hi, held=None):  # type: ignore[no-untyped-def]
        seen.append((lo, hi))
        return real(sql, schema, n_words, lo, hi, held)

    monkeypatch.setattr(store, "_load_segments", spy)
    return seen


def answers(db: Database, voc: Vocabulary, images: list[np.ndarray]) -> list[object]:
    out: list[object] = []
    for d in images[::7]:
        bow = voc.transform(d)[0]
        out.append(db.query(bow, 5, exclude_recent=3))
        out.append(db.scores(bow).tolist())
    return out


def build_map(
    path: Path, voc: Vocabulary, images: list[np.ndarray], config: DatabaseConfig = SMALL
) -> list[object]:
    with Database(voc, path, config) as db:
        fill(db, voc, images)
        db.flush()
        assert all(s.name is not None for s in db.index.segments)
        return answers(db, voc, images)


def test_reopen_maps_the_index(voc: Vocabulary, many_images: list[np.ndarray], tmp_path: Path,
                               loads: list[tuple[int, int]]) -> None:
    path = tmp_path / "map.sqlite"
    before = build_map(path, voc, many_images)
    loads.clear()
    with Database(voc, path, DatabaseConfig(tail_postings=1 << 20)) as db:
        assert loads == [] and len(db) == len(many_images)  # nothing rebuilt
        assert answers(db, voc, many_images) == before
        fill(db, voc, many_images[:40], start=len(many_images))  # continues; kept unsorted
    loads.clear()
    with Database(voc, path, SMALL) as db:
        covered = sum(hi - lo for lo, hi in loads)
        assert covered == 40  # only the latest additions are read back
        assert len(db) == len(many_images) + 40
        assert db.query(voc.transform(many_images[5])[0], 1)[0].entry_id in (5, len(many_images) + 5)


def _segment_files(path: Path) -> list[Path]:
    return sorted(index_dir(path).glob("seg-*.sci"))


@pytest.mark.parametrize("damage", ["delete", "header", "truncate", "swap", "manifest", "hostile-name"])
def test_damaged_index_is_rebuilt_from_the_entries(
    damage: str, voc: Vocabulary, many_images: list[np.ndarray], tmp_path: Path,
    caplog: pytest.LogCaptureFixture, loads: list[tuple[int, int]],
) -> None:
    path = tmp_path / "map.sqlite"
    before = build_map(path, voc, many_images, DatabaseConfig(tail_postings=500))
    files = _segment_files(path)
    assert len(files) >= 2  # one to damage, one to keep
    victim = files[0]
    if damage == "delete":
        victim.unlink()
    elif damage == "header":
        raw = bytearray(victim.read_bytes())
        raw[40] ^= 0xFF
        victim.write_bytes(bytes(raw))
    elif damage == "truncate":
        victim.write_bytes(victim.read_bytes()[:1000])
    elif damage == "swap":  # two valid files exchanged: each covers other entries than named
        other = files[1].read_bytes()
        files[1].write_bytes(victim.read_bytes())
        victim.write_bytes(other)
    else:
        with sqlite3.connect(path) as conn:
            text = "{not json" if damage == "manifest" else json.dumps(
                {"version": 1, "next_gen": 3, "segments": [["../../etc/passwd", 0, 1, 1, 0]]})
            conn.execute("UPDATE meta SET value = ? WHERE key = 'index'", (text,))
    caplog.set_level(logging.WARNING)
    loads.clear()
    with Database(voc, path) as db:
        assert answers(db, voc, many_images) == before
        assert loads  # the uncovered entries were read back
        assert any(str(path) in r.getMessage() for r in caplog.records)
        db.flush()  # ... and written to new index files
        assert db.check() == []
    loads.clear()
    with Database(voc, path) as db:
        assert loads == [] and answers(db, voc, many_images) == before


def test_orphans_and_stale_files_are_deleted_and_nothing_else(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "map.sqlite"
    before = build_map(path, voc, images)
    d = index_dir(path)
    (d / "seg-99999999.sci").write_bytes(b"left by a killed merge")
    (d / "notes.txt").write_text("mine")
    with Database(voc, path) as db:
        assert answers(db, voc, images) == before
    assert not (d / "seg-99999999.sci").exists() and (d / "notes.txt").read_text() == "mine"
    # without its SQLite files the map's index files are refused, never taken over and deleted
    # by a new map (issue 34: a 0-byte or deleted map.sqlite destroyed them); the run command
    # removes a map it starts over with remove_database, files and index alike
    for suffix in ("", "-wal", "-shm"):
        Path(str(path) + suffix).unlink(missing_ok=True)
    stale = {f.name for f in _segment_files(path)}
    with pytest.raises(DatabaseError, match="refusing to start a new map"):
        Database(voc, path)
    assert stale == {f.name for f in _segment_files(path)}
    remove_database(path)
    with Database(voc, path) as db:
        fill(db, voc, images[:5])
        assert db.query(voc.transform(images[3])[0], 1)[0].entry_id == 3
        db.flush()
    assert _segment_files(path)  # the new map's own
    remove_database(path)
    assert not path.exists() and (d / "notes.txt").exists() and not _segment_files(path)


V1_SCHEMA = """
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


def write_format_1(path: Path, voc: Vocabulary, images: list[np.ndarray]) -> None:
    """A map as stablecues 0.1 (database format 1) wrote it, statement for statement."""
    conn = sqlite3.connect(path, isolation_level=None)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.executescript(V1_SCHEMA)
    want = {"format_version": "1", "vocabulary_fingerprint": voc.fingerprint,
            "vocabulary": json.dumps({"k": voc.k, "L": voc.levels, "words": voc.n_words,
                                      "weighting": int(voc.weighting), "scoring": int(voc.scoring)}),
            "levels_up": str(voc.levels_up)}
    conn.executemany("INSERT INTO meta VALUES (?, ?)", list(want.items()))
    for i, d in enumerate(images):
        bow, fvec = voc.transform(d)
        f = fake_features(d)
        payload = {"fvec": fvec.nodes, "keypoints": f.keypoints, "descriptors": f.descriptors,
                   "octaves": f.octaves, "angles": f.angles, "responses": f.responses, "sizes": f.sizes,
                   "image_size": np.array(f.image_size, np.int32)}
        bow_blob = pack_arrays({"words": bow.words, "weights": bow.weights.astype(np.float32)})
        conn.execute("INSERT INTO entries (id, timestamp, n_features, bow, payload, meta) "
                     "VALUES (?, ?, ?, ?, ?, ?)",
                     (i, float(i), len(f), bow_blob, pack_arrays(payload), json.dumps({"i": i})))
    conn.close()


def test_format_1_map_is_read_as_it_is_and_migrated_by_a_writer(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "old.sqlite"
    write_format_1(path, voc, images)
    with Database(voc) as mem:
        fill(mem, voc, images)
        expected = answers(mem, voc, images)
    raw = path.read_bytes()
    with Database(voc, path, readonly=True) as reader:
        assert answers(reader, voc, images) == expected
        assert reader.sessions() == {0: len(images)} and reader.column("session") == [0] * len(images)
        assert reader.entry(4).meta == {"i": 4}
    assert path.read_bytes() == raw and not index_dir(path).exists()  # a reader writes nothing
    with Database(voc, path) as db:
        assert answers(db, voc, images) == expected
        fill(db, voc, images[:3], start=len(images), session=1)
        db.flush()
    with sqlite3.connect(path) as conn:
        assert conn.execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone() == ("2",)
    with Database(voc, path) as db:
        assert db.sessions() == {0: len(images), 1: 3}
        assert db.entry(len(images) + 1).meta == {"i": len(images) + 1}


def test_reader_follows_writer_merges_and_removals(
    voc: Vocabulary, many_images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "map.sqlite"
    writer = Database(voc, path, SMALL)
    fill(writer, voc, many_images[:100])
    writer.flush()
    reader = Database(voc, path, readonly=True)
    assert len(reader) == 100
    fill(writer, voc, many_images[100:], start=100)
    writer.remove([7])
    writer.compact()  # replaces (and deletes) every index file the reader mapped
    assert reader.refresh() == len(many_images) - 100
    assert answers(reader, voc, many_images) == answers(writer, voc, many_images)
    assert 7 not in reader.ids().tolist()
    reader.close()
    writer.close()


def test_one_writer_at_a_time(voc: Vocabulary, images: list[np.ndarray], tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    first = Database(voc, path)
    fill(first, voc, images[:3])
    second = Database(voc, path)  # opening is fine (it reads) ...
    bow, fvec = voc.transform(images[3])
    with pytest.raises(DatabaseError, match="another Database object or process is writing"):
        second.add(bow, fvec, fake_features(images[3]))  # ... writing is not
    first.close()
    second.add(bow, fvec, fake_features(images[3]))  # the file is free: it catches up first
    assert len(second) == 4 and second.entry(2).meta == {"i": 2}
    del second  # dropped without close(): the lock goes with it
    gc.collect()
    with Database(voc, path) as third:
        fill(third, voc, images[4:6], start=4)
        assert len(third) == 6


def test_full_durability(voc: Vocabulary, images: list[np.ndarray], tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    cfg = DatabaseConfig(durability="full", tail_postings=300, maintenance="inline")
    before = build_map(path, voc, images, cfg)
    with Database(voc, path, cfg) as db:
        assert answers(db, voc, images) == before


def test_missing_directory_is_not_created(voc: Vocabulary, tmp_path: Path) -> None:
    with pytest.raises(DatabaseError, match="does not exist"):
        Database(voc, tmp_path / "nope" / "dir" / "map.sqlite")
    assert not (tmp_path / "nope").exists()


def test_a_damaged_segment_body_never_answers(
    voc: Vocabulary, many_images: list[np.ndarray], tmp_path: Path, caplog: pytest.LogCaptureFixture,
) -> None:
    """A flipped byte inside a segment's postings passes the header and table checks of the
    open (a 10^6 map reopens without reading its bodies), but the body is checked before the
    segment first answers: a reader refuses in one line naming the file, the writer rebuilds
    it from the entries (a warning names it) and answers as before; `check` names it too."""
    path = tmp_path / "map.sqlite"
    before = build_map(path, voc, many_images, DatabaseConfig(tail_postings=500))
    victim = _segment_files(path)[0]
    raw = bytearray(victim.read_bytes())
    raw[128 + 8 * 3 + 5] ^= 0x40  # a weight of the 4th posting
    victim.write_bytes(bytes(raw))
    with Database(voc, path, readonly=True) as reader:
        assert len(reader.check()) == 1 and str(victim) in reader.check()[0]
    with Database(voc, path, readonly=True) as reader:
        with pytest.raises(DatabaseError, match="checksum mismatch") as err:
            reader.query(voc.transform(many_images[0])[0], 5)
        assert str(victim) in str(err.value) and "stablecues map repair" in str(err.value)
        assert "\n" not in str(err.value)
    caplog.set_level(logging.WARNING)
    with Database(voc, path) as db:
        assert answers(db, voc, many_images) == before
        assert any(str(victim) in r.getMessage() and "rebuilding" in r.getMessage() for r in caplog.records)
        db.flush()
        assert db.check() == []
    with Database(voc, path, readonly=True) as reader:
        assert answers(reader, voc, many_images) == before


@pytest.mark.parametrize("first", ["merge", "compact"])
def test_a_damaged_segment_met_first_by_maintenance_is_rebuilt(
    first: str, voc: Vocabulary, many_images: list[np.ndarray], tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A damaged segment body met first by a merge (adds, no query) or by `compact` stopped the
    index's maintenance for the rest of the session ("index maintenance stopped"). A reopened
    map's file is now merged only once checked (a merge that checked it stalled an add for
    seconds at 10^6 entries): the adds go on without touching it, the first query checks it and
    rebuilds it from the entries; `compact` checks and rebuilds it itself."""
    path = tmp_path / "map.sqlite"
    cfg = DatabaseConfig(tail_postings=500)
    half = len(many_images) // 2
    build_map(path, voc, many_images[:half], cfg)
    victim = _segment_files(path)[0]
    raw = bytearray(victim.read_bytes())
    raw[128 + 8 * 3 + 5] ^= 0x40  # a weight of the 4th posting
    victim.write_bytes(bytes(raw))
    caplog.set_level(logging.WARNING)
    with Database(voc, path, cfg) as db:
        if first == "merge":
            fill(db, voc, many_images[half:], start=half)
            db.flush()
            assert not any("maintenance stopped" in r.getMessage() for r in caplog.records)
            answers(db, voc, many_images[:1])  # the first query checks the reopened files
        else:
            db.remove([3])
            db.compact()
            fill(db, voc, many_images[half:], start=half)
            db.flush()
        messages = [r.getMessage() for r in caplog.records]
        assert any(str(victim) in m and "rebuilding" in m for m in messages), messages
        assert not any("maintenance stopped" in m for m in messages), messages
        assert db.check() == []
        got = answers(db, voc, many_images)
    expected_path = tmp_path / "clean.sqlite"
    with Database(voc, expected_path, cfg) as clean:
        fill(clean, voc, many_images)
        if first == "compact":
            clean.remove([3])
        assert got == answers(clean, voc, many_images)

"""Damaged and hostile database files (issue 12): each gives one clear line naming the file
and what was expected, never a traceback from deep inside, never an allocation the file does
not justify, and never a write that loses what the file held."""

from __future__ import annotations

import json
import sqlite3
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from dbkit import fill
from stablecues.database import Database
from stablecues.database.packing import pack_arrays, unpack_arrays
from stablecues.errors import DatabaseError, StableCuesError
from stablecues.vocabulary import Vocabulary


def one_line(exc: BaseException, path: Path) -> str:
    text = str(exc)
    assert "\n" not in text and str(path) in text, text
    return text


@pytest.fixture
def small_map(voc: Vocabulary, images: list[np.ndarray], tmp_path: Path) -> Path:
    path = tmp_path / "map.sqlite"
    with Database(voc, path) as db:
        fill(db, voc, images[:8])
        db.flush()  # index files cover every entry: opening reads none of them
    return path


def edit(path: Path, sql: str, args: tuple[object, ...] = ()) -> None:
    with sqlite3.connect(path) as conn:
        conn.execute(sql, args)


@pytest.mark.parametrize(
    ("value", "expected"),
    [("{not json", "meta is not JSON"), ("[1, 2]", "expected an object"), ("[" * 100_000, "not JSON")],
)
def test_entry_meta_that_is_not_a_json_object(
    value: str, expected: str, small_map: Path, voc: Vocabulary
) -> None:
    edit(small_map, "UPDATE entries SET meta = ? WHERE id = 5", (value,))
    with Database(voc, small_map) as db:
        assert db.entry(4).meta == {"i": 4}  # the other entries are fine
        for read in (lambda: db.entry(5), lambda: db.column("meta")):
            with pytest.raises(DatabaseError, match=expected) as err:
                read()
            assert "entry 5" in one_line(err.value, small_map)


def test_loop_detector_reopening_such_a_map_says_so_in_one_line(tmp_path: Path) -> None:
    from stablecues import LoopDetector
    from stablecues.vocabulary import default_vocabulary

    path = tmp_path / "map.sqlite"
    voc = default_vocabulary()
    with Database(voc, path) as db:
        bow, fvec = voc.transform(np.zeros((0, 32), np.uint8))
        from stablecues.types import Features

        db.add(bow, fvec, Features.empty((64, 48)), meta={"frame": 0})
    edit(path, "UPDATE entries SET meta = 'frame=0' WHERE id = 0")
    with pytest.raises(StableCuesError) as err:
        LoopDetector(database=path)
    one_line(err.value, path)


@pytest.mark.parametrize("value", ["yesterday", b"\x00\x01"])
def test_entry_timestamp_that_is_not_a_number(value: object, small_map: Path, voc: Vocabulary) -> None:
    edit(small_map, "UPDATE entries SET timestamp = ? WHERE id = 2", (value,))
    with Database(voc, small_map) as db:
        for read in (lambda: db.entry(2), lambda: db.column("timestamp")):
            with pytest.raises(DatabaseError, match="timestamp is .* expected a number") as err:
                read()
            assert "entry 2" in one_line(err.value, small_map)


def test_session_and_counts_that_are_not_integers(small_map: Path, voc: Vocabulary) -> None:
    edit(small_map, "UPDATE entries SET session = 'x', n_features = 'many' WHERE id = 3")
    with Database(voc, small_map) as db:
        for name in ("session", "n_features"):
            with pytest.raises(DatabaseError, match=f"{name} is str") as err:
                db.column(name)
            one_line(err.value, small_map)
    for f in Path(str(small_map) + "-index").glob("seg-*.sci"):
        f.unlink()  # the sessions are then read from the entries
    with pytest.raises(DatabaseError, match="entry 3: session is str") as err:
        Database(voc, small_map)
    one_line(err.value, small_map)


def test_stored_bow_that_is_not_sorted_words_of_the_vocabulary(
    small_map: Path, voc: Vocabulary, tmp_path: Path
) -> None:
    words = np.array([5, 3, voc.n_words + 9], np.int32)
    bad = pack_arrays({"words": words, "weights": np.ones(3, np.float32)})
    edit(small_map, "UPDATE entries SET bow = ? WHERE id = 6", (bad,))
    with Database(voc, small_map) as db:
        with pytest.raises(DatabaseError, match="not sorted ids below") as err:
            db.entry(6)
        one_line(err.value, small_map)
    # and when the index has to be rebuilt from the entries: the map opens without that entry's
    # vector (named in a warning), and reading it stays one line
    for f in Path(str(small_map) + "-index").glob("seg-*.sci"):
        f.unlink()
    with Database(voc, small_map) as db:
        with pytest.raises(DatabaseError, match="entry 6") as err:
            db.entry(6)
        one_line(err.value, small_map)


def hostile_blob(header: object) -> bytes:
    h = json.dumps(header).encode()
    body = b"SCA1" + struct.pack("<I", len(h)) + h + b"\0" * 16
    return body + struct.pack("<I", zlib.crc32(body))


@pytest.mark.parametrize(
    ("header", "expected"),
    [
        ({"words": ["<i4", [10**9, 10**9], 0]}, "does not fit"),  # 4 EB claimed, 16 bytes held
        ({"words": ["<i4", [-1], 0]}, "bad shape"),
        ({"words": ["|O", [1], 0]}, "not allowed"),
        ({"words": ["<i4", [1], -8]}, "does not fit"),
        ({"words": "<i4"}, "bad array description"),
        ([1, 2], "not an object"),
    ],
)
def test_hostile_blob_headers(header: object, expected: str) -> None:
    with pytest.raises(DatabaseError, match=expected):
        unpack_arrays(hostile_blob(header), "map.sqlite: entry 1")


def test_hostile_blob_length_and_checksum() -> None:
    good = pack_arrays({"a": np.arange(4)})
    long_header = b"SCA1" + struct.pack("<I", 2**31) + good[8:]
    for blob, expected in ((good[:-1], "checksum"), (long_header, "checksum"), (good[:10], "bad magic"),
                           ("text", "expected a blob")):
        with pytest.raises(DatabaseError, match=expected):
            unpack_arrays(blob, "entry")  # type: ignore[arg-type]


def test_hostile_entry_ids(small_map: Path, voc: Vocabulary) -> None:
    edit(small_map, "INSERT INTO entries (id, n_features, bow, payload, meta) VALUES (?, 0, x'', x'', '{}')",
         (10**12,))
    with pytest.raises(DatabaseError, match="entry ids up to 1000000000000") as err:
        Database(voc, small_map)  # and no index of 10^12 entries is allocated
    one_line(err.value, small_map)
    edit(small_map, "UPDATE entries SET id = 20 WHERE id = 10")
    edit(small_map, "DELETE FROM entries WHERE id = 1000000000000")
    edit(small_map, "UPDATE entries SET id = 11 WHERE id = 7")  # a gap at 7..10
    with pytest.raises(DatabaseError, match="not contiguous") as err:
        db = Database(voc, small_map)
        db.entry(7)
    one_line(err.value, small_map)


def test_truncated_and_corrupt_database_files(small_map: Path, voc: Vocabulary, tmp_path: Path) -> None:
    with sqlite3.connect(small_map) as conn:
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    data = small_map.read_bytes()
    rng = np.random.default_rng(0)
    for k in range(12):
        bad = tmp_path / f"bad{k}.sqlite"
        raw = bytearray(data[: len(data) // 2] if k == 0 else data)
        if k:
            at = rng.integers(100, len(raw) - 64, 4)
            for a in at:
                raw[a : a + 16] = rng.integers(0, 256, 16, dtype=np.uint8).tobytes()
        bad.write_bytes(bytes(raw))
        try:
            with Database(voc, bad, readonly=True) as db:
                for i in range(len(db)):
                    db.entry(i)
                db.column("meta")
                db.query(db.entry(0).bow, 3)
        except StableCuesError as exc:  # only the project's one-line errors, nothing else
            one_line(exc, bad)
        assert bad.read_bytes() == bytes(raw)  # a reader never writes


def test_other_sqlite_files_are_refused_untouched(voc: Vocabulary, tmp_path: Path) -> None:
    path = tmp_path / "notes.sqlite"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE notes (t TEXT)")
        conn.execute("INSERT INTO notes VALUES ('keep me')")
    raw = path.read_bytes()
    with pytest.raises(DatabaseError, match="not a stablecues database") as err:
        Database(voc, path)
    one_line(err.value, path)
    assert path.read_bytes() == raw


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [("format_version", "abc", "database format abc"), ("format_version", "3", "database format 3"),
     ("uuid", "zz", "not 32 hex digits"), ("levels_up", "7", "levels_up=7")],
)
def test_hostile_metadata(key: str, value: str, expected: str, small_map: Path, voc: Vocabulary) -> None:
    edit(small_map, "UPDATE meta SET value = ? WHERE key = ?", (value, key))
    with pytest.raises(DatabaseError, match=expected) as err:
        Database(voc, small_map)
    one_line(err.value, small_map)


def test_a_map_without_segments_opens_past_one_corrupt_vector(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A small map (no sealed segments) with one corrupt BoW blob could not be opened at all
    (issue 34, item 3): it opens, the entry is left out of every query and named in a warning,
    reading it is one line, and removing it makes the map whole again."""
    import logging

    db_path = tmp_path / "db.sqlite"
    with Database(voc, db_path) as db:
        fill(db, voc, images[:10])
        bow = db.entry(3).bow
    with sqlite3.connect(db_path) as conn:
        conn.execute("UPDATE entries SET bow = X'00112233' WHERE id = 3")
    conn.close()
    with caplog.at_level(logging.WARNING), Database(voc, db_path) as db:
        assert len(db) == 10
        hits = [r.entry_id for r in db.query(bow, max_results=10)]
        assert hits and 3 not in hits
        with pytest.raises(DatabaseError, match="entry 3: stored arrays are corrupt") as err:
            db.entry(3)
        assert "\n" not in str(err.value)
        assert db.remove([3]) == 1
    assert any("1 entry with a corrupt BoW vector left out of every query (entry 3" in r.getMessage()
               for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING), Database(voc, db_path) as db:
        assert db.ids().tolist() == [0, 1, 2, 4, 5, 6, 7, 8, 9]
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]

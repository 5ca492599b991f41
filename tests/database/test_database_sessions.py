"""Maps that live long: sessions, queries by session, removal by id / session / time with
compaction, and merging map files."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest

from dbkit import brute_scores, fake_features, fill
from stablecues.database import Database, DatabaseConfig, merge_maps
from stablecues.errors import DatabaseError, InputError
from stablecues.vocabulary import Vocabulary, train_vocabulary

SMALL = DatabaseConfig(tail_postings=400, merge_chunk=300)


def two_sessions(db: Database, voc: Vocabulary, images: list[np.ndarray]) -> None:
    fill(db, voc, images[:15])  # session 0
    assert db.new_session() == 1 and db.session == 1
    fill(db, voc, images[15:], start=15)


def test_sessions_are_stored_and_filter_queries(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "map.sqlite"
    with Database(voc, path, SMALL) as db:
        two_sessions(db, voc, images)
        assert db.sessions() == {0: 15, 1: 15}
    with Database(voc, path, SMALL) as db:
        assert db.session == 1  # the latest session continues unless told otherwise
        assert db.column("session") == [0] * 15 + [1] * 15
        bow = voc.transform(images[20])[0]
        every = db.query(bow, 0)
        within = db.query(bow, 0, sessions=1)
        other = db.query(bow, 0, exclude_sessions=db.session)
        assert {r.entry_id for r in within} == {r.entry_id for r in every if r.entry_id >= 15}
        assert {r.entry_id for r in other} == {r.entry_id for r in every if r.entry_id < 15}
        assert db.query(bow, 0, sessions=[0, 1]) == every
        assert within[0].entry_id == 20
        dense = db.scores(bow, exclude_sessions=[1])
        assert np.all(dense[15:] == 0) and np.array_equal(dense[:15], db.scores(bow)[:15])
        with pytest.raises(InputError, match="session"):
            db.query(bow, sessions=["a"])  # type: ignore[list-item]
    with Database(voc, path, session=7) as db:
        assert db.add(*voc.transform(images[0]), fake_features(images[0])) == 30
        assert db.sessions()[7] == 1
    with pytest.raises(InputError, match="session"):
        Database(voc, session=-1)


def test_remove_by_id_session_and_time_then_compact(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "map.sqlite"
    with Database(voc, path, SMALL) as db:
        two_sessions(db, voc, images)
        assert db.remove([3, 4, 999]) == 2
        assert db.remove([3]) == 0  # already removed
        assert db.remove(session=1, before=20.0) == 5  # ids 15..19 (timestamp = id)
        assert db.remove(after=28.0) == 2
        gone = {3, 4, 15, 16, 17, 18, 19, 28, 29}
        assert set(db.ids().tolist()) == set(range(30)) - gone and len(db) == 30
        for i in (4, 17):
            with pytest.raises(InputError, match="removed"):
                db.entry(i)
        assert db.column("meta")[4] is None and np.isnan(db.column("timestamp")[4])
        for d in images[::4]:
            bow = voc.transform(d)[0]
            got = {r.entry_id: r.score for r in db.query(bow, 0)}
            assert not gone & set(got)
            assert got == pytest.approx(brute_scores(db, voc, d))
        before = [db.query(voc.transform(d)[0], 0) for d in images]
        postings = db.index.n_postings
        size = db.stats()["file_bytes"]
        db.compact()
        assert db.index.n_postings < postings and db.stats()["file_bytes"] < size
        assert [db.query(voc.transform(d)[0], 0) for d in images] == before
        with pytest.raises(InputError, match="needs ids"):
            db.remove()
        # ids are never given out again
        assert db.add(*voc.transform(images[0]), fake_features(images[0])) == 30
    with Database(voc, path) as db:
        assert set(db.ids().tolist()) == set(range(31)) - gone
        assert [db.query(voc.transform(d)[0], 0, max_id=30) for d in images] == before


def test_merge_two_maps(voc: Vocabulary, images: list[np.ndarray], tmp_path: Path) -> None:
    a, b, out = tmp_path / "a.sqlite", tmp_path / "b.sqlite", tmp_path / "ab.sqlite"
    with Database(voc, a, SMALL) as db:
        two_sessions(db, voc, images)
        db.remove([2])
    with Database(voc, b, SMALL) as db:
        fill(db, voc, images[5:25], with_3d=True, session=4)
        expected_b = [db.query(voc.transform(d)[0], 0) for d in images]
    report = merge_maps(voc, [a, b], out)
    assert report.entries == 50 and report.offsets == (0, 30) and report.session_offsets == (0, 2)
    da, dbb = Database(voc, a, readonly=True), Database(voc, b, readonly=True)
    with Database(voc, out) as m:
        assert m.sessions() == {0: 14, 1: 15, 6: 20}
        for i in (0, 14, 29):
            assert m.entry(i).meta == da.entry(i).meta
        for i in range(20):
            e, f = m.entry(30 + i), dbb.entry(i)
            assert e.meta == f.meta and np.array_equal(e.points3d, f.points3d)  # type: ignore[arg-type]
            assert np.array_equal(e.features.descriptors, f.features.descriptors)
        with pytest.raises(InputError, match="removed"):
            m.entry(2)
        for d, want in zip(images, expected_b, strict=True):
            bow = voc.transform(d)[0]
            got = m.query(bow, 0, sessions=6)
            assert [(r.entry_id - 30, r.score) for r in got] == [(r.entry_id, r.score) for r in want]
            assert m.query(bow, 0, exclude_sessions=6) == da.query(bow, 0)
        m.flush()
        assert m.check() == []
    da.close()
    dbb.close()
    with pytest.raises(DatabaseError, match="exists"):
        merge_maps(voc, [a, b], out)
    other = train_vocabulary(images, k=6, levels=4, seed=1, levels_up=2, progress=False)
    with pytest.raises(DatabaseError, match="not with this vocabulary"):
        merge_maps(other, [a, b], tmp_path / "x.sqlite")
    assert not (tmp_path / "x.sqlite").exists()
    with pytest.raises(DatabaseError, match="twice"):
        merge_maps(voc, [a, a], tmp_path / "y.sqlite")


def test_merge_counts_every_row(voc: Vocabulary, images: list[np.ndarray], tmp_path: Path) -> None:
    a, out = tmp_path / "a.sqlite", tmp_path / "out.sqlite"
    with Database(voc, a) as db:
        fill(db, voc, images[:4])
    merge_maps(voc, [a], out)
    with sqlite3.connect(out) as conn:
        assert conn.execute("SELECT COUNT(*), MAX(id) FROM entries").fetchone() == (4, 3)

"""SIGKILL a writer while it adds, removes, compacts, and while its index files are being
written and merged: every acknowledged change survives, and the index and the entries never
disagree (the reopened index scores every probe exactly as one rebuilt from the entries)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import stablecues.database.store as store
from stablecues.database import Database, InvertedIndex
from stablecues.database.files import Manifest, index_dir
from stablecues.types import DescriptorKind
from stablecues.vocabulary import Vocabulary, save_vocabulary
from stablecues.vocabulary.incremental import IncrementalVocabulary

WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    sys.path.insert(0, {tests!r})
    from dbkit import fake_features
    from stablecues.database import Database, DatabaseConfig
    from stablecues.vocabulary import load_vocabulary
    incremental = {incremental}
    if incremental:  # words learned from the entries, saved every 7 (a kill lands between saves)
        from stablecues.types import DescriptorKind
        from stablecues.vocabulary.incremental import IncrementalVocabulary
        voc = IncrementalVocabulary(DescriptorKind("binary", 32), save_every=7, purge_after=5)
    else:
        voc = load_vocabulary({voc!r}, levels_up=2)
    cfg = DatabaseConfig(tail_postings=250, merge_chunk=120, maintenance={mode!r})
    db = Database(voc, {db!r}, cfg)
    i = len(db)
    rng = np.random.default_rng(i)
    pool = np.random.default_rng(99).integers(0, 256, (300, 32), dtype=np.uint8)
    while True:
        if incremental:  # places seen again: pool rows with a few bits flipped
            d = pool[rng.integers(0, 300, 100)] ^ (rng.random((100, 32)) < 0.01).astype(np.uint8)
            bow, fvec = voc.learn(d)
        else:
            d = rng.integers(0, 256, (100, 32), dtype=np.uint8)
            bow, fvec = voc.transform(d)
        db.add(bow, fvec, fake_features(d), meta={{"i": i}}, session=i // 50)
        print("A", i, flush=True)
        if {compact} and i % 17 == 16:
            gone = rng.choice(i + 1, 3, replace=False).tolist()
            db.remove(gone)
            print("R", *gone, flush=True)
            db.compact(vacuum=i % 2 == 0)
            print("C", flush=True)
        i += 1
    """
)


def orphans(path: Path) -> int:
    """Index files the manifest does not name (a write or merge was cut short)."""
    import sqlite3

    with sqlite3.connect(path) as conn:
        row = conn.execute("SELECT value FROM meta WHERE key = 'index'").fetchone()
    named = {r.file for r in Manifest.parse(row[0] if row else None, str(path)).segments}
    return sum(f.name not in named for f in index_dir(path).glob("seg-*.sci"))


def check_consistent(db: Database, acked: int, removed: set[int]) -> None:
    n = len(db)
    assert n >= acked  # every acknowledged add survived
    live = db.ids().tolist()
    assert not removed & set(live)  # every acknowledged removal survived
    assert [db.entry(i).meta["i"] for i in live] == live
    # the index as reopened == the index rebuilt from the entries, bit for bit
    voc = db.vocabulary
    ref = InvertedIndex(voc.n_words, voc.scoring)
    segs = store._load_segments(db._sql, db._schema, voc.n_words, 0, n)
    sessions = np.concatenate([s.sessions for s in segs])
    ref.reset(segs, n, sessions, np.setdiff1d(np.arange(n), live))
    assert np.array_equal(db.index.sessions(), sessions)
    for i in live[:: max(len(live) // 12, 1)]:
        bow = db.entry(i).bow
        a, b = db.index.scores(bow.words, bow.weights), ref.scores(bow.words, bow.weights)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        assert db.query(bow, 1)[0].entry_id == i
    assert db.check() == []


def incremental_voc() -> IncrementalVocabulary:
    """The writer's incremental vocabulary (same settings, nothing learned)."""
    return IncrementalVocabulary(DescriptorKind("binary", 32), save_every=7, purge_after=5)


def check_words(db: Database) -> None:
    """The words a reopened map continues with == those learned again from its entries, in order."""
    ref = incremental_voc()
    for i in range(len(db)):
        d = db._stored_of(i)
        assert d is not None  # removed entries are saved in the words before they go
        ref.replay(d)
    got = db.vocabulary
    assert isinstance(got, IncrementalVocabulary)
    assert (got.images, got.words_made, got.words_live) == (ref.images, ref.words_made, ref.words_live)
    n = ref._made  # the ids used
    assert got._made == n and got._cursor == ref._cursor
    assert np.array_equal(got._words[:n], ref._words[:n]) and np.array_equal(got._df[:n], ref._df[:n])
    assert np.array_equal(got._alive[:n], ref._alive[:n]) and np.array_equal(got._last[:n], ref._last[:n])
    assert np.array_equal(got._wkeys[:n], ref._wkeys[:n])


def kill_rounds(voc: Vocabulary | None, tmp_path: Path, mode: str, compact: bool, rounds: int) -> int:
    """``voc`` None: the writer learns an incremental vocabulary (no removals then: a removed
    entry keeps no descriptors to learn again)."""
    voc_path, db_path = tmp_path / "v.scv", tmp_path / "db.sqlite"
    if voc is not None:
        save_vocabulary(voc, voc_path)
    tests = str(Path(__file__).parents[1])
    script = WRITER.format(tests=tests, voc=str(voc_path), db=str(db_path), mode=mode, compact=compact,
                           incremental=voc is None)
    rng = np.random.default_rng(0)
    acked, removed, cut = 0, set(), 0
    for _ in range(rounds):
        proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
        assert proc.stdout is not None
        target = int(rng.integers(3, 40))
        deadline = time.time() + 120
        lines = 0
        while lines < target and time.time() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            kind, *ids = line.split()
            if kind == "A":
                acked = int(ids[0]) + 1
            elif kind == "R":
                removed.update(int(x) for x in ids)
            lines += 1
        time.sleep(float(rng.random()) * 0.004)  # anywhere in the next add, flush or merge
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        assert lines == target, "writer did not run"
        cut += orphans(db_path) > 0
        with Database(voc if voc is not None else incremental_voc(), db_path) as db:
            check_consistent(db, acked, removed)
            if voc is None:
                check_words(db)
    return cut


@pytest.mark.parametrize("mode", ["background", "inline"])
def test_kills_during_adds_and_index_maintenance(mode: str, voc: Vocabulary, tmp_path: Path) -> None:
    kill_rounds(voc, tmp_path, mode, compact=False, rounds=5)


def test_kills_while_an_incremental_vocabulary_learns(tmp_path: Path) -> None:
    """A writer killed between two saves of its words: the reopened map learns the entries added
    since again and continues with exactly the words an uninterrupted writer would have."""
    kill_rounds(None, tmp_path, "background", compact=False, rounds=5)


def test_kills_during_removal_and_compaction(voc: Vocabulary, tmp_path: Path) -> None:
    kill_rounds(voc, tmp_path, "background", compact=True, rounds=5)


@pytest.mark.slow
@pytest.mark.parametrize("compact", [False, True])
def test_many_kills(compact: bool, voc: Vocabulary, tmp_path: Path) -> None:
    cut = kill_rounds(voc, tmp_path, "background", compact=compact, rounds=40)
    assert cut > 0  # some kills did land in the middle of an index write

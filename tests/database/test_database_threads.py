"""One database object shared by real threads: queries and entry reads while threads add and
the background maintenance merges index files."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from dbkit import fake_features
from stablecues.database import Database, DatabaseConfig
from stablecues.vocabulary import Vocabulary

CONFIG = DatabaseConfig(tail_postings=300, merge_chunk=200)  # flushes and merges all the time
BACKGROUND = DatabaseConfig(tail_postings=300, merge_chunk=200, maintenance="background")


def run_threads(targets: list) -> None:  # type: ignore[type-arg]
    errors: list[BaseException] = []

    def guard(fn):  # type: ignore[no-untyped-def]
        def body() -> None:
            try:
                fn()
            except BaseException as exc:  # noqa: BLE001 - re-raised in the main thread
                errors.append(exc)
        return body

    threads = [threading.Thread(target=guard(t)) for t in targets]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert not any(t.is_alive() for t in threads), "a thread hung"
    if errors:
        raise errors[0]


@pytest.mark.parametrize(("path", "config"), [(None, CONFIG), ("map.sqlite", CONFIG), (None, BACKGROUND),
                                              ("map.sqlite", BACKGROUND)])
def test_queries_while_one_thread_adds(
    path: str | None, config: DatabaseConfig, voc: Vocabulary, many_images: list[np.ndarray], tmp_path: Path
) -> None:
    images = many_images[:200]
    bows = [voc.transform(d) for d in images]
    with Database(voc) as ref:  # every query's exact answer against every entry
        for i, (bow, fvec) in enumerate(bows):
            ref.add(bow, fvec, fake_features(images[i]))
        probes = list(range(0, 200, 9))
        exact = {q: dict(zip(*(x.tolist() for x in ref.index.scores(bows[q][0].words, bows[q][0].weights)),
                             strict=True)) for q in probes}
    db = Database(voc, None if path is None else tmp_path / path, config)
    done = threading.Event()
    checked = [0]

    def writer() -> None:
        try:
            for i, (bow, fvec) in enumerate(bows):
                assert db.add(bow, fvec, fake_features(images[i]), meta={"i": i}) == i
        finally:
            done.set()

    def reader(seed: int) -> None:
        rng = np.random.default_rng(seed)
        while not done.is_set() or checked[0] < 50:
            q = int(rng.choice(probes))
            n0 = len(db)
            got = {r.entry_id: r.score for r in db.query(bows[q][0], max_results=0)}
            n1 = len(db)
            want = exact[q]
            assert all(e < n1 and want[e] == s for e, s in got.items())  # bit-identical scores
            assert {e for e in want if e < n0} <= set(got)  # nothing stored is missed
            if n0:
                e = int(rng.integers(0, n0))
                assert db.entry(e).meta == {"i": e}
            checked[0] += 1

    run_threads([writer, *(lambda s=s: reader(s) for s in range(3))])
    db.flush()
    assert len(db) == 200 and db.query(bows[150][0], 1)[0].entry_id == 150
    db.close()


@pytest.mark.parametrize("config", [CONFIG, BACKGROUND])
def test_adds_from_several_threads_get_distinct_ids(
    config: DatabaseConfig, voc: Vocabulary, many_images: list[np.ndarray]
) -> None:
    db = Database(voc, None, config)
    got: list[int] = []
    lock = threading.Lock()

    def adder(part: list[np.ndarray]) -> None:
        for d in part:
            bow, fvec = voc.transform(d)
            eid = db.add(bow, fvec, fake_features(d))
            with lock:
                got.append(eid)

    run_threads([lambda p=many_images[k::3]: adder(p) for k in range(3)])
    assert sorted(got) == list(range(len(many_images)))
    for eid in (0, 123, 299):
        bow = db.entry(eid).bow
        assert db.query(bow, 1)[0].score == pytest.approx(1.0)
    db.close()

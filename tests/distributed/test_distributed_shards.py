"""Sharded maps on a real LocalCluster (two worker processes): entries split by session or by
region, each shard held open by one worker, queries fanned out and merged give the top-K of one
map holding everything (same ids in the same order, scores to 1e-9)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from dbkit import fake_features, make_images
from stablecues.database import Database, DatabaseConfig, merge_maps
from stablecues.distributed import (
    ShardedMap,
    ShardLayout,
    layout_of_maps,
    open_client,
    split_map,
    worker_addresses,
)
from stablecues.errors import ConfigError, DatabaseError, InputError
from stablecues.types import BowVector, QueryResult
from stablecues.vocabulary import Vocabulary

pytest.importorskip("distributed")

SMALL = DatabaseConfig(tail_postings=400, merge_chunk=300)
N = 60  # entries: sessions 0, 1, 2 of 20 each; entries 7 and 33 removed


def _pose(i: int) -> np.ndarray:
    """Camera i drives along x, and each session drifts in y (positions spread along x most)."""
    pose = np.eye(4)
    pose[:3, 3] = [3.0 * (i % 20), 0.5 * (i // 20), 0.0]
    return pose


@pytest.fixture(scope="module")
def pics() -> list[np.ndarray]:
    return make_images(N, seed=4)


@pytest.fixture(scope="module")
def source(voc: Vocabulary, pics: list[np.ndarray], tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("one_map") / "map.sqlite"
    with Database(voc, path, SMALL) as db:
        for i, d in enumerate(pics):
            if i and i % 20 == 0:
                db.new_session()
            bow, fvec = voc.transform(d)
            db.add(bow, fvec, fake_features(d), timestamp=float(i), pose=_pose(i), meta={"i": i},
                   arrays={"sigma": np.full(3, i, np.float32)})
        assert db.remove([7, 33]) == 2
        db.flush()
    return path


@pytest.fixture(scope="module")
def client():  # type: ignore[no-untyped-def]
    with open_client(workers=2, threads_per_worker=1) as c:
        worker_addresses(c, least=2)
        yield c


def _queries(voc: Vocabulary, images: list[np.ndarray]) -> list[BowVector]:
    """The map's own images (each its own best match), mixes of two, and fresh descriptors."""
    rng = np.random.default_rng(9)
    out = [voc.transform(images[i])[0] for i in range(0, N, 3)]
    for i in range(0, N - 1, 7):
        out.append(voc.transform(np.concatenate([images[i][:50], images[i + 1][50:]]))[0])
    out.append(voc.transform(rng.integers(0, 256, (80, 32), dtype=np.uint8))[0])
    out.append(BowVector.empty())
    return out


def _same(got: list[QueryResult], want: list[QueryResult]) -> None:
    assert [r.entry_id for r in got] == [r.entry_id for r in want]
    np.testing.assert_allclose([r.score for r in got], [r.score for r in want], rtol=0, atol=1e-9)


def _check_against(one: Database, sharded: ShardedMap, bows: list[BowVector]) -> None:
    cases = [
        {"max_results": 5},
        {"max_results": 1},
        {"max_results": 0},  # every entry sharing a word
        {"max_results": 8, "exclude_recent": 15},
        {"max_results": 8, "min_id": 10, "max_id": 45},
        {"max_results": 8, "sessions": [0, 2]},
        {"max_results": 8, "exclude_sessions": 1},
        {"max_results": 8, "sessions": 1, "exclude_recent": 25},
    ]
    for kw in cases:
        batch = sharded.query_many(bows, **kw)  # type: ignore[arg-type]
        for bow, got in zip(bows, batch, strict=True):
            _same(got, one.query(bow, **kw))  # type: ignore[arg-type]
    _same(sharded.query(bows[0], 3), one.query(bows[0], 3))


def test_split_by_session_answers_as_one_map(voc: Vocabulary, pics: list[np.ndarray], source: Path,
                                             client, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    layout = split_map(voc, source, tmp_path / "shards", 2, by="session")
    assert layout.entries == N and layout.by == "session"
    held = [np.asarray(s.ids) for s in layout.shards]
    assert sorted(np.concatenate(held).tolist()) == [i for i in range(N) if i not in (7, 33)]
    # whole sessions per shard, balanced: {0, 2} and {1}, or the like
    with Database(voc, source, readonly=True) as one:
        sess = one.index.sessions()
        assert not set(sess[held[0]].tolist()) & set(sess[held[1]].tolist())
        with ShardedMap(client, layout, voc, timeout_s=60) as sharded:
            info = sharded.describe()
            assert len({d["worker"] for d in info}) == 2  # one shard per worker
            assert len({d["pid"] for d in info}) == 2 and os.getpid() not in {d["pid"] for d in info}
            assert sum(d["entries"] for d in info) == N - 2
            assert len(sharded) == len(one)
            _check_against(one, sharded, _queries(voc, pics))


def test_split_by_region_with_more_shards_than_workers(voc: Vocabulary, pics: list[np.ndarray],
                                                       source: Path, client, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    layout = split_map(voc, source, tmp_path / "regions", 3, by="region")
    xs = [sorted({_pose(i)[0, 3] for i in s.ids.tolist()}) for s in layout.shards]
    spans = sorted((min(x), max(x)) for x in xs)
    assert spans[0][1] <= spans[1][0] and spans[1][1] <= spans[2][0]  # slabs along x
    assert max(s.ids.size for s in layout.shards) - min(s.ids.size for s in layout.shards) <= 1
    # the shard files keep everything an entry has
    with Database(voc, layout.shards[1].path, readonly=True) as shard, \
            Database(voc, source, readonly=True) as one:
        gid = int(layout.shards[1].ids[3])
        a, b = shard.entry(3), one.entry(gid)
        np.testing.assert_array_equal(a.features.descriptors, b.features.descriptors)
        np.testing.assert_array_equal(a.pose, b.pose)
        assert a.meta == b.meta and a.timestamp == b.timestamp
        np.testing.assert_array_equal(shard.extra_arrays(3)["sigma"], one.extra_arrays(gid)["sigma"])
        assert shard.column("session")[3] == one.column("session")[gid]

        reloaded = ShardLayout.load(tmp_path / "regions")
        assert [s.ids.tolist() for s in reloaded.shards] == [s.ids.tolist() for s in layout.shards]
        with ShardedMap(client, reloaded, voc, timeout_s=60) as sharded:
            assert len(set(sharded.placement)) == 2 and len(sharded.placement) == 3
            _check_against(one, sharded, _queries(voc, pics))


def test_maps_made_apart_answer_as_their_merge(voc: Vocabulary, pics: list[np.ndarray], client,  # type: ignore[no-untyped-def]
                                               tmp_path: Path) -> None:
    paths = []
    for k, part in enumerate((pics[:25], pics[25:])):
        p = tmp_path / f"robot{k}.sqlite"
        with Database(voc, p, SMALL) as db:
            for i, d in enumerate(part):
                if i == 10:
                    db.new_session()
                bow, fvec = voc.transform(d)
                db.add(bow, fvec, fake_features(d), timestamp=float(i))
            if k == 1:
                db.remove([4])
        paths.append(p)
    merge_maps(voc, paths, tmp_path / "merged.sqlite")
    layout = layout_of_maps(voc, paths)
    assert [s.session_offset for s in layout.shards] == [0, 2] and layout.entries == N
    with Database(voc, tmp_path / "merged.sqlite", readonly=True) as one, \
            ShardedMap(client, layout, voc, timeout_s=60) as sharded:
        assert one.sessions() == {0: 10, 1: 15, 2: 9, 3: 25}  # entry 4 of robot 1 removed
        _check_against(one, sharded, _queries(voc, pics))


def test_layouts_and_splits_refuse_bad_input(voc: Vocabulary, source: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="3 sessions cannot fill 4 shards"):
        split_map(voc, source, tmp_path / "a", 4, by="session")
    with pytest.raises(ConfigError, match="split by"):
        split_map(voc, source, tmp_path / "a", 2, by="time")  # type: ignore[arg-type]
    with pytest.raises(DatabaseError, match="map file not found"):
        split_map(voc, tmp_path / "nope.sqlite", tmp_path / "a", 2)
    no_pose = tmp_path / "no_pose.sqlite"
    with Database(voc, no_pose, SMALL) as db:
        for d in make_images(3, seed=1):
            bow, fvec = voc.transform(d)
            db.add(bow, fvec, fake_features(d))
    with pytest.raises(DatabaseError, match="entry 0 has no pose"):
        split_map(voc, no_pose, tmp_path / "b", 2, by="region")

    layout = split_map(voc, source, tmp_path / "ok", 2)
    with pytest.raises(DatabaseError, match="already there"):
        split_map(voc, source, tmp_path / "ok", 2)
    manifest = tmp_path / "ok" / "shards.json"
    doc = json.loads(manifest.read_text())
    for broken in ({**doc, "shards": []}, {**doc, "entries": -1}, {**doc, "format": "x"},
                   {**doc, "shards": [{"map": 1}]}, {**doc, "entries": 3}):
        manifest.write_text(json.dumps(broken))
        with pytest.raises(DatabaseError, match="shards.json|ids"):
            ShardLayout.load(tmp_path / "ok")
    manifest.write_text("{not json")
    with pytest.raises(DatabaseError):
        ShardLayout.load(manifest)
    ids_file = layout.shards[0].path.with_name(layout.shards[0].path.name + ".ids.npy")
    manifest.write_text(json.dumps(doc))
    np.save(ids_file, np.array([5, 3, 4], np.int64))
    with pytest.raises(DatabaseError, match="strictly increasing"):
        ShardLayout.load(tmp_path / "ok")
    ids_file.write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(DatabaseError, match="not a NumPy array"):
        ShardLayout.load(tmp_path / "ok")


def test_a_shard_that_does_not_match_its_layout_is_refused(voc: Vocabulary, source: Path, client,  # type: ignore[no-untyped-def]
                                                           tmp_path: Path) -> None:
    layout = split_map(voc, source, tmp_path / "s", 2)
    wrong = ShardLayout((layout.shards[0].__class__(layout.shards[0].path, np.arange(N, dtype=np.int64)),),
                        N)
    with pytest.raises(DatabaseError, match="its layout names 60"):
        ShardedMap(client, wrong, voc, timeout_s=60)
    with ShardedMap(client, layout, voc, timeout_s=60) as sharded, pytest.raises(InputError):
        sharded.query_many(["not a bow"])  # type: ignore[list-item]

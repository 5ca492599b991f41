"""Sharded maps: entries split across workers by session or by region, each shard a map file
held open by one worker, queries fanned out to every shard and merged by score.

The merged answer is the one a single map holding every entry gives: the same ids, in the
same order (best score first, ties by the lower id), with the same scores. That holds because
a DBoW2 score depends only on the two BoW vectors (the vocabulary fixes the weights), and each
shard keeps its entries in global id order, so its own tie-breaks agree with the global ones.

Global ids: a map split with :func:`split_map` keeps the ids of the map it came from (each
shard stores which global id each of its entries has); maps made apart (one per robot or per
day) and served with :func:`layout_of_maps` get the ids and sessions
:func:`stablecues.database.merge_maps` would give them, the first map's first.

On a cluster, each worker must be able to open its shard's file at the path in the layout (a
shared file system, or the worker's own disk holding that file).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from ..errors import ConfigError, DatabaseError, DatasetError, InputError
from ..types import BowVector, QueryResult

log = logging.getLogger(__name__)

MANIFEST = "shards.json"
SplitBy = Literal["session", "region"]
_MAX_SHARDS = 4096


@dataclass(frozen=True)
class Shard:
    """One shard: a map file and the global id of each of its entries.

    Attributes:
        path: the shard's map file.
        ids: (n,) int64 global id of local entry 0, 1, ..., strictly increasing.
        session_offset: added to the shard's session ids to give global ones.
    """

    path: Path
    ids: np.ndarray
    session_offset: int = 0


@dataclass(frozen=True)
class ShardLayout:
    """Which entries each shard holds.

    Attributes:
        shards: the shards.
        entries: size of the global id space (the one map's ``len``; removed entries count).
        by: how the entries were split ("session", "region" or "maps").
    """

    shards: tuple[Shard, ...]
    entries: int
    by: str = "session"

    def __post_init__(self) -> None:
        seen = np.concatenate([s.ids for s in self.shards] or [np.zeros(0, np.int64)])
        for s in self.shards:
            if s.ids.ndim != 1 or s.ids.dtype != np.int64 or (s.ids.size > 1 and np.any(np.diff(s.ids) <= 0)):
                raise DatabaseError(f"{s.path}: its global ids must be a strictly increasing int64 list")
        if seen.size and (seen.min() < 0 or seen.max() >= self.entries):
            raise DatabaseError(f"shard ids outside the map's 0..{self.entries - 1}")
        if np.unique(seen).size != seen.size:
            raise DatabaseError("two shards hold the same entry id")

    def save(self, folder: str | Path) -> Path:
        """Write ``folder/shards.json`` and each shard's ids next to its map (``<map>.ids.npy``).
        Shard paths inside ``folder`` are kept relative, so the folder can move."""
        root = Path(folder)
        docs = []
        for s in self.shards:
            ids_path = s.path.with_name(s.path.name + ".ids.npy")
            np.save(ids_path, s.ids, allow_pickle=False)
            docs.append({"map": _relative(s.path, root), "ids": _relative(ids_path, root),
                         "entries": int(s.ids.size), "session_offset": s.session_offset})
        from ..runs import write_json

        path = root / MANIFEST
        write_json(path, {"format": "stablecues-shards", "version": 1, "by": self.by, "entries": self.entries,
                          "shards": docs})
        return path

    @classmethod
    def load(cls, folder: str | Path) -> ShardLayout:
        """Read a layout written by :meth:`save` (``folder`` or its ``shards.json``).

        Raises:
            DatabaseError: missing or malformed manifest or ids file.
        """
        from ..runs import read_json

        path = Path(folder)
        path = path / MANIFEST if path.is_dir() else path
        try:
            doc = read_json(path, "shard layout")
        except DatasetError as exc:
            raise DatabaseError(str(exc)) from None
        shards_doc, entries = doc.get("shards"), doc.get("entries")
        if (doc.get("format") != "stablecues-shards" or not isinstance(shards_doc, list) or not shards_doc
                or len(shards_doc) > _MAX_SHARDS or not _whole(entries)):
            raise DatabaseError(f"{path}: expected a stablecues-shards manifest with 'entries' and a list of "
                                f"1..{_MAX_SHARDS} 'shards'")
        n = int(cast(int, entries))
        shards = [_shard_from(d, path, n) for d in shards_doc]
        return cls(tuple(shards), n, str(doc.get("by", "session")))


def _whole(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _relative(path: Path, root: Path) -> str:
    try:
        return str(path.resolve().relative_to(root.resolve()))
    except ValueError:
        return str(path.resolve())


def _shard_from(doc: object, manifest: Path, entries: int) -> Shard:
    where = f"{manifest}: shard {doc!r:.60}"
    if (not isinstance(doc, dict) or not isinstance(doc.get("map"), str)
            or not isinstance(doc.get("ids"), str) or not _whole(doc.get("session_offset", 0))):
        raise DatabaseError(f"{where}: expected 'map', 'ids' (file names) and 'session_offset'")
    ids_path = manifest.parent / doc["ids"]
    if not ids_path.is_file() or ids_path.stat().st_size > 128 + 8 * entries:
        raise DatabaseError(f"{ids_path}: expected the shard's ids, at most {entries} int64 "
                            "(missing or larger)")
    try:
        ids = np.load(ids_path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DatabaseError(f"{ids_path}: not a NumPy array of ids ({exc})") from exc
    if ids.ndim != 1 or ids.dtype != np.int64:
        raise DatabaseError(f"{ids_path}: expected a 1-D int64 array, found {ids.dtype} {ids.shape}")
    return Shard(manifest.parent / doc["map"], ids, int(doc.get("session_offset", 0)))


# ---------------------------------------------------------------------------------- splitting
def split_map(
    vocabulary: Any,
    source: str | Path,
    out: str | Path,
    shards: int = 2,
    *,
    by: SplitBy = "session",
    config: Any | None = None,
) -> ShardLayout:
    """Split a map file into ``shards`` map files (``out/shard-000.sqlite``, ...) and write
    the layout (``out/shards.json``). Removed entries are left out; ids stay the source's.

    Args:
        vocabulary: the map's vocabulary.
        source: the map file.
        out: folder for the shards (created; it must not hold a layout already).
        shards: how many shards.
        by: "session" (whole sessions per shard, balanced by entry count, largest first) or
            "region" (slabs of equal entry count along the axis in which the entries' camera
            positions spread most; every entry needs a pose).
        config: :class:`~stablecues.database.DatabaseConfig` of the shard maps.

    Raises:
        ConfigError: fewer than 1 shard, an unknown ``by``, or more shards than sessions (or entries).
        DatabaseError: a missing or corrupt source, an entry without a pose (``by="region"``),
            or a layout already in ``out``.
    """
    from ..database import Database

    if by not in ("session", "region"):
        raise ConfigError(f"split by {by!r}: expected 'session' or 'region'")
    if not isinstance(shards, int) or not 1 <= shards <= _MAX_SHARDS:
        raise ConfigError(f"shards: expected 1..{_MAX_SHARDS}, got {shards!r}")
    src_path, root = Path(source), Path(out)
    if not src_path.is_file():
        raise DatabaseError(f"{src_path}: map file not found")
    if (root / MANIFEST).exists():
        raise DatabaseError(f"{root / MANIFEST}: a shard layout is already there")
    paths = [root / f"shard-{k:03d}.sqlite" for k in range(shards)]
    there = [p for p in paths if p.exists()]
    if there:
        raise DatabaseError(f"{there[0]}: exists; split_map writes new shard files")
    root.mkdir(parents=True, exist_ok=True)
    with Database(vocabulary, src_path, readonly=True) as src:
        ids = src.ids()
        sessions = src.index.sessions()[ids].astype(np.int64)
        groups = (_by_session(ids, sessions, shards, src_path) if by == "session"
                  else _by_region(src, ids, shards, src_path))
        made = []
        for path, group in zip(paths, groups, strict=True):
            target = Database(vocabulary, path, config)
            _copy_entries(src, group, sessions[np.searchsorted(ids, group)], target)
            made.append(Shard(path, group))
        layout = ShardLayout(tuple(made), len(src), by)
    layout.save(root)
    return layout


def _by_session(ids: np.ndarray, sessions: np.ndarray, shards: int, where: Path) -> list[np.ndarray]:
    names, counts = np.unique(sessions, return_counts=True)
    if names.size < shards:
        raise ConfigError(f"{where}: {names.size} sessions cannot fill {shards} shards split by session")
    load = np.zeros(shards, np.int64)
    owner: dict[int, int] = {}
    for i in np.lexsort((names, -counts)):  # largest session first, to the least loaded shard
        k = int(np.argmin(load))
        owner[int(names[i])] = k
        load[k] += counts[i]
    of = np.array([owner[int(s)] for s in sessions], np.int64)
    return [ids[of == k] for k in range(shards)]


def _by_region(src: Any, ids: np.ndarray, shards: int, where: Path) -> list[np.ndarray]:
    if ids.size < shards:
        raise ConfigError(f"{where}: {ids.size} entries cannot fill {shards} shards")
    xyz = np.empty((ids.size, 3))
    for n, i in enumerate(ids.tolist()):
        pose = src.entry(i).pose
        if pose is None or not np.isfinite(pose[:3, 3]).all():
            raise DatabaseError(f"{where}: entry {i} has no pose; a split by region needs every entry's pose")
        xyz[n] = pose[:3, 3]
    axis = int(np.argmax(np.ptp(xyz, axis=0))) if ids.size else 0
    order = np.argsort(xyz[:, axis], kind="stable")
    return [np.sort(ids[part]) for part in np.array_split(order, shards)]


def _copy_entries(src: Any, ids: np.ndarray, sessions: np.ndarray, target: Any) -> None:
    """Add the source's entries ``ids`` (in order) to ``target``, and close it."""
    try:
        for i, s in zip(ids.tolist(), sessions.tolist(), strict=True):
            e = src.entry(i)
            target.add(e.bow, e.fvec, e.features, points3d=e.points3d, timestamp=e.timestamp, pose=e.pose,
                       meta=e.meta, arrays=src.extra_arrays(i) or None, session=int(s))
        target.flush()
    finally:
        target.close()


def layout_of_maps(vocabulary: Any, maps: Sequence[str | Path]) -> ShardLayout:
    """Serve maps made apart as shards of one map: ids and sessions as
    :func:`stablecues.database.merge_maps` would give them (the maps in this order).

    Raises:
        DatabaseError: a missing or corrupt map, or one named twice.
    """
    from ..database import Database

    paths = [Path(p) for p in maps]
    if not paths:
        raise ConfigError("layout_of_maps: no maps given")
    if len({p.resolve() for p in paths}) != len(paths):
        raise DatabaseError("layout_of_maps: a map is named twice")
    shards, entry_shift, session_shift = [], 0, 0
    for p in paths:
        if not p.is_file():
            raise DatabaseError(f"{p}: map file not found")
        with Database(vocabulary, p, readonly=True) as db:
            shards.append(Shard(p, np.arange(len(db), dtype=np.int64) + entry_shift, session_shift))
            sessions = db.index.sessions()
            entry_shift += len(db)
            session_shift += int(sessions.max()) + 1 if sessions.size else 0
    return ShardLayout(tuple(shards), entry_shift, "maps")


# ---------------------------------------------------------------------------------- serving
class ShardServer:
    """One shard held open (read-only) by a worker: a Dask actor that :class:`ShardedMap`
    places; it answers queries in global ids and global sessions.

    Args:
        vocabulary: the maps' vocabulary.
        shard: which map file and which global ids.
    """

    def __init__(self, vocabulary: Any, shard: Shard) -> None:
        from ..database import Database

        self.shard = shard
        self.ids = np.asarray(shard.ids, np.int64)
        self.db = Database(vocabulary, shard.path, readonly=True)
        if len(self.db) < self.ids.size:
            n = len(self.db)
            self.db.close()
            raise DatabaseError(f"{shard.path}: holds {n} entries, its layout names {self.ids.size}")

    def describe(self) -> dict[str, Any]:
        """Where the shard is served, and what it holds."""
        return {"path": str(self.shard.path), "entries": int(self.ids.size), "pid": os.getpid(),
                "sessions": {k + self.shard.session_offset: v for k, v in self.db.sessions().items()}}

    def query_many(
        self, bows: Sequence[BowVector], max_results: int, min_id: int, max_id: int,
        sessions: list[int] | None, exclude_sessions: list[int] | None,
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each query's best ``max_results`` of this shard: (global ids int64, scores float64)."""
        lo = int(np.searchsorted(self.ids, min_id, "left"))
        hi = int(np.searchsorted(self.ids, max_id, "left"))
        off = self.shard.session_offset
        keep = None if sessions is None else [s - off for s in sessions if s >= off]
        drop = [s - off for s in exclude_sessions or [] if s >= off] or None  # none of ours: keep all
        out = []
        for bow in bows:
            if hi <= lo or (keep is not None and not keep):
                out.append((np.zeros(0, np.int64), np.zeros(0)))
                continue
            res = self.db.query(bow, max_results, min_id=lo, max_id=hi, sessions=keep, exclude_sessions=drop)
            local = np.array([r.entry_id for r in res], np.int64)
            out.append((self.ids[local], np.array([r.score for r in res], np.float64)))
        return out

    def close(self) -> None:
        self.db.close()


class ShardedMap:
    """A map whose entries are spread over the workers of a Dask cluster, one shard each
    (round robin when there are more shards than workers); :meth:`query` fans out and merges.

    Use it as a context manager, or call :meth:`close`: the shards are released from the
    workers.

    Args:
        client: a ``distributed.Client``.
        layout: the shards (:func:`split_map`, :meth:`ShardLayout.load`, :func:`layout_of_maps`).
        vocabulary: the maps' vocabulary (sent once to every worker).
        timeout_s: how long to wait for a shard to open, or for a query's answers.

    Raises:
        DatabaseError: a shard's map cannot be opened on its worker.
        ClusterError: no worker, or a shard did not open in time.
    """

    def __init__(
        self, client: Any, layout: ShardLayout, vocabulary: Any, *, timeout_s: float = 120.0
    ) -> None:
        from ..vocabulary import higher_is_better
        from .cluster import ClusterError, worker_addresses

        self.layout = layout
        self.timeout_s = timeout_s
        self._higher_better = higher_is_better(vocabulary.scoring)
        workers = worker_addresses(client)
        voc = client.scatter(vocabulary, broadcast=True, hash=False)
        self.placement = [workers[k % len(workers)] for k in range(len(layout.shards))]
        self._futures = [
            client.submit(ShardServer, voc, shard, actor=True, workers=[w], allow_other_workers=False,
                          pure=False)
            for shard, w in zip(layout.shards, self.placement, strict=True)
        ]
        try:
            self._actors = [f.result(timeout=timeout_s) for f in self._futures]
        except TimeoutError as exc:
            self.close()
            raise ClusterError(f"a shard did not open on its worker in {timeout_s:.0f} s") from exc
        except BaseException:
            self.close()
            raise
        finally:
            del voc

    def __enter__(self) -> ShardedMap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        """Size of the global id space (as the one map's ``len``)."""
        return self.layout.entries

    def describe(self) -> list[dict[str, Any]]:
        """Each shard's path, entries, sessions, serving process and worker address."""
        calls = [a.describe() for a in self._actors]
        return [{**c.result(timeout=self.timeout_s), "worker": w}
                for c, w in zip(calls, self.placement, strict=True)]

    def query(
        self,
        bow: BowVector,
        max_results: int = 10,
        exclude_recent: int = 0,
        max_id: int | None = None,
        min_id: int = 0,
        *,
        sessions: int | Iterable[int] | None = None,
        exclude_sessions: int | Iterable[int] | None = None,
    ) -> list[QueryResult]:
        """What :meth:`stablecues.database.Database.query` of the one map gives (same arguments)."""
        return self.query_many([bow], max_results, exclude_recent, max_id, min_id, sessions=sessions,
                               exclude_sessions=exclude_sessions)[0]

    def query_many(
        self,
        bows: Sequence[BowVector],
        max_results: int = 10,
        exclude_recent: int = 0,
        max_id: int | None = None,
        min_id: int = 0,
        *,
        sessions: int | Iterable[int] | None = None,
        exclude_sessions: int | Iterable[int] | None = None,
    ) -> list[list[QueryResult]]:
        """:meth:`query` for several BoW vectors: one round trip per shard for them all."""
        from .cluster import ClusterError

        for b in bows:
            if not isinstance(b, BowVector):
                raise InputError(f"query: expected BowVector, got {type(b).__name__}")
        hi = self.layout.entries - max(int(exclude_recent), 0)
        if max_id is not None:
            hi = min(hi, int(max_id))
        keep, drop = _sessions(sessions, "sessions"), _sessions(exclude_sessions, "exclude_sessions")
        calls = [a.query_many(list(bows), int(max_results), max(int(min_id), 0), hi, keep, drop)
                 for a in self._actors]
        try:
            answers = [c.result(timeout=self.timeout_s) for c in calls]
        except TimeoutError as exc:
            raise ClusterError(f"a shard did not answer in {self.timeout_s:.0f} s") from exc
        return [self._merge([a[q] for a in answers], int(max_results)) for q in range(len(bows))]

    def _merge(self, parts: list[tuple[np.ndarray, np.ndarray]], max_results: int) -> list[QueryResult]:
        ids = np.concatenate([p[0] for p in parts] or [np.zeros(0, np.int64)])
        scores = np.concatenate([p[1] for p in parts] or [np.zeros(0)])
        key = -scores if self._higher_better else scores
        order = np.lexsort((ids, key))
        if max_results > 0:
            order = order[:max_results]
        return [QueryResult(int(ids[i]), float(scores[i])) for i in order]

    def close(self) -> None:
        """Release the shards: each worker closes its map."""
        actors, self._actors = getattr(self, "_actors", []), []
        for a in actors:
            try:
                a.close().result(timeout=self.timeout_s)
            except Exception as exc:  # a worker already gone: its shard went with it
                log.debug("closing a shard: %s", exc)
        for f in getattr(self, "_futures", []):
            f.release()
        self._futures = []


def _sessions(value: int | Iterable[int] | None, what: str) -> list[int] | None:
    if value is None:
        return None
    arr = np.atleast_1d(np.asarray(list(value) if not isinstance(value, int | np.integer) else value))
    if arr.dtype.kind not in "iu":
        raise InputError(f"{what}: expected session ids (integers), got {arr.dtype}")
    return [int(s) for s in arr.tolist()]

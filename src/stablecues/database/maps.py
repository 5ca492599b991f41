"""Merging map files: several maps made with one vocabulary become one.

Entries keep their order: the first map's entries keep their ids, the second's follow, and
so on (ids shifted by the entries before them); sessions are shifted the same way so that
no two maps share a session id. Everything is copied: BoW vectors, direct indexes, features,
3D points, poses, metadata, removed entries (as removed), and the inverse index, whose
segment files are copied with shifted ids instead of being rebuilt from the entries.
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatabaseError
from ..vocabulary import Vocabulary
from .files import index_dir, remove_database
from .segments import MergeJob, Segment, ensure_all_verified
from .store import Database, DatabaseConfig


@dataclass(frozen=True)
class MergeReport:
    """What :func:`merge_maps` made.

    Attributes:
        path: the merged map.
        entries: its number of entry ids.
        offsets: for each source, what was added to its entry ids.
        session_offsets: for each source, what was added to its session ids.
    """

    path: Path
    entries: int
    offsets: tuple[int, ...]
    session_offsets: tuple[int, ...]


def merge_maps(
    vocabulary: Vocabulary,
    sources: Sequence[str | Path],
    out: str | Path,
    config: DatabaseConfig | None = None,
) -> MergeReport:
    """Merge map files into a new one.

    Args:
        vocabulary: the vocabulary every source was made with (each source's fingerprint is
            checked against it).
        sources: the map files, in the order their entries should follow each other.
        out: the new map file (must not exist).
        config: settings of the new map.

    Returns:
        where each source's entries and sessions went.

    Raises:
        DatabaseError: a source is missing, corrupt, made with another vocabulary or named
            twice, or ``out`` exists.
    """
    out = Path(out)
    paths = [Path(s) for s in sources]
    if not paths:
        raise DatabaseError("merge_maps: no source maps given")
    resolved = [p.resolve() for p in paths]
    if len(set(resolved)) != len(resolved):
        raise DatabaseError("merge_maps: a source map is named twice")
    if out.exists() or index_dir(out).exists():
        raise DatabaseError(f"{out}: exists; merge_maps writes a new map file")
    if out.resolve() in resolved:
        raise DatabaseError(f"{out}: is one of the sources")
    opened = [Database(vocabulary, p, readonly=True) for p in paths]
    try:
        target = Database(vocabulary, out, config)
        try:
            report = _merge_into(target, opened, out)
            target.close()
            return report
        except BaseException:
            target.close()
            remove_database(out)
            raise
    finally:
        for db in opened:
            db.close()


def _merge_into(target: Database, sources: list[Database], out: Path) -> MergeReport:
    offsets: list[int] = []
    session_offsets: list[int] = []
    segments: list[Segment] = []
    entry_shift = session_shift = 0
    for src in sources:
        offsets.append(entry_shift)
        session_offsets.append(session_shift)
        _copy_rows(target, src, entry_shift, session_shift)
        # the bodies and tables checked first (in parallel): a damaged file copied would come
        # out under a fresh checksum
        ensure_all_verified(src.index.segments, len(src))
        for seg in src.index.segments:
            segments.append(_copy_segment(target, seg, entry_shift, session_shift))
        sessions = src.index.sessions()
        entry_shift += len(src)
        session_shift += (int(sessions.max()) + 1) if sessions.size else 0
    n = entry_shift
    sessions = np.concatenate([np.asarray(s.sessions, np.int32) for s in segments] or [np.zeros(0, np.int32)])
    removed = np.concatenate([_removed(src) + off for src, off in zip(sources, offsets, strict=True)])
    index = target.index
    index.reset(segments, n, sessions, removed if removed.size else None)
    if target._files is not None:
        target._files.commit(segments)
    if len(target) != n:
        raise DatabaseError(f"{out}: merged map holds {len(target)} entries, expected {n}")
    return MergeReport(out, n, tuple(offsets), tuple(session_offsets))


def _removed(src: Database) -> np.ndarray:
    alive = src.index.alive()
    return np.zeros(0, np.int64) if alive is None else np.flatnonzero(~alive[: len(src)])


def _copy_rows(target: Database, src: Database, entry_shift: int, session_shift: int) -> None:
    assert src.path is not None
    uri = f"{src.path.resolve().as_uri()}?mode=ro"
    sql = target._sql
    schema = src._schema
    with sql.lock:
        conn = sql.conn
        try:
            conn.execute("ATTACH DATABASE ? AS src", (uri,))
            try:
                conn.execute("BEGIN IMMEDIATE")
                try:
                    conn.execute(
                        "INSERT INTO main.entries (id, timestamp, n_features, bow, payload, meta, session, "
                        f"removed) SELECT id + ?, timestamp, n_features, bow, payload, meta, "
                        f"{schema.session_sql} + ?, {schema.removed_sql} FROM src.entries ORDER BY id",
                        (entry_shift, session_shift),
                    )
                    (count,) = conn.execute("SELECT COUNT(*) FROM main.entries WHERE id >= ?",
                                            (entry_shift,)).fetchone()
                    if count != len(src):
                        raise DatabaseError(f"{src.path}: copied {count} entries, the map has {len(src)}")
                except BaseException:
                    conn.execute("ROLLBACK")
                    raise
                conn.execute("COMMIT")
            finally:
                conn.execute("DETACH DATABASE src")
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(f"{src.path}: cannot copy its entries ({exc})") from exc


def _copy_segment(target: Database, seg: Segment, entry_shift: int, session_shift: int) -> Segment:
    files = target._files
    index = target.index
    sink = files.sink if files is not None else index._memory_sink
    job = MergeJob([seg], sink, index.n_words, index.chunk, shift=entry_shift, session_shift=session_shift)
    try:
        while not job.step():
            if job.waiting:  # its file is being written by the index files' thread
                time.sleep(0.001)
    except BaseException:
        job.abort()
        raise
    assert job.result is not None
    return job.result

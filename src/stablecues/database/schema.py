"""The SQLite side of a database file: tables, format versions, migration, checked values.

Format 2 (this code) adds a ``session`` and a ``removed`` column to format 1's ``entries`` and
keeps the inverse index in segment files named by a manifest in ``meta``. A writer migrates a
format-1 file in place when it opens it (two ``ALTER TABLE ... ADD COLUMN``, which rewrite
nothing); a read-only reader reads it as it is (every entry in session 0, none removed).

Every value read back from a file is checked here before it is used: a file edited by hand
or damaged gives one :class:`~stablecues.errors.DatabaseError` naming the file and the entry,
never a traceback from deep inside.
"""

from __future__ import annotations

import json
import math
import sqlite3
import threading
import uuid as uuid_mod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from ..errors import DatabaseError, VocabularyError
from ..vocabulary import Vocabulary
from ..vocabulary.incremental import IncrementalVocabulary, words_path

FORMAT_VERSION = 2
READABLE_VERSIONS = ("1", "2")

TABLES = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS entries (
    id INTEGER PRIMARY KEY,
    timestamp REAL,
    n_features INTEGER NOT NULL,
    bow BLOB NOT NULL,
    payload BLOB NOT NULL,
    meta TEXT NOT NULL,
    session INTEGER NOT NULL DEFAULT 0,
    removed INTEGER NOT NULL DEFAULT 0
);
"""
REMOVED_INDEX = "CREATE INDEX IF NOT EXISTS entries_removed ON entries(id) WHERE removed != 0"
MAX_SESSION = 2**31 - 1


class Sql:
    """A connection shared by threads: every use holds ``lock``.

    Attributes:
        conn: the connection (autocommit; transactions are explicit).
        lock: re-entrant lock around every statement sequence.
        where: the file's name, for messages.
        readonly: opened read-only.
    """

    def __init__(self, conn: sqlite3.Connection, where: str, readonly: bool) -> None:
        self.conn = conn
        self.lock = threading.RLock()
        self.where = where
        self.readonly = readonly

    @contextmanager
    def write(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE ... COMMIT, ROLLBACK on any error)."""
        if self.readonly:
            raise DatabaseError(f"{self.where}: opened read-only")
        with self.lock:
            try:
                self.conn.execute("BEGIN IMMEDIATE")
            except sqlite3.OperationalError as exc:
                raise DatabaseError(f"{self.where}: cannot write ({exc}; another writer?)") from exc
            try:
                yield self.conn
            except BaseException:
                self.conn.execute("ROLLBACK")
                raise
            else:
                self.conn.execute("COMMIT")

    @contextmanager
    def snapshot(self) -> Iterator[sqlite3.Connection]:
        """One read transaction: every statement inside sees the same state of the file."""
        with self.lock:
            self.conn.execute("BEGIN")
            try:
                yield self.conn
            finally:
                self.conn.execute("COMMIT")

    def rows(self, sql: str, args: tuple[Any, ...] = (), what: str = "entries") -> list[Any]:
        with self.lock:
            try:
                return self.conn.execute(sql, args).fetchall()
            except sqlite3.DatabaseError as exc:
                raise DatabaseError(f"{self.where}: cannot read {what} ({exc})") from exc


@dataclass
class Schema:
    """What an opened file holds.

    Attributes:
        version: its format version.
        columns: names of the ``entries`` columns.
        uuid: the database's id (None for a format-1 file opened read-only).
        manifest: the index manifest's text, if any.
    """

    version: int
    columns: set[str]
    uuid: bytes | None
    manifest: str | None

    @property
    def session_sql(self) -> str:
        return "session" if "session" in self.columns else "0"

    @property
    def removed_sql(self) -> str:
        return "removed" if "removed" in self.columns else "0"


def vocabulary_meta(voc: Vocabulary | IncrementalVocabulary) -> dict[str, str]:
    return {
        "vocabulary_fingerprint": voc.fingerprint,
        "vocabulary": json.dumps({"k": voc.k, "L": voc.levels, "words": voc.n_words,
                                  "weighting": int(voc.weighting), "scoring": int(voc.scoring)}),
        "levels_up": str(voc.levels_up),
    }


def prepare(sql: Sql, voc: Vocabulary | IncrementalVocabulary) -> Schema:
    """Create a new file's tables, check an existing file's metadata against the vocabulary,
    and migrate a format-1 file (writers only). A file holding other tables is refused
    without being written to."""
    where = sql.where
    try:
        tables = {r[0] for r in sql.conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        have = dict(sql.conn.execute("SELECT key, value FROM meta").fetchall()) if "meta" in tables else {}
        empty = ("entries" not in tables
                 or sql.conn.execute("SELECT 1 FROM entries LIMIT 1").fetchone() is None)
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"{where}: not a stablecues database or corrupt ({exc})") from exc
    if tables - {"meta", "entries"} or (tables and not have and not empty):
        raise DatabaseError(f"{where}: not a stablecues database (tables: {', '.join(sorted(tables))[:80]})")
    if not have:
        if sql.readonly:
            raise DatabaseError(f"{where}: empty database (no metadata)")
        return _create(sql, voc)
    check_vocabulary(have, voc, where)
    if have.get("format_version") == "1" and not sql.readonly:
        have = _migrate_v1(sql)
    version = int(have["format_version"])
    ident = have.get("uuid")
    try:
        uuid = bytes.fromhex(ident) if ident is not None else None
    except (ValueError, TypeError):
        uuid = None
    if ident is not None and (uuid is None or len(uuid) != 16):
        raise DatabaseError(f"{where}: database id {str(ident)[:40]!r} is not 32 hex digits")
    return Schema(version, _columns(sql), uuid, have.get("index"))


def _create(sql: Sql, voc: Vocabulary | IncrementalVocabulary) -> Schema:
    new_id = uuid_mod.uuid4().hex
    try:
        with sql.write() as conn:
            for statement in TABLES.split(";"):
                if statement.strip():
                    conn.execute(statement)
            _add_columns(conn)
            rows = {"format_version": str(FORMAT_VERSION), **vocabulary_meta(voc), "uuid": new_id}
            conn.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", list(rows.items()))
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"{sql.where}: cannot create the database ({exc})") from exc
    return Schema(FORMAT_VERSION, _columns(sql), bytes.fromhex(new_id), None)


def check_vocabulary(have: dict[str, Any], voc: Vocabulary | IncrementalVocabulary, where: str) -> None:
    """Refuse a file of another format or made with another vocabulary."""
    if str(have.get("format_version")) not in READABLE_VERSIONS:
        raise DatabaseError(f"{where}: database format {str(have.get('format_version'))[:20]}, "
                            f"expected one of {', '.join(READABLE_VERSIONS)}")
    if have.get("vocabulary_fingerprint") != voc.fingerprint:
        theirs = str(have.get("vocabulary_fingerprint", "?"))[:12]
        made_incremental = '"k": 0,' in str(have.get("vocabulary", ""))
        if made_incremental != isinstance(voc, IncrementalVocabulary):
            how = ("an incremental vocabulary (open it with --vocab incremental, vocabulary: incremental)"
                   if made_incremental else "a trained vocabulary, not an incremental one")
            raise DatabaseError(f"{where}: made with {how}")
        if isinstance(voc, IncrementalVocabulary):
            raise DatabaseError(f"{where}: made by an incremental vocabulary with other settings"
                                f"{_incremental_settings(where)}; this one has {voc.settings()}")
        raise DatabaseError(
            f"{where}: made with vocabulary {theirs}..., not with this vocabulary "
            f"{voc.fingerprint[:12]}... (open it with the vocabulary it was built with)"
        )
    if have.get("levels_up") != str(voc.levels_up):
        raise DatabaseError(
            f"{where}: direct index stored at levels_up={str(have.get('levels_up'))[:20]}, "
            f"the vocabulary uses {voc.levels_up}"
        )


def _columns(sql: Sql) -> set[str]:
    try:
        cols = {row[1] for row in sql.conn.execute("PRAGMA table_info(entries)").fetchall()}
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"{sql.where}: not a stablecues database or corrupt ({exc})") from exc
    need = {"id", "timestamp", "n_features", "bow", "payload", "meta"}
    if not need <= cols:
        raise DatabaseError(f"{sql.where}: not a stablecues database (entries table lacks "
                            f"{', '.join(sorted(need - cols))})")
    return cols


def _add_columns(conn: sqlite3.Connection) -> None:
    cols = {row[1] for row in conn.execute("PRAGMA table_info(entries)").fetchall()}
    if "session" not in cols:
        conn.execute("ALTER TABLE entries ADD COLUMN session INTEGER NOT NULL DEFAULT 0")
    if "removed" not in cols:
        conn.execute("ALTER TABLE entries ADD COLUMN removed INTEGER NOT NULL DEFAULT 0")
    conn.execute(REMOVED_INDEX)


def _migrate_v1(sql: Sql) -> dict[str, Any]:
    """Format 1 -> 2 in one transaction: add the columns, an id, the removed-entries index."""
    try:
        with sql.write() as conn:
            _add_columns(conn)
            conn.execute("INSERT OR REPLACE INTO meta VALUES ('uuid', ?)", (uuid_mod.uuid4().hex,))
            conn.execute("UPDATE meta SET value = ? WHERE key = 'format_version'", (str(FORMAT_VERSION),))
            return dict(conn.execute("SELECT key, value FROM meta").fetchall())
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"{sql.where}: cannot migrate the format-1 database ({exc})") from exc


# ---------------------------------------------------------------------------- checked values
def timestamp_value(value: object, where: str, eid: int) -> float:
    """A stored timestamp as a float (NULL -> NaN)."""
    if value is None:
        return math.nan
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    raise DatabaseError(f"{where}: entry {eid}: timestamp is {type(value).__name__} "
                        f"{str(value)[:40]!r}, expected a number")


def int_value(value: object, where: str, eid: int, name: str) -> int:
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    raise DatabaseError(f"{where}: entry {eid}: {name} is {type(value).__name__} "
                        f"{str(value)[:40]!r}, expected an integer")


def meta_value(text: object, where: str, eid: int) -> dict[str, Any] | None:
    """A stored ``meta`` column: a JSON object (None for a removed entry)."""
    if not isinstance(text, str):
        raise DatabaseError(f"{where}: entry {eid}: meta is {type(text).__name__}, expected JSON text")
    try:
        value = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise DatabaseError(f"{where}: entry {eid}: meta is not JSON ({str(exc)[:80]})") from None
    if value is not None and not isinstance(value, dict):
        raise DatabaseError(f"{where}: entry {eid}: meta is a JSON {type(value).__name__}, "
                            "expected an object")
    return value


def _incremental_settings(where: str) -> str:
    """`` (the settings its words file records)`` for a map at ``where``, or nothing."""
    try:
        return f" ({IncrementalVocabulary.of_words_file(words_path(where)).settings()})"
    except (VocabularyError, OSError, ValueError):
        return ""

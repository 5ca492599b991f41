"""Checking and repairing a map file (``stablecues map check|repair``).

:func:`check_map` opens a map with the vocabulary it was made with (found among the shipped
ones by the fingerprint the file records, or given), and reports what it holds and what is
damaged: the entry log's records that could not be recovered (named when the map is opened),
index files whose header or body fail their checks, entry ids without a row in the SQLite file,
and SQLite's own integrity check. ``repair=True`` opens it as the writer and salvages what is
intact: damaged index files are rebuilt from the entries, ids without a row become removed
entries (their data is lost and they leave the queries), and the entry log's intact records
are written to SQLite; what could not be saved is listed.
"""

from __future__ import annotations

import logging
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import DatabaseError, VocabularyError
from ..types import DescriptorKind
from ..vocabulary import DEFAULT_VOCABULARIES, Vocabulary, default_vocabulary
from ..vocabulary.incremental import IncrementalVocabulary, words_path
from .store import Database

__all__ = ["MapReport", "check_map", "map_vocabulary"]


@dataclass
class MapReport:
    """What :func:`check_map` found (and, repairing, did).

    Attributes:
        path: the map.
        vocabulary: where its vocabulary came from ("default:orb", a file).
        entries: entry ids given out.
        present: entries not removed.
        sessions: distinct sessions.
        segments: index segments (persisted files and in-memory runs).
        warnings: what opening the map said (lost entry-log records, rebuilt index files).
        problems: what the check found.
        repaired: the check ran with ``repair``.
    """

    path: Path
    vocabulary: str
    entries: int = 0
    present: int = 0
    sessions: int = 0
    segments: int = 0
    warnings: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    repaired: bool = False

    @property
    def ok(self) -> bool:
        """Nothing lost or damaged found."""
        return not self.problems and not self.warnings


def _meta(path: Path, key: str) -> object:
    """One value of a map file's metadata, None when absent (read-only, nothing written).

    Raises:
        DatabaseError: not a map file, or not readable as one.
    """
    if not path.is_file():
        raise DatabaseError(f"{path}: map file not found" if not path.exists() else f"{path}: not a file")
    try:
        conn = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
        try:
            row = conn.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        finally:
            conn.close()
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"{path}: not a stablecues map or corrupt ({exc})") from None
    return None if row is None else row[0]


def _recorded_fingerprint(path: Path) -> str:
    """The vocabulary fingerprint a map file records."""
    value = _meta(path, "vocabulary_fingerprint")
    if not isinstance(value, str):
        raise DatabaseError(f"{path}: not a stablecues map (no vocabulary fingerprint)")
    return value


def _made_incremental(path: Path) -> bool:
    """Whether a map file records an incremental vocabulary (k = 0)."""
    return '"k": 0,' in str(_meta(path, "vocabulary"))


def map_vocabulary(path: Path) -> tuple[Vocabulary | IncrementalVocabulary, str]:
    """The shipped vocabulary a map was made with (by the fingerprint it records).

    Raises:
        DatabaseError: not a map, or made with a vocabulary that is not shipped (give it).
    """
    recorded = _recorded_fingerprint(path)
    words = words_path(path)
    if words.is_file():  # an incremental vocabulary's map: its settings are in the words file
        try:
            inc = IncrementalVocabulary.of_words_file(words)
        except VocabularyError as exc:
            raise DatabaseError(str(exc)) from None
        if inc.fingerprint == recorded:
            return inc, "incremental"
    for name in DEFAULT_VOCABULARIES:
        voc = default_vocabulary(name)
        if voc.fingerprint == recorded:
            return voc, f"default:{name}"
    for kind in (DescriptorKind("binary", 32), DescriptorKind("float", 64), DescriptorKind("float", 128)):
        inc = IncrementalVocabulary(kind)  # the default settings (ORB, XFeat, SIFT): the words
        if inc.fingerprint == recorded:  # file is missing, the words are learned again from the entries
            return inc, "incremental"
    if not words.exists() and _made_incremental(path):
        raise DatabaseError(f"{path}: made with an incremental vocabulary of settings other than the "
                            f"defaults, and its words file {words} (which records them) is missing")
    raise DatabaseError(f"{path}: made with vocabulary {recorded[:12]}..., none of the shipped ones "
                        f"({', '.join(DEFAULT_VOCABULARIES)}): give it with --vocab")


class _Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def check_map(path: str | Path, vocabulary: Vocabulary | IncrementalVocabulary | None = None, *,
              repair: bool = False, vocabulary_source: str = "given") -> MapReport:
    """Check (and with ``repair`` salvage) a map file.

    Args:
        path: the map's SQLite file.
        vocabulary: the vocabulary it was made with (None: the shipped one it records).
        repair: open it as the writer and repair what can be (see the module docstring);
            without it the map is opened read-only and nothing is written.
        vocabulary_source: how ``vocabulary`` was given, for the report.

    Raises:
        DatabaseError: not a map, another vocabulary's, or one that cannot be opened at all.
    """
    p = Path(path)
    if vocabulary is None:
        vocabulary, vocabulary_source = map_vocabulary(p)
    else:
        _recorded_fingerprint(p)  # a missing file or a foreign one: named before anything opens
    report = MapReport(p, vocabulary_source, repaired=repair)
    collect = _Collect()
    logger = logging.getLogger("stablecues")
    logger.addHandler(collect)
    try:
        with Database(vocabulary, p, readonly=not repair) as db:
            report.problems = db.check(repair=repair)
            if repair:
                db.flush()
            report.entries = len(db)
            report.present = int(db.ids().size)
            report.sessions = len(db.sessions())
            report.segments = len(db.index.segments)
    finally:
        logger.removeHandler(collect)
    report.warnings = collect.messages
    return report

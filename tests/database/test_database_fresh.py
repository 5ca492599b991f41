"""A missing or 0-byte SQLite file beside a map's index segments or entry log is refused, not
taken for a new map (which would delete the segments its empty manifest does not name)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dbkit import fill
from stablecues.database import Database
from stablecues.database.entrylog import log_path
from stablecues.database.files import index_dir, stored_segments
from stablecues.errors import DatabaseError
from stablecues.vocabulary import Vocabulary


def test_an_emptied_or_deleted_sqlite_file_never_deletes_the_segments(
    voc: Vocabulary, images: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "map.sqlite"
    with Database(voc, path) as db:
        fill(db, voc, images)
        db.flush()
    segments = stored_segments(path)
    assert segments, "the map should have index segment files"
    before = {name: (index_dir(path) / name).read_bytes() for name in segments}
    saved = path.read_bytes()
    for damage in ("empty", "deleted"):
        if damage == "empty":
            path.write_bytes(b"")
        else:
            path.unlink()
        with pytest.raises(DatabaseError, match="refusing to start a new map") as info:
            Database(voc, path)
        message = str(info.value)
        assert "\n" not in message and str(path) in message and str(index_dir(path)) in message
        assert {n: (index_dir(path) / n).read_bytes() for n in stored_segments(path)} == before
    path.write_bytes(saved)  # restored: the map opens with every entry
    with Database(voc, path) as db:
        assert len(db) == len(images)


def test_a_new_map_still_opens_where_nothing_of_an_old_one_remains(voc: Vocabulary, tmp_path: Path) -> None:
    path = tmp_path / "new.sqlite"
    index_dir(path).mkdir()  # an empty index folder is not a map
    with Database(voc, path) as db:
        assert len(db) == 0
    empty = tmp_path / "empty.sqlite"
    empty.write_bytes(b"")
    with Database(voc, empty) as db:
        assert len(db) == 0
    assert not log_path(tmp_path / "other.sqlite").exists()

"""``stablecues map check|repair``: a healthy map, a damaged index file, rows deleted from the
SQLite file, and files that are not maps."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from dbkit import fill
from stablecues.cli.main import main
from stablecues.database import Database, DatabaseConfig
from stablecues.database.files import index_dir
from stablecues.vocabulary import default_vocabulary

N = 120


def _map(path: Path) -> list[np.ndarray]:
    """A map of N entries with the shipped ORB vocabulary, its index in several files."""
    voc = default_vocabulary("orb")
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (150, 32), dtype=np.uint8) for _ in range(N)]
    with Database(voc, path, DatabaseConfig(tail_postings=2000, merge_chunk=500)) as db:
        fill(db, voc, images)
        db.flush()
    assert len(sorted(index_dir(path).glob("seg-*.sci"))) >= 2
    return images


def _best(path: Path, d: np.ndarray) -> int:
    voc = default_vocabulary("orb")
    with Database(voc, path, readonly=True) as db:
        return db.query(voc.transform(d)[0], 1)[0].entry_id


def test_a_healthy_map_checks_clean(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "map.sqlite"
    _map(path)
    raw = path.read_bytes()
    out = tmp_path / "report.json"
    assert main(["map", "check", str(path), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"{N} entry ids, {N} present" in text and "vocabulary default:orb" in text
    assert "nothing lost or damaged" in text
    doc = json.loads(out.read_text())
    assert doc["ok"] and doc["entries"] == N and doc["problems"] == []
    assert path.read_bytes() == raw  # check writes nothing


def test_a_damaged_index_file_is_named_and_rebuilt(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "map.sqlite"
    images = _map(path)
    victim = sorted(index_dir(path).glob("seg-*.sci"))[0]
    raw = bytearray(victim.read_bytes())
    raw[128 + 8 * 10 + 1] ^= 0x10  # an entry id inside the first posting run
    victim.write_bytes(bytes(raw))
    assert main(["map", "check", str(path)]) == 1
    text = capsys.readouterr().out
    assert f"problem: {victim}: index file body is corrupt (checksum mismatch)" in text
    assert f"stablecues map repair {path}" in text
    assert main(["map", "repair", str(path)]) == 0
    assert "repaired:" in capsys.readouterr().out
    assert main(["map", "check", str(path)]) == 0
    assert "nothing lost or damaged" in capsys.readouterr().out
    assert _best(path, images[7]) == 7


def test_rows_deleted_from_sqlite_are_found_and_become_removed_entries(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Rows deleted inside the range an index file covers: the ids would still answer queries
    with nothing to read. check names them; repair makes them removed entries (lost, said so)
    and every other entry answers as before."""
    path = tmp_path / "map.sqlite"
    images = _map(path)
    with sqlite3.connect(path) as conn:
        conn.execute("DELETE FROM entries WHERE id IN (5, 6, 40)")
    assert main(["map", "check", str(path)]) == 1
    text = capsys.readouterr().out
    assert f"3 of the entry ids 0..{N - 1} have no row in the SQLite file (ids 5, 6, 40)" in text
    assert main(["map", "repair", str(path)]) == 0
    capsys.readouterr()
    assert main(["map", "check", str(path)]) == 0
    assert f"{N} entry ids, {N - 3} present, 3 removed" in capsys.readouterr().out
    voc = default_vocabulary("orb")
    with Database(voc, path, readonly=True) as db:
        assert 5 not in db.ids().tolist()
        assert db.query(voc.transform(images[5])[0], 1)[0].entry_id != 5
    assert _best(path, images[41]) == 41


@pytest.mark.parametrize("what", ["missing", "folder", "text", "foreign"])
def test_not_a_map_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], what: str) -> None:
    path = tmp_path / "map.sqlite"
    if what == "folder":
        path.mkdir()
    elif what == "text":
        path.write_text("hello")
    elif what == "foreign":
        with sqlite3.connect(path) as conn:
            conn.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
            conn.execute("INSERT INTO meta VALUES ('vocabulary_fingerprint', 'abcdef0123456789')")
    assert main(["map", "check", str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("stablecues map: error:") and str(path) in err and "\n" not in err
    assert {"missing": "not found", "folder": "not a file", "text": "not a stablecues map",
            "foreign": "none of the shipped ones"}[what] in err

"""Vocabulary files: round trips of both formats, truncated and corrupt files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stablecues.errors import VocabularyError
from stablecues.vocabulary import (
    Vocabulary,
    default_vocabulary,
    load_vocabulary,
    save_vocabulary,
    train_vocabulary,
)


@pytest.fixture(scope="module")
def voc() -> Vocabulary:
    rng = np.random.default_rng(0)
    sets = [rng.integers(0, 256, (120, 32), dtype=np.uint8) for _ in range(6)]
    return train_vocabulary(sets, k=5, levels=3, seed=0, progress=False)


def same(a: Vocabulary, b: Vocabulary) -> None:
    assert (a.k, a.levels, a.weighting, a.scoring) == (b.k, b.levels, b.weighting, b.scoring)
    np.testing.assert_array_equal(a.parents, b.parents)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)
    np.testing.assert_array_equal(a.weights, b.weights)
    q = np.random.default_rng(7).integers(0, 256, (50, 32), dtype=np.uint8)
    ba, _ = a.transform(q)
    bb, _ = b.transform(q)
    np.testing.assert_array_equal(ba.words, bb.words)
    np.testing.assert_array_equal(ba.weights, bb.weights)


@pytest.mark.parametrize("name", ["v.scv", "v.txt"])
def test_round_trip(voc: Vocabulary, tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    save_vocabulary(voc, path)
    back = load_vocabulary(path)
    same(voc, back)
    assert back.fingerprint == voc.fingerprint


def test_text_to_binary_to_text(voc: Vocabulary, tmp_path: Path) -> None:
    save_vocabulary(voc, tmp_path / "a.txt")
    save_vocabulary(load_vocabulary(tmp_path / "a.txt"), tmp_path / "b.scv")
    save_vocabulary(load_vocabulary(tmp_path / "b.scv"), tmp_path / "c.txt")
    assert (tmp_path / "a.txt").read_text() == (tmp_path / "c.txt").read_text()


def test_text_format_is_orbslam_layout(voc: Vocabulary, tmp_path: Path) -> None:
    save_vocabulary(voc, tmp_path / "v.txt")
    lines = (tmp_path / "v.txt").read_text().splitlines()
    assert lines[0].split() == ["5", "3", "0", "0"]  # k L scoring(L1) weighting(TF-IDF)
    assert len(lines) == voc.n_nodes  # header + one line per non-root node
    first = lines[1].split()
    assert len(first) == 35 and first[0] == "0" and first[1] in ("0", "1")


def test_handwritten_orbslam_text_loads(tmp_path: Path) -> None:
    d = " ".join(["0"] * 32)
    e = " ".join(["255"] * 32)
    text = f"2 2  0 0\n0 0 {d} 0\n0 0 {e} 0\n1 1 {d} 0.5\n1 1 {e} 0.7\n2 1 {e} 0.3\n"
    (tmp_path / "orb.txt").write_text(text)
    v = load_vocabulary(tmp_path / "orb.txt")
    assert v.n_words == 3 and v.n_nodes == 6
    assert v.node_word[v.leaves_of(np.full((1, 32), 255, np.uint8))][0] == 2
    assert v.weights[v.word_nodes].tolist() == [0.5, 0.7, 0.3]


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(VocabularyError, match="not found"):
        load_vocabulary(tmp_path / "nope.scv")


def test_truncated_binary(voc: Vocabulary, tmp_path: Path) -> None:
    save_vocabulary(voc, tmp_path / "v.scv")
    data = (tmp_path / "v.scv").read_bytes()
    for cut in (10, 40, len(data) // 2, len(data) - 1):
        (tmp_path / "t.scv").write_bytes(data[:cut])
        with pytest.raises(VocabularyError, match="t.scv: truncated"):
            load_vocabulary(tmp_path / "t.scv")


def test_corrupt_binary(voc: Vocabulary, tmp_path: Path) -> None:
    save_vocabulary(voc, tmp_path / "v.scv")
    data = bytearray((tmp_path / "v.scv").read_bytes())
    data[-100] ^= 0xFF
    (tmp_path / "c.scv").write_bytes(bytes(data))
    with pytest.raises(VocabularyError, match="checksum"):
        load_vocabulary(tmp_path / "c.scv")


def test_truncated_and_garbage_text(voc: Vocabulary, tmp_path: Path) -> None:
    save_vocabulary(voc, tmp_path / "v.txt")
    text = (tmp_path / "v.txt").read_text()
    (tmp_path / "t.txt").write_text(text[: len(text) // 2])
    with pytest.raises(VocabularyError, match="t.txt"):
        load_vocabulary(tmp_path / "t.txt")
    (tmp_path / "g.txt").write_text("hello world\n")
    with pytest.raises(VocabularyError, match="first line"):
        load_vocabulary(tmp_path / "g.txt")
    (tmp_path / "b.txt").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(VocabularyError):
        load_vocabulary(tmp_path / "b.txt")


def test_default_vocabulary_ships_and_loads() -> None:
    v = default_vocabulary()
    assert v.k == 10 and v.levels == 5 and v.n_words > 50_000
    bow, _ = v.transform(np.random.default_rng(0).integers(0, 256, (100, 32), dtype=np.uint8))
    assert len(bow) > 0


def test_text_with_header_only_is_refused(tmp_path: Path) -> None:
    (tmp_path / "h.txt").write_text("10 6  0 0\n")
    with pytest.raises(VocabularyError, match="no node lines"):
        load_vocabulary(tmp_path / "h.txt")

"""Vocabulary files: round trips of both formats, truncated and corrupt files."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from vocab_files import array_view, edit_binary, join_binary, split_binary

from stablecues.errors import InputError, VocabularyError
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


# ----------------------------------------------------------------------------- crafted binary files
# Each file below carries a valid CRC: the checks behind it, not the checksum, must catch it.


def binary_error(path: Path, *expected: str) -> None:
    """Load ``path``: one VocabularyError line naming the file and each ``expected``."""
    with pytest.raises(VocabularyError) as info:
        load_vocabulary(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)), message
    for part in expected:
        assert part in message, message


@pytest.fixture
def saved(voc: Vocabulary, tmp_path: Path) -> Path:
    save_vocabulary(voc, tmp_path / "v.scv")
    return tmp_path / "v.scv"


def test_out_of_range_child_table(saved: Path, tmp_path: Path) -> None:
    def kid(body: bytearray, header: dict[str, Any]) -> None:
        array_view(body, header, "children")[0, 1] = 1_000_000

    binary_error(edit_binary(saved, tmp_path / "c.scv", payload=kid),
                 "children table disagrees with the parents")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_binary_weights(voc: Vocabulary, saved: Path, tmp_path: Path, bad: float) -> None:
    word = int(voc.word_nodes[2])

    def weight(body: bytearray, header: dict[str, Any]) -> None:
        array_view(body, header, "weights")[word] = bad

    binary_error(edit_binary(saved, tmp_path / "w.scv", payload=weight),
                 f"node {word} has weight {bad}", "must be finite")


def test_negative_levels_up(voc: Vocabulary, saved: Path, tmp_path: Path) -> None:
    path = edit_binary(saved, tmp_path / "u.scv", header=lambda h: h.update(levels_up=-5))
    binary_error(path, "levels_up must be an integer >= 0, got -5")
    with pytest.raises(VocabularyError, match=r"v\.scv: expected levels_up >= 0, got -1"):
        load_vocabulary(saved, levels_up=-1)
    with pytest.raises(InputError, match="levels_up: expected an integer >= 0"):
        voc.transform(np.zeros((3, 32), np.uint8), levels_up=-5)


def test_billion_way_branching_names_the_file(saved: Path, tmp_path: Path) -> None:
    path = edit_binary(saved, tmp_path / "k.scv", header=lambda h: h.update(k=10**9))
    binary_error(path, "header: expected 2 <= k <= 1048576, got k=1000000000")
    path = edit_binary(saved, tmp_path / "L.scv", header=lambda h: h.update(L=0))
    binary_error(path, "expected 1 <= L <= 64")


def test_header_only_binary(saved: Path, tmp_path: Path) -> None:
    magic, version, header, _ = split_binary(saved.read_bytes())
    (tmp_path / "h.scv").write_bytes(join_binary(magic, version, header, b"", fix_crc=False))
    binary_error(tmp_path / "h.scv", "truncated vocabulary file")


@pytest.mark.parametrize(("edit", "expected"), [
    (lambda h: h["arrays"]["parents"].update(dtype="<f8"), "array 'parents' must be <i4"),
    (lambda h: h["arrays"]["weights"].update(dtype="|O"), "array 'weights' must be <f8"),
    (lambda h: h["arrays"]["descriptors"].update(shape=[10**12, 32]), "array 'descriptors' must be"),
    (lambda h: h["arrays"]["children"].update(shape=[h["n_nodes"], 10**9]), "runs past the"),
    (lambda h: h["arrays"]["weights"].update(offset=10**15 * 64), "runs past the"),
    (lambda h: h["arrays"]["weights"].update(offset=h["arrays"]["weights"]["offset"] + 3), "must be <f8"),
    (lambda h: h["arrays"].pop("parents"), "array 'parents' must be"),
    (lambda h: h.update(n_nodes="12"), "n_nodes must be an integer >= 0"),
    (lambda h: h.update(weighting=9), "weighting 9 (expected 0..3)"),
    (lambda h: h.update(fingerprint=None), "no fingerprint"),
    (lambda h: h.update(payload_bytes=10**15), "truncated vocabulary file"),
])
def test_corrupt_binary_headers(saved: Path, tmp_path: Path, edit: Any, expected: str) -> None:
    binary_error(edit_binary(saved, tmp_path / "x.scv", header=edit), expected)


def test_binary_header_that_is_not_an_object(saved: Path, tmp_path: Path) -> None:
    magic, version, _, payload = split_binary(saved.read_bytes())
    text = b"[" * 100_000 + b"]" * 100_000
    head = struct.pack("<8sII", magic, version, len(text)) + text
    (tmp_path / "j.scv").write_bytes(head + b"\0" * ((-len(head)) % 64) + bytes(payload))
    binary_error(tmp_path / "j.scv", "corrupt vocabulary header")


def test_memory_mapped_binary_transforms_like_a_read_one(voc: Vocabulary, saved: Path) -> None:
    mapped = load_vocabulary(saved, mmap=True)
    q = np.random.default_rng(3).integers(0, 256, (200, 32), dtype=np.uint8)
    for a, b in zip(mapped.transform(q), voc.transform(q), strict=True):
        for x, y in zip(vars(a).values(), vars(b).values(), strict=True):
            np.testing.assert_array_equal(x, y)

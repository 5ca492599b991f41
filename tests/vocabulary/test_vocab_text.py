"""DBoW2 / ORB-SLAM text vocabularies: what ORB-SLAM's loader makes of our files, and bad files."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from orbslam_text import load_orbslam_text
from vocab_files import small_vocabulary

from stablecues.errors import VocabularyError
from stablecues.vocabulary import Vocabulary, default_vocabulary, load_vocabulary, save_vocabulary


@pytest.fixture(scope="module")
def voc() -> Vocabulary:
    return small_vocabulary()


def one_line_error(path: Path, *expected: str) -> str:
    """Load ``path``, expecting one VocabularyError line naming the file and each ``expected``."""
    with pytest.raises(VocabularyError) as info:
        load_vocabulary(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)), message
    for part in expected:
        assert part in message, message
    return message


def node_lines(voc: Vocabulary) -> list[str]:
    """Node lines as ORB-SLAM's saveToTextFile writes them (values, not spacing)."""
    return [
        f"{voc.parents[i]} {int(voc.is_leaf[i])} {' '.join(map(str, voc.descriptors[i]))} "
        f"{float(voc.weights[i])!r}"
        for i in range(1, voc.n_nodes)
    ]


# ----------------------------------------------------------------------------- ORB-SLAM's loader
def test_orbslam_loader_reads_exactly_the_nodes_written(voc: Vocabulary, tmp_path: Path) -> None:
    save_vocabulary(voc, tmp_path / "v.txt")
    data = (tmp_path / "v.txt").read_bytes()
    assert not data.endswith(b"\n")
    loaded = load_orbslam_text(data)
    assert loaded is not None
    assert (loaded.k, loaded.levels, loaded.scoring, loaded.weighting) == (
        voc.k, voc.levels, int(voc.scoring), int(voc.weighting))
    assert len(loaded.nodes) == voc.n_nodes - 1 and loaded.n_words == voc.n_words
    assert [n.parent for n in loaded.nodes] == voc.parents[1:].tolist()
    assert [n.is_leaf for n in loaded.nodes] == voc.is_leaf[1:].tolist()
    assert [n.descriptor for n in loaded.nodes] == voc.descriptors[1:].tolist()
    assert [n.weight for n in loaded.nodes] == voc.weights[1:].tolist()  # exact doubles


def test_orbslam_loader_model_shows_the_final_newline_phantom(voc: Vocabulary, tmp_path: Path) -> None:
    """The reason for writing no final newline: ORB-SLAM reads one more, empty, node line."""
    save_vocabulary(voc, tmp_path / "v.txt")
    loaded = load_orbslam_text((tmp_path / "v.txt").read_bytes() + b"\n")
    assert loaded is not None
    assert len(loaded.nodes) == voc.n_nodes and loaded.n_words == voc.n_words + 1
    phantom = loaded.nodes[-1]
    assert phantom.parent == int(voc.parents[-1]) and phantom.descriptor == [None] * 32
    # our own reader takes either form, as ORB-SLAM's ORBvoc.txt ends with a newline
    (tmp_path / "nl.txt").write_bytes((tmp_path / "v.txt").read_bytes() + b"\n")
    assert load_vocabulary(tmp_path / "nl.txt").n_nodes == voc.n_nodes


@pytest.fixture(scope="module")
def shipped_text(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("shipped") / "ORBvoc.txt"
    save_vocabulary(default_vocabulary(), path)
    return path


def test_shipped_vocabulary_as_orbslam_text_has_one_line_per_node(shipped_text: Path) -> None:
    """What ORB-SLAM's getline loop counts: one node per line after the header, no more."""
    data = shipped_text.read_bytes()
    assert not data.endswith(b"\n") and data.count(b"\n") == default_vocabulary().n_nodes - 1


@pytest.mark.slow
def test_shipped_vocabulary_round_trips_through_orbslam_text(shipped_text: Path) -> None:
    """The whole 96,618-word file through the model of ORB-SLAM's loader (about 10 s)."""
    voc = default_vocabulary()
    loaded = load_orbslam_text(shipped_text.read_bytes())
    assert loaded is not None and loaded.n_words == voc.n_words == 96_618
    assert len(loaded.nodes) == voc.n_nodes - 1
    assert [n.parent for n in loaded.nodes] == voc.parents[1:].tolist()
    assert [n.descriptor for n in loaded.nodes] == voc.descriptors[1:].tolist()
    assert np.array_equal([n.weight for n in loaded.nodes], voc.weights[1:])


def test_shipped_vocabulary_round_trips_through_text(shipped_text: Path) -> None:
    voc = default_vocabulary()
    back = load_vocabulary(shipped_text)
    assert back.fingerprint == voc.fingerprint
    for name in ("parents", "descriptors", "weights"):
        np.testing.assert_array_equal(getattr(back, name), getattr(voc, name))


def test_orbslam_written_layout_loads(voc: Vocabulary, tmp_path: Path) -> None:
    """ORB-SLAM's own writer: two spaces before the weight, six digits, a final newline."""
    lines = [f"{voc.k} {voc.levels}  {int(voc.scoring)} {int(voc.weighting)}"]
    for i in range(1, voc.n_nodes):
        desc = "".join(f"{b} " for b in voc.descriptors[i])
        lines.append(f"{voc.parents[i]} {int(voc.is_leaf[i])} {desc} {voc.weights[i]:g}")
    (tmp_path / "orb.txt").write_text("\n".join(lines) + "\n")
    back = load_vocabulary(tmp_path / "orb.txt")
    np.testing.assert_array_equal(back.parents, voc.parents)
    np.testing.assert_array_equal(back.descriptors, voc.descriptors)
    np.testing.assert_allclose(back.weights, voc.weights, rtol=1e-5)


def test_text_reader_parses_numbers_as_float_does(tmp_path: Path) -> None:
    """Weights written in every way a C++ or Python writer might: the same doubles as float()."""
    d = " ".join(["7"] * 32)
    weights = ["0.69314718055994529", "1e-05", "2.5E+3", ".5", "5.", "-0.0", "0", "123456789012345678",
               "0.1000000000000000055511151231257827", "4.9406564584124654e-324"]
    body = "\n".join(f"0 1 {d} {w}" for w in weights)
    (tmp_path / "w.txt").write_text(f"{len(weights)} 1 0 0\n\r\n{body}\r\n\n")
    v = load_vocabulary(tmp_path / "w.txt")
    assert v.weights[1:].tolist() == [float(w) for w in weights]


# ----------------------------------------------------------------------------- bad text files
def test_header_claiming_a_billion_children_allocates_nothing(tmp_path: Path) -> None:
    """ORB-SLAM's loader would reserve k^(L+1) nodes (317 GiB for this header)."""
    d = " ".join(["0"] * 32)
    (tmp_path / "k.txt").write_text(f"1000000000 3 0 0\n0 1 {d} 1.0\n0 1 {d} 2.0")
    tracemalloc.start()
    try:
        one_line_error(tmp_path / "k.txt", "expected 2 <= k <= 1048576", "k=1000000000")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20
    (tmp_path / "L.txt").write_text(f"10 1000000 0 0\n0 1 {d} 1.0")
    one_line_error(tmp_path / "L.txt", "expected 1 <= L <= 64")
    (tmp_path / "huge.txt").write_text("9" * 5000 + " 3 0 0\n")
    one_line_error(tmp_path / "huge.txt", "first line must be 'k L scoring weighting'")


@pytest.mark.parametrize("text", ["10 6  0 0", "10 6  0 0\n", "10 6  0 0\n\n  \n"])
def test_header_only_text(tmp_path: Path, text: str) -> None:
    (tmp_path / "h.txt").write_text(text)
    one_line_error(tmp_path / "h.txt", "no node lines after the header")


def test_truncated_text(voc: Vocabulary, tmp_path: Path) -> None:
    save_vocabulary(voc, tmp_path / "v.txt")
    text = (tmp_path / "v.txt").read_text()
    starts = [i + 1 for i, c in enumerate(text) if c == "\n"]
    for line in (2, len(starts) // 2, len(starts) - 1):  # cut inside the descriptor of a line
        (tmp_path / "t.txt").write_text(text[: starts[line] + 20])
        one_line_error(tmp_path / "t.txt", f"line {line + 2} has", "expected 35", "truncated?")


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf", "NaN"])
def test_non_finite_weights_are_refused(voc: Vocabulary, tmp_path: Path, bad: str) -> None:
    lines = [f"{voc.k} {voc.levels} 0 0", *node_lines(voc)]
    word = int(voc.word_nodes[3])
    lines[word] = lines[word].rsplit(" ", 1)[0] + " " + bad
    (tmp_path / "w.txt").write_text("\n".join(lines))
    one_line_error(tmp_path / "w.txt", f"line {word + 1}: weight", "not a finite number")


@pytest.mark.parametrize(("edit", "expected"), [
    (lambda t: t.replace(" 255 ", " 256 ", 1), "descriptor bytes must lie in 0..255"),
    (lambda t: t.replace(" 1 ", " x ", 1), "expected whole numbers"),
    (lambda t: t.replace(" 1 ", " 1.0 ", 1), "expected whole numbers"),
    (lambda t: t.replace("\n0 1", "\n12345678901 1", 1), "a number of 11 digits"),
    (lambda t: t.replace("1 255", "1 \x00 255", 1), "line 2: control byte 0"),
    (lambda t: t.rsplit(" ", 1)[0] + " 0x1p3", "weight '0x1p3' is not a number"),
    (lambda t: t.rsplit(" ", 1)[0] + " 1" + "0" * 70, "line 3: the weight is not a number"),
    (lambda t: t.replace(" 1.5", " " * 5000 + "1.5"), "line 2 is longer than 4096 bytes"),
    (lambda t: t.rsplit("\n", 1)[0] + "\n" + t.rsplit("\n", 1)[1] + " 7", "has 36 numbers"),
])
def test_malformed_node_lines(tmp_path: Path, edit: object, expected: str) -> None:
    d = " ".join(["255"] * 32)
    body = f"\n0 1 {d} 1.5\n0 1 {d} 2.5"
    (tmp_path / "m.txt").write_text("3 1 0 0" + edit(body))  # type: ignore[operator]
    one_line_error(tmp_path / "m.txt", expected)


def test_parents_and_leaf_flags_are_checked(tmp_path: Path) -> None:
    d = " ".join(["1"] * 32)
    (tmp_path / "p.txt").write_text(f"3 2 0 0\n0 0 {d} 0\n\n5 1 {d} 1.0")
    one_line_error(tmp_path / "p.txt", "line 4: parent 5 of node 2 must be a node that comes before it")
    (tmp_path / "f.txt").write_text(f"3 2 0 0\n0 1 {d} 0\n1 1 {d} 1.0")
    one_line_error(tmp_path / "f.txt", "line 2: leaf flag disagrees with the tree")
    (tmp_path / "deep.txt").write_text(f"3 1 0 0\n0 0 {d} 0\n1 1 {d} 1.0")
    one_line_error(tmp_path / "deep.txt", "more than L=1 levels deep")


def test_uneven_fan_out_is_refused_before_its_table_is_allocated(tmp_path: Path) -> None:
    """3000 children under the root, each with one child: a padded table of 9 M slots."""
    d = " ".join(["3"] * 32)
    lines = ["3000 2 0 0"] + [f"0 0 {d} 0"] * 3000 + [f"{i} 1 {d} 1" for i in range(1, 3001)]
    (tmp_path / "fan.txt").write_text("\n".join(lines))
    one_line_error(tmp_path / "fan.txt", "fan-out is too uneven")


def test_binary_garbage_and_long_lines(tmp_path: Path) -> None:
    (tmp_path / "b.txt").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    one_line_error(tmp_path / "b.txt", "first line must be")
    (tmp_path / "nul.txt").write_bytes(b"2 1 0 0\n" + b"\x00" * 100)
    one_line_error(tmp_path / "nul.txt", "line 2: control byte 0")
    (tmp_path / "long.txt").write_bytes(b"2 1 0 0\n" + b"7 " * (3 << 21))
    one_line_error(tmp_path / "long.txt", "line 2 is longer than 4096 bytes")

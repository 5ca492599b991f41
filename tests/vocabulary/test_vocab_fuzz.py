"""Bounded fuzzing of the vocabulary parsers: every input gives a Vocabulary or a VocabularyError.

Fixed seed (hypothesis' derandomize), a small number of examples by default; set
``STABLECUES_FUZZ_EXAMPLES`` for a longer run, e.g. ``STABLECUES_FUZZ_EXAMPLES=5000 pytest
tests/vocabulary/test_vocab_fuzz.py``. A Vocabulary that loads must also transform descriptors.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from vocab_files import join_binary, small_vocabulary, split_binary

from stablecues.errors import StableCuesError
from stablecues.vocabulary import Vocabulary, load_vocabulary, save_vocabulary

EXAMPLES = int(os.environ.get("STABLECUES_FUZZ_EXAMPLES", "60"))
FUZZ = settings(max_examples=EXAMPLES, derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
QUERY = np.random.default_rng(0).integers(0, 256, (40, 32), dtype=np.uint8)


def _valid_files() -> tuple[bytes, bytes]:
    voc = small_vocabulary(k=3, levels=2, images=2)
    with tempfile.TemporaryDirectory() as tmp:
        save_vocabulary(voc, Path(tmp) / "v.txt")
        save_vocabulary(voc, Path(tmp) / "v.scv")
        return (Path(tmp) / "v.txt").read_bytes(), (Path(tmp) / "v.scv").read_bytes()


VALID_TEXT, VALID_BINARY = _valid_files()


def loads_or_refuses(data: bytes, suffix: str) -> None:
    """The property: a Vocabulary that transforms, or one line of StableCuesError; nothing else.
    A memory-mapped file is checked when first used (its load takes a millisecond), so there
    the line may come from the first transform instead of the load."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"fuzz{suffix}"
        path.write_bytes(data)
        for mmap in (False, True):
            try:
                voc = load_vocabulary(path, mmap=mmap)
                assert isinstance(voc, Vocabulary)
                bow, fvec = voc.transform(QUERY)
            except StableCuesError as exc:  # one short line that names the file
                message = str(exc)
                assert message.startswith(str(path)) and "\n" not in message, message
                assert len(message) < len(str(path)) + 250, message
                continue
            assert len(fvec) == QUERY.shape[0] and np.isfinite(bow.weights).all()


# ----------------------------------------------------------------------------- text
TOKENS = st.sampled_from([b"0", b"1", b"255", b"256", b"-1", b"1.5", b"nan", b"inf", b"1e308", b"1e999",
                          b"99999999999", b"0x10", b"", b"\t", b"\r", b"\x00", b"\xff", b"+3"])


@st.composite
def text_edits(draw: Any) -> bytes:
    """A valid text vocabulary with a few random edits: cut, flip, insert, replace a token."""
    data = bytearray(VALID_TEXT)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["cut", "flip", "insert", "token", "newline", "header"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if kind == "cut":
            del data[at:]
        elif kind == "flip" and data:
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "insert":
            data[at:at] = draw(st.binary(max_size=12))
        elif kind == "token":
            tokens = bytes(data).split(b" ")
            tokens[draw(st.integers(0, len(tokens) - 1))] = draw(TOKENS)
            data = bytearray(b" ".join(tokens))
        elif kind == "newline":
            data[at:at] = b"\n" * draw(st.integers(1, 2))
        else:
            header = b" ".join(str(draw(st.integers(-3, 10**12))).encode() for _ in range(4))
            data = bytearray(header + bytes(data)[bytes(data).find(b"\n"):])
    return bytes(data)


@st.composite
def text_lines(draw: Any) -> bytes:
    """A header and lines of random tokens from a small alphabet of plausible and hostile ones."""
    header = draw(st.lists(st.sampled_from([b"2", b"3", b"10", b"0", b"1", b"1000000000", b"64", b"x"]),
                           min_size=0, max_size=5))
    lines = draw(st.lists(st.lists(TOKENS, min_size=0, max_size=40), max_size=8))
    body = b"\n".join(b" ".join(line) for line in lines)
    return b" ".join(header) + b"\n" + body


@FUZZ
@given(st.one_of(text_edits(), text_lines(), st.binary(max_size=300)))
def test_text_parser_fuzz(data: bytes) -> None:
    loads_or_refuses(data, ".txt")


# ----------------------------------------------------------------------------- binary
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6,
)
HEADER_FIELDS = ["k", "L", "weighting", "scoring", "n_nodes", "levels_up", "fingerprint", "payload_bytes"]
ARRAY_FIELDS = ["offset", "dtype", "shape"]


@st.composite
def binary_edits(draw: Any) -> bytes:
    """A valid binary vocabulary with header fields or payload bytes changed, CRC recomputed (so
    that the checks behind the checksum are what is tested), or raw bytes flipped and cut."""
    magic, version, header, payload = split_binary(VALID_BINARY)
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["field", "array", "payload", "raw"]))
        if kind == "field":
            header[draw(st.sampled_from(HEADER_FIELDS))] = draw(JSON_VALUES)
        elif kind == "array":
            spec = header["arrays"][draw(st.sampled_from(["parents", "descriptors", "weights", "children"]))]
            if isinstance(spec, dict):
                spec[draw(st.sampled_from(ARRAY_FIELDS))] = draw(
                    JSON_VALUES | st.lists(st.integers(-2, 10**13), max_size=3))
        elif kind == "payload" and payload:
            at = draw(st.integers(0, len(payload) - 1))
            payload[at : at + 4] = draw(st.binary(min_size=1, max_size=4))
        else:
            data = bytearray(join_binary(magic, version, header, payload))
            at = draw(st.integers(0, len(data) - 1))
            data[at] ^= 1 << draw(st.integers(0, 7))
            return bytes(data[: draw(st.integers(0, len(data)))])
    return join_binary(magic, version, header, payload)


@FUZZ
@given(binary_edits())
def test_binary_parser_fuzz(data: bytes) -> None:
    loads_or_refuses(data, ".scv")


@FUZZ
@given(st.binary(max_size=200).map(lambda b: b"SCVOCAB\0" + b))
def test_binary_prefix_fuzz(data: bytes) -> None:
    loads_or_refuses(data, ".scv")

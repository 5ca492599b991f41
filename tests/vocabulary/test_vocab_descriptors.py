"""Hamming distance and bitwise majority against brute force."""

from __future__ import annotations

import numpy as np

from stablecues.vocabulary.descriptors import (
    as_words,
    bitwise_majority,
    hamming_cross,
    hamming_rows,
    majority_by_label,
)


def brute_hamming(a: np.ndarray, b: np.ndarray) -> int:
    return sum(bin(int(x) ^ int(y)).count("1") for x, y in zip(a, b, strict=True))


def test_hamming_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (7, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    d = hamming_cross(as_words(a), as_words(b))
    assert d.shape == (7, 5)
    for i in range(7):
        for j in range(5):
            assert d[i, j] == brute_hamming(a[i], b[j])
    rows = hamming_rows(as_words(a[:5]), as_words(b))
    assert rows.tolist() == [brute_hamming(a[i], b[i]) for i in range(5)]
    assert hamming_cross(as_words(a), as_words(~a)).diagonal().tolist() == [256] * 7


def brute_majority(desc: np.ndarray) -> np.ndarray:
    bits = [[(int(d[i // 8]) >> (7 - i % 8)) & 1 for i in range(256)] for d in desc]
    counts = np.sum(bits, axis=0)
    out = np.zeros(32, np.uint8)
    for i in range(256):
        if counts[i] * 2 > len(desc):
            out[i // 8] |= 1 << (7 - i % 8)
    return out


def test_majority_matches_brute_force_including_ties() -> None:
    rng = np.random.default_rng(1)
    for n in (1, 2, 3, 4, 9):
        desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        np.testing.assert_array_equal(bitwise_majority(desc), brute_majority(desc))
    assert bitwise_majority(np.zeros((0, 32), np.uint8)).tolist() == [0] * 32


def test_majority_by_label_both_paths_agree_with_brute_force() -> None:
    rng = np.random.default_rng(2)
    for n in (40, 30_000):  # small: matmul path; large: histogram path
        desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        labels = rng.integers(0, 4, n)
        labels[labels == 3] = 0  # group 3 stays empty
        centres, sizes = majority_by_label(desc, labels, 4)
        assert sizes.tolist() == np.bincount(labels, minlength=4).tolist()
        for g in range(3):
            np.testing.assert_array_equal(centres[g], bitwise_majority(desc[labels == g]))
        assert centres[3].tolist() == [0] * 32

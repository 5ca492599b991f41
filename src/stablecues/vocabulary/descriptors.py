"""Operations on descriptors: Hamming distance and bitwise majority for binary ones, squared
Euclidean distance and means for float ones.

Binary descriptors are (N, B) uint8 arrays of any byte width B (32 for ORB). For distances
they are viewed as (N, ceil(B / 8)) uint64 words, zero-padded when B is not a multiple of 8
(the padding XORs to zero, so distances are unchanged); ``np.bitwise_count`` on the XOR,
summed over the words by hand, is about 4x faster than ``.sum(-1)`` on this kind of machine.
Float descriptors are (N, D) float32 arrays (128 for SIFT).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..types import DESCRIPTOR_BYTES, ORB_DESCRIPTOR, DescriptorKind

WORDS = DESCRIPTOR_BYTES // 8


def check_descriptors(
    descriptors: np.ndarray, name: str = "descriptors", kind: DescriptorKind = ORB_DESCRIPTOR
) -> None:
    """Raise InputError unless ``descriptors`` is an (N, size) array of ``kind`` (default:
    (N, 32) uint8, ORB's); float descriptors must also be finite."""
    kind.check(descriptors, name)
    if kind.kind == "float" and descriptors.size and not np.isfinite(descriptors).all():
        raise InputError(f"{name}: expected finite float32 values, got NaN or infinite ones")


def n_words(n_bytes: int) -> int:
    """How many uint64 words hold a binary descriptor of ``n_bytes`` bytes."""
    return -(-n_bytes // 8)


def as_words(descriptors: np.ndarray) -> np.ndarray:
    """View (N, B) uint8 descriptors as (N, ceil(B / 8)) uint64 words.

    Copies only when the array is not contiguous or B is not a multiple of 8 (then the last
    word is zero-padded).
    """
    d = np.ascontiguousarray(descriptors, dtype=np.uint8)
    width = d.shape[1]
    if width % 8:
        padded = np.zeros((d.shape[0], n_words(width) * 8), np.uint8)
        padded[:, :width] = d
        d = padded
    return d.view(np.uint64).reshape(d.shape[0], d.shape[1] // 8)


def popcount_words(x: np.ndarray) -> np.ndarray:
    """Bit count over the last axis of a (..., W) uint64 array: (...) int32."""
    c = np.bitwise_count(x)
    if c.shape[-1] != WORDS:
        return c.sum(axis=-1, dtype=np.int32)
    return (
        c[..., 0].astype(np.int32) + c[..., 1].astype(np.int32)
        + c[..., 2].astype(np.int32) + c[..., 3].astype(np.int32)
    )


def hamming_cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """All pairwise Hamming distances.

    Args:
        a: (N, W) uint64 words (see :func:`as_words`).
        b: (M, W) uint64 words.

    Returns:
        (N, M) int32 distances in [0, 64 W].
    """
    return popcount_words(a[:, None, :] ^ b[None, :, :])


def hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distances of two aligned (N, W) uint64 arrays: (N,) int32."""
    return popcount_words(a ^ b)


def bitwise_majority(descriptors: np.ndarray) -> np.ndarray:
    """Centre of a set of binary descriptors: each bit set when more than half the set has it.

    Ties (exactly half) give 0, as DBoW2's ``FORB::meanValue``. An empty set gives zeros.

    Args:
        descriptors: (N, B) uint8.

    Returns:
        (B,) uint8.
    """
    n = descriptors.shape[0]
    if n == 0:
        return np.zeros(descriptors.shape[1], np.uint8)
    counts = np.unpackbits(descriptors, axis=1).sum(axis=0, dtype=np.int64)
    return np.packbits(counts * 2 > n)


_BIT_TABLE = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).astype(np.float64)


def majority_by_label(descriptors: np.ndarray, labels: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Bitwise-majority centres of ``k`` groups at once, exactly and in little memory.

    Args:
        descriptors: (N, B) uint8.
        labels: (N,) int group of each descriptor, in [0, k).
        k: number of groups.

    Returns:
        centres (k, B) uint8 and sizes (k,) int64; empty groups get zero centres.
    """
    n = labels.shape[0]
    sizes = np.bincount(labels, minlength=k).astype(np.int64)
    if n * k <= 200_000:
        onehot = np.zeros((k, n), np.float32)
        onehot[labels, np.arange(n)] = 1.0
        counts = onehot @ np.unpackbits(descriptors, axis=1).astype(np.float32)
    else:
        # per byte column: a histogram of byte values per group, then bits per value
        counts = np.empty((k, 8 * descriptors.shape[1]), np.float64)
        base = labels.astype(np.int64) * 256
        for c in range(descriptors.shape[1]):
            hist = np.bincount(base + descriptors[:, c], minlength=k * 256).reshape(k, 256)
            counts[:, c * 8 : (c + 1) * 8] = hist @ _BIT_TABLE
    centres = np.packbits(counts * 2 > sizes[:, None], axis=1)
    return centres, sizes


def squared_l2_cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """All pairwise squared Euclidean distances of float descriptors.

    Computed as ``|a|^2 - 2 a.b + |b|^2`` in float64 (one matrix product), clipped at 0.

    Args:
        a: (N, D) float32.
        b: (M, D) float32.

    Returns:
        (N, M) float64.
    """
    a64 = a.astype(np.float64)
    b64 = b.astype(np.float64)
    d = (a64 * a64).sum(axis=1)[:, None] - 2.0 * (a64 @ b64.T) + (b64 * b64).sum(axis=1)[None, :]
    return np.maximum(d, 0.0)


def mean_by_label(descriptors: np.ndarray, labels: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of each of ``k`` groups of float descriptors (summed in float64).

    Args:
        descriptors: (N, D) float32.
        labels: (N,) int group of each descriptor, in [0, k).
        k: number of groups.

    Returns:
        centres (k, D) float32 and sizes (k,) int64; empty groups get zero centres.
    """
    sizes = np.bincount(labels, minlength=k).astype(np.int64)
    centres = np.zeros((k, descriptors.shape[1]), np.float32)
    used = np.flatnonzero(sizes)
    if used.size == 0:
        return centres, sizes
    order = np.argsort(labels, kind="stable")
    starts = np.concatenate(([0], np.cumsum(sizes[used])[:-1]))
    sums = np.add.reduceat(descriptors[order], starts, axis=0, dtype=np.float64)
    centres[used] = (sums / sizes[used][:, None]).astype(np.float32)
    return centres, sizes

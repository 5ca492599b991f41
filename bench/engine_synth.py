"""Synthetic material for the engine benchmarks: a 10^6-word tree and entries around its leaves.

Kept apart from ``bench_engine.py`` so that the scale runs can import it in subprocesses.
"""

from __future__ import annotations

import numpy as np

from stablecues.vocabulary import Scoring, Vocabulary, Weighting


def _masks(n_bits: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 32) uint8 masks with exactly ``n_bits`` bits set each."""
    bits = np.zeros((count, 256), np.uint8)
    cols = np.argsort(rng.random((count, 256)), axis=1)[:, :n_bits]
    bits[np.arange(count)[:, None], cols] = 1
    return np.packbits(bits, axis=1)


def _flip(parent: np.ndarray, n_bits: int, rng: np.random.Generator) -> np.ndarray:
    """Copies of ``parent`` rows with ``n_bits`` random bits flipped each (from a mask pool)."""
    pool = _masks(n_bits, min(parent.shape[0], 1 << 15), rng)
    return parent ^ pool[rng.integers(0, pool.shape[0], parent.shape[0])]


def synthetic_vocabulary(k: int = 10, levels: int = 6, seed: int = 0) -> Vocabulary:
    """A complete k-ary tree of depth L whose centres form a real hierarchy (children are their
    parent with fewer and fewer bits flipped), with random IDF weights on the leaves."""
    rng = np.random.default_rng(seed)
    parents = [np.array([-1], np.int32)]
    desc = [np.zeros((1, 32), np.uint8)]
    level_nodes = np.array([0])
    level_desc = rng.integers(0, 256, (1, 32), dtype=np.uint8)
    next_id = 1
    for level in range(1, levels + 1):
        flips = max(64 >> (level - 1), 4)
        rep = np.repeat(level_desc, k, axis=0)
        child_desc = _flip(rep, flips, rng) if level > 1 else rng.integers(0, 256, rep.shape, dtype=np.uint8)
        child_par = np.repeat(level_nodes, k).astype(np.int32)
        ids = np.arange(next_id, next_id + child_par.size)
        next_id += child_par.size
        parents.append(child_par)
        desc.append(child_desc)
        level_nodes, level_desc = ids, child_desc
    par = np.concatenate(parents)
    weights = np.zeros(par.size)
    n_leaves = k**levels
    weights[-n_leaves:] = rng.uniform(0.5, 8.0, n_leaves)
    return Vocabulary(k, levels, par, np.concatenate(desc), weights, Weighting.TF_IDF, Scoring.L1)


class EntryMaker:
    """Descriptor sets 'drawn around the vocabulary's leaves', like a camera driving along.

    Word popularity is heavy-tailed, p(rank) ~ 1 / (rank + offset), and consecutive entries share
    half their words, as consecutive frames do. The offset sets how much a query touches: the
    expected postings per query per stored entry is sum(df^2) over words (df: the fraction of
    entries holding the word). Measured on 176 real frames (CamVid, KITTI, EuRoC, TUM) with the
    shipped 96,618-word vocabulary that sum is 46; a tree with ten times the words splits each
    word about ten ways, so about 4.6 is realistic for 10^6 words, which offset = 10,000 gives
    (offset = 200 would give ~70, a far more skewed vocabulary than k-means trees produce).
    """

    def __init__(
        self, voc: Vocabulary, n_features: int = 1000, seed: int = 1, offset: float = 10_000.0
    ) -> None:
        self.voc = voc
        self.n = n_features
        self.rng = np.random.default_rng(seed)
        leaves = voc.word_nodes
        ranks = np.arange(leaves.size)
        p = 1.0 / (ranks + offset)
        self.cdf = np.cumsum(p) / p.sum()
        self.leaf_perm = self.rng.permutation(leaves)
        self.prev: np.ndarray | None = None
        # a pool of 3-bit noise masks, XORed onto the leaf centres
        self.masks = _masks(3, 1 << 16, self.rng)

    def next(self) -> np.ndarray:
        """(n_features, 32) uint8 descriptors of the next synthetic image."""
        fresh = self.leaf_perm[np.searchsorted(self.cdf, self.rng.random(self.n))]
        if self.prev is not None:
            keep = self.rng.random(self.n) < 0.5
            fresh[keep] = self.prev[keep]
        self.prev = fresh
        noise = self.masks[self.rng.integers(0, self.masks.shape[0], self.n)]
        return self.voc.descriptors[fresh] ^ noise

"""Training a vocabulary: hierarchical k-majority clustering of binary descriptors.

As DBoW2's ``TemplatedVocabulary::create``: the descriptors are split into k clusters with
k-means++ seeding, Hamming distance and bitwise-majority centres; every cluster with more
than one descriptor is split again, down to L levels. A node with at most k descriptors gets
one child per descriptor. Words are the leaves; their IDF weight is ``log(N / N_i)`` over the
training images (N images, N_i of them containing the word). Seeded and deterministic.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Sequence

import numpy as np
from tqdm import tqdm

from ..errors import InputError
from .descriptors import as_words, check_descriptors, hamming_cross, majority_by_label
from .scoring import Scoring, Weighting
from .tree import Vocabulary

log = logging.getLogger(__name__)

_CHUNK = 65_536


def _nearest(words: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of and distance to the nearest centre for every descriptor, in chunks."""
    n = words.shape[0]
    label = np.empty(n, np.int64)
    dist = np.empty(n, np.int32)
    for s in range(0, n, _CHUNK):
        d = hamming_cross(words[s : s + _CHUNK], centres)
        label[s : s + _CHUNK] = d.argmin(axis=1)
        dist[s : s + _CHUNK] = d[np.arange(d.shape[0]), label[s : s + _CHUNK]]
    return label, dist


def kmeans_plus_plus(words: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeds (Hamming distance, probability proportional to squared distance).

    Args:
        words: (N, 4) uint64 descriptors, N > k.
        k: wanted number of seeds.
        rng: random generator.

    Returns:
        (m,) int64 indices of the seeds, m <= k (fewer when the set has fewer distinct points).
    """
    n = words.shape[0]
    seeds = [int(rng.integers(n))]
    d = hamming_cross(words, words[seeds[-1] : seeds[-1] + 1])[:, 0].astype(np.float64)
    while len(seeds) < k:
        p = d * d
        total = p.sum()
        if total <= 0:
            break
        nxt = int(np.searchsorted(np.cumsum(p), rng.random() * total, side="right"))
        nxt = min(nxt, n - 1)
        seeds.append(nxt)
        d = np.minimum(d, hamming_cross(words, words[nxt : nxt + 1])[:, 0])
    return np.array(seeds, np.int64)


def kmajority(
    descriptors: np.ndarray, k: int, rng: np.random.Generator, max_iter: int = 15
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster binary descriptors into at most k groups (k-means++ seeds, majority centres).

    Args:
        descriptors: (N, 32) uint8, N > k.
        k: number of clusters.
        rng: random generator.
        max_iter: iteration limit (stops earlier when assignments no longer change).

    Returns:
        centres (m, 32) uint8 and labels (N,) int64 in [0, m), m <= k, no empty cluster.
    """
    words = as_words(descriptors)
    seeds = kmeans_plus_plus(words, k, rng)
    centres = descriptors[seeds].copy()
    labels = np.full(descriptors.shape[0], -1, np.int64)
    for _ in range(max_iter):
        new, _ = _nearest(words, as_words(centres))
        if np.array_equal(new, labels):
            break
        labels = new
        m = centres.shape[0]
        new_centres, sizes = majority_by_label(descriptors, labels, m)
        # an emptied cluster keeps its previous centre
        centres = np.where((sizes > 0)[:, None], new_centres, centres)
    used = np.unique(labels)
    remap = np.full(centres.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return centres[used], remap[labels]


def train_vocabulary(
    descriptor_sets: Sequence[np.ndarray],
    k: int = 10,
    levels: int = 5,
    weighting: Weighting = Weighting.TF_IDF,
    scoring: Scoring = Scoring.L1,
    seed: int = 0,
    max_iter: int = 15,
    levels_up: int | None = None,
    progress: bool = True,
) -> Vocabulary:
    """Train a vocabulary tree from the descriptors of a set of training images.

    Args:
        descriptor_sets: one (N_i, 32) uint8 array per training image.
        k: branching factor (>= 2).
        levels: depth L (>= 1).
        weighting: word weighting.
        scoring: scoring the vocabulary's BoW vectors are normalised for.
        seed: random seed; the same inputs and seed give the same tree.
        max_iter: k-majority iterations per node.
        levels_up: default direct-index level of the returned vocabulary (None: L - 2).
        progress: show a progress bar.

    Returns:
        The trained vocabulary.
    """
    if k < 2 or levels < 1:
        raise InputError(f"vocabulary training needs k >= 2 and L >= 1, got k={k}, L={levels}")
    for i, d in enumerate(descriptor_sets):
        check_descriptors(d, f"descriptors of training image {i}")
    sets = [d for d in descriptor_sets]
    if not sets or sum(d.shape[0] for d in sets) == 0:
        raise InputError("vocabulary training needs at least one descriptor")
    data = np.ascontiguousarray(np.concatenate(sets, axis=0))
    rng = np.random.default_rng(seed)
    parents: list[int] = [-1]
    centres: list[np.ndarray] = [np.zeros(32, np.uint8)]
    queue: deque[tuple[int, np.ndarray, int]] = deque([(0, np.arange(data.shape[0]), 0)])
    bar = tqdm(total=data.shape[0] * levels, desc="vocabulary", unit="desc", disable=not progress,
               leave=False)
    while queue:
        node, idx, level = queue.popleft()
        bar.update(idx.size)
        if idx.size <= k:
            groups_c = data[idx]
            groups = [idx[i : i + 1] for i in range(idx.size)]
        else:
            groups_c, labels = kmajority(data[idx], k, rng, max_iter)
            order = np.argsort(labels, kind="stable")
            cuts = np.searchsorted(labels[order], np.arange(1, groups_c.shape[0]))
            groups = np.split(idx[order], cuts)
        for c, members in zip(groups_c, groups, strict=True):
            child = len(parents)
            parents.append(node)
            centres.append(c)
            if level + 1 < levels and members.size > 1:
                queue.append((child, members, level + 1))
    bar.close()
    n = len(parents)
    voc = Vocabulary(
        k, levels, np.array(parents, np.int32), np.stack(centres).astype(np.uint8),
        np.zeros(n, np.float64), weighting, scoring, levels_up,
    )
    weights = np.zeros(n, np.float64)
    if weighting in (Weighting.TF_IDF, Weighting.IDF):
        n_images = len(sets)
        counts = np.zeros(voc.n_words, np.int64)
        for d in sets:
            if d.shape[0]:
                counts[np.unique(voc.node_word[voc.leaves_of(d)])] += 1
        idf = np.log(n_images / np.maximum(counts, 1))
        weights[voc.word_nodes] = idf
    else:
        weights[voc.word_nodes] = 1.0
    log.info("trained vocabulary: %d nodes, %d words", n, voc.n_words)
    return Vocabulary(k, levels, voc.parents, voc.descriptors, weights, weighting, scoring, levels_up)

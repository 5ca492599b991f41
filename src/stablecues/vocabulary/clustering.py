"""Growing a vocabulary tree: the clustering of one node and of whole subtrees.

The pieces :func:`stablecues.vocabulary.train_vocabulary` is made of, apart so that
:mod:`.distributed` can grow subtrees on other machines with the same code (see
:mod:`.train` for the seeding that makes a subtree the same wherever it grows, and for the
fixed-order distance sums that make float distances reproducible to the bit).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from .descriptors import (
    as_words,
    hamming_cross,
    majority_by_label,
    mean_by_label,
)

log = logging.getLogger(__name__)

_CHUNK = 65_536
_EXACT_ROWS = 4096  # rows per block of the fixed-order distance sum
_F32_EPS = 2.0**-24  # unit roundoff of float32

#: a node's children as found by the clustering: (path of each child, (m, D) centres)
Path_ = tuple[int, ...]
Nodes = list[tuple[Path_, np.ndarray]]


def node_rng(seed: int, path: Path_) -> np.random.Generator:
    """The random stream of the node at ``path`` (child slots from the root; the root: ())."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=tuple(int(p) for p in path)))


# ---------------------------------------------------------------------------------- binary
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


def kmeans_plus_plus(
    points: np.ndarray, k: int, rng: np.random.Generator,
    distance: Callable[[np.ndarray, int], np.ndarray] | None = None,
) -> np.ndarray:
    """k-means++ seeds: each next seed drawn with probability proportional to D(x)^2.

    Args:
        points: (N, 4) uint64 binary descriptors (see :func:`.descriptors.as_words`), or any
            (N, D) points with ``distance`` given; N > k.
        k: wanted number of seeds.
        rng: random generator.
        distance: ``(points, i) -> (N,) float64`` the squared distance D(x)^2 of every point
            to point ``i``; default: squared Hamming distance of uint64 words.

    Returns:
        (m,) int64 indices of the seeds, m <= k (fewer when the set has fewer distinct points).
    """
    if distance is None:
        def distance(p: np.ndarray, i: int) -> np.ndarray:
            d = hamming_cross(p, p[i : i + 1])[:, 0].astype(np.float64)
            return d * d
    n = points.shape[0]
    seeds = [int(rng.integers(n))]
    p = distance(points, seeds[-1])
    while len(seeds) < k:
        total = p.sum()
        if total <= 0:
            break
        nxt = int(np.searchsorted(np.cumsum(p), rng.random() * total, side="right"))
        nxt = min(nxt, n - 1)
        seeds.append(nxt)
        p = np.minimum(p, distance(points, nxt))
    return np.array(seeds, np.int64)


def kmajority(
    descriptors: np.ndarray, k: int, rng: np.random.Generator, max_iter: int = 15
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster binary descriptors into at most k groups (k-means++ seeds, majority centres).

    Args:
        descriptors: (N, B) uint8, N > k.
        k: number of clusters.
        rng: random generator.
        max_iter: iteration limit (stops earlier when assignments no longer change).

    Returns:
        centres (m, B) uint8 and labels (N,) int64 in [0, m), m <= k, no empty cluster.
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
        new_centres, sizes = majority_by_label(descriptors, labels, centres.shape[0])
        # an emptied cluster keeps its previous centre
        centres = np.where((sizes > 0)[:, None], new_centres, centres)
    return _compact(centres, labels)


def _compact(centres: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop clusters nobody was assigned to; labels renumbered in order."""
    used = np.unique(labels)
    remap = np.full(centres.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return centres[used], remap[labels]


# ---------------------------------------------------------------------------------- float
def squared_l2_exact(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Squared Euclidean distance of each point to one centre, summed dimension by dimension
    in float64 (the order the vocabulary's descent uses): the same bits on every machine.

    Args:
        points: (N, D) float32 or float64.
        centre: (D,) float32 or float64.

    Returns:
        (N,) float64.
    """
    acc = np.zeros(points.shape[0])
    c = centre.astype(np.float64)
    for s in range(0, points.shape[0], _EXACT_ROWS):
        cols = np.ascontiguousarray(points[s : s + _EXACT_ROWS].T, np.float64)  # (D, rows): cache-friendly
        part = acc[s : s + _EXACT_ROWS]
        for j in range(cols.shape[0]):
            diff = c[j] - cols[j]
            part += diff * diff
    return acc


def nearest_centre(points: np.ndarray, centres: np.ndarray, sq_norms: np.ndarray | None = None) -> np.ndarray:
    """Index of the nearest centre (squared Euclidean, ties to the lowest index) of each point.

    A float32 matrix product ranks the centres; where a point's two nearest are within the
    product's rounding bound of each other, they are compared again in a fixed order
    (:func:`squared_l2_exact`), so the result does not depend on the BLAS library or its
    thread count: it is the index :func:`squared_l2_exact` finds nearest, on every machine.

    Args:
        points: (N, D) float32.
        centres: (m, D) float32.
        sq_norms: (N,) squared norms of the points (computed when None), for the bound.

    Returns:
        (N,) int64.
    """
    n, dim = points.shape
    labels = np.empty(n, np.int64)
    c64 = centres.astype(np.float64)
    cc = (c64 * c64).sum(axis=1)
    xx = (points.astype(np.float64) ** 2).sum(axis=1) if sq_norms is None else sq_norms
    # |error| of cc - 2 x.c per entry <= 2 D u |x||c| with u = 2^-24 (float32): twice that
    # separates the two smallest safely; |x||c| <= (|x|^2 + |c|^2) / 2
    slack = 4.0 * dim * _F32_EPS * (xx + cc.max(initial=0.0)) + 1e-9
    for s in range(0, n, _CHUNK):
        x = points[s : s + _CHUNK]
        d = cc[None, :] - 2.0 * (x @ centres.T).astype(np.float64)
        lab = d.argmin(axis=1)
        if centres.shape[0] > 1:
            part = np.partition(d, 1, axis=1)
            close = np.flatnonzero(part[:, 1] - part[:, 0] <= slack[s : s + _CHUNK])
            if close.size:
                lab[close] = _exact_nearest(x[close], c64)
        labels[s : s + _CHUNK] = lab
    return labels


def _exact_nearest(points: np.ndarray, c64: np.ndarray) -> np.ndarray:
    """The nearest centre of a few points by :func:`squared_l2_exact`'s fixed-order sums."""
    d = np.stack([squared_l2_exact(c64, p) for p in points])  # (r, m)
    return d.argmin(axis=1)


def kmeans(
    descriptors: np.ndarray, k: int, rng: np.random.Generator, max_iter: int = 15
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster float descriptors into at most k groups (k-means++ seeds, Lloyd's iterations
    with squared Euclidean distance and mean centres).

    Args:
        descriptors: (N, D) float32, N > k.
        k: number of clusters.
        rng: random generator.
        max_iter: iteration limit (stops earlier when assignments no longer change).

    Returns:
        centres (m, D) float32 and labels (N,) int64 in [0, m), m <= k, no empty cluster.
    """
    seeds = kmeans_plus_plus(descriptors, k, rng, lambda p, i: squared_l2_exact(p, p[i]))
    centres = descriptors[seeds].copy()
    labels = np.full(descriptors.shape[0], -1, np.int64)
    norms = np.einsum("ij,ij->i", descriptors, descriptors, dtype=np.float64)
    for _ in range(max_iter):
        new = nearest_centre(descriptors, centres, norms)
        if np.array_equal(new, labels):
            break
        labels = new
        new_centres, sizes = mean_by_label(descriptors, labels, centres.shape[0])
        centres = np.where((sizes > 0)[:, None], new_centres, centres)
    return _compact(centres, labels)


# ---------------------------------------------------------------------------------- the tree
def split_node(
    data: np.ndarray, k: int, rng: np.random.Generator, max_iter: int
) -> tuple[np.ndarray, list[np.ndarray]]:
    """The children of a node holding ``data``: their centres and their members.

    Args:
        data: (N, D) descriptors under the node (uint8 binary or float32), N >= 1.

    Returns:
        centres (m, D) of the node's dtype, and per child the (n_i,) int64 indices (into
        ``data``, ascending) of its members. At most k descriptors: one child each.
    """
    n = data.shape[0]
    if n <= k:
        return data.copy(), [np.array([i], np.int64) for i in range(n)]
    cluster = kmeans if data.dtype == np.float32 else kmajority
    centres, labels = cluster(data, k, rng, max_iter)
    order = np.argsort(labels, kind="stable")
    cuts = np.searchsorted(labels[order], np.arange(1, centres.shape[0]))
    return centres, np.split(order, cuts)


#: a node still to be split: (path, indices into the data of the descriptors under it, depth)
Pending = tuple[Path_, np.ndarray, int]


def expand(
    data: np.ndarray, path: Path_, level: int, k: int, levels: int, seed: int, max_iter: int,
    progress: Any = None, until: int | None = None,
) -> tuple[Nodes, list[Pending]]:
    """Every node below the node at ``path`` (depth ``level``), which holds ``data``.

    Args:
        data: (N, D) descriptors under the node, in input order.
        path: the node's child slots from the root (() for the root).
        level: its depth (``len(path)``).
        k, levels, seed, max_iter: as :func:`train_vocabulary`.
        progress: a tqdm bar updated with the descriptors clustered, or None.
        until: nodes at this depth are not split but returned as pending (None: split all).

    Returns:
        (path, centre) of each node found below, in no particular order, and the pending
        nodes (those at depth ``until`` that need splitting), in path order.
    """
    out: Nodes = []
    pending: list[Pending] = []
    stack: list[Pending] = [(tuple(path), np.arange(data.shape[0]), level)]
    while stack:
        node, idx, lev = stack.pop()
        if lev == until:
            pending.append((node, idx, lev))
            continue
        if progress is not None:
            progress.update(idx.size)
        centres, groups = split_node(data[idx], k, node_rng(seed, node), max_iter)
        for slot, members in enumerate(groups):
            child = (*node, slot)
            out.append((child, centres[slot]))
            if lev + 1 < levels and members.size > 1:
                stack.append((child, idx[members], lev + 1))
    pending.sort(key=lambda p: p[0])
    return out, pending


def grow_subtree(
    data: np.ndarray, path: Path_, level: int, k: int, levels: int, seed: int, max_iter: int,
    progress: Any = None,
) -> Nodes:
    """Every node below the node at ``path``: :func:`expand` to the leaves."""
    return expand(data, path, level, k, levels, seed, max_iter, progress)[0]


def assemble_tree(nodes: Nodes, dim: int, dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    """Parents and centres of the whole tree, numbered breadth first (by depth, then path).

    Args:
        nodes: (path, centre) of every node except the root.
        dim: descriptor width; dtype: uint8 or float32.

    Returns:
        parents (n,) int32 (root -1) and centres (n, dim) (the root's zero).
    """
    ordered = sorted(nodes, key=lambda pc: (len(pc[0]), pc[0]))
    ids: dict[Path_, int] = {(): 0}
    parents = np.empty(len(ordered) + 1, np.int32)
    parents[0] = -1
    centres = np.zeros((len(ordered) + 1, dim), dtype)
    for i, (path, centre) in enumerate(ordered, start=1):
        ids[path] = i
        parents[i] = ids[path[:-1]]
        centres[i] = centre
    return parents, centres

"""The vocabulary tree: nodes, words, weights, and the transform of descriptors into BoW vectors."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from ..errors import InputError, VocabularyError
from ..types import DESCRIPTOR_BYTES, BowVector, DescriptorKind, FeatureVector
from .descriptors import as_words, check_descriptors
from .scoring import Scoring, Weighting, normalise, scoring_name, weighting_name


@dataclass(frozen=True)
class VocabularyInfo:
    """Summary of a vocabulary, as ``stablecues vocab info`` prints it."""

    k: int
    levels: int
    n_nodes: int
    n_words: int
    weighting: str
    scoring: str
    max_depth: int
    fingerprint: str


class Vocabulary:
    """A DBoW2-style hierarchical vocabulary of binary words.

    Node 0 is the root. Every other node has a parent, a 256-bit centre and, for leaves (words),
    a weight (the IDF for TF-IDF and IDF weighting, 1 otherwise). A parent's id is always lower
    than its children's, as in DBoW2's files. Leaves may sit at any depth up to ``levels``.

    Args:
        k: branching factor.
        levels: depth L of the tree (the root is level 0, leaves at most at level L).
        parents: (n,) int32 parent of each node (-1 for the root).
        descriptors: (n, 32) uint8 node centres (the root's is ignored).
        weights: (n,) float64 node weights (used for leaves).
        weighting: how BoW weights are made.
        scoring: how BoW vectors are compared (decides their normalisation).
        levels_up: default level of the direct index, counted up from the leaves' level L;
            None: ``L - 2``, i.e. the direct index groups features under the ~k^2 nodes of
            level 2, as ORB-SLAM does with its 6-level vocabulary and ``levelsup = 4`` (coarser
            groups make matching slower, finer ones miss correspondences).
        fingerprint: identity of the tree; computed from the arrays when not given.
    """

    def __init__(
        self,
        k: int,
        levels: int,
        parents: np.ndarray,
        descriptors: np.ndarray,
        weights: np.ndarray,
        weighting: Weighting = Weighting.TF_IDF,
        scoring: Scoring = Scoring.L1,
        levels_up: int | None = None,
        fingerprint: str | None = None,
        children: np.ndarray | None = None,
    ) -> None:
        n = parents.shape[0]
        if n < 1 or parents[0] != -1:
            raise VocabularyError("vocabulary: node 0 must be the root (parent -1)")
        if descriptors.shape != (n, DESCRIPTOR_BYTES) or weights.shape != (n,):
            raise VocabularyError(
                f"vocabulary: arrays disagree: {n} parents, descriptors {descriptors.shape}, "
                f"weights {weights.shape}"
            )
        if n > 1 and (np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, n))):
            raise VocabularyError("vocabulary: every node's parent must come before it")
        if k < 2 or levels < 1:
            raise VocabularyError(f"vocabulary: need k >= 2 and L >= 1, got k={k}, L={levels}")
        self.k = int(k)
        self.levels = int(levels)
        self.parents = np.ascontiguousarray(parents, np.int32)
        self.descriptors = np.ascontiguousarray(descriptors, np.uint8)
        self.weights = np.ascontiguousarray(weights, np.float64)
        self.weighting = Weighting(weighting)
        self.scoring = Scoring(scoring)
        self.children = children if children is not None else _children_table(self.parents, self.k)
        if self.children.shape != (n, self.k):
            raise VocabularyError(f"vocabulary: a node has more than k={self.k} children")
        self.is_leaf = self.children[:, 0] < 0
        self.is_leaf[0] = n == 1
        self.word_nodes = np.flatnonzero(self.is_leaf).astype(np.int32)
        self.node_word = np.full(n, -1, np.int32)
        self.node_word[self.word_nodes] = np.arange(self.word_nodes.size, dtype=np.int32)
        self.depth = _depths(self.parents)
        if int(self.depth.max(initial=0)) > self.levels:
            raise VocabularyError(
                f"vocabulary: tree is {int(self.depth.max())} levels deep but the header says L={levels}"
            )
        self._build_search_tables()
        self.levels_up = max(self.levels - 2, 0) if levels_up is None else int(levels_up)
        self._di_cache: dict[int, np.ndarray] = {}
        self._fingerprint = fingerprint

    def _build_search_tables(self) -> None:
        """Per internal node, its children's centres side by side: one contiguous (k * 4)
        uint64 row, so each level of the descent gathers one block per descriptor."""
        internal = np.flatnonzero(~self.is_leaf).astype(np.int32)
        self._row = np.full(self.n_nodes, -1, np.int32)
        self._row[internal] = np.arange(internal.size, dtype=np.int32)
        kids = self.children[internal]  # (I, k)
        words = as_words(self.descriptors)
        blocks = words[np.where(kids >= 0, kids, 0)]  # (I, k, 4)
        self._blocks = np.ascontiguousarray(blocks.reshape(internal.size, self.k * 4))
        self._block_kids = kids
        missing = kids < 0
        self._penalty = (np.where(missing, 1024, 0).astype(np.uint32) if missing.any() else None)

    # ------------------------------------------------------------------ properties
    @property
    def n_nodes(self) -> int:
        return int(self.parents.shape[0])

    @property
    def n_words(self) -> int:
        return int(self.word_nodes.shape[0])

    @property
    def word_weights(self) -> np.ndarray:
        """(W,) float64 weight of each word."""
        return self.weights[self.word_nodes]

    @property
    def fingerprint(self) -> str:
        """SHA-256 over k, L, weighting, scoring and the node arrays (hex)."""
        if self._fingerprint is None:
            h = hashlib.sha256()
            h.update(f"{self.k} {self.levels} {int(self.weighting)} {int(self.scoring)}".encode())
            for arr in (self.parents, self.descriptors, self.weights):
                h.update(np.ascontiguousarray(arr).tobytes())
            self._fingerprint = h.hexdigest()
        return self._fingerprint

    @property
    def descriptor_kind(self) -> DescriptorKind:
        """What the words are made of: binary, 32 bytes (ORB's descriptors)."""
        return DescriptorKind("binary", int(self.descriptors.shape[1]))

    def info(self) -> VocabularyInfo:
        return VocabularyInfo(
            k=self.k,
            levels=self.levels,
            n_nodes=self.n_nodes,
            n_words=self.n_words,
            weighting=weighting_name(self.weighting),
            scoring=scoring_name(self.scoring),
            max_depth=int(self.depth.max(initial=0)),
            fingerprint=self.fingerprint,
        )

    def __repr__(self) -> str:
        i = self.info()
        return (f"Vocabulary(k={i.k}, L={i.levels}, words={i.n_words}, "
                f"weighting={i.weighting}, scoring={i.scoring})")

    # ------------------------------------------------------------------ transform
    def leaves_of(self, descriptors: np.ndarray) -> np.ndarray:
        """Descend the tree: the leaf node each descriptor reaches.

        At each level a descriptor moves to the child with the nearest centre (Hamming), as
        DBoW2 does; ties go to the lowest child id.

        Args:
            descriptors: (N, 32) uint8.

        Returns:
            (N,) int32 leaf node ids.

        Raises:
            InputError: descriptors that are not (N, 32) uint8; descriptors of another kind
                (float, or binary of another width) are named as such.
        """
        self._check_kind(descriptors)
        check_descriptors(descriptors)
        n = descriptors.shape[0]
        cur = np.zeros(n, np.int32)
        if n == 0 or self.n_nodes == 1:
            return cur
        q = as_words(descriptors)
        k = self.k
        active = np.arange(n)
        while active.size:
            rows = self._row[cur[active]]
            x = np.take(self._blocks, rows, axis=0)  # (M, k*4) child centres
            np.bitwise_xor(x, np.tile(q[active], (1, k)), out=x)
            counts = np.bitwise_count(x).view(np.uint32)  # 4 byte-counts per uint32
            # sum the four bytes of each uint32 into its top byte (each <= 64, so no carry);
            # a sum of exactly 256 wraps to 0: that is the all-bits-differ pattern 0x40404040
            d = (counts * np.uint32(0x01010101)) >> np.uint32(24)
            d[counts == 0x40404040] = 256
            if self._penalty is not None:
                d += self._penalty[rows]
            best = self._block_kids[rows, d.argmin(axis=1)]
            cur[active] = best
            active = active[~self.is_leaf[best]]
        return cur

    def _check_kind(self, descriptors: np.ndarray) -> None:
        """One clear line for descriptors of another kind than the words (e.g. SIFT's)."""
        if not isinstance(descriptors, np.ndarray) or descriptors.ndim != 2:
            return  # check_descriptors says what is wrong
        if descriptors.dtype not in (np.uint8, np.float32) or descriptors.shape[1] < 1:
            return
        kind = DescriptorKind.of(descriptors)
        if kind != self.descriptor_kind:
            raise InputError(
                f"descriptors are {kind} but the vocabulary holds {self.descriptor_kind} words: "
                "train a vocabulary for them"
            )

    def direct_index_nodes(self, leaves: np.ndarray, levels_up: int | None = None) -> np.ndarray:
        """Node at level ``L - levels_up`` above each leaf (the leaf itself when shallower).

        Args:
            leaves: (N,) int32 leaf node ids.
            levels_up: levels above the leaves; defaults to the vocabulary's ``levels_up``.

        Returns:
            (N,) int32 node ids.
        """
        up = self.levels_up if levels_up is None else int(levels_up)
        table = self._di_cache.get(up)
        if table is None:
            target = max(self.levels - up, 0)
            table = np.arange(self.n_nodes, dtype=np.int32)
            depth = self.depth.astype(np.int32).copy()
            while True:
                deep = depth > target
                if not deep.any():
                    break
                table[deep] = self.parents[table[deep]]
                depth[deep] -= 1
            self._di_cache[up] = table
        return table[leaves]

    def transform(
        self, descriptors: np.ndarray, levels_up: int | None = None
    ) -> tuple[BowVector, FeatureVector]:
        """Bag-of-words vector and direct index of one image's descriptors.

        Weights follow DBoW2: TF-IDF and TF add each feature's word weight, IDF and binary
        count a word once; words of zero weight are left out (and so are their features from
        the direct index, node -1). The vector is normalised as the scoring needs; without
        normalisation (dot product) TF weights are divided by the number of distinct words, as
        DBoW2 does.

        Args:
            descriptors: (N, 32) uint8.
            levels_up: direct-index level above the leaves (default: ``self.levels_up``).

        Returns:
            (BowVector, FeatureVector); both empty for N = 0.

        Raises:
            InputError: descriptors of another kind than the vocabulary's words, e.g. "descriptors
                are 128-dim float32 but the vocabulary holds 32-byte binary words: ...".
        """
        up = self.levels_up if levels_up is None else int(levels_up)
        leaves = self.leaves_of(descriptors)
        if leaves.size == 0:
            return BowVector.empty(), FeatureVector(np.zeros(0, np.int32), up)
        w = self.weights[leaves]
        ok = w > 0
        nodes = np.where(ok, self.direct_index_nodes(leaves, up), -1).astype(np.int32)
        words = self.node_word[leaves[ok]]
        if words.size == 0:
            return BowVector.empty(), FeatureVector(nodes, up)
        uniq, inverse = np.unique(words, return_inverse=True)
        if self.weighting in (Weighting.TF_IDF, Weighting.TF):
            values: np.ndarray = np.bincount(inverse, weights=w[ok], minlength=uniq.size)
            if self.scoring == Scoring.DOT_PRODUCT:
                values = values / uniq.size
        else:
            values = self.weights[self.word_nodes[uniq]].astype(np.float64)
        values = normalise(values, self.scoring)
        return BowVector(uniq.astype(np.int32), values), FeatureVector(nodes, up)


def _children_table(parents: np.ndarray, k: int) -> np.ndarray:
    """(n, k) int32 children of each node in id order, -1 padded."""
    n = parents.shape[0]
    table = np.full((n, k), -1, np.int32)
    if n <= 1:
        return table
    child = np.arange(1, n, dtype=np.int32)
    par = parents[1:].astype(np.int64)
    order = np.argsort(par, kind="stable")
    par_sorted, child_sorted = par[order], child[order]
    starts = np.searchsorted(par_sorted, par_sorted, side="left")
    slot = np.arange(par_sorted.size) - starts
    if slot.size and int(slot.max()) >= k:
        bad = int(par_sorted[int(slot.argmax())])
        raise VocabularyError(f"vocabulary: node {bad} has more than k={k} children")
    table[par_sorted, slot] = child_sorted
    return table


def _depths(parents: np.ndarray) -> np.ndarray:
    """(n,) int16 depth of each node (root 0); parents precede children."""
    n = parents.shape[0]
    depth = np.zeros(n, np.int16)
    if n <= 1:
        return depth
    # parents precede children, so a few vectorised passes settle every depth
    par = parents.astype(np.int64)
    par[0] = 0
    while True:
        new = depth[par] + 1
        new[0] = 0
        if np.array_equal(new, depth):
            return depth
        depth = new.astype(np.int16)

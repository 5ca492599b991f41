"""The vocabulary tree: nodes, words, weights, and the transform of descriptors into BoW vectors."""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError, VocabularyError
from ..types import ORB_DESCRIPTOR, BowVector, DescriptorKind, FeatureVector
from . import engine as _engine
from .descriptors import as_words, check_descriptors, n_words
from .scoring import Scoring, Weighting, normalise, scoring_name, weighting_name

#: Largest branching factor a vocabulary may declare (a flat vocabulary of 2^20 words; DBoW2's
#: text loader stops at 20). Tables are sized by the children nodes really have, never by k.
MAX_K = 1 << 20
#: Deepest tree a vocabulary may declare (DBoW2's text loader stops at 10).
MAX_LEVELS = 64
#: The padded search table (internal nodes x most children of any node) may hold at most this
#: many slots per node, plus :data:`_SLOTS_SPARE`: a tree whose fan-out is so uneven that the
#: table would dwarf the tree itself is refused rather than allocated (36 bytes a slot).
_SLOTS_PER_NODE = 16
_SLOTS_SPARE = 1 << 22


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


class _Prepared:
    """An attribute of :class:`Vocabulary` that :meth:`Vocabulary._prepare` builds: reading it
    before prepares the vocabulary; after, the value sits in the instance's dict, which a
    non-data descriptor like this one leaves to plain attribute lookup (no cost per read)."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        obj._prepare()
        try:
            return obj.__dict__[self.name]
        except KeyError:
            raise AttributeError(self.name) from None


def _search_tables(descriptors: np.ndarray, n: int, inner: np.ndarray, kids: np.ndarray) -> dict[str, Any]:
    """Per inner node, its children's centres side by side: one contiguous (w * 4) uint64 row,
    so each level of the descent gathers one block per descriptor.

    Args:
        descriptors: (n, B) uint8 or (n, D) float32 centres.
        n: the number of nodes.
        inner: (I,) int32 ids of the nodes that have children, ascending.
        kids: (I, w) int32 their children in id order, -1 padded.
    """
    row = np.full(n, -1, np.int32)  # row of each inner node, -1: a leaf
    row[inner] = np.arange(inner.size, dtype=np.int32)
    is_float = descriptors.dtype == np.float32
    # binary: (n, W) uint64 words; float: (n, D) float32 as they are
    cells = descriptors if is_float else as_words(descriptors)
    blocks = cells[np.where(kids >= 0, kids, 0)]  # (I, w, W or D)
    penalty: np.ndarray | None = None
    missing = kids < 0
    if missing.any():  # a padded slot is never the nearest child
        if is_float:
            penalty = np.where(missing, np.inf, 0.0)
        else:
            far = max(1024, 64 * cells.shape[1] + 1)
            penalty = np.where(missing, far, 0).astype(np.uint32)
    table = np.ascontiguousarray(blocks.reshape(inner.size, kids.shape[1] * cells.shape[1]))
    counts = (kids >= 0).sum(axis=1, dtype=np.int32)
    return {"_row": row, "_blocks": table, "_block_kids": kids, "_block_counts": counts, "_penalty": penalty}


def _same_children(given: np.ndarray, n: int, is_leaf: np.ndarray, kids: np.ndarray) -> bool:
    """Whether ``given`` is the tree's (n, w') children table (w' >= w, -1 padded), or an empty
    (n, 0) one (not stored)."""
    given = np.asarray(given)
    if given.ndim != 2 or given.shape[0] != n:
        return False
    if given.shape[1] == 0:
        return True
    if given.shape[1] < kids.shape[1]:
        return False
    expected = np.full(given.shape, -1, np.int32)
    expected[~is_leaf, : kids.shape[1]] = kids
    return bool(np.array_equal(given, expected))


class Vocabulary:
    """A DBoW2-style hierarchical vocabulary of binary or float words.

    Node 0 is the root. Every other node has a parent, a centre and, for leaves (words), a
    weight (the IDF for TF-IDF and IDF weighting, 1 otherwise). A parent's id is always lower
    than its children's, as in DBoW2's files. Leaves may sit at any depth up to ``levels``.

    The centres' dtype decides the descriptor kind (:attr:`descriptor_kind`): uint8 centres of
    B bytes are binary words compared by Hamming distance (B = 32 for ORB, any B >= 1 works),
    float32 centres of D dimensions are float words compared by Euclidean distance (D = 128
    for SIFT). Weighting, scoring, the direct index and the files are the same for both.

    Args:
        k: branching factor, 2 <= k <= :data:`MAX_K`.
        levels: depth L of the tree (the root is level 0, leaves at most at level L),
            1 <= L <= :data:`MAX_LEVELS`.
        parents: (n,) integer parent of each node (-1 for the root).
        descriptors: (n, B) uint8 binary or (n, D) float32 (finite) node centres (the root's
            is ignored).
        weights: (n,) finite float node weights (used for leaves; <= 0 stops a word).
        weighting: how BoW weights are made.
        scoring: how BoW vectors are compared (decides their normalisation).
        levels_up: default level of the direct index, counted up from the leaves' level L
            (>= 0); None: ``L - 2``, i.e. the direct index groups features under the ~k^2
            nodes of level 2, as ORB-SLAM does with its 6-level vocabulary and ``levelsup = 4``
            (coarser groups make matching slower, finer ones miss correspondences).
        fingerprint: identity of the tree; computed from the arrays when not given.
        children: the (n, w) children table, when the caller has it; it is checked against
            ``parents``, which decide.

    Raises:
        VocabularyError: arrays that do not form such a tree, out-of-range k, L or levels_up,
            or weights that are NaN or infinite. Messages start with "vocabulary:"; the file
            loaders replace that with the file's name.
    """

    # built by _prepare(), on first use when the vocabulary was made with deferred=True (a file
    # loaded in a millisecond); read like plain attributes either way
    parents: np.ndarray = _Prepared()  # type: ignore[assignment]
    descriptors: np.ndarray = _Prepared()  # type: ignore[assignment]
    weights: np.ndarray = _Prepared()  # type: ignore[assignment]
    is_leaf: np.ndarray = _Prepared()  # type: ignore[assignment]
    word_nodes: np.ndarray = _Prepared()  # type: ignore[assignment]
    node_word: np.ndarray = _Prepared()  # type: ignore[assignment]
    depth: np.ndarray = _Prepared()  # type: ignore[assignment]
    _row: np.ndarray = _Prepared()  # type: ignore[assignment]
    _blocks: np.ndarray = _Prepared()  # type: ignore[assignment]
    _block_kids: np.ndarray = _Prepared()  # type: ignore[assignment]
    _block_counts: np.ndarray = _Prepared()  # type: ignore[assignment]
    _penalty: np.ndarray | None = _Prepared()  # type: ignore[assignment]
    _dense_children: np.ndarray | None = _Prepared()  # type: ignore[assignment]

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
        claimed_fingerprint: str | None = None,
        source: str | None = None,
        deferred: Callable[[], None] | None = None,
    ) -> None:
        check_header(k, levels, levels_up)
        self.k = int(k)
        self.levels = int(levels)
        self._kind: DescriptorKind | None = None
        self.weighting = Weighting(weighting)
        self.scoring = Scoring(scoring)
        self.levels_up = max(self.levels - 2, 0) if levels_up is None else int(levels_up)
        self._di_cache: dict[int, np.ndarray] = {}
        self._fingerprint = fingerprint
        # a file's recorded fingerprint, checked against the content when first asked for
        self._claimed = claimed_fingerprint if fingerprint is None else None
        self._source = source or "vocabulary"
        self._engine_request = "auto"
        self._engine: str | None = None
        self._raw: tuple[Any, ...] | None = (parents, descriptors, weights, children, deferred)
        self._prepare_lock = threading.Lock()
        if deferred is None:
            self._prepare()

    def _prepare(self) -> None:
        """Check the arrays and build the search tables (once). With ``deferred`` (a file's
        integrity check: its CRC), that runs first; the loaders pass it so that a load takes a
        millisecond and the checks run when the vocabulary is first used.

        Raises:
            VocabularyError: as the constructor (a loader's file name leading the message).
        """
        with self._prepare_lock:
            raw = self._raw
            if raw is None:
                return
            parents, descriptors, weights, children, deferred = raw
            try:
                if deferred is not None:
                    deferred()
                self.__dict__.update(self._prepared(parents, descriptors, weights, children))
            except VocabularyError as exc:
                if deferred is None or self._source == "vocabulary":
                    raise
                raise VocabularyError(f"{self._source}: {str(exc).removeprefix('vocabulary: ')}") from None
            self._raw = None

    def _prepared(self, parents: np.ndarray, descriptors: np.ndarray, weights: np.ndarray,
                  children: np.ndarray | None) -> dict[str, Any]:
        """The attributes :meth:`_prepare` sets."""
        out: dict[str, Any] = {}
        out["parents"], out["descriptors"], out["weights"] = _check_arrays(parents, descriptors, weights)
        n = int(out["parents"].shape[0])
        inner, kids = _child_table(out["parents"], self.k)
        is_leaf = np.ones(n, bool)
        is_leaf[inner] = False
        out["is_leaf"] = is_leaf
        out["_dense_children"] = None
        out.update(_search_tables(out["descriptors"], n, inner, kids))
        if children is not None and not _same_children(children, n, is_leaf, kids):
            raise VocabularyError("vocabulary: the children table disagrees with the parents")
        word_nodes = np.flatnonzero(is_leaf).astype(np.int32)
        node_word = np.full(n, -1, np.int32)
        node_word[word_nodes] = np.arange(word_nodes.size, dtype=np.int32)
        out["word_nodes"], out["node_word"] = word_nodes, node_word
        out["depth"] = _depths(out["parents"], self.levels)
        return out

    def __getstate__(self) -> dict[str, Any]:
        """Pickled prepared (a worker process gets the checked arrays, not the file's check)."""
        self._prepare()
        state = dict(self.__dict__)
        state.pop("_prepare_lock", None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._prepare_lock = threading.Lock()

    @property
    def children(self) -> np.ndarray:
        """(n, w) int32 children of each node in id order, -1 padded; w is the most children
        any node has (at most k). Built on first use (n x w entries: large for a wide tree)."""
        if self._dense_children is None:
            table = np.full((self.n_nodes, self._block_kids.shape[1]), -1, np.int32)
            table[~self.is_leaf] = self._block_kids
            self._dense_children = table
        return self._dense_children

    # ------------------------------------------------------------------ properties
    @property
    def n_nodes(self) -> int:
        return int(self.parents.shape[0])

    @property
    def n_words(self) -> int:
        return int(self.word_nodes.shape[0])

    @property
    def max_children(self) -> int:
        """The most children any node has (at most k)."""
        return int(self._block_kids.shape[1])

    @property
    def word_weights(self) -> np.ndarray:
        """(W,) float64 weight of each word."""
        return self.weights[self.word_nodes]

    @property
    def fingerprint(self) -> str:
        """SHA-256 over k, L, weighting, scoring, the descriptor kind (when not ORB's, so that
        ORB vocabularies keep their fingerprints) and the node arrays (hex)."""
        if self._fingerprint is None:
            h = hashlib.sha256()
            h.update(f"{self.k} {self.levels} {int(self.weighting)} {int(self.scoring)}".encode())
            if self.descriptor_kind != ORB_DESCRIPTOR:
                h.update(f" {self.descriptor_kind.kind} {self.descriptor_kind.size}".encode())
            for arr in (self.parents, self.descriptors, self.weights):
                h.update(np.ascontiguousarray(arr).tobytes())
            digest = h.hexdigest()
            if self._claimed is not None and digest != self._claimed:
                raise VocabularyError(f"{self._source}: the vocabulary's content does not match the "
                                      "fingerprint its header records (a modified or corrupt file)")
            self._fingerprint = digest
        return self._fingerprint

    @property
    def descriptor_kind(self) -> DescriptorKind:
        """What the words are made of: binary with their byte width (32: ORB's descriptors) or
        float with their dimension (128: SIFT's)."""
        if self._kind is None:
            size = int(self.descriptors.shape[1])
            self._kind = DescriptorKind("float", size) if self.is_float else DescriptorKind("binary", size)
        return self._kind

    @property
    def is_float(self) -> bool:
        """Whether the words are float vectors (Euclidean distance) rather than binary ones."""
        return bool(self.descriptors.dtype == np.float32)

    @property
    def engine(self) -> str:
        """The engine this vocabulary's transforms run on: ``"compiled"`` or ``"numpy"``.

        Set it to ``"auto"`` (the default: compiled when numba works here), ``"compiled"`` or
        ``"numpy"``; both engines give identical results (see :mod:`.engine`). Under ``"auto"``
        reading it starts loading the compiled kernels in the background and answers
        ``"numpy"`` until they are there (:meth:`warm_up` waits for them).
        """
        if self._engine is not None:
            return self._engine
        value = _engine.resolve(self._engine_request)
        settled = value == "compiled" or _engine.kernels_failed()
        if settled or _engine.requested(self._engine_request) != "auto":
            self._engine = value  # the kernels are there, or were not asked for, or failed here
        return value

    @engine.setter
    def engine(self, name: str) -> None:
        _engine.check_engine(name)
        self._engine_request = name
        self._engine = None

    def warm_up(self) -> str:
        """Choose the engine and load its kernels now, and build the default direct-index table.

        The first transform would otherwise pay it: with numba, importing it and loading the
        cached machine code (about 0.4 s), or compiling it the first time on a machine (a few
        seconds). Call it when a SLAM system starts, before the loop. Returns the engine.
        """
        self.direct_index_table()
        if _engine.requested(self._engine_request) == "auto":
            _engine.compiled_kernels(wait=True)
        return self.engine

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

        At each level a descriptor moves to the child with the nearest centre (Hamming for
        binary words, Euclidean for float ones), as DBoW2 does; ties go to the lowest child id.

        Args:
            descriptors: (N, B) uint8 or (N, D) float32, of the vocabulary's kind.

        Returns:
            (N,) int32 leaf node ids.

        Raises:
            InputError: descriptors of another kind than the words (float for binary words,
                binary of another width, ...) are named as such; other malformed arrays,
                NaN or infinite float descriptors.
        """
        self._check_kind(descriptors)
        check_descriptors(descriptors, kind=self.descriptor_kind)
        n = descriptors.shape[0]
        if n == 0 or self.n_nodes == 1:
            return np.zeros(n, np.int32)
        q = self._query(descriptors)
        if self.engine == "compiled":
            out = np.empty(n, np.int32)
            self._descend_kernel()(q, self._blocks, self._block_kids, self._block_counts, self._row, out)
            return out
        return self._leaves_numpy_float(q) if self.is_float else self._leaves_numpy(q)

    def _query(self, descriptors: np.ndarray) -> np.ndarray:
        """Descriptors as the search tables hold them: (N, W) uint64 words or (N, D) float32,
        contiguous and writable (the compiled kernels have one signature: writable arrays)."""
        q = (np.ascontiguousarray(descriptors, np.float32) if self.is_float
             else as_words(descriptors))
        return q if q.flags.writeable else q.copy()

    def _descend_kernel(self) -> Any:
        """The compiled descent for this vocabulary's words (see :mod:`._compiled`)."""
        kernels = _engine.compiled_kernels()
        assert kernels is not None  # resolved to "compiled" only when they load
        if self.is_float:
            return kernels.descend_float
        return kernels.descend if n_words(self.descriptors.shape[1]) == 4 else kernels.descend_words

    def _leaves_numpy(self, q: np.ndarray) -> np.ndarray:
        """The NumPy descent: all descriptors a level at a time. ``q``: (N, W) uint64."""
        n, words = q.shape
        cur = np.zeros(n, np.int32)
        k = self._block_kids.shape[1]
        active = np.arange(n)
        while active.size:
            rows = self._row[cur[active]]
            x = np.take(self._blocks, rows, axis=0)  # (M, k*W) child centres
            np.bitwise_xor(x, np.tile(q[active], (1, k)), out=x)
            if words == 4:
                counts = np.bitwise_count(x).view(np.uint32)  # 4 byte-counts per uint32
                # sum the four bytes of each uint32 into its top byte (each <= 64, so no carry);
                # a sum of exactly 256 wraps to 0: that is the all-bits-differ pattern 0x40404040
                d = (counts * np.uint32(0x01010101)) >> np.uint32(24)
                d[counts == 0x40404040] = 256
            else:
                d = np.bitwise_count(x).reshape(rows.size, k, words).sum(axis=2, dtype=np.uint32)
            if self._penalty is not None:
                d += self._penalty[rows]
            best = self._block_kids[rows, d.argmin(axis=1)]
            cur[active] = best
            active = active[~self.is_leaf[best]]
        return cur

    def _leaves_numpy_float(self, q: np.ndarray) -> np.ndarray:
        """The NumPy descent of float descriptors: all a level at a time. ``q``: (N, D) float32.

        Squared distances are summed dimension by dimension in float64, in the order the
        compiled kernel sums them, so both engines choose the same children to the last bit.
        """
        n, dim = q.shape
        cur = np.zeros(n, np.int32)
        k = self._block_kids.shape[1]
        active = np.arange(n)
        while active.size:
            rows = self._row[cur[active]]
            x = np.take(self._blocks, rows, axis=0).reshape(rows.size, k, dim)
            xt = np.ascontiguousarray(x.transpose(2, 0, 1), np.float64)  # (D, M, k)
            qt = np.ascontiguousarray(q[active].T, np.float64)[:, :, None]  # (D, M, 1)
            d = np.zeros((rows.size, k))
            for j in range(dim):
                diff = xt[j] - qt[j]
                d += diff * diff
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

    def _levels_up(self, levels_up: int | None) -> int:
        if levels_up is None:
            return self.levels_up
        if not isinstance(levels_up, int | np.integer) or levels_up < 0:
            raise InputError(f"levels_up: expected an integer >= 0, got {levels_up!r:.60}")
        return int(levels_up)

    def direct_index_table(self, levels_up: int | None = None) -> np.ndarray:
        """(n,) int32: for every node, its ancestor at level ``L - levels_up`` (itself when
        shallower). Computed once per ``levels_up`` and kept."""
        up = self._levels_up(levels_up)
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
        return table

    def direct_index_nodes(self, leaves: np.ndarray, levels_up: int | None = None) -> np.ndarray:
        """Node at level ``L - levels_up`` above each leaf (the leaf itself when shallower).

        Args:
            leaves: (N,) int32 leaf node ids.
            levels_up: levels above the leaves (>= 0); defaults to the vocabulary's ``levels_up``.

        Returns:
            (N,) int32 node ids.
        """
        return self.direct_index_table(levels_up)[leaves]

    def transform(
        self, descriptors: np.ndarray, levels_up: int | None = None,
        weights: np.ndarray | None = None,
    ) -> tuple[BowVector, FeatureVector]:
        """Bag-of-words vector and direct index of one image's descriptors.

        Weights follow DBoW2: TF-IDF and TF add each feature's word weight, IDF and binary
        count a word once; words of zero weight are left out (and so are their features from
        the direct index, node -1). The vector is normalised as the scoring needs; without
        normalisation (dot product) TF weights are divided by the number of distinct words, as
        DBoW2 does.

        Per-feature ``weights`` (e.g. how stable a feature's semantic class is) scale what each
        feature gives its word before normalisation: with TF-IDF and TF a word's value is
        ``sum over its features of weights[f] * word_weight``; with IDF and binary the word
        still counts once, as ``word_weight * max over its features of weights[f]``. A feature
        of weight 0 is dropped as a stopped word is (node -1 in the direct index). Without
        ``weights`` (None) the result is DBoW2's, exactly; all-ones weights give the same.

        Args:
            descriptors: (N, B) uint8 or (N, D) float32, of the vocabulary's kind.
            levels_up: direct-index level above the leaves (>= 0; default: ``self.levels_up``).
            weights: (N,) finite floats >= 0, one per descriptor, or None.

        Returns:
            (BowVector, FeatureVector); both empty for N = 0.

        Raises:
            InputError: descriptors of another kind than the vocabulary's words, e.g. "descriptors
                are 128-dim float32 but the vocabulary holds 32-byte binary words: ..."; weights
                of the wrong shape, negative, NaN or infinite; a negative ``levels_up``.
        """
        up = self._levels_up(levels_up)
        self._check_kind(descriptors)
        check_descriptors(descriptors, kind=self.descriptor_kind)
        n = descriptors.shape[0]
        fw = _feature_weights(weights, n)
        if n == 0:
            return BowVector.empty(), FeatureVector(np.zeros(0, np.int32), up)
        if self.engine == "compiled" and self.n_nodes > 1:
            kernels = _engine.compiled_kernels()
            assert kernels is not None  # resolved to "compiled" only when they load
            q = self._query(descriptors)
            args = (self.weights, self.node_word, self.direct_index_table(up),
                    fw if fw is not None else np.empty(0), fw is not None, self._adds_features)
            descend = self._descend_kernel()
            if descend is kernels.descend:  # ORB's 4 words: descent and assembly in one call
                words, values, nodes = kernels.transform(
                    q, self._blocks, self._block_kids, self._block_counts, self._row, *args)
            else:
                leaves = np.empty(n, np.int32)
                descend(q, self._blocks, self._block_kids, self._block_counts, self._row, leaves)
                words, values, nodes = kernels.assemble(leaves, *args)
        else:
            leaves = self.leaves_of(descriptors) if self.n_nodes > 1 else np.zeros(n, np.int32)
            words, values, nodes = self._assemble_numpy(leaves, up, fw)
        if words.size == 0:
            return BowVector.empty(), FeatureVector(nodes, up)
        if self._adds_features and self.scoring == Scoring.DOT_PRODUCT:
            values = values / words.size
        return BowVector(words, normalise(values, self.scoring)), FeatureVector(nodes, up)

    @property
    def _adds_features(self) -> bool:
        """TF-IDF and TF add up a word's features; IDF and binary count a word once."""
        return self.weighting in (Weighting.TF_IDF, Weighting.TF)

    def _assemble_numpy(
        self, leaves: np.ndarray, up: int, fw: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Words (ascending), their values before normalisation, and direct-index nodes."""
        w = self.weights[leaves]
        ok = w > 0
        if fw is not None:
            ok &= fw > 0
        nodes = np.where(ok, self.direct_index_nodes(leaves, up), -1).astype(np.int32)
        words = self.node_word[leaves[ok]]
        if words.size == 0:
            return np.zeros(0, np.int32), np.zeros(0, np.float64), nodes
        uniq, inverse = np.unique(words, return_inverse=True)
        if self._adds_features:
            add = w[ok] if fw is None else w[ok] * fw[ok]
            values: np.ndarray = np.bincount(inverse, weights=add, minlength=uniq.size)
        else:
            values = self.weights[self.word_nodes[uniq]].astype(np.float64)
            if fw is not None:
                top = np.zeros(uniq.size)
                np.maximum.at(top, inverse, fw[ok])
                values = values * top
        return uniq.astype(np.int32), values, nodes


def _feature_weights(weights: np.ndarray | None, n: int) -> np.ndarray | None:
    """Checked (N,) float64 per-feature weights, or None."""
    if weights is None:
        return None
    arr = np.asarray(weights)
    if arr.shape != (n,) or arr.dtype.kind not in "fiub":
        raise InputError(
            f"weights: expected {n} numbers (one per descriptor), got a {arr.dtype} array of "
            f"shape {arr.shape}"
        )
    fw = np.ascontiguousarray(arr, np.float64)
    if n and not (np.isfinite(fw).all() and fw.min() >= 0):
        raise InputError("weights: expected finite numbers >= 0, got negative, NaN or infinite ones")
    return fw


def check_header(k: int, levels: int, levels_up: int | None) -> None:
    """k, L and levels_up within the documented limits (integers)."""
    for name, value, lo, hi in (("k", k, 2, MAX_K), ("L", levels, 1, MAX_LEVELS)):
        if not isinstance(value, int | np.integer) or not lo <= value <= hi:
            raise VocabularyError(f"vocabulary: expected {lo} <= {name} <= {hi}, got {name}={value!r:.60}")
    if levels_up is not None and (not isinstance(levels_up, int | np.integer) or levels_up < 0):
        raise VocabularyError(f"vocabulary: expected levels_up >= 0, got {levels_up!r:.60}")


def _check_arrays(
    parents: np.ndarray, descriptors: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The node arrays, checked and made contiguous: int32 parents, uint8 or finite float32
    centres, float64 finite weights."""
    parents, descriptors, weights = np.asarray(parents), np.asarray(descriptors), np.asarray(weights)
    n = parents.shape[0] if parents.ndim == 1 else -1
    if n < 1 or parents.dtype.kind not in "iu" or int(parents[0]) != -1:
        raise VocabularyError("vocabulary: node 0 must be the root (parent -1) of integer parents")
    shape_ok = descriptors.ndim == 2 and descriptors.shape[0] == n and descriptors.shape[1] >= 1
    if not shape_ok or weights.shape != (n,):
        raise VocabularyError(
            f"vocabulary: arrays disagree: {n} parents, descriptors {descriptors.shape} "
            f"(expected ({n}, D), D >= 1), weights {weights.shape}"
        )
    if n > 1 and (np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, n))):
        raise VocabularyError("vocabulary: every node's parent must come before it")
    if descriptors.dtype not in (np.uint8, np.float32) or weights.dtype.kind not in "fiu":
        raise VocabularyError(
            f"vocabulary: expected uint8 (binary) or float32 (float) centres and float weights, "
            f"got {descriptors.dtype} and {weights.dtype}"
        )
    if descriptors.dtype == np.float32 and not np.isfinite(descriptors).all():
        bad = int(np.flatnonzero(~np.isfinite(descriptors).all(axis=1))[0])
        raise VocabularyError(f"vocabulary: node {bad} has a NaN or infinite centre")
    w = np.ascontiguousarray(weights, np.float64)
    if not w.flags.writeable:  # a memory-mapped file: the compiled kernels take writable arrays
        w = w.copy()
    if not np.isfinite(w).all():
        bad = int(np.flatnonzero(~np.isfinite(w))[0])
        raise VocabularyError(f"vocabulary: node {bad} has weight {w[bad]}: weights must be finite")
    return np.ascontiguousarray(parents, np.int32), np.ascontiguousarray(descriptors), w


def _child_table(parents: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The nodes that have children, and their children: (I,) int32 ids ascending, (I, w) int32
    children in id order, -1 padded, w the most children any node has (at most k).

    Sized by the tree, never by k; a tree whose table would be far larger than the tree (a few
    nodes with very many children, many with few) is refused before anything is allocated.
    """
    n = parents.shape[0]
    if n <= 1:
        return np.zeros(0, np.int32), np.zeros((0, 1), np.int32)
    child = np.arange(1, n, dtype=np.int32)
    par = parents[1:].astype(np.int64)
    if np.all(par[1:] >= par[:-1]):  # breadth-first files: already grouped by parent
        par_sorted, child_sorted = par, child
    else:
        order = np.argsort(par, kind="stable")
        par_sorted, child_sorted = par[order], child[order]
    index = np.arange(par_sorted.size)
    first = np.empty(par_sorted.size, bool)  # where a parent's run of children begins
    first[0] = True
    np.not_equal(par_sorted[1:], par_sorted[:-1], out=first[1:])
    slot = index - np.maximum.accumulate(np.where(first, index, 0))
    width = int(slot.max()) + 1
    if width > k:
        bad = int(par_sorted[int(slot.argmax())])
        raise VocabularyError(f"vocabulary: node {bad} has more than k={k} children")
    inner = par_sorted[first].astype(np.int32)
    if inner.size * width > _SLOTS_PER_NODE * n + _SLOTS_SPARE:
        raise VocabularyError(
            f"vocabulary: {n} nodes whose fan-out is too uneven (up to {width} children, "
            f"{inner.size} inner nodes): the search table would need "
            f"{inner.size * width * 36 / 2**30:.1f} GiB"
        )
    table = np.full(inner.size * width, -1, np.int32)
    table[(np.cumsum(first) - 1) * width + slot] = child_sorted
    return inner, table.reshape(inner.size, width)


def _depths(parents: np.ndarray, levels: int) -> np.ndarray:
    """(n,) int16 depth of each node (root 0); parents precede children.

    Raises:
        VocabularyError: a node deeper than ``levels``.
    """
    n = parents.shape[0]
    depth = np.zeros(n, np.int16)
    if n <= 1:
        return depth
    # parents precede children, so one vectorised pass per level settles every depth; a
    # tree no deeper than L settles within L + 1 passes
    par = parents.astype(np.int64)
    par[0] = 0
    for _ in range(levels + 1):
        new = depth[par] + 1
        new[0] = 0
        if np.array_equal(new, depth):
            return depth
        depth = new.astype(np.int16)
    raise VocabularyError(f"vocabulary: the tree is more than L={levels} levels deep")

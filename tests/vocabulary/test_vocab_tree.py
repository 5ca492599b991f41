"""Training, transform and direct index of the vocabulary tree."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import InputError, VocabularyError
from stablecues.vocabulary import Scoring, Vocabulary, Weighting, engine, train_vocabulary
from stablecues.vocabulary.descriptors import as_words, hamming_cross


def clustered(n_centres: int, per: int, noise_bits: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors scattered a few bits around random centres (well separated)."""
    rng = np.random.default_rng(seed)
    centres = rng.integers(0, 256, (n_centres, 32), dtype=np.uint8)
    bits = np.unpackbits(np.repeat(centres, per, axis=0), axis=1)
    for row in bits:
        row[rng.choice(256, noise_bits, replace=False)] ^= 1
    return np.packbits(bits, axis=1), centres


def reference_descent(voc: Vocabulary, d: np.ndarray) -> int:
    """Pure-Python greedy descent, the definition the vectorised transform must follow."""
    node = 0
    while not voc.is_leaf[node]:
        kids = [c for c in voc.children[node] if c >= 0]
        dists = [sum(bin(int(a) ^ int(b)).count("1") for a, b in zip(d, voc.descriptors[c], strict=True))
                 for c in kids]
        node = kids[int(np.argmin(dists))]
    return node


@pytest.fixture(scope="module")
def small_voc() -> tuple[Vocabulary, list[np.ndarray]]:
    desc, _ = clustered(40, 25, 12, seed=0)
    rng = np.random.default_rng(1)
    perm = rng.permutation(desc.shape[0])
    sets = [desc[perm[i::10]] for i in range(10)]
    return train_vocabulary(sets, k=4, levels=3, seed=0, progress=False), sets


def test_training_is_deterministic(small_voc: tuple[Vocabulary, list[np.ndarray]]) -> None:
    voc, sets = small_voc
    again = train_vocabulary(sets, k=4, levels=3, seed=0, progress=False)
    assert again.fingerprint == voc.fingerprint
    other = train_vocabulary(sets, k=4, levels=3, seed=1, progress=False)
    assert other.fingerprint != voc.fingerprint


def test_tree_structure(small_voc: tuple[Vocabulary, list[np.ndarray]]) -> None:
    voc, _ = small_voc
    assert voc.k == 4 and voc.levels == 3
    assert int(voc.depth.max()) <= 3
    assert (voc.parents[1:] < np.arange(1, voc.n_nodes)).all()
    assert ((voc.children >= 0).sum(axis=1) <= 4).all()
    assert voc.n_words == int(voc.is_leaf.sum()) > 16
    assert (voc.word_weights >= 0).all()


def test_transform_follows_the_greedy_descent(small_voc: tuple[Vocabulary, list[np.ndarray]]) -> None:
    voc, sets = small_voc
    rng = np.random.default_rng(5)
    queries = np.concatenate([sets[0][:30], rng.integers(0, 256, (20, 32), dtype=np.uint8)])
    leaves = voc.leaves_of(queries)
    assert leaves.tolist() == [reference_descent(voc, q) for q in queries]


def test_flat_tree_equals_exhaustive_nearest_word() -> None:
    desc, _ = clustered(12, 10, 20, seed=3)
    voc = train_vocabulary([desc], k=12, levels=1, seed=0, progress=False)
    rng = np.random.default_rng(9)
    q = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    words = voc.descriptors[voc.word_nodes]
    d = hamming_cross(as_words(q), as_words(words))
    got = voc.node_word[voc.leaves_of(q)]
    # the word reached is at the minimum distance (ties may pick any of them)
    assert (d[np.arange(q.shape[0]), got] == d.min(axis=1)).all()


def hierarchical_data(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points around 27 leaf centres that form a clear 3 x 3 x 3 hierarchy."""
    rng = np.random.default_rng(seed)

    def flip(c: np.ndarray, n: int) -> np.ndarray:
        bits = np.unpackbits(c)
        bits[rng.choice(256, n, replace=False)] ^= 1
        return np.packbits(bits)

    leaves = []
    for top in rng.integers(0, 256, (3, 32), dtype=np.uint8):
        for mid in [flip(top, 48) for _ in range(3)]:
            leaves += [flip(mid, 16) for _ in range(3)]
    centres = np.array(leaves)
    points = np.array([flip(c, 2) for c in centres for _ in range(8)])
    return points, centres


def test_separated_clusters_reach_their_exhaustive_nearest_leaf() -> None:
    points, centres = hierarchical_data(seed=4)
    voc = train_vocabulary([points], k=3, levels=3, seed=0, progress=False)
    words = voc.descriptors[voc.word_nodes]
    for q in (centres, points):
        nearest = hamming_cross(as_words(q), as_words(words)).min(axis=1)
        reached = voc.leaves_of(q)
        got = hamming_cross(as_words(q), as_words(voc.descriptors[reached])).diagonal()
        np.testing.assert_array_equal(got, nearest)


def test_bow_vector_and_direct_index(small_voc: tuple[Vocabulary, list[np.ndarray]]) -> None:
    voc, sets = small_voc
    bow, fvec = voc.transform(sets[2])
    assert bow.words.dtype == np.int32 and (np.diff(bow.words) > 0).all()
    assert bow.weights.sum() == pytest.approx(1.0)  # L1 normalised
    assert len(fvec) == sets[2].shape[0] and fvec.levels_up == voc.levels_up
    # levels_up=0: the direct-index node is the leaf itself; higher: its ancestor
    _, f0 = voc.transform(sets[2], levels_up=0)
    leaves = voc.leaves_of(sets[2])
    ok = f0.nodes >= 0
    np.testing.assert_array_equal(f0.nodes[ok], leaves[ok])
    _, f1 = voc.transform(sets[2], levels_up=1)
    ok = f1.nodes >= 0
    deep = voc.depth[leaves] == voc.levels
    np.testing.assert_array_equal(f1.nodes[ok & deep], voc.parents[leaves[ok & deep]])
    groups = f1.groups()
    assert sum(len(ix) for ix in groups.values()) == int(ok.sum())
    # the nodes' stable sorting order, computed once and read-only (matching reuses it)
    np.testing.assert_array_equal(f1.order, np.argsort(f1.nodes, kind="stable"))
    assert f1.order is f1.order and not f1.order.flags.writeable
    for node, ix in groups.items():
        assert (np.diff(ix) > 0).all() and (f1.nodes[ix] == node).all()


def test_weightings() -> None:
    desc, _ = clustered(8, 10, 10, seed=6)
    sets = [desc[:40], desc[40:]]
    tfidf = train_vocabulary(sets, k=4, levels=2, seed=0, progress=False)
    binary = train_vocabulary(sets, k=4, levels=2, seed=0, weighting=Weighting.BINARY,
                              scoring=Scoring.DOT_PRODUCT, progress=False)
    assert (binary.word_weights == 1.0).all()
    b, _ = binary.transform(desc[:5])
    assert (b.weights == 1.0).all()  # binary: each word once, weight 1, no normalisation
    # IDF = log(N / N_i) with N = 2 images
    assert set(np.round(np.unique(tfidf.word_weights), 6)) <= {0.0, round(float(np.log(2)), 6)}


def test_empty_descriptors_pass_through(small_voc: tuple[Vocabulary, list[np.ndarray]]) -> None:
    voc, _ = small_voc
    bow, fvec = voc.transform(np.zeros((0, 32), np.uint8))
    assert len(bow) == 0 and len(fvec) == 0
    assert fvec.groups() == {}


def test_bad_inputs() -> None:
    with pytest.raises(InputError, match="descriptors"):
        train_vocabulary([np.zeros((5, 16), np.int16)], progress=False)
    with pytest.raises(InputError, match="one kind per vocabulary"):
        train_vocabulary([np.zeros((5, 32), np.uint8), np.zeros((5, 16), np.uint8)], progress=False)
    with pytest.raises(InputError, match="at least one"):
        train_vocabulary([np.zeros((0, 32), np.uint8)], progress=False)
    voc = train_vocabulary([np.random.default_rng(0).integers(0, 256, (50, 32), dtype=np.uint8)],
                           k=3, levels=2, progress=False)
    with pytest.raises(InputError, match="uint8"):
        voc.transform(np.zeros((3, 32), np.int32))


# ----------------------------------------------------------------------------- per-feature weights
ENGINES = ["numpy", pytest.param("compiled", marks=pytest.mark.skipif(
    engine.compiled_kernels() is None, reason="numba is not available"))]
A, B = np.zeros(32, np.uint8), np.full(32, 255, np.uint8)


def two_words(weighting: Weighting, scoring: Scoring, name: str, idf: tuple[float, float] = (0.5, 2.0)
              ) -> Vocabulary:
    """Root with two words: A (all zeros, weight 0.5) and B (all ones, weight 2)."""
    voc = Vocabulary(2, 1, np.array([-1, 0, 0]), np.stack([A, A, B]), np.array([0.0, *idf]),
                     weighting, scoring)
    voc.engine = name
    return voc


FEATURES = np.stack([A, A, B])  # two features on word A, one on word B


@pytest.mark.parametrize("name", ENGINES)
def test_feature_weights_tf_idf_hand_computed(name: str) -> None:
    voc = two_words(Weighting.TF_IDF, Scoring.L1, name)
    bow, fvec = voc.transform(FEATURES, weights=np.array([1.0, 0.5, 2.0]))
    # A: 1.0 * 0.5 + 0.5 * 0.5 = 0.75; B: 2.0 * 2 = 4; L1-normalised
    assert bow.words.tolist() == [0, 1]
    np.testing.assert_array_equal(bow.weights, np.array([0.75, 4.0]) / 4.75)
    assert fvec.nodes.tolist() == [1, 1, 2]
    plain, _ = voc.transform(FEATURES)  # DBoW2: A 0.5 + 0.5, B 2
    np.testing.assert_array_equal(plain.weights, np.array([1.0, 2.0]) / 3.0)


@pytest.mark.parametrize("name", ENGINES)
def test_feature_weights_idf_and_binary_take_the_largest(name: str) -> None:
    idf = two_words(Weighting.IDF, Scoring.L1, name)
    bow, _ = idf.transform(FEATURES, weights=np.array([1.0, 0.5, 2.0]))
    np.testing.assert_array_equal(bow.weights, np.array([0.5 * 1.0, 2.0 * 2.0]) / 4.5)
    binary = two_words(Weighting.BINARY, Scoring.DOT_PRODUCT, name, idf=(1.0, 1.0))
    bow, _ = binary.transform(FEATURES, weights=np.array([0.25, 0.75, 3.0]))
    assert bow.weights.tolist() == [0.75, 3.0]  # no normalisation for the dot product


@pytest.mark.parametrize("name", ENGINES)
def test_feature_weights_tf_dot_product(name: str) -> None:
    tf = two_words(Weighting.TF, Scoring.DOT_PRODUCT, name, idf=(1.0, 1.0))
    bow, _ = tf.transform(FEATURES, weights=np.array([1.0, 0.5, 2.0]))
    assert bow.weights.tolist() == [1.5 / 2, 2.0 / 2]  # DBoW2 divides by the number of words


@pytest.mark.parametrize("name", ENGINES)
def test_zero_weight_drops_a_feature_as_a_stopped_word_does(name: str) -> None:
    voc = two_words(Weighting.TF_IDF, Scoring.L1, name)
    bow, fvec = voc.transform(FEATURES, weights=np.array([0.0, 0.5, 2.0]))
    np.testing.assert_array_equal(bow.weights, np.array([0.25, 4.0]) / 4.25)
    assert fvec.nodes.tolist() == [-1, 1, 2]
    bow, fvec = voc.transform(FEATURES, weights=np.zeros(3))
    assert len(bow) == 0 and fvec.nodes.tolist() == [-1, -1, -1]
    stopped = two_words(Weighting.TF_IDF, Scoring.L1, name, idf=(0.0, 2.0))
    bow, fvec = stopped.transform(FEATURES, weights=np.array([1.0, 1.0, 0.5]))
    assert bow.words.tolist() == [1] and fvec.nodes.tolist() == [-1, -1, 2]


@pytest.mark.parametrize("name", ENGINES)
def test_unit_weights_give_the_unweighted_result(name: str,
                                                 small_voc: tuple[Vocabulary, list[np.ndarray]]) -> None:
    voc, sets = small_voc
    for weighting in Weighting:
        twin = Vocabulary(voc.k, voc.levels, voc.parents, voc.descriptors, voc.weights, weighting,
                          Scoring.L2)
        twin.engine = name
        a, fa = twin.transform(sets[1])
        b, fb = twin.transform(sets[1], weights=np.ones(sets[1].shape[0], np.float32))
        np.testing.assert_array_equal(a.words, b.words)
        np.testing.assert_array_equal(a.weights, b.weights)
        np.testing.assert_array_equal(fa.nodes, fb.nodes)


@pytest.mark.parametrize("bad", [np.ones(2), np.ones((3, 1)), np.array([1.0, -0.5, 1.0]),
                                 np.array([1.0, np.nan, 1.0]), np.array([np.inf, 1.0, 1.0]),
                                 np.array(["a", "b", "c"])])
def test_bad_feature_weights(bad: np.ndarray) -> None:
    voc = two_words(Weighting.TF_IDF, Scoring.L1, "numpy")
    with pytest.raises(InputError, match="weights: expected"):
        voc.transform(FEATURES, weights=bad)


def test_vocabulary_arrays_are_checked() -> None:
    parents, desc = np.array([-1, 0, 0]), np.stack([A, A, B])
    with pytest.raises(VocabularyError, match="node 2 has weight nan"):
        Vocabulary(2, 1, parents, desc, np.array([0.0, 1.0, np.nan]))
    with pytest.raises(VocabularyError, match="expected levels_up >= 0"):
        Vocabulary(2, 1, parents, desc, np.ones(3), levels_up=-5)
    with pytest.raises(VocabularyError, match="expected 2 <= k <= 1048576"):
        Vocabulary(10**9, 1, parents, desc, np.ones(3))
    with pytest.raises(VocabularyError, match="more than k=2 children"):
        Vocabulary(2, 1, np.array([-1, 0, 0, 0]), np.stack([A, A, B, B]), np.ones(4))
    with pytest.raises(VocabularyError, match="children table disagrees"):
        Vocabulary(2, 1, parents, desc, np.ones(3), children=np.array([[2, 1], [-1, -1], [-1, -1]]))


def test_children_table_is_sized_by_the_tree_not_by_k() -> None:
    voc = Vocabulary(1 << 20, 1, np.array([-1, 0, 0]), np.stack([A, A, B]), np.ones(3))
    assert voc.children.shape == (3, 2) and voc.k == 1 << 20
    assert voc.node_word[voc.leaves_of(np.stack([B, A]))].tolist() == [1, 0]

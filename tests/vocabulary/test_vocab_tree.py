"""Training, transform and direct index of the vocabulary tree."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import InputError
from stablecues.vocabulary import Scoring, Vocabulary, Weighting, train_vocabulary
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
        train_vocabulary([np.zeros((5, 16), np.uint8)], progress=False)
    with pytest.raises(InputError, match="at least one"):
        train_vocabulary([np.zeros((0, 32), np.uint8)], progress=False)
    voc = train_vocabulary([np.random.default_rng(0).integers(0, 256, (50, 32), dtype=np.uint8)],
                           k=3, levels=2, progress=False)
    with pytest.raises(InputError, match="uint8"):
        voc.transform(np.zeros((3, 32), np.int32))

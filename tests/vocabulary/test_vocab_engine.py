"""The compiled transform against the NumPy one: identical BoW vectors and direct indexes, bit for
bit, on real ORB descriptors; and how the engine is chosen, including without numba."""

from __future__ import annotations

import pickle
import sys
from pathlib import Path

import numpy as np
import pytest
from vocab_files import small_vocabulary

from conftest import shared_path
from stablecues import vocabulary as vocabulary_package
from stablecues.engine import Kernels
from stablecues.errors import ConfigError
from stablecues.features import OrbExtractor
from stablecues.imageio import read_image
from stablecues.types import BowVector, FeatureVector
from stablecues.vocabulary import Scoring, Vocabulary, Weighting, default_vocabulary, engine


def with_engine(voc: Vocabulary, name: str, weighting: Weighting | None = None,
                scoring: Scoring | None = None) -> Vocabulary:
    """The same tree, on the given engine (and weighting / scoring, when given)."""
    twin = Vocabulary(voc.k, voc.levels, voc.parents, voc.descriptors, voc.weights,
                      weighting if weighting is not None else voc.weighting,
                      scoring if scoring is not None else voc.scoring, voc.levels_up)
    twin.engine = name
    return twin


def assert_identical(a: tuple[BowVector, FeatureVector], b: tuple[BowVector, FeatureVector]) -> None:
    np.testing.assert_array_equal(a[0].words, b[0].words)
    np.testing.assert_array_equal(a[0].weights, b[0].weights)  # bit for bit, not approximately
    np.testing.assert_array_equal(a[1].nodes, b[1].nodes)
    assert a[0].words.dtype == b[0].words.dtype and a[1].nodes.dtype == b[1].nodes.dtype
    assert a[1].levels_up == b[1].levels_up


@pytest.fixture(scope="module")
def camvid_descriptors() -> list[np.ndarray]:
    """ORB descriptors (about 1000 each) of six CamVid test frames."""
    files = sorted(shared_path("camvid", "test").glob("*.jpg"))[::40]
    extractor = OrbExtractor()
    return [extractor.extract(read_image(f, "grey")).descriptors for f in files]


@pytest.fixture(scope="module")
def near_words() -> list[np.ndarray]:
    """Descriptors a few bits from the shipped vocabulary's words (no data needed)."""
    voc = default_vocabulary()
    rng = np.random.default_rng(11)
    out = []
    for _ in range(4):
        d = voc.descriptors[rng.choice(voc.word_nodes, 1000)].copy()
        flips = rng.integers(0, 256, (1000, 6))
        for j in range(flips.shape[1]):
            d[np.arange(1000), flips[:, j] // 8] ^= (1 << (flips[:, j] % 8)).astype(np.uint8)
        out.append(d)
    out.append(rng.integers(0, 256, (1000, 32), dtype=np.uint8))
    return out


needs_numba = pytest.mark.skipif(engine.compiled_kernels() is None, reason="numba is not available")


@needs_numba
@pytest.mark.parametrize(("weighting", "scoring"), [
    (Weighting.TF_IDF, Scoring.L1), (Weighting.TF, Scoring.DOT_PRODUCT), (Weighting.IDF, Scoring.L2),
    (Weighting.BINARY, Scoring.BHATTACHARYYA), (Weighting.TF_IDF, Scoring.KL),
    (Weighting.IDF, Scoring.DOT_PRODUCT),
])
def test_engines_agree_on_real_descriptors(camvid_descriptors: list[np.ndarray], weighting: Weighting,
                                           scoring: Scoring) -> None:
    shipped = default_vocabulary()
    compiled = with_engine(shipped, "compiled", weighting, scoring)
    numpy = with_engine(shipped, "numpy", weighting, scoring)
    rng = np.random.default_rng(0)
    for d in camvid_descriptors:
        assert d.shape[0] > 900
        np.testing.assert_array_equal(compiled.leaves_of(d), numpy.leaves_of(d))
        assert_identical(compiled.transform(d), numpy.transform(d))
        for up in (0, 1, 4, 9):
            assert_identical(compiled.transform(d, levels_up=up), numpy.transform(d, levels_up=up))
        w = rng.random(d.shape[0]) * (rng.random(d.shape[0]) > 0.25)  # a quarter dropped
        assert_identical(compiled.transform(d, weights=w), numpy.transform(d, weights=w))


@needs_numba
def test_engines_agree_without_data(near_words: list[np.ndarray], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(engine.ENV_VARIABLE, raising=False)
    shipped = with_engine(default_vocabulary(), "auto")
    compiled, numpy = with_engine(shipped, "compiled"), with_engine(shipped, "numpy")
    for d in near_words:
        assert_identical(compiled.transform(d), numpy.transform(d))
        assert_identical(compiled.transform(d, weights=np.full(d.shape[0], 0.3)),
                         numpy.transform(d, weights=np.full(d.shape[0], 0.3)))
    # the default engine on a machine with numba is the compiled one, and it is today's result
    assert shipped.engine == "compiled"
    assert_identical(shipped.transform(near_words[0]), numpy.transform(near_words[0]))


@needs_numba
def test_engines_agree_on_uneven_trees_and_edge_inputs() -> None:
    """Nodes with fewer children than k, stopped words, read-only and non-contiguous inputs."""
    rng = np.random.default_rng(5)
    voc = small_vocabulary(k=7, levels=4, seed=2, images=3)
    weights = voc.weights.copy()
    weights[voc.word_nodes[::5]] = 0.0  # stopped words
    voc = Vocabulary(voc.k, voc.levels, voc.parents, voc.descriptors, weights)
    assert (voc.children >= 0).sum(axis=1).max() <= 7 and voc.depth.max() <= 4
    compiled, numpy = with_engine(voc, "compiled"), with_engine(voc, "numpy")
    d = rng.integers(0, 256, (300, 64), dtype=np.uint8)[:, ::2]  # not contiguous
    ro = np.ascontiguousarray(d)
    ro.flags.writeable = False
    for q in (d, ro, d[:1], d[:0]):
        assert_identical(compiled.transform(q), numpy.transform(q))
    root_only = Vocabulary(2, 1, np.array([-1]), np.zeros((1, 32), np.uint8), np.ones(1))
    q = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    assert_identical(with_engine(root_only, "compiled").transform(q),
                     with_engine(root_only, "numpy").transform(q))


def test_engine_names_and_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    voc = default_vocabulary()
    twin = with_engine(voc, "numpy")
    assert twin.engine == "numpy"
    with pytest.raises(ConfigError, match="vocabulary engine 'fast'"):
        twin.engine = "fast"
    monkeypatch.setenv(engine.ENV_VARIABLE, "numpy")
    assert with_engine(voc, "auto").engine == "numpy"
    monkeypatch.setenv(engine.ENV_VARIABLE, "turbo")
    with pytest.raises(ConfigError, match="STABLECUES_ENGINE='turbo'"):
        _ = with_engine(voc, "auto").engine


def test_without_numba_the_numpy_engine_is_chosen(monkeypatch: pytest.MonkeyPatch) -> None:
    """As on a machine where numba cannot be installed: imports fail, 'auto' means NumPy."""
    monkeypatch.setitem(sys.modules, "numba", None)  # import numba -> ImportError
    monkeypatch.delitem(sys.modules, "stablecues.vocabulary._compiled", raising=False)
    monkeypatch.delattr(vocabulary_package, "_compiled", raising=False)
    monkeypatch.setattr(engine, "_KERNELS", Kernels(engine._load, "the vocabulary transform"))
    assert engine.compiled_kernels() is None
    voc = with_engine(default_vocabulary(), "auto")
    assert voc.engine == "numpy"
    d = np.random.default_rng(1).integers(0, 256, (50, 32), dtype=np.uint8)
    assert_identical(voc.transform(d), with_engine(voc, "numpy").transform(d))
    voc.engine = "compiled"
    with pytest.raises(ImportError, match="pip install numba"):
        _ = voc.engine


@needs_numba
def test_kernels_are_cached_on_disk() -> None:
    """The JIT cache is on, so a new process loads machine code instead of compiling it."""
    from stablecues.vocabulary import _compiled

    for kernel in (_compiled.descend, _compiled.assemble, _compiled.transform):
        assert kernel._cache is not None and type(kernel._cache).__name__ == "FunctionCache"
    assert Path(_compiled.__file__).is_file()


def test_a_pickled_vocabulary_transforms_the_same(near_words: list[np.ndarray]) -> None:
    """Vocabularies travel to worker processes (Dask) by pickle: no kernel goes with them."""
    voc = default_vocabulary()
    twin = pickle.loads(pickle.dumps(voc))
    assert twin.engine == voc.engine and twin.fingerprint == voc.fingerprint
    assert_identical(twin.transform(near_words[1]), voc.transform(near_words[1]))


@needs_numba
@pytest.mark.parametrize("setting", [None, "0"])
def test_loading_the_kernels_freezes_what_numbas_import_left(setting: str | None) -> None:
    """Once numba is imported, the objects alive (about 86,000, most of them numba's) go to the
    collector's permanent generation, so that a full collection, which may run inside any add,
    walks the few objects made since (in a fresh process: 10-34 ms with them, under 5 without);
    no collection runs while they load, and the collector is on again after;
    STABLECUES_GC_FREEZE=0 leaves the collector as it is. Objects made later are still
    collected, cycles included."""
    import os
    import subprocess

    code = (
        "import gc, weakref\n"
        "from stablecues.vocabulary.engine import compiled_kernels\n"
        "assert compiled_kernels() is not None\n"
        "class Node: pass\n"
        "a, b = Node(), Node(); a.b, b.a = b, a\n"
        "ref = weakref.ref(a); del a, b\n"
        "gc.collect()\n"
        "print(gc.get_freeze_count(), ref() is None, gc.isenabled())\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "STABLECUES_GC_FREEZE"}
    if setting is not None:
        env["STABLECUES_GC_FREEZE"] = setting
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    frozen, cycle_freed, enabled = out.stdout.split()
    assert cycle_freed == "True" and enabled == "True"  # paused while they loaded, not after
    assert (int(frozen) > 50_000) if setting is None else (int(frozen) == 0)

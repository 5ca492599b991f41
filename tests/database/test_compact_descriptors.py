"""Compact storage of float descriptors (``DatabaseConfig.descriptor_storage``): int8 per
dimension with one float32 scale per entry, the same features back from a memory map and a
file, float32 payloads of older maps still read, binary descriptors untouched, and malformed
quantised arrays refused in one line."""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dbkit import fake_features, fill
from stablecues.database import Database, DatabaseConfig
from stablecues.database.packing import pack_arrays, unpack_arrays
from stablecues.errors import DatabaseError, InputError
from stablecues.vocabulary import Vocabulary, train_vocabulary

INT8 = DatabaseConfig(descriptor_storage="int8")
FLOAT32 = DatabaseConfig(descriptor_storage="float32")


def xfeat_like(n: int, seed: int) -> np.ndarray:
    """(n, 64) float32 L2-normalised descriptors, as XFeat gives them."""
    d = np.random.default_rng(seed).normal(size=(n, 64))
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def sift_like(n: int, seed: int) -> np.ndarray:
    """(n, 128) float32 descriptors with values in 0..255, as SIFT gives them."""
    return (np.random.default_rng(seed).random((n, 128)) * 255).astype(np.float32)


SETS = {64: [xfeat_like(120, s) for s in range(6)], 128: [sift_like(120, s) for s in range(6)]}


@pytest.fixture(scope="module", params=[64, 128], ids=["xfeat64", "sift128"])
def float_voc(request: pytest.FixtureRequest) -> tuple[Vocabulary, list[np.ndarray]]:
    sets = SETS[request.param]
    return train_vocabulary(sets, k=4, levels=2, seed=0, progress=False), sets


def add_all(db: Database, voc: Vocabulary, sets: list[np.ndarray]) -> None:
    for i, d in enumerate(sets):
        bow, fvec = voc.transform(d)
        db.add(bow, fvec, fake_features(d), timestamp=float(i))


def payloads(path: Path) -> list[dict[str, np.ndarray]]:
    with sqlite3.connect(path) as conn:
        rows = conn.execute("SELECT payload FROM entries ORDER BY id").fetchall()
    return [unpack_arrays(r[0]) for r in rows]


def set_payload(path: Path, eid: int, payload: dict[str, np.ndarray]) -> None:
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE entries SET payload = ? WHERE id = ?", (pack_arrays(payload), eid))


def step(d: np.ndarray) -> float:
    """The quantisation step of one entry's descriptors."""
    return float(np.float32(np.abs(d).max() / 127))


def test_int8_is_the_default_and_other_values_are_refused() -> None:
    assert DatabaseConfig().descriptor_storage == "int8"
    with pytest.raises(InputError, match="descriptor_storage must be 'float32' or 'int8', not 'fp16'"):
        DatabaseConfig(descriptor_storage="fp16")  # type: ignore[arg-type]


def test_memory_and_file_give_identical_features_within_half_a_step(
    float_voc: tuple[Vocabulary, list[np.ndarray]], tmp_path: Path
) -> None:
    voc, sets = float_voc
    path = tmp_path / "map.sqlite"
    held = []
    with Database(voc, None, INT8) as mem, Database(voc, path, INT8) as disk:
        add_all(mem, voc, sets)
        add_all(disk, voc, sets)
        for i, d in enumerate(sets):
            a, b = mem.entry(i).features, disk.entry(i).features
            held.append(a.descriptors)
            assert a.descriptors.dtype == np.float32 and a.descriptors.shape == d.shape
            np.testing.assert_array_equal(a.descriptors, b.descriptors)
            err = np.abs(a.descriptors.astype(np.float64) - d)
            assert err.max() <= step(d) / 2 * (1 + 1e-5)
            assert err.max() > 0  # quantised, not kept as they were
            np.testing.assert_array_equal(a.keypoints, b.keypoints)
    with Database(voc, path, FLOAT32, readonly=True) as again:  # the setting now does not matter
        for i, d in enumerate(held):
            np.testing.assert_array_equal(again.entry(i).features.descriptors, d)


def test_stored_descriptor_bytes_per_feature(float_voc: tuple[Vocabulary, list[np.ndarray]],
                                             tmp_path: Path) -> None:
    voc, sets = float_voc
    small, big = tmp_path / "int8.sqlite", tmp_path / "float32.sqlite"
    for path, config in ((small, INT8), (big, FLOAT32)):
        with Database(voc, path, config) as db:
            add_all(db, voc, sets)
    with sqlite3.connect(small) as a, sqlite3.connect(big) as b:
        blobs_small = [r[0] for r in a.execute("SELECT payload FROM entries ORDER BY id")]
        blobs_big = [r[0] for r in b.execute("SELECT payload FROM entries ORDER BY id")]
    for d, p, blob_small, blob_big in zip(sets, payloads(small), blobs_small, blobs_big, strict=True):
        n, dim = d.shape
        assert "descriptors" not in p
        assert p["qdescriptors"].dtype == np.int8 and p["qdescriptors"].shape == (n, dim)
        assert p["qdescriptors"].nbytes / n == dim  # 64 bytes per 64-dim descriptor
        assert p["qscale"].dtype == np.float32 and p["qscale"].shape == (1,)
        # the packed payload: 3 bytes a dimension less, minus the scale and its header field
        saved = len(blob_big) - len(blob_small)
        assert n * dim * 3 - 64 <= saved < n * dim * 3


def test_float32_payloads_of_older_maps_still_read(
    float_voc: tuple[Vocabulary, list[np.ndarray]], tmp_path: Path
) -> None:
    voc, sets = float_voc
    path = tmp_path / "map.sqlite"
    with Database(voc, path, FLOAT32) as db:  # writes what maps held before int8 storage
        add_all(db, voc, sets[:3])
    assert all(p["descriptors"].dtype == np.float32 and "qdescriptors" not in p for p in payloads(path))
    with Database(voc, path) as db:  # reopened with the default (int8): both kinds in one map
        bow, fvec = voc.transform(sets[3])
        db.add(bow, fvec, fake_features(sets[3]))
        for i in range(3):
            np.testing.assert_array_equal(db.entry(i).features.descriptors, sets[i])  # exact
        assert np.abs(db.entry(3).features.descriptors - sets[3]).max() <= step(sets[3]) / 2 * (1 + 1e-5)
    assert ["qdescriptors" in p for p in payloads(path)] == [False, False, False, True]


def test_binary_descriptors_are_never_quantised(voc: Vocabulary, images: list[np.ndarray],
                                                tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    with Database(voc, path, INT8) as db, Database(voc, None, INT8) as mem:
        fill(db, voc, images[:4])
        fill(mem, voc, images[:4])
        for i in range(4):
            np.testing.assert_array_equal(db.entry(i).features.descriptors, images[i])
            np.testing.assert_array_equal(mem.entry(i).features.descriptors, images[i])
    for p, d in zip(payloads(path), images, strict=False):
        assert "qdescriptors" not in p and "qscale" not in p
        assert p["descriptors"].dtype == np.uint8 and p["descriptors"].nbytes == d.nbytes


@pytest.mark.parametrize("n", [0, 5], ids=["no-features", "all-zero"])
def test_empty_and_all_zero_descriptors(n: int, tmp_path: Path) -> None:
    voc = train_vocabulary(SETS[64], k=4, levels=2, seed=0, progress=False)
    d = np.zeros((n, 64), np.float32)
    feats = fake_features(d)
    with Database(voc, tmp_path / "map.sqlite", INT8) as db:
        bow, fvec = voc.transform(d)
        db.add(bow, fvec, feats)
        got = db.entry(0).features
    assert got.descriptors.dtype == np.float32 and got.descriptors.shape == (n, 64)
    assert not got.descriptors.any()
    (p,) = payloads(tmp_path / "map.sqlite")
    assert p["qscale"].tolist() == [0.0] and p["qdescriptors"].shape == (n, 64)


def test_non_finite_descriptors_are_refused_for_int8(tmp_path: Path) -> None:
    voc = train_vocabulary(SETS[64], k=4, levels=2, seed=0, progress=False)
    d = xfeat_like(10, 1)
    bow, fvec = voc.transform(d)
    d[3, 5] = np.nan
    with Database(voc, None, INT8) as db, pytest.raises(InputError, match="finite"):
        db.add(bow, fvec, fake_features(d))


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (lambda p: {**p, "qdescriptors": p["qdescriptors"].astype(np.int16)}, "expected int8"),
        (lambda p: {**p, "qdescriptors": p["qdescriptors"].reshape(-1)}, "expected int8"),
        (lambda p: {**p, "qdescriptors": p["qdescriptors"][:, :0]}, "D >= 1"),
        (lambda p: {**p, "qdescriptors": p["qdescriptors"][:-1]}, "stored features are malformed"),
        (lambda p: {**p, "qdescriptors": np.full_like(p["qdescriptors"], -128)}, "-128"),
        (lambda p: {k: v for k, v in p.items() if k != "qscale"}, "found qdescriptors;"),
        (lambda p: {k: v for k, v in p.items() if k != "qdescriptors"}, "found qscale;"),
        (lambda p: {**p, "descriptors": np.zeros((len(p["fvec"]), 64), np.float32)},
         "found descriptors, qdescriptors, qscale"),
        (lambda p: {**p, "qscale": p["qscale"].astype(np.float64)}, "expected float32"),
        (lambda p: {**p, "qscale": np.ones(2, np.float32)}, "expected float32 \\(1,\\)"),
        (lambda p: {**p, "qscale": np.array([np.nan], np.float32)}, "qscale is nan"),
        (lambda p: {**p, "qscale": np.array([np.inf], np.float32)}, "qscale is inf"),
        (lambda p: {**p, "qscale": np.array([-0.01], np.float32)}, "finite positive"),
        (lambda p: {**p, "qscale": np.zeros(1, np.float32)}, "0 only when every qdescriptor is 0"),
    ],
    ids=["int16", "1-d", "no-dims", "rows", "minus-128", "no-scale", "no-values", "both", "scale-f64",
         "scale-shape", "scale-nan", "scale-inf", "scale-negative", "scale-zero"],
)
def test_malformed_quantised_descriptors_give_one_line(
    change: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]], expected: str, tmp_path: Path
) -> None:
    voc = train_vocabulary(SETS[64], k=4, levels=2, seed=0, progress=False)
    path = tmp_path / "map.sqlite"
    with Database(voc, path, INT8) as db:
        add_all(db, voc, SETS[64][:3])
    set_payload(path, 1, change(payloads(path)[1]))
    with Database(voc, path, readonly=True) as db:
        assert len(db.entry(0).features) == 120  # the other entries are fine
        with pytest.raises(DatabaseError, match=expected) as err:
            db.entry(1)
    text = str(err.value)
    assert "\n" not in text and str(path) in text and "entry 1" in text, text

"""Float (SIFT-like) and other-width binary vocabularies: training, transform on both engines,
files, kind mismatches, and the shipped SIFT vocabulary on real descriptors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from vocab_files import split_binary

from conftest import shared_path
from malformed_cases import tampered_vocabulary
from stablecues.errors import ConfigError, InputError, VocabularyError
from stablecues.features import SiftExtractor
from stablecues.imageio import read_image
from stablecues.types import DescriptorKind
from stablecues.vocabulary import (
    DEFAULT_VOCABULARIES,
    Vocabulary,
    Weighting,
    default_vocabulary,
    default_vocabulary_path,
    engine,
    load_vocabulary,
    save_vocabulary,
    train_vocabulary,
)
from stablecues.vocabulary.train import nearest_centre, squared_l2_exact

ENGINES = ["numpy", pytest.param("compiled", marks=pytest.mark.skipif(
    engine.compiled_kernels() is None, reason="numba is not available"))]


def blobs(
    n_images: int = 8, per: int = 60, dim: int = 16, seed: int = 0
) -> tuple[list[np.ndarray], np.ndarray]:
    """Float descriptors around 6 well separated centres; returns the sets and the centres."""
    rng = np.random.default_rng(seed)
    centres = (rng.permutation(6 * dim).reshape(6, dim) % 6 * 40.0).astype(np.float32)
    centres[np.arange(6), np.arange(6)] += 400.0  # every centre far from every other
    sets = []
    for _ in range(n_images):
        which = rng.integers(0, 6, per)
        sets.append((centres[which] + rng.normal(0, 2.0, (per, dim))).astype(np.float32))
    return sets, centres


def twin(voc: Vocabulary, name: str) -> Vocabulary:
    other = Vocabulary(voc.k, voc.levels, voc.parents, voc.descriptors, voc.weights, voc.weighting,
                       voc.scoring, voc.levels_up)
    other.engine = name
    return other


# ----------------------------------------------------------------------------- training
def test_float_training_finds_the_clusters() -> None:
    sets, centres = blobs()
    voc = train_vocabulary(sets, k=6, levels=1, progress=False)
    assert voc.descriptor_kind == DescriptorKind("float", 16) and voc.is_float
    assert voc.n_words == 6 and voc.descriptors.dtype == np.float32
    # each word's centre is the mean of one blob: within the noise of a true centre
    dist = np.sqrt(((voc.descriptors[voc.word_nodes][:, None, :] - centres[None]) ** 2).sum(-1))
    assert sorted(dist.argmin(axis=1).tolist()) == list(range(6))
    assert dist.min(axis=1).max() < 1.5
    # every descriptor of a blob falls into that blob's word
    for d in sets:
        leaves = voc.leaves_of(d)
        truth = np.sqrt(((d[:, None, :] - centres[None]) ** 2).sum(-1)).argmin(axis=1)
        word_of_blob = {int(t): int(leaf) for t, leaf in zip(truth, leaves, strict=True)}
        assert len(set(word_of_blob.values())) == len(word_of_blob)


def test_float_training_is_seeded_and_idf_weighted() -> None:
    sets, _ = blobs(seed=3)
    a = train_vocabulary(sets, k=3, levels=3, seed=5, progress=False)
    b = train_vocabulary(sets, k=3, levels=3, seed=5, progress=False)
    assert a.fingerprint == b.fingerprint
    np.testing.assert_array_equal(a.descriptors, b.descriptors)
    c = train_vocabulary(sets, k=3, levels=3, seed=6, progress=False)
    assert c.fingerprint != a.fingerprint
    # IDF as for binary words: log(N / N_i) over the training images
    counts = np.zeros(a.n_words)
    for d in sets:
        counts[np.unique(a.node_word[a.leaves_of(d)])] += 1
    np.testing.assert_allclose(a.word_weights, np.log(len(sets) / np.maximum(counts, 1)))
    flat = train_vocabulary(sets, k=3, levels=2, weighting=Weighting.TF, progress=False)
    assert np.all(flat.word_weights == 1.0)


def test_a_node_of_at_most_k_descriptors_gets_one_word_each() -> None:
    d = np.array([[0, 0], [10, 0], [0, 10]], np.float32)
    voc = train_vocabulary([d], k=4, levels=2, progress=False)
    assert voc.n_words == 3
    np.testing.assert_array_equal(np.sort(voc.descriptors[voc.word_nodes], axis=0), np.sort(d, axis=0))


def test_nearest_centre_is_the_fixed_order_one_even_at_exact_ties() -> None:
    rng = np.random.default_rng(1)
    centres = rng.normal(0, 50, (5, 128)).astype(np.float32)
    mid = ((centres[1] + centres[3]) / 2).astype(np.float32)
    # points exactly between two centres (ties), near-ties, and ordinary points
    pts = np.concatenate([np.stack([mid, mid]), rng.normal(0, 50, (300, 128)).astype(np.float32)])
    got = nearest_centre(pts, centres)
    c64 = centres.astype(np.float64)
    want = np.stack([squared_l2_exact(c64, p) for p in pts]).argmin(axis=1)
    np.testing.assert_array_equal(got, want)


# ----------------------------------------------------------------------------- transform
def hand_vocabulary() -> Vocabulary:
    """Root with three float words at (0,0), (10,0), (0,10); weights 1, 2, 3."""
    desc = np.array([[0, 0], [0, 0], [10, 0], [0, 10]], np.float32)
    return Vocabulary(3, 1, np.array([-1, 0, 0, 0]), desc, np.array([0.0, 1.0, 2.0, 3.0]),
                      Weighting.TF_IDF)


@pytest.mark.parametrize("name", ENGINES)
def test_float_transform_by_hand(name: str) -> None:
    voc = twin(hand_vocabulary(), name)
    q = np.array([[1, 1], [9, 1], [8, -1], [5, 5], [-3, 9]], np.float32)
    # (5, 5) is as near (10, 0) as (0, 10), and nearer neither than (0, 0): sqrt(50) each -> word 0
    np.testing.assert_array_equal(voc.leaves_of(q), [1, 2, 2, 1, 3])
    bow, fvec = voc.transform(q)
    assert bow.words.tolist() == [0, 1, 2]
    np.testing.assert_allclose(bow.weights, np.array([2.0, 4.0, 3.0]) / 9.0)  # TF-IDF, L1
    assert fvec.nodes.tolist() == [1, 2, 2, 1, 3]


@pytest.mark.parametrize("name", ENGINES)
def test_float_ties_go_to_the_lowest_child(name: str) -> None:
    voc = twin(hand_vocabulary(), name)
    q = np.array([[5, 5], [10, 10]], np.float32)  # (10, 10): equally near words 1 and 2
    np.testing.assert_array_equal(voc.leaves_of(q), [1, 2])


def test_float_engines_agree_bit_for_bit() -> None:
    if engine.compiled_kernels() is None:
        pytest.skip("numba is not available")
    rng = np.random.default_rng(4)
    sets = [rng.integers(0, 120, (300, 128)).astype(np.float32) for _ in range(6)]
    voc = train_vocabulary(sets, k=4, levels=4, progress=False)
    q = np.concatenate([rng.integers(0, 120, (500, 128)).astype(np.float32),
                        rng.normal(60, 30, (500, 128)).astype(np.float32)])
    fw = rng.random(q.shape[0])
    a, b = twin(voc, "numpy"), twin(voc, "compiled")
    np.testing.assert_array_equal(a.leaves_of(q), b.leaves_of(q))
    for weights in (None, fw):
        (ba, fa), (bb, fb) = a.transform(q, weights=weights), b.transform(q, weights=weights)
        np.testing.assert_array_equal(ba.words, bb.words)
        np.testing.assert_array_equal(ba.weights, bb.weights)
        np.testing.assert_array_equal(fa.nodes, fb.nodes)


@pytest.mark.parametrize("width", [1, 8, 20, 61, 64])
def test_binary_words_of_any_width(width: int) -> None:
    rng = np.random.default_rng(width)
    sets = [rng.integers(0, 256, (80, width), dtype=np.uint8) for _ in range(5)]
    voc = train_vocabulary(sets, k=4, levels=3, progress=False)
    assert voc.descriptor_kind == DescriptorKind("binary", width)
    q = rng.integers(0, 256, (200, width), dtype=np.uint8)
    leaves = twin(voc, "numpy").leaves_of(q)
    if engine.compiled_kernels() is not None:
        np.testing.assert_array_equal(twin(voc, "compiled").leaves_of(q), leaves)
    # a flat tree's word is the exhaustive nearest (Hamming over the real bits, ties lowest)
    flat = train_vocabulary(sets, k=16, levels=1, progress=False)
    bits = np.unpackbits(q, axis=1)[:, None, :] != np.unpackbits(flat.descriptors[1:], axis=1)[None]
    np.testing.assert_array_equal(flat.leaves_of(q), bits.sum(-1).argmin(axis=1) + 1)


def test_kinds_that_disagree_are_named_in_one_line() -> None:
    voc = hand_vocabulary()
    with pytest.raises(InputError, match="descriptors are 32-byte binary but the vocabulary holds "
                                         "2-dim float32 words"):
        voc.transform(np.zeros((3, 32), np.uint8))
    with pytest.raises(InputError, match="descriptors are 3-dim float32 but the vocabulary holds 2-dim"):
        voc.leaves_of(np.zeros((3, 3), np.float32))
    with pytest.raises(InputError, match="finite"):
        voc.transform(np.array([[np.nan, 0]], np.float32))
    with pytest.raises(InputError, match="float32"):
        voc.transform(np.zeros((3, 2), np.float64))
    with pytest.raises(VocabularyError, match="NaN or infinite centre"):
        Vocabulary(2, 1, np.array([-1, 0, 0]), np.array([[0, 0], [np.inf, 0], [1, 1]], np.float32),
                   np.zeros(3))
    with pytest.raises(VocabularyError, match="uint8 .binary. or float32"):
        Vocabulary(2, 1, np.array([-1, 0, 0]), np.zeros((3, 2), np.float64), np.zeros(3))


def test_empty_float_descriptors_pass_through() -> None:
    bow, fvec = hand_vocabulary().transform(np.zeros((0, 2), np.float32))
    assert len(bow) == 0 and len(fvec) == 0


# ----------------------------------------------------------------------------- files
def test_float_file_round_trip_records_the_kind(tmp_path: Path) -> None:
    sets, _ = blobs()
    voc = train_vocabulary(sets, k=3, levels=3, progress=False)
    path = tmp_path / "f.scv"
    save_vocabulary(voc, path)
    _, version, header, _ = split_binary(path.read_bytes())
    assert version == 2 and header["descriptor"] == {"kind": "float", "size": 16}
    assert header["arrays"]["descriptors"]["dtype"] == "<f4"
    for mmap in (False, True):
        back = load_vocabulary(path, mmap=mmap)
        assert back.descriptor_kind == voc.descriptor_kind and back.fingerprint == voc.fingerprint
        np.testing.assert_array_equal(back.descriptors, voc.descriptors)
        np.testing.assert_array_equal(back.weights, voc.weights)
        q = sets[0]
        np.testing.assert_array_equal(back.transform(q)[0].weights, voc.transform(q)[0].weights)


def test_orb_files_stay_version_1_and_other_widths_are_version_2(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    orb = train_vocabulary([rng.integers(0, 256, (60, 32), dtype=np.uint8)], k=4, levels=2, progress=False)
    save_vocabulary(orb, tmp_path / "orb.scv")
    _, version, header, _ = split_binary((tmp_path / "orb.scv").read_bytes())
    assert version == 1 and "descriptor" not in header
    wide = train_vocabulary([rng.integers(0, 256, (60, 61), dtype=np.uint8)], k=4, levels=2, progress=False)
    save_vocabulary(wide, tmp_path / "wide.scv")
    back = load_vocabulary(tmp_path / "wide.scv")
    assert back.descriptor_kind == DescriptorKind("binary", 61)
    assert back.fingerprint == wide.fingerprint != orb.fingerprint


def test_a_corrupt_descriptor_field_is_one_line(tmp_path: Path) -> None:
    from vocab_files import join_binary

    sets, _ = blobs()
    voc = train_vocabulary(sets, k=3, levels=2, progress=False)
    save_vocabulary(voc, tmp_path / "f.scv")
    magic, version, header, payload = split_binary((tmp_path / "f.scv").read_bytes())
    for bad in ({"kind": "complex", "size": 16}, {"kind": "float", "size": 0}, None, "float",
                {"kind": "float", "size": 15}):
        if bad is None:
            header.pop("descriptor")
        else:
            header["descriptor"] = bad
        (tmp_path / "bad.scv").write_bytes(join_binary(magic, version, header, payload))
        with pytest.raises(VocabularyError, match="bad.scv: corrupt vocabulary header") as err:
            load_vocabulary(tmp_path / "bad.scv")
        assert "\n" not in str(err.value)


def test_the_text_format_refuses_float_words(tmp_path: Path) -> None:
    with pytest.raises(VocabularyError, match=r"f\.txt: the DBoW2/ORB-SLAM text format holds 32-byte "
                                              "binary words only.*2-dim float32.*save it as .scv"):
        save_vocabulary(hand_vocabulary(), tmp_path / "f.txt")
    assert list(tmp_path.iterdir()) == []


def test_shipped_vocabularies_by_extractor() -> None:
    assert set(DEFAULT_VOCABULARIES) == {"orb", "sift", "xfeat"}
    assert default_vocabulary() is default_vocabulary("orb")
    assert default_vocabulary().descriptor_kind == DescriptorKind("binary", 32)
    sift = default_vocabulary("sift")
    assert sift.descriptor_kind == DescriptorKind("float", 128)
    assert default_vocabulary_path("sift").stat().st_size < 20 * 2**20
    xfeat = default_vocabulary("xfeat")
    assert xfeat.descriptor_kind == DescriptorKind("float", 64) and xfeat.n_words == 10_000
    assert default_vocabulary_path("xfeat").stat().st_size < 20 * 2**20
    with pytest.raises(ConfigError, match="no vocabulary is shipped for features 'akaze'"):
        default_vocabulary_path("akaze")


def test_shipped_sift_vocabulary_on_real_frames() -> None:
    """Real SIFT descriptors of two CamVid revisit frames: both engines agree to the bit, and a
    frame is more like its neighbour than like a frame of another drive."""
    root = shared_path("camvid_revisit_dev", "train_drives", "frames")
    files = sorted(root.glob("*.jpg"))
    voc = default_vocabulary("sift")
    extractor = SiftExtractor()
    desc = [extractor.extract(read_image(files[i], "grey")).descriptors for i in (0, 2, 200)]
    bows = [twin(voc, "numpy").transform(d)[0] for d in desc]
    if engine.compiled_kernels() is not None:
        for d, b in zip(desc, bows, strict=True):
            c = twin(voc, "compiled").transform(d)[0]
            np.testing.assert_array_equal(c.words, b.words)
            np.testing.assert_array_equal(c.weights, b.weights)
    from stablecues.vocabulary import score

    assert score(bows[0], bows[1], voc.scoring) > score(bows[0], bows[2], voc.scoring)


# ----------------------------------------------------------------------------- the command line
def test_cli_info_default_describes_the_shipped_vocabularies(capsys: pytest.CaptureFixture[str]) -> None:
    from stablecues.cli.main import main

    assert main(["vocab", "info", "default"]) == 0
    out = capsys.readouterr().out
    assert str(default_vocabulary_path()) in out and "descriptors: 32-byte binary" in out
    assert f"words:       {default_vocabulary().n_words}" in out
    assert "made from:   468 images (camvid/train, camvid/val)" in out
    assert "remade by:   python scripts/make_vocabulary.py" in out
    assert main(["vocab", "info", "default:sift"]) == 0
    out = capsys.readouterr().out
    assert "descriptors: 128-dim float32" in out and "make_sift_vocabulary.py" in out
    assert main(["vocab", "info", "default:akaze"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no vocabulary is shipped for features 'akaze'" in err


def test_cli_trains_a_sift_vocabulary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import cv2

    from stablecues.cli.main import main

    (tmp_path / "imgs").mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        img = np.full((160, 200), 120, np.uint8)
        for _ in range(80):
            x, y = int(rng.integers(0, 190)), int(rng.integers(0, 150))
            cv2.circle(img, (x, y), int(rng.integers(2, 12)), int(rng.integers(0, 256)), -1)
        cv2.imwrite(str(tmp_path / "imgs" / f"{i}.png"), img)
    out = tmp_path / "sift.scv"
    assert main(["vocab", "train", str(tmp_path / "imgs"), "--features", "sift", "--k", "4",
                 "--levels", "2", "--out", str(out)]) == 0
    assert "128-dim float32 descriptors" in capsys.readouterr().out
    assert load_vocabulary(out).descriptor_kind == DescriptorKind("float", 128)
    assert main(["vocab", "convert", str(out), str(tmp_path / "sift.txt")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "text format holds 32-byte binary words only" in err
    assert not (tmp_path / "sift.txt").exists()


# ----------------------------------------------------------------------------- database and detector
def test_detector_and_database_take_the_sift_vocabulary(tmp_path: Path) -> None:
    import cv2

    from stablecues.database import Database
    from stablecues.detection import LoopDetector, preset
    from stablecues.types import Frame

    rng = np.random.default_rng(3)
    images = []
    for _ in range(4):
        img = np.full((240, 320), 110, np.uint8)
        for _ in range(120):
            x, y = int(rng.integers(0, 310)), int(rng.integers(0, 230))
            cv2.circle(img, (x, y), int(rng.integers(2, 14)), int(rng.integers(0, 256)), -1)
        images.append(img)
    voc = default_vocabulary("sift")
    cfg = preset("bow-nogeom", {"features": {"name": "sift"}, "query": {"exclude_recent": 0}})
    path = tmp_path / "map.sqlite"
    det = LoopDetector(cfg, vocabulary=voc, database=path)
    for i, img in enumerate(images):
        det.store(Frame(index=i, name=f"{i}", timestamp=float(i), image=img))
    d = det.process(Frame(index=4, name="again", timestamp=4.0, image=images[2]), store=False)
    assert d.candidate_frame == 2
    det.close()
    with Database(voc, path, readonly=True) as db:  # float descriptors persist as they were
        entry = db.entry(1)
        assert entry.features.descriptors.dtype == np.float32 and entry.features.descriptors.shape[1] == 128
    with pytest.raises(ConfigError, match="128-dim float32 descriptors but the vocabulary holds 32-byte"):
        LoopDetector(cfg, vocabulary=default_vocabulary("orb"))


@pytest.mark.parametrize("edit", ["centroid", "relabel"])
def test_a_vocabulary_whose_content_does_not_match_its_fingerprint_is_refused(
    edit: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The header's fingerprint was trusted: a centroid set to 3e38 or float words relabelled as
    binary, with the CRC fixed, loaded under the original fingerprint and a map built with the
    original took them (issue 34). The fingerprint is now checked against the content when it
    is first asked for: the map, `vocab info` and `run --vocab` refuse in one line."""
    from stablecues.cli.main import main
    from stablecues.database import Database
    from stablecues.vocabulary import default_vocabulary_path, load_vocabulary

    original = default_vocabulary_path("xfeat")
    bad = tmp_path / f"{edit}.scv"
    tampered_vocabulary(original, bad, edit)
    voc = load_vocabulary(bad)  # loading stays fast: nothing hashed yet
    with pytest.raises(VocabularyError, match=f"{edit}.scv: the vocabulary's content does not match"):
        _ = voc.fingerprint
    with Database(load_vocabulary(original), tmp_path / "map.sqlite"):
        pass
    with pytest.raises(VocabularyError, match="does not match the fingerprint"):
        Database(load_vocabulary(bad), tmp_path / "map.sqlite")
    assert main(["vocab", "info", str(bad)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "does not match the fingerprint" in err
    assert load_vocabulary(original).fingerprint == load_vocabulary(original, mmap=True).fingerprint


def test_a_mapped_vocabulary_loads_at_once_and_is_checked_on_first_use(tmp_path: Path) -> None:
    """`load_vocabulary(..., mmap=True)` (the shipped vocabularies load so) reads the header and
    maps the arrays: the CRC and the tree's checks run when the vocabulary is first used, and a
    damaged file is refused there in one line naming it (issue 38: a load in under a
    millisecond, its integrity still checked). A pickled copy is checked before it travels."""
    import pickle

    from stablecues.vocabulary import default_vocabulary_path, load_vocabulary

    original = default_vocabulary_path("xfeat")
    bad = tmp_path / "flipped.scv"
    raw = bytearray(original.read_bytes())
    raw[-100] ^= 0x01  # a byte of the children table: only the CRC sees it
    bad.write_bytes(bytes(raw))
    voc = load_vocabulary(bad, mmap=True)  # no error yet: nothing was checked
    with pytest.raises(VocabularyError, match=r"flipped.scv: vocabulary checksum mismatch") as err:
        voc.transform(np.zeros((3, 64), np.float32))
    assert "\n" not in str(err.value)
    with pytest.raises(VocabularyError, match="checksum mismatch"):
        load_vocabulary(bad)  # read whole: checked at once, as before
    good = load_vocabulary(original, mmap=True)
    twin = pickle.loads(pickle.dumps(good))
    d = np.random.default_rng(0).standard_normal((40, 64)).astype(np.float32)
    assert twin.fingerprint == load_vocabulary(original).fingerprint
    np.testing.assert_array_equal(twin.transform(d)[0].words, good.transform(d)[0].words)

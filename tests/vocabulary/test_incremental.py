"""The incremental vocabulary: words made and merged by distance, purged, kept current, saved
beside a map and continued; its kernels against plain Python; a real revisit found with it."""

from __future__ import annotations

import hashlib
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from dbkit import fake_features
from stablecues.cli.main import main as cli_main
from stablecues.database import Database
from stablecues.database.mapcheck import check_map
from stablecues.database.store import DatabaseError
from stablecues.datasets import open_dataset
from stablecues.detection import LoopDetector, preset
from stablecues.errors import ConfigError, InputError, VocabularyError
from stablecues.evaluation import evaluate_detections
from stablecues.features import make_extractor
from stablecues.groundtruth import load_ground_truth
from stablecues.imageio import read_image
from stablecues.types import DescriptorKind
from stablecues.vocabulary import _incremental
from stablecues.vocabulary._incremental import held
from stablecues.vocabulary.incremental import IncrementalVocabulary, words_path

ORB = DescriptorKind("binary", 32)
XFEAT = DescriptorKind("float", 64)


def flip(d: np.ndarray, bits: int, rng: np.random.Generator) -> np.ndarray:
    """``d`` with ``bits`` distinct random bits of every row flipped."""
    pos = np.argsort(rng.random((d.shape[0], 256)), axis=1)[:, :bits]
    mask = np.zeros((d.shape[0], 256), np.uint8)
    np.put_along_axis(mask, pos, 1, axis=1)
    return d ^ np.packbits(mask, axis=1, bitorder="little")


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.unpackbits(a ^ b, axis=1).sum(axis=1)


def state(voc: IncrementalVocabulary) -> str:
    """A digest of everything that decides the words."""
    n = voc._made
    h = hashlib.sha256()
    for arr in (voc._words[:n], voc._df[:n], voc._last[:n], voc._alive[:n], voc._wkeys[:n]):
        h.update(np.ascontiguousarray(arr).tobytes())
    h.update(f"{voc.images} {voc.words_made} {voc.words_live} {voc._cursor}".encode())
    return h.hexdigest()


@pytest.fixture(scope="module")
def orb_frames() -> list[np.ndarray]:
    """ORB descriptors of 12 consecutive real frames (a CamVid revisit development drive)."""
    files = sorted(shared_path("camvid_revisit_dev", "val_drive", "frames").glob("*"))[:12]
    ex = make_extractor("orb")
    return [ex.extract(read_image(f, "grey")).descriptors for f in files]


def test_words_grow_join_and_stay_apart_by_the_threshold(orb_frames: list[np.ndarray]) -> None:
    voc = IncrementalVocabulary(ORB, threshold=64, purge_after=0)
    a = orb_frames[0]
    bow, fvec = voc.learn(a)
    assert voc.images == 1 and 0 < voc.words_made <= len(a)  # a word per descriptor (twins share one)
    assert len(fvec) == len(a) and bow.words.size == np.unique(bow.words).size
    made = voc.words_made
    again = voc.transform(a)[0]  # nothing learned by a query
    assert voc.words_made == made and np.array_equal(again.words, bow.words)
    rng = np.random.default_rng(0)
    moved = flip(a, 8, rng)  # 8 bits from their words: each joins an existing word
    voc.learn(moved)
    assert voc.words_made == made
    assert np.all(voc._df[np.unique(bow.words)] == 2)
    far = flip(a, 100, rng)  # 100 bits from their own words, and from every other word
    nearest = np.array([hamming(voc._descriptors_of(np.arange(made)), row[None]).min() for row in far])
    voc.learn(far)
    assert voc.words_made - made == int((nearest > 64).sum()) > 0  # a new word for each that joined none
    assert voc.images == 3


def test_a_word_is_the_nearest_within_the_threshold(orb_frames: list[np.ndarray]) -> None:
    """Every descriptor's word is within the threshold, and the hash tables find a word for
    most descriptors that have one within it (86 % here with 16 tables of 12 bits), most often
    the nearest: the index is approximate, as iBoW-LCD's trees are."""
    voc = IncrementalVocabulary(ORB, threshold=64, purge_after=0)
    for d in orb_frames[:6]:
        voc.learn(d)
    q = orb_frames[6]
    got = voc._assign(q)
    words = voc._descriptors_of(np.arange(voc.words_made))
    dist = np.unpackbits(q[:, None, :] ^ words[None], axis=2).sum(axis=2)
    best = dist.min(axis=1)
    hit = got >= 0
    assert np.all(dist[np.flatnonzero(hit), got[hit]] <= 64)
    reachable = best <= 64
    assert hit[reachable].mean() >= 0.8
    exact = dist[np.flatnonzero(hit), got[hit]] == best[hit]
    assert exact.mean() >= 0.7  # the nearest word itself: 77 % here


def test_words_seen_once_are_purged_and_weights_stay_current(orb_frames: list[np.ndarray]) -> None:
    voc = IncrementalVocabulary(ORB, threshold=64, purge_after=3)
    first = voc.learn(orb_frames[0])[0].words
    rng = np.random.default_rng(1)
    for k in range(17):  # unrelated images: none of the first image's words again
        voc.learn(flip(orb_frames[1 + k % 10], 110, rng))
    # purged at image 16 (every 16 images): seen once, not for more than 3 images
    assert not voc._alive[first].any()
    assert (voc.transform(orb_frames[0])[0].words.size == 0
            or not np.isin(voc.transform(orb_frames[0])[0].words, first).any())
    fresh = IncrementalVocabulary(ORB, threshold=64, purge_after=0)
    b1 = fresh.learn(orb_frames[0])[0]
    fresh.learn(orb_frames[0])
    b2 = fresh.transform(orb_frames[0])[0]
    # IDF now: log(1 + N / n_w) with every word in both images: the same value for every word
    assert np.allclose(b2.weights.sum(), 1.0) and b1.words.size == b2.words.size


def test_compiled_kernels_equal_plain_python(orb_frames: list[np.ndarray],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The numba kernels and the same functions as plain Python make the same words, binary and
    float (small inputs: plain Python is slow)."""
    if _incremental.kernels() is _incremental.plain() or not _incremental._compiled[0]:
        pytest.skip("numba is not available: only the plain path runs")
    rng = np.random.default_rng(3)
    binary = [d[:80] for d in orb_frames[:4]]
    floats = [rng.normal(size=(60, 64)).astype(np.float32) for _ in range(3)]
    floats = [f / np.linalg.norm(f, axis=1, keepdims=True) for f in floats]
    floats.append(floats[0] + 0.01 * rng.normal(size=floats[0].shape).astype(np.float32))
    reused = [flip(d, 100, rng) for _ in range(5) for d in binary]  # 20 unrelated images: ids given again
    for kind, images, thr, purge, space in ((ORB, binary, 64, 0, 1 << 22), (XFEAT, floats, 0.7, 0, 1 << 22),
                                            (ORB, reused, 64, 1, 150)):
        digests = []
        for plain in (False, True):
            if plain:
                monkeypatch.setattr(_incremental, "kernels", _incremental.plain)
            voc = IncrementalVocabulary(kind, threshold=thr, purge_after=purge, id_space=space)
            bows = [voc.learn(d)[0] for d in images]
            digests.append((state(voc), [b.words.tolist() for b in bows]))
            monkeypatch.undo()
        assert digests[0] == digests[1]
        assert voc.words_made > voc._made or space > 150


def test_the_words_do_not_depend_on_how_the_index_is_laid_out(orb_frames: list[np.ndarray],
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """The index rebuilt after every image, or never (every new word in an overflow page, every
    purged one left in), or with no room to spare in its runs: the same words, image for image."""
    from stablecues.vocabulary import incremental

    rng = np.random.default_rng(5)
    images = [flip(orb_frames[k % 12], 6 * (k // 12), rng) for k in range(40)]
    digests = []
    for mode in ("every image", "never", "no slack"):
        monkeypatch.setattr(incremental, "FREEZE_MIN", 0 if mode == "every image" else 1 << 40)
        monkeypatch.setattr(incremental, "FREEZE_SHARE", 1 << 40)
        if mode == "no slack":
            monkeypatch.setattr(_incremental, "SLACK_MIN", 0)
            monkeypatch.setattr(_incremental, "SLACK_SHIFT", 60)
        voc = IncrementalVocabulary(ORB, purge_after=4, id_space=9000)
        bows = [voc.learn(d)[0].words.tolist() for d in images]
        if mode == "never":
            assert voc._indexed == 0 and voc._dead_linked > 0
        digests.append((state(voc), bows))
        monkeypatch.undo()
    assert digests[0] == digests[1] == digests[2]


def run_slots(voc: IncrementalVocabulary) -> np.ndarray:
    """The slots in use in the runs of every table."""
    start, fill = voc._runs["r_start"], voc._runs["r_fill"]
    return np.concatenate([np.arange(start[b], start[b] + fill[b]) for b in range(fill.size)])


def buckets(voc: IncrementalVocabulary) -> list[list[int]]:
    """The word ids in each bucket's run (sorted), every table; the index holds no page."""
    assert int(voc._pool["state"][0]) == 0
    start, fill, ids = (voc._runs[a] for a in ("r_start", "r_fill", "r_ids"))
    return [sorted(ids[start[b]: start[b] + fill[b]].tolist()) for b in range(fill.size)]


def test_a_compacted_index_holds_what_a_fresh_build_does(orb_frames: list[np.ndarray]) -> None:
    """The index compacted from itself (words purged, words in pages, ids given again to new
    words while the old words' slots are still linked) holds in each bucket exactly the live
    words that a build from the words alone puts there, each word's copy its descriptor."""
    rng = np.random.default_rng(8)
    voc = IncrementalVocabulary(ORB, purge_after=2, id_space=3000)
    stale = reused = 0
    for k in range(40):
        voc.learn(flip(orb_frames[k % 12], 3 * (k // 12), rng))
        if k % 5 != 4:
            continue
        ids, desc = voc._runs["r_ids"], voc._runs["r_desc"]
        used = run_slots(voc)
        moved = (desc[used] != voc._words[ids[used]]).any(axis=1)  # a slot of an id given again
        stale += int((voc._alive[ids[used]].astype(bool) & moved).sum())
        spare = voc._spare
        if spare is not None:  # the runs the rebuild may write into: what they held must not matter
            held(spare["r_ids"])[:] = rng.integers(0, 3000, held(spare["r_ids"]).shape)
            held(spare["r_desc"])[:] = rng.integers(0, 2**63, held(spare["r_desc"]).shape, dtype=np.uint64)
        voc._compact()
        reused += spare is not None and held(voc._runs["r_ids"]) is held(spare["r_ids"])
        got = buckets(voc)
        used = run_slots(voc)
        assert np.array_equal(voc._runs["r_desc"][used], voc._words[voc._runs["r_ids"][used]])
        voc._freeze()
        assert got == buckets(voc), f"image {k}"
    assert stale > 0 and voc.words_made > 3000  # old slots of ids given again were dropped
    assert reused > 0  # rebuilds wrote into the runs of the one before


def test_ids_of_purged_words_are_given_again_once_all_are_used(orb_frames: list[np.ndarray],
                                                               tmp_path: Path,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    """A small id space: once every id is used, new words take the ids of purged ones (said
    once in the log), a slot left by the old word never answers for the new one, and a map
    reopened in the middle continues with the same words."""
    rng = np.random.default_rng(6)
    images = [flip(orb_frames[k % 12], 3 * (k // 12), rng) for k in range(48)]
    space = 3000
    whole = IncrementalVocabulary(ORB, purge_after=2, id_space=space)
    with caplog.at_level("WARNING"):
        for d in images:
            whole.learn(d)
    assert whole.words_made > space and whole._made == space  # ids were given again
    assert sum("ids of purged words" in r.message for r in caplog.records) == 1
    assert whole.words_live == int(whole._alive.sum()) <= space
    # no slot left by a purged word answers for the new word that took its id: every word found is
    # within the threshold of the word as it is now
    q = images[-1]
    words = whole._assign(q)
    found = words >= 0
    assert found.sum() > 100
    assert (hamming(q[found], whole._descriptors_of(words[found])) <= whole.threshold).all()
    # reopened halfway (the words saved and restored), it continues as the uninterrupted run
    half = IncrementalVocabulary(ORB, purge_after=2, id_space=space)
    for d in images[:30]:
        half.learn(d)
    half.save(tmp_path / "w.words", bytes(16))
    again = IncrementalVocabulary(ORB, purge_after=2, id_space=space)
    again.restore(tmp_path / "w.words", bytes(16))
    assert state(again) == state(half)
    for d in images[30:]:
        again.learn(d)
    assert state(again) == state(whole)


def test_same_frames_same_words_in_a_fresh_process(orb_frames: list[np.ndarray], tmp_path: Path) -> None:
    np.save(tmp_path / "d.npy", np.concatenate(orb_frames[:8]))
    script = textwrap.dedent(f"""
        import sys, hashlib, numpy as np
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_incremental import state, ORB
        from stablecues.vocabulary.incremental import IncrementalVocabulary
        d = np.load({str(tmp_path / "d.npy")!r})
        voc = IncrementalVocabulary(ORB, purge_after=2)
        for part in np.array_split(d, 8):
            voc.learn(part)
        print(state(voc))
    """)
    runs = {subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                           cwd=Path(__file__).parents[1]).stdout.strip() for _ in range(2)}
    voc = IncrementalVocabulary(ORB, purge_after=2)
    for part in np.array_split(np.concatenate(orb_frames[:8]), 8):
        voc.learn(part)
    assert runs == {state(voc)}


def test_a_map_saves_its_words_and_continues_them(orb_frames: list[np.ndarray], tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    whole = IncrementalVocabulary(ORB, purge_after=3, save_every=4)
    for d in orb_frames:
        whole.learn(d)
    voc = IncrementalVocabulary(ORB, purge_after=3, save_every=4)
    with Database(voc, path) as db:
        for d in orb_frames[:7]:
            bow, fvec = voc.learn(d)
            db.add(bow, fvec, fake_features(d))
    assert words_path(path).is_file()
    again = IncrementalVocabulary(ORB, purge_after=3, save_every=4)
    with Database(again, path) as db:
        assert again.images == 7
        with pytest.raises(ConfigError, match="one map"):
            Database(again, tmp_path / "other.sqlite")
        for d in orb_frames[7:]:
            bow, fvec = again.learn(d)
            db.add(bow, fvec, fake_features(d))
        removed = db.remove([2, 5])
        assert removed == 2
        db.new_session()
        bow, fvec = again.learn(orb_frames[0])
        db.add(bow, fvec, fake_features(orb_frames[0]))
    whole.learn(orb_frames[0])
    assert state(again) == state(whole)
    report = check_map(path)  # `stablecues map check` finds the words' settings in MAP.words
    assert report.ok and report.vocabulary == "incremental"
    third = IncrementalVocabulary(ORB, purge_after=3, save_every=4)
    with Database(third, path, readonly=True) as db:
        assert len(db) == len(orb_frames) + 1 and state(third) == state(whole)
        assert db.query(third.transform(orb_frames[9])[0], 1)[0].entry_id == 9
    with (pytest.raises(InputError, match="learn"),  # add without learning: refused in one line
          Database(IncrementalVocabulary(ORB, purge_after=3, save_every=4), path) as db):
        db.add(*IncrementalVocabulary(ORB).learn(orb_frames[1]), fake_features(orb_frames[1]))


def test_a_reader_follows_the_writers_words(orb_frames: list[np.ndarray], tmp_path: Path) -> None:
    """A reader that refreshes learns the entries the writer added since (and takes the writer's
    words file when a newer one was saved): its words are the writer's, and it finds the new
    frames."""
    path = tmp_path / "map.sqlite"
    writer_voc = IncrementalVocabulary(ORB, purge_after=3, save_every=5)
    with Database(writer_voc, path) as writer:
        for d in orb_frames[:3]:
            writer.add(*writer_voc.learn(d), fake_features(d))
        writer.flush()
        reader_voc = IncrementalVocabulary(ORB, purge_after=3, save_every=5)
        with Database(reader_voc, path, readonly=True) as reader:
            assert reader_voc.images == 3
            saves = []
            restore = reader_voc.restore
            reader_voc.restore = lambda *a: saves.append(a) or restore(*a)  # type: ignore[method-assign]
            # entries published with the words file older than them (as between two saves: the
            # reader learns them from the entries), then twice with a newer one (the reader reads it)
            for k, step in enumerate((orb_frames[3:4], orb_frames[4:9], orb_frames[9:])):
                older = words_path(path).read_bytes()
                for d in step:
                    writer.add(*writer_voc.learn(d), fake_features(d))
                writer.flush()  # publishes the entries (and saves the words)
                if k == 0:
                    words_path(path).write_bytes(older)
                assert reader.refresh() == len(step)
                assert state(reader_voc) == state(writer_voc)
            assert len(saves) == 2  # the second and third steps read the writer's newer words file
            assert reader.query(reader_voc.transform(orb_frames[10])[0], 1)[0].entry_id == 10


@pytest.mark.parametrize("damage", ["truncated", "flipped", "settings", "other map", "garbage"])
def test_a_damaged_words_file_is_refused_in_one_line(orb_frames: list[np.ndarray], tmp_path: Path,
                                                     damage: str) -> None:
    path = tmp_path / "map.sqlite"
    voc = IncrementalVocabulary(ORB, save_every=2)
    with Database(voc, path) as db:
        for d in orb_frames[:4]:
            db.add(*voc.learn(d), fake_features(d))
    wp = words_path(path)
    raw = bytearray(wp.read_bytes())
    other = IncrementalVocabulary(ORB, save_every=2)
    if damage == "truncated":
        wp.write_bytes(raw[:-7])
    elif damage == "flipped":
        raw[200] ^= 0x10
        wp.write_bytes(bytes(raw))
    elif damage == "garbage":
        wp.write_bytes(b"\x00" * 300)
    elif damage == "settings":
        other = IncrementalVocabulary(ORB, save_every=2, threshold=50)
    else:
        with Database(IncrementalVocabulary(ORB), tmp_path / "b.sqlite") as db2:
            v2 = db2.vocabulary
            assert isinstance(v2, IncrementalVocabulary)
            db2.add(*v2.learn(orb_frames[0]), fake_features(orb_frames[0]))
        words_path(tmp_path / "b.sqlite").replace(wp)
    if damage == "settings":  # another vocabulary's map: refused by the map's own record, both named
        with pytest.raises(DatabaseError, match="map.sqlite") as refused:
            Database(other, path)
        assert "threshold 64" in str(refused.value) and "threshold 50" in str(refused.value)
        return
    with pytest.raises(DatabaseError) as info:
        Database(other, path)
    message = str(info.value)
    assert str(wp) in message and "\n" not in message
    with pytest.raises(VocabularyError):
        IncrementalVocabulary(ORB, save_every=2).restore(wp, bytes(16))


def test_settings_out_of_range_are_refused() -> None:
    for bad in ({"threshold": -1}, {"tables": 0}, {"bits": 30}, {"id_space": 0}, {"purge_after": -2}):
        with pytest.raises(ConfigError):
            IncrementalVocabulary(ORB, **bad)  # type: ignore[arg-type]
    with pytest.raises(InputError):
        IncrementalVocabulary(ORB).learn(np.zeros((3, 64), np.float32))


def test_the_incremental_vocabulary_finds_the_loops_of_a_real_revisit() -> None:
    """val_drive (CamVid development revisit, 49 frames, the second pass under another light):
    ``fast`` with words learned from the drive itself finds most of its loops and no false one
    (11 of 15 at 100 % precision; the trained vocabulary 15: bench_incremental.py)."""
    root = shared_path("camvid_revisit_dev", "val_drive")
    ds = open_dataset(root / "frames", format="folder")
    gt = load_ground_truth(root / "gt.png")
    det = LoopDetector(preset("fast", {"vocabulary": "incremental"}))
    assert isinstance(det.vocabulary, IncrementalVocabulary)
    decisions = [det.process(ds[i]) for i in range(len(ds))]
    q = np.array([d.frame_index for d in decisions])
    cand = np.array([d.candidate_frame if d.accepted else -1 for d in decisions])
    conf = np.array([d.confidence if d.accepted else 0.0 for d in decisions])
    ev = evaluate_detections(gt.matrix, q, cand, conf)
    assert ev.recall_at_100p >= 0.7 and ev.fp == 0
    assert det.vocabulary.words_live > 1000


def test_cli_run_with_an_incremental_vocabulary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    frames = shared_path("camvid_revisit_dev", "val_drive", "frames")
    out = tmp_path / "run"
    args = ["run", str(frames), "--preset", "fast", "--vocab", "incremental", "--out", str(out),
            "--max-frames", "12", "--no-progress", "--pictures", "0"]
    assert cli_main(args) == 0
    assert (out / "map.sqlite.words").is_file()
    capsys.readouterr()
    assert cli_main(["run", str(frames), "--preset", "fast", "--out", str(out), "--resume",
                     "--no-progress"]) == 1  # the map's vocabulary is not the shipped one
    err = capsys.readouterr().err.strip()
    assert "incremental" in err and "\n" not in err
    assert cli_main([*args[:-5], "--resume", "--no-progress", "--pictures", "0"]) == 0


def test_words_lost_after_a_removal_are_learned_again_without_it(orb_frames: list[np.ndarray],
                                                                 tmp_path: Path) -> None:
    """A map whose words file is gone, with an entry removed: it reopens (the removed entry's
    descriptors are gone, its words are not learned again), and a new map may replace it."""
    from stablecues.database.files import remove_database

    path = tmp_path / "map.sqlite"
    voc = IncrementalVocabulary(ORB, save_every=100)
    with Database(voc, path) as db:
        for d in orb_frames[:6]:
            db.add(*voc.learn(d), fake_features(d))
        db.remove([1])
    words_path(path).unlink()
    report = check_map(path)  # default settings: found without the words file (said in a warning)
    assert report.vocabulary == "incremental" and not report.problems
    assert any("missing" in w for w in report.warnings)
    again = IncrementalVocabulary(ORB, save_every=100)
    with Database(again, path) as db:
        assert again.images == 6 and len(db) == 6
        db.add(*again.learn(orb_frames[6]), fake_features(orb_frames[6]))
    assert words_path(path).is_file()
    other = tmp_path / "other.sqlite"  # other settings, no words file: says what is missing
    with Database(IncrementalVocabulary(ORB, threshold=50), other) as db:
        db.add(*db.vocabulary.learn(orb_frames[0]), fake_features(orb_frames[0]))  # type: ignore[union-attr]
    words_path(other).unlink()
    with pytest.raises(DatabaseError, match="words file .* is missing"):
        check_map(other)
    remove_database(path)  # what `run --overwrite` does: the words go with the map
    assert not words_path(path).exists()
    with Database(IncrementalVocabulary(ORB), path) as db:
        assert len(db) == 0


def test_a_float_map_stores_what_its_vocabulary_learned(tmp_path: Path) -> None:
    """Float descriptors are stored as int8: the vocabulary must learn that form (what a reopened
    map learns again), and an add of other descriptors is refused in one line."""
    rng = np.random.default_rng(4)
    d = rng.normal(size=(50, 64)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    feats = fake_features(d)
    voc = IncrementalVocabulary(XFEAT)
    with Database(voc, tmp_path / "f.sqlite") as db:
        with pytest.raises(InputError, match="stored_form"):
            db.add(*voc.learn(d), feats)
        voc.forget()
        db.add(*voc.learn(db.stored_form(d)), feats)
        assert len(db) == 1

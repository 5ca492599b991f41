"""VLAD (the second retrieval vote): the codebook, the vectors, and the vote in the detector."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from test_run_break import STEP, _wall

from stablecues import Frame, LoopDetector, preset
from stablecues.detection.run import STAGES, run_stages
from stablecues.errors import ConfigError, ModelError
from stablecues.vocabulary.vlad import (
    MAX_CODEBOOK_VALUES,
    VladCodebook,
    codebook_provenance,
    default_codebook,
    load_codebook,
    vlad_similarity,
)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_the_vector_is_the_intra_normalised_residual_sum() -> None:
    """Two centres on the axes; each descriptor's residual lands in its centre's block, each
    block is made a unit vector on its own, the whole one too; order does not matter."""
    book = VladCodebook(np.array([[1.0, 0.0], [0.0, 1.0]], np.float32))
    d = _unit(np.array([[1.0, 0.2], [1.0, -0.1], [0.1, 1.0]], np.float32))
    v = book.encode(d)
    first = (d[0] - [1, 0]) + (d[1] - [1, 0])
    second = d[2] - [0, 1]
    want = np.concatenate([first / np.linalg.norm(first), second / np.linalg.norm(second)]) / math.sqrt(2)
    np.testing.assert_allclose(v, want, atol=1e-6)
    np.testing.assert_allclose(book.encode(d[::-1]), v, atol=1e-6)
    np.testing.assert_allclose(book.encode(d * 3.0), v, atol=1e-6)  # descriptors made unit first
    assert not book.encode(np.zeros((0, 2), np.float32)).any()  # no descriptors: zeros
    assert vlad_similarity(v, np.stack([v, np.zeros_like(v)])).tolist() == pytest.approx([1.0, 0.0])
    with pytest.raises(ModelError, match=r"expected \(N, 2\)"):
        book.encode(np.zeros((4, 3), np.float32))


def test_the_shipped_codebook_and_its_provenance() -> None:
    book = default_codebook("xfeat")
    assert (book.k, book.dim, book.size) == (32, 64, 2048)
    meta = codebook_provenance("xfeat")
    assert meta["fingerprint"] == book.fingerprint and meta["k"] == 32
    sources = meta["sources"]
    assert isinstance(sources, list)
    assert not any("gardens" in s.lower() or "corridor" in s.lower() for s in sources)
    rng = np.random.default_rng(0)
    a = rng.standard_normal((500, 64)).astype(np.float32)
    va, vb = book.encode(a), book.encode(a[:400])  # most of the same descriptors: similar
    vc = book.encode(rng.standard_normal((500, 64)).astype(np.float32))
    assert float(va @ vb) > float(va @ vc)
    assert float(np.linalg.norm(va)) == pytest.approx(1.0, abs=1e-5)
    with pytest.raises(ModelError, match="no shipped VLAD codebook for 'orb'"):
        default_codebook("orb")


@pytest.mark.parametrize(("content", "message"), [
    (None, "not found"),
    (b"not numpy", "not a .npy"),
    ("int", "expected a \\(K, D\\) float"),
    ("3d", "expected a \\(K, D\\) float"),
    ("nan", "finite float centres"),
    ("truncated", "header claims"),
    ("huge", "larger than"),
])
def test_a_bad_codebook_file_is_one_line(tmp_path: Path, content: object, message: str) -> None:
    p = tmp_path / "book.npy"
    if isinstance(content, bytes):
        p.write_bytes(content)
    elif content == "int":
        np.save(p, np.zeros((4, 8), np.int32))
    elif content == "3d":
        np.save(p, np.zeros((2, 4, 8), np.float32))
    elif content == "nan":
        np.save(p, np.full((4, 8), np.nan, np.float32))
    elif content == "truncated":
        np.save(p, np.zeros((64, 64), np.float32))
        p.write_bytes(p.read_bytes()[:-100])
    elif content == "huge":
        with p.open("wb") as f:  # a header claiming 2^22 + 1 centres over 32 bytes of data
            np.lib.format.write_array_header_1_0(
                f, {"descr": "<f4", "fortran_order": False, "shape": (MAX_CODEBOOK_VALUES + 1, 4)})
            f.write(bytes(32))
    with pytest.raises(ModelError, match=message) as err:
        load_codebook(p)
    assert "\n" not in str(err.value) and str(p) in str(err.value)


def _stream() -> list[Frame]:
    """Frames 0-11 drive along a wall; frame 12 cuts back to the start (5 px off) and frames
    12-19 drive the same stretch again (as test_sequence.py's stream)."""
    pano = _wall(11)
    xs = [STEP * i for i in range(12)] + [5 + STEP * i for i in range(8)]
    return [Frame(index=i, name=f"{i}.png", timestamp=float(i),
                  image=np.ascontiguousarray(pano[:, x:x + 320])) for i, x in enumerate(xs)]


def _config(weight: float) -> object:
    return preset("learned", {"query": {"exclude_recent": 6, "vlad": weight},
                              "min_confidence": 0.0, "similarity": False})


def _decisions(det: LoopDetector, frames: list[Frame]) -> list[tuple[object, ...]]:
    out: list[tuple[object, ...]] = []
    for d in map(det.process, frames):
        out.append((d.status, d.candidate_frame, d.score, d.confidence))
    return out


def test_the_vote_finds_the_second_drive_and_a_reopened_map_scores_as_before(tmp_path: Path) -> None:
    """XFeat on the wall stream with the VLAD vote at 0.5: the second drive's loops are found
    near their true frames, the run times the stage ``vlad``; a map reopened in the middle (its
    vectors read back from the entries) gives the decisions of the uninterrupted run."""
    frames = _stream()
    config = _config(0.5)
    det = LoopDetector(config)
    whole = []
    for f in frames:
        d = det.process(f)
        whole.append((d.status, d.candidate_frame, d.score, d.confidence))
        assert "vlad" in d.timings
        if f.index >= 12:
            assert d.accepted and abs(d.candidate_frame - (f.index - 12)) <= 1, (f.index, d)
    bow_alone = _decisions(LoopDetector(_config(0.0)), frames)
    assert [d[2] for d in bow_alone] != [d[2] for d in whole]  # the vote moved the scores
    path = tmp_path / "map.sqlite"
    with LoopDetector(config, database=path) as det:
        first = _decisions(det, frames[:15])
    with LoopDetector(config, database=path) as det:
        assert len(det._vlad or ()) == 15
        rest = _decisions(det, frames[15:])
    assert [d[:2] for d in first + rest] == [d[:2] for d in whole]
    np.testing.assert_allclose(np.array([d[2:] for d in first + rest], float),
                               np.array([d[2:] for d in whole], float), rtol=1e-5)
    # a map made without the vote gets its vectors from the stored descriptors when reopened with it
    plain = tmp_path / "plain.sqlite"
    with LoopDetector(_config(0.0), database=plain) as det:
        _decisions(det, frames[:6])
    with LoopDetector(config, database=plain) as det:
        assert len(det._vlad or ()) == 6 and det._vlad is not None and det._vlad.latest is not None


def test_vote_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match=r"query.vlad .* must be in \[0, 1\]"):
        preset("learned", {"query": {"vlad": 1.5}})
    with pytest.raises(ConfigError, match="float \\(learned\\) descriptors"):
        LoopDetector(preset("fast", {"query": {"vlad": 0.5}}))
    with pytest.raises(ConfigError, match="query.vlad_codebook: no-such.npy: VLAD codebook file not found"):
        LoopDetector(preset("learned", {"query": {"vlad": 0.5, "vlad_codebook": "no-such.npy"}}))
    assert run_stages(preset("learned", {"query": {"vlad": 0.0}})) == STAGES
    assert run_stages(preset("learned")).index("vlad") == STAGES.index("query")

"""LoopDetector: islands, a revisit found, determinism, a killed detector continues, the CLI."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.cli.main import main
from stablecues.detection import LoopDetector, Status, compute_islands, preset
from stablecues.errors import ConfigError
from stablecues.types import Frame

FRAMES = 60
REVISIT_FROM = 44  # frames 44.. look at the places of frames 4..


def panorama(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((300, 2400), 110, np.uint8)
    for _ in range(2500):
        x, y = int(rng.integers(0, 2400)), int(rng.integers(0, 300))
        if rng.random() < 0.5:
            cv2.rectangle(
                img,
                (x, y),
                (x + int(rng.integers(3, 25)), y + int(rng.integers(3, 25))),
                int(rng.integers(0, 256)),
                -1,
            )
        else:
            cv2.circle(img, (x, y), int(rng.integers(2, 12)), int(rng.integers(0, 256)), -1)
    return cv2.GaussianBlur(img, (3, 3), 0)


def place_of(i: int) -> int:
    """x offset of frame i: a drive along the panorama, then a revisit of its start."""
    if i < REVISIT_FROM:
        return 40 * i
    return 40 * (i - REVISIT_FROM + 4) + 7  # 7 px off the first pass


def make_frames() -> list[Frame]:
    pano = panorama()
    frames = []
    for i in range(FRAMES):
        x = place_of(i)
        frames.append(
            Frame(index=i, name=f"{i:04d}.png", timestamp=float(i), image=pano[20:260, x : x + 320].copy())
        )
    return frames


def ground_truth() -> np.ndarray:
    gt = np.zeros((FRAMES, FRAMES), bool)
    for i in range(REVISIT_FROM, FRAMES):
        for j in range(REVISIT_FROM):
            gt[i, j] = abs(place_of(i) - place_of(j)) <= 60
    return gt


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return make_frames()


def fast(name: str) -> object:
    return preset(name, {"query": {"exclude_recent": 10, "temporal_k": 2}, "features": {"n_features": 400}})


def test_islands_group_nearby_ids() -> None:
    islands = compute_islands(np.array([10, 3, 11, 30, 4, 13]), np.array([0.5, 0.2, 0.9, 0.4, 0.1, 0.3]), 2)
    assert [(i.first, i.last, i.best) for i in islands] == [(3, 4, 3), (10, 13, 11), (30, 30, 30)]
    assert islands[1].score == pytest.approx(1.7) and islands[1].best_score == pytest.approx(0.9)
    assert compute_islands(np.zeros(0, int), np.zeros(0), 3) == []


def test_revisit_is_detected_and_nothing_else(frames: list[Frame]) -> None:
    det = LoopDetector(fast("bow"))  # type: ignore[arg-type]
    decisions = [det.process(f) for f in frames]
    gt = ground_truth()
    loops = [d for d in decisions if d.accepted]
    assert len(loops) >= 8
    for d in loops:
        assert d.frame_index >= REVISIT_FROM and gt[d.frame_index, d.candidate_frame]
        assert d.verification is not None and d.verification.accepted
    assert decisions[0].status == Status.CLOSE_MATCHES_ONLY
    assert all(set(d.timings) >= {"extract", "transform", "query", "add", "total"} for d in decisions)


def test_same_frames_same_decisions(frames: list[Frame]) -> None:
    def statuses() -> list[tuple[str, int, float]]:
        det = LoopDetector(fast("bow"))  # type: ignore[arg-type]
        return [(d.status.value, d.candidate, round(d.score, 9)) for d in map(det.process, frames)]

    assert statuses() == statuses()


def test_killed_and_reopened_detector_continues(frames: list[Frame], tmp_path: Path) -> None:
    cfg = fast("bow")
    whole = LoopDetector(cfg)  # type: ignore[arg-type]
    expected = [(d.status, d.candidate, d.score) for d in map(whole.process, frames)]
    db = tmp_path / "map.sqlite"
    first = LoopDetector(cfg, database=db)  # type: ignore[arg-type]
    got = [(d.status, d.candidate, d.score) for d in map(first.process, frames[:47])]
    del first  # no close(): as if the process died here
    second = LoopDetector(cfg, database=db)  # type: ignore[arg-type]
    assert len(second) == 47
    got += [(d.status, d.candidate, d.score) for d in map(second.process, frames[47:])]
    assert [g[:2] for g in got] == [e[:2] for e in expected]
    assert all(
        math.isclose(g[2], e[2], rel_tol=1e-6, abs_tol=1e-9) for g, e in zip(got, expected, strict=True)
    )


def test_unknown_preset_and_setting() -> None:
    with pytest.raises(ConfigError, match="unknown preset"):
        preset("nope")
    with pytest.raises(ConfigError, match="unknown setting"):
        preset("bow", {"query": {"alpah": 0.1}})
    for bad in ({"viewpoint_steps": -1}, {"viewpoint_inliers": 1.5}, {"viewpoint_margin": -0.1}):
        with pytest.raises(ConfigError, match="viewpoint"):
            preset("default", {"query": bad})
    assert preset("default").query.viewpoint_steps == 3
    assert preset("paper").query.viewpoint_steps == 0 and preset("bow").query.viewpoint_steps == 0


def test_cli_run_and_eval_end_to_end(
    frames: list[Frame], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "seq"
    (folder / "images").mkdir(parents=True)
    for f in frames:
        cv2.imwrite(str(folder / "images" / f.name), f.image)
    np.save(folder / "loops.npy", ground_truth())
    out = tmp_path / "run"
    assert (
        main(
            [
                "run",
                str(folder),
                "--format",
                "folder",
                "--preset",
                "bow",
                "--out",
                str(out),
                "--no-progress",
                "--set",
                "query.exclude_recent=10",
                "--set",
                "query.temporal_k=2",
                "--set",
                "features.n_features=400",
            ]
        )
        == 0
    )
    assert (out / "decisions.csv").exists() and (out / "similarity.npy").exists()
    assert (
        main(
            [
                "eval",
                str(out),
                "--gt",
                str(folder / "loops.npy"),
                "--protocol",
                "tolerance",
                "--tolerance",
                "1",
                "--json",
                str(tmp_path / "e.json"),
            ]
        )
        == 0
    )
    import json

    result = json.loads((tmp_path / "e.json").read_text())
    assert result["fp"] == 0 and result["tp"] >= 8 and result["recall_at_100p"] > 0.4
    sim = np.load(out / "similarity.npy")
    assert sim.shape == (FRAMES, FRAMES) and np.allclose(np.triu(sim), 0)


def test_run_refuses_to_delete_a_named_database(frames: list[Frame], tmp_path: Path) -> None:
    from stablecues.detection.run import run_dataset
    from stablecues.errors import DatasetError

    db = tmp_path / "precious.sqlite"
    db.write_bytes(b"keep me")
    with pytest.raises(DatasetError, match="exists"):
        run_dataset(frames[:3], fast("bow"), tmp_path / "run", database=db, progress=False)  # type: ignore[arg-type]
    assert db.read_bytes() == b"keep me"


def test_map_points_without_calibration_are_verified(frames: list[Frame]) -> None:
    """A SLAM system hands in its own features and map points, no calibration: every frame gets
    a decision (query and stored points share one noise model)."""
    import dataclasses

    from stablecues.features import OrbConfig, OrbExtractor

    ex = OrbExtractor(OrbConfig(n_features=400))
    det = LoopDetector(fast("triangles-only"))  # type: ignore[arg-type]
    decisions = []
    for f in frames:
        feats = ex.extract(f.image)
        # a fronto-parallel wall 4 m away, seen from the frame's x offset: consistent across visits
        x = (feats.keypoints[:, 0] - 160 + place_of(f.index)) / 80.0
        y = (feats.keypoints[:, 1] - 120) / 80.0
        pts = np.stack([x - place_of(f.index) / 80.0, y, np.full_like(x, 4.0)], axis=1).astype(np.float32)
        decisions.append(det.process(dataclasses.replace(f, points3d=pts), features=feats))
    assert len(decisions) == FRAMES
    checked = [d for d in decisions if d.verification is not None]
    assert checked and all(d.verification.method.value == "triangles" for d in checked)
    assert any(d.accepted for d in checked)


def test_a_true_loop_in_the_second_island_is_found() -> None:
    """CamVid revisit frame 144 (second traversal, changed appearance): the best BoW island is a
    wrong place; the second holds the true loop (frame 3). DLoopDetector verifies only the best
    and rejects; verifying the best islands finds it, by the most geometric inliers."""
    from conftest import shared_path
    from stablecues.datasets import open_dataset

    ds = open_dataset(shared_path("camvid_revisit_dev", "train_drives", "frames"), format="folder")
    decisions = {}
    for k in (1, 5):
        over = {"query": {"islands_verified": k, "refine": 0, "viewpoint_steps": 0}, "similarity": False}
        det = LoopDetector(preset("fast", over))  # the islands, without the network
        for i in range(144):
            det.store(ds[i])
        decisions[k] = det.process(ds[144])
    one, five = decisions[1], decisions[5]
    assert not one.accepted and len(one.checked) == 1 and one.candidate_frame != 3
    assert five.accepted and five.candidate_frame == 3 and len(five.checked) == 5
    assert five.verification is not None
    assert five.verification.n_inliers == max(c.verification.n_inliers for c in five.checked)
    extras = five.extras()
    assert extras["checked"][0][0] == five.islands[0][2]  # best island first
    assert [c[0] for c in extras["checked"]] == [i[2] for i in five.islands[:5]]
    assert any(f == 3 for f, _ in five.results) and extras["verifier"] == "fundamental"


def test_monocular_stream_triangulates_and_resumes(tmp_path: Path) -> None:
    """A monocular drive (no calibration: the focal is guessed from the image size) gets 3D from
    its neighbouring frames; a detector reopened on its map continues exactly as one that never
    stopped, because the map's latest entries become the next frame's neighbours."""
    from stablecues.synthetic import SyntheticTown, SyntheticTownConfig

    town = SyntheticTown(SyntheticTownConfig(frames=36, width=256, height=192, loops=1, seed=1, noise=1.0))
    stream = [Frame(index=f.index, name=str(f.index), timestamp=float(f.index), image=f.image)
              for f in (town.frame(i, right=False, depth=False, labels=False) for i in range(36))]
    cfg = preset("mono-triangles", {"similarity": False, "query": {"exclude_recent": 5},
                                    "weighting": None, "masking": None})
    det = LoopDetector(cfg)
    whole = [det.process(f) for f in stream]
    sources = {d.points_source for d in whole}
    assert "mono-guessed-focal" in sources
    assert all(d.extras()["points"] == d.points_source for d in whole)
    stored = [det.db.entry(k).meta for k in range(len(det))]
    assert any(m.get("points") == "mono-guessed-focal" and "sigma_depth" in m for m in stored)
    db = tmp_path / "map.sqlite"
    first = LoopDetector(cfg, database=db)
    got = [first.process(f) for f in stream[:20]]
    first.close()
    second = LoopDetector(cfg, database=db)
    got += [second.process(f) for f in stream[20:]]
    assert [(d.status, d.candidate_frame, d.points_source) for d in got] == [
        (d.status, d.candidate_frame, d.points_source) for d in whole
    ]


def test_the_accepted_loop_walks_to_the_nearest_viewpoint() -> None:
    """Corridor query 65 (frame 176): without the walk the accepted loop is reference 68 (30
    inliers), outside the ground truth's 63-67, where the scene looks 0.20 (log) smaller; the walk
    steps to reference 67, inside the ground truth, whose scale is nearer the query's, and the loop
    keeps the support of 30 inliers.

    Query 64 (frame 175), used before, hangs on a retrieval tie (references 68 and 64 within 0.0002
    of each other) that the int8 segmentation network breaks differently by CPU: onnxruntime's
    u8s8 kernels saturate on x86 CPUs with AVX2 but without VNNI. Query 65 gives the same loop, the
    same inliers and the same scale changes with either kernel; the properties of the walk are
    asserted, the frames only as the ground truth bounds them."""
    from conftest import shared_path
    from stablecues.datasets import open_dataset

    folder = shared_path("corridor")
    ds = open_dataset(folder, format="vprbench")
    truth = {int(row[0]): {int(r) for r in row[1]} for row in np.load(folder / "ground_truth_new.npy",
                                                                        allow_pickle=True)}[65]
    assert truth == {63, 64, 65, 66, 67}
    decisions = {}
    for steps in (0, 3):
        cfg = preset("default", {"query": {"viewpoint_steps": steps}, "similarity": False})
        det = LoopDetector(cfg)
        for i in range(176):
            det.store(ds[i])
        decisions[steps] = det.process(ds[176])
    q = cfg.query
    still, walked = decisions[0], decisions[3]
    assert still.accepted and walked.accepted
    assert still.verification is not None and walked.verification is not None
    # without the walk: a near miss seen from further along the corridor, far enough off to walk
    assert still.candidate_frame not in truth and abs(still.candidate_frame - 65) <= 3
    assert abs(still.verification.scale_change) > q.viewpoint_scale
    # the walk: at most viewpoint_steps entries along the map, into the ground truth, to a nearer scale
    assert walked.candidate_frame in truth and walked.candidate_frame != still.candidate_frame
    assert abs(walked.candidate_frame - still.candidate_frame) <= q.viewpoint_steps
    assert abs(walked.verification.scale_change) < abs(still.verification.scale_change) - 0.05
    # an accepted step with fewer inliers than the place's support, which the loop keeps
    assert walked.verification.n_inliers >= q.viewpoint_inliers * still.verification.n_inliers
    assert walked.verification.n_inliers < still.verification.n_inliers
    assert int(walked.confidence) == still.verification.n_inliers
    # as measured with either kernel: 68 (30 inliers, scale change -0.204) -> 67 (29, -0.073)
    assert walked.candidate_frame in [c[0] for c in walked.extras()["checked"]]


def test_removed_entries_are_never_verified(frames: list[Frame]) -> None:
    """Entries removed from the map (``Database.remove``) are neither proposed nor verified as
    an island's neighbours (``query.refine``) or on the walk to the nearest viewpoint: the
    revisit goes on without an error, and no removed entry is named."""
    over = {"query": {"exclude_recent": 10, "refine": 3, "viewpoint_steps": 3, "viewpoint_scale": 0.0,
                      "viewpoint_margin": 0.0, "viewpoint_inliers": 0.0},
            "features": {"n_features": 400}, "similarity": False}
    det = LoopDetector(preset("fast", over))
    for f in frames[:REVISIT_FROM]:
        det.store(f)
    gone = {5, 7, 9, 11}
    assert det.db.remove(sorted(gone)) == len(gone)
    decisions = [det.process(f) for f in frames[REVISIT_FROM:]]
    assert any(d.accepted for d in decisions)
    for d in decisions:
        assert d.candidate_frame not in gone
        assert not gone & {c.frame for c in d.checked}


def test_a_map_whose_newest_entries_were_removed_reopens(frames: list[Frame], tmp_path: Path) -> None:
    """A map file whose newest entries were removed (``remove(after=...)``) reopens in a
    detector, which continues from the newest entry still there, with monocular neighbours
    too; it once failed on the removed entries' empty meta."""
    path = tmp_path / "map.sqlite"
    over = {"features": {"n_features": 300}, "similarity": False, "monocular": {}}
    with LoopDetector(preset("fast", over), database=path) as det:
        for f in frames[:15]:
            det.store(f)
        assert det.db.remove(after=12.0) == 3
    with LoopDetector(preset("fast", over), database=path) as det:
        assert len(det) == 15
        assert det._prev_bow is not None and det._prev_bow == det.db.entry(11).bow
        d = det.process(frames[15])
        assert d.entry_id == 15 and d.candidate_frame not in (12, 13, 14)

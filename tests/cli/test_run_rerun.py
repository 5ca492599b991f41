"""``stablecues run --rerun FILE.rrd``: the recording, read back with Rerun's own reader, holds
what the run decided (issue 14.2).

The sequence is a short synthetic town drive (poses, label images, loops), run with the
``dynamic`` mask taking its classes from the label images, so keypoints carry class ids, loops
are accepted and the trajectory is known.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from stablecues.cli.main import main
from stablecues.runs import load_run

pytest.importorskip("rerun")

FRAMES = 40
OPTIONS = [
    "--preset", "dynamic", "--set", 'semantic_source="labels"', "--set", "query.exclude_recent=5",
    "--set", "query.temporal_k=1", "--no-progress", "--pictures", "0",
]  # fmt: skip


def read_rrd(path: Path) -> dict[str, dict[str, list[Any]]]:
    """entity path -> column -> values, rows in frame order, through ``rerun.chunk.RrdReader``."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        columns = {}
        for name, column in zip(batch.schema.names, batch.columns, strict=True):
            if pa.types.is_temporal(column.type):  # timelines as integer nanoseconds
                column = column.cast(pa.int64())
            columns[name] = column
        rows[chunk.entity_path] += pa.table(columns).to_pylist()
    out: dict[str, dict[str, list[Any]]] = {}
    for entity, items in rows.items():
        items.sort(key=lambda r: r.get("frame") or 0)
        out[entity] = {name: [r[name] for r in items] for name in items[0]}
    return out


def single(values: list[Any]) -> list[Any]:
    """The one instance each row holds (scalars, blobs, any-values)."""
    assert all(len(v) == 1 for v in values)
    return [v[0] for v in values]


def decode(blob: list[int]) -> np.ndarray:
    """A logged JPEG image, decoded (BGR)."""
    image = cv2.imdecode(np.frombuffer(bytes(blob), np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image


@pytest.fixture(scope="module")
def town(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("town") / "town"
    argv = ["synth", "--out", str(root), "--frames", str(FRAMES), "--width", "320", "--height", "240",
            "--loops", "1", "--seed", "1", "-q"]
    assert main(argv) == 0
    return root


@pytest.fixture(scope="module")
def recorded(town: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("rec")
    rrd = tmp / "run.rrd"
    assert main(["run", str(town), "--out", str(tmp / "run"), *OPTIONS, "--rerun", str(rrd)]) == 0
    return tmp / "run", read_rrd(rrd)


def test_every_frame_is_logged_on_both_timelines(town: Path, recorded: tuple[Path, dict[str, Any]]) -> None:
    out, rec = recorded
    run = load_run(out)
    assert len(run) == FRAMES
    expected = {
        "/camera", "/camera/image", "/camera/image/keypoints", "/scores/top", "/detection/decisions",
        "/loops/accepted", "/loops/pair", "/loops/pair/matches", "/world/camera", "/world/trajectory/0000",
        "/world/loops/0000", "/timing/extract", "/timing/query", "/timing/total",
    }
    assert expected <= set(rec), expected - set(rec)
    image = rec["/camera/image"]
    assert image["frame"] == list(range(FRAMES))
    # the time timeline holds the frames' stamps (synthetic stamps are seconds of a day: durations)
    np.testing.assert_allclose(np.array(image["time"]) * 1e-9, run.timestamps, atol=1e-6)
    first = decode(single(image["EncodedImage:blob"])[0])
    assert first.shape == (240, 320, 3)
    assert len(rec["/scores/top"]["frame"]) == FRAMES
    assert len(rec["/detection/decisions"]["frame"]) == FRAMES
    assert rec["/timing/extract"]["frame"] == list(range(FRAMES))


def test_keypoints_are_the_kept_ones_with_their_classes(
    town: Path, recorded: tuple[Path, dict[str, Any]]
) -> None:
    out, rec = recorded
    extra = load_run(out).extra()
    kp = rec["/camera/image/keypoints"]
    assert kp["frame"] == list(range(FRAMES))
    for k in range(FRAMES):
        assert len(kp["Points2D:positions"][k]) == extra[k]["n_kept"], k
    # classes: the label image's class under each keypoint
    for k, path in enumerate(sorted((town / "labels").iterdir())):
        labels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        xy = np.rint(np.array(kp["Points2D:positions"][k]).reshape(-1, 2)).astype(int)
        ids = np.array(kp["Points2D:class_ids"][k], int)
        under = labels[xy[:, 1].clip(0, 239), xy[:, 0].clip(0, 319)]
        np.testing.assert_array_equal(ids, under, err_msg=str(k))
    context = single(rec["/camera"]["AnnotationContext:context"])[0]
    names = [c["class_description"]["info"]["label"] for c in context]
    assert names[8:] == ["Car", "Pedestrian", "Bicyclist", "Unlabelled"]


def test_accepted_loops_with_matches_and_edges(recorded: tuple[Path, dict[str, Any]]) -> None:
    out, rec = recorded
    run = load_run(out)
    extra = run.extra()
    accepted = [int(f) for f in run.frames[run.accepted]]
    assert accepted, "the town drive should close loops"
    loops = rec["/loops/accepted"]
    assert loops["frame"] == accepted == single(loops["query_frame"])
    assert single(loops["candidate_frame"]) == [int(c) for c in run.candidates[run.accepted]]
    inliers = single(loops["inliers"])
    assert inliers == [extra[f]["inliers"] for f in accepted]
    # the pair picture: query and candidate side by side, one line per inlier match
    pair = rec["/loops/pair"]
    assert pair["frame"] == accepted
    image = decode(single(pair["EncodedImage:blob"])[0])
    assert image.shape == (240, 640, 3)
    strips = rec["/loops/pair/matches"]["LineStrips2D:strips"]
    assert [len(s) for s in strips] == inliers
    assert all(len(line) == 2 and line[0][0] < 320 <= line[1][0] for s in strips for line in s)
    # edges on the trajectory: the last logging holds one edge per accepted loop, between the poses
    edges = rec["/world/loops/0000"]["LineStrips3D:strips"][-1]
    assert len(edges) == len(accepted)
    track = rec["/world/trajectory/0000"]["LineStrips3D:strips"]
    assert len(track[-1][0]) == FRAMES
    positions = np.array(track[-1][0])
    for edge, f, c in zip(edges, single(loops["query_frame"]), single(loops["candidate_frame"]), strict=True):
        np.testing.assert_allclose(edge, [positions[f], positions[c]], rtol=1e-6)


def test_stage_times_are_the_runs(recorded: tuple[Path, dict[str, Any]]) -> None:
    out, rec = recorded
    run = load_run(out)
    for stage in ("extract", "query", "transform"):
        logged = np.array(single(rec[f"/timing/{stage}"]["Scalars:scalars"]))
        np.testing.assert_allclose(logged, run.stage_ms[stage], rtol=1e-3, atol=1e-3, err_msg=stage)


def test_rerun_spawn_without_a_display_is_one_line(
    town: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    out = tmp_path / "run"
    assert main(["run", str(town), "--out", str(out), *OPTIONS, "--rerun-spawn"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("stablecues run: error: ")
    assert ("needs a display" in err) or ("no Rerun viewer found" in err)
    assert not out.exists()  # refused before the run started


def test_rerun_spawn_without_a_viewer_is_one_line(
    town: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))  # no `rerun` executable on PATH
    monkeypatch.setitem(__import__("sys").modules, "rerun_cli", None)  # nor a bundled one
    assert main(["run", str(town), "--out", str(tmp_path / "run"), *OPTIONS, "--rerun-spawn"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "no Rerun viewer found" in err and 'pip install "stablecues[rerun]"' in err


def test_rerun_file_in_a_missing_folder_is_one_line(
    town: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rrd = tmp_path / "nowhere" / "run.rrd"
    assert main(["run", str(town), "--out", str(tmp_path / "run"), *OPTIONS, "--rerun", str(rrd)]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "does not exist" in err

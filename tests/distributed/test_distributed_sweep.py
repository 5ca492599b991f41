"""stablecues sweep: a grid of datasets x presets x overrides as tasks of a real LocalCluster
(two worker processes) gives the serial sweep's decisions and metrics exactly, writes the run
folders and one merged table, and turns bad input into rows or one-line errors."""

from __future__ import annotations

import csv
import json
import os
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from stablecues.cli.main import main
from stablecues.distributed import (
    VOLATILE_COLUMNS,
    ClusterError,
    SweepDataset,
    SweepOptions,
    open_client,
    plan_sweep,
    read_table,
    run_sweep,
    worker_addresses,
)
from stablecues.distributed.sweep import override_tag
from stablecues.errors import ConfigError, DatasetError
from stablecues.runs import load_run
from stablecues.synthetic import SyntheticTownConfig, write_sequence

pytest.importorskip("distributed")

TIMEOUT_S = 240.0  # a sweep that does not finish by then is a failure, not a hang


@pytest.fixture(scope="module")
def sequences(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two small synthetic drives (loops.npy ground truth beside the images); the first
    revisits streets from frame 20 on, and the detector accepts loops there."""
    root = tmp_path_factory.mktemp("sweep_data")
    out = []
    for seed, name, frames, width in ((0, "town_a", 40, 256), (5, "town_b", 12, 192)):
        cfg = SyntheticTownConfig(frames=frames, width=width, height=width * 3 // 4, loops=1, seed=seed)
        out.append(write_sequence(cfg, root / name, progress=False, right=False, labels=False))
    return out


@pytest.fixture(scope="module")
def client():  # type: ignore[no-untyped-def]
    with open_client(workers=2, threads_per_worker=1) as c:
        worker_addresses(c, least=2)
        yield c


def _grid(sequences: list[Path], overrides: tuple = ({},)) -> list:  # type: ignore[type-arg]
    datasets = [SweepDataset(p) for p in sequences]
    return plan_sweep(datasets, ["bow", "fast"], overrides)


def _decisions(run_dir: Path) -> dict[str, np.ndarray]:
    run = load_run(run_dir)
    return {"frames": run.frames, "status": run.status.astype(str), "candidates": run.candidates,
            "scores": run.scores, "raw_scores": run.raw_scores, "accepted": run.accepted}


def _stable(row: dict) -> dict:  # type: ignore[type-arg]
    return {k: v for k, v in row.items() if k not in VOLATILE_COLUMNS and k != "run"}


def test_cluster_sweep_equals_serial_sweep(sequences: list[Path], client, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    tasks = _grid(sequences)
    assert len(tasks) == 4
    options = SweepOptions(max_frames=30)
    serial = run_sweep(tasks, tmp_path / "serial", options)
    dist = run_sweep(tasks, tmp_path / "dask", options, client=client, timeout_s=TIMEOUT_S)
    assert serial.engine == "serial" and dist.engine.startswith("tcp://")
    assert not serial.failures and not dist.failures

    # same rows, in the grid's order, whichever worker ran them
    assert [Path(r["run"]).name for r in dist.rows] == [t.folder for t in tasks]
    assert [_stable(r) for r in dist.rows] == [_stable(r) for r in serial.rows]
    assert any(r["loops"] > 0 for r in serial.rows)  # the comparison covers accepted loops
    assert all(r["protocol"] == "exact" for r in dist.rows) and dist.rows[0]["positives"] > 0
    # ran in the two worker processes, not here
    pids = {r["worker"].rsplit(":", 1)[1] for r in dist.rows}
    assert len(pids) == 2 and str(os.getpid()) not in pids

    for t in tasks:
        a, b = _decisions(tmp_path / "serial" / t.folder), _decisions(tmp_path / "dask" / t.folder)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"{t.folder}: {key}")
        ea = json.loads((tmp_path / "serial" / t.folder / "eval_exact.json").read_text())
        eb = json.loads((tmp_path / "dask" / t.folder / "eval_exact.json").read_text())
        for key in ("tp", "fp", "fn", "recall_at_100p", "auc", "pr_curve", "gt_sha256"):
            assert ea[key] == eb[key], f"{t.folder}: {key}"
        meta = load_run(tmp_path / "dask" / t.folder).meta
        assert meta["preset"] == t.preset and meta["sweep_task"] == t.folder

    # the merged table, as CSV and JSON
    assert read_table(tmp_path / "dask") == dist.rows
    with dist.csv_path.open(newline="") as fh:
        table = list(csv.DictReader(fh))
    assert [r["run"] for r in table] == [r["run"] for r in dist.rows]
    assert [int(r["tp"]) for r in table] == [r["tp"] for r in dist.rows]
    assert json.loads(table[0]["statuses"]) == dist.rows[0]["statuses"]


def test_run_folders_are_named_by_dataset_preset_and_overrides(sequences: list[Path]) -> None:
    tasks = _grid(sequences, ({}, {"query": {"alpha": 0.35}}))
    tag = override_tag({"query": {"alpha": 0.35}})
    assert len(tag) == 8 and tag == override_tag({"query": {"alpha": 0.35}})
    assert [t.folder for t in tasks[:4]] == ["town_a__bow", f"town_a__bow__{tag}", "town_a__fast",
                                             f"town_a__fast__{tag}"]


def test_cli_sweep_on_a_running_scheduler(sequences: list[Path], client, tmp_path: Path,  # type: ignore[no-untyped-def]
                                          capsys: pytest.CaptureFixture[str]) -> None:
    address = client.scheduler_info()["address"]
    out = tmp_path / "cli"
    argv = ["sweep", f"a={sequences[0]}", f"b={sequences[1]}", "--preset", "bow", "--vary",
            "query.temporal_k=[1,2]", "--max-frames", "10", "--scheduler", address, "--out", str(out),
            "--timeout", str(TIMEOUT_S)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert f"4 tasks on {address}" in text and "[4/4]" in text
    rows = read_table(out)
    assert [r["dataset"] for r in rows] == ["a", "a", "b", "b"]
    assert all(r["frames"] == 10 and r["error"] is None for r in rows)
    assert {json.loads(r["overrides"])["query"]["temporal_k"] for r in rows} == {1, 2}

    # the same again: refused before anything runs; --resume re-evaluates the complete runs
    assert main(argv) == 1
    assert "exists and is not empty" in capsys.readouterr().err
    before = (out / rows[0]["run"].rsplit("/", 1)[1] / "decisions.csv").read_bytes()
    assert main([*argv, "--resume"]) == 0
    again = read_table(out)
    assert [_stable(r) for r in again] == [_stable(r) for r in rows]
    assert (out / rows[0]["run"].rsplit("/", 1)[1] / "decisions.csv").read_bytes() == before


def test_a_bad_dataset_fails_its_own_row_only(sequences: list[Path], client, tmp_path: Path,  # type: ignore[no-untyped-def]
                                              capsys: pytest.CaptureFixture[str]) -> None:
    address = client.scheduler_info()["address"]
    corrupt = tmp_path / "corrupt"
    (corrupt / "images").mkdir(parents=True)
    (corrupt / "images" / "000000.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    argv = ["sweep", str(sequences[0]), str(tmp_path / "missing"), str(corrupt), "--preset", "bow",
            "--max-frames", "6", "--scheduler", address, "--out", str(tmp_path / "out")]
    assert main(argv) == 1
    captured = capsys.readouterr()
    assert "2 of 3 tasks failed" in captured.err and "Traceback" not in captured.err + captured.out
    rows = read_table(tmp_path / "out")
    assert rows[0]["error"] is None and rows[0]["frames"] == 6
    assert "missing" in rows[1]["error"] and rows[1]["error"].startswith("DatasetError")
    assert "corrupt" in rows[2]["error"] and "\n" not in rows[2]["error"]


def test_serial_cli_and_bad_grids(sequences: list[Path], tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sweep", str(sequences[0]), "--preset", "bow", "--serial", "--max-frames", "5",
                 "--out", str(tmp_path / "s")]) == 0
    assert "1 tasks, serially" in capsys.readouterr().out
    bad = [
        (["--vary", "query.alpha=0.2"], "JSON list"),
        (["--vary", "query.alpha=[]"], "JSON list"),
        (["--set", "query.nonsense=1"], "nonsense"),
        (["--gt", "nobody=x.npy"], "NAME=FILE"),
        (["--workers", "0"], "at least one worker"),
        (["--timeout", "nan"], "--timeout: expected a positive number of seconds, got nan"),
        (["--timeout", "-1"], "--timeout: expected a positive number of seconds, got -1.0"),
    ]
    for extra, words in bad:
        assert main(["sweep", str(sequences[0]), "--out", str(tmp_path / "x"), *extra]) == 1
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, (extra, err)


def test_plan_sweep_checks_the_grid(sequences: list[Path]) -> None:
    a = SweepDataset(sequences[0])
    with pytest.raises(ConfigError, match="named 'town_a'"):
        plan_sweep([a, SweepDataset(sequences[0])], ["bow"])
    with pytest.raises(ConfigError, match="twice"):
        plan_sweep([a], ["bow", "bow"])
    with pytest.raises(ConfigError):
        plan_sweep([a], ["no-such-preset"])
    with pytest.raises(ConfigError, match="at least one"):
        plan_sweep([], ["bow"])
    with pytest.raises(ConfigError, match="run folder"):
        SweepDataset(sequences[0], name="a__b")
    with pytest.raises(ConfigError, match="tolerance"):
        SweepOptions(protocol="tolerance")


def test_tolerance_protocol_and_explicit_ground_truth(sequences: list[Path], tmp_path: Path) -> None:
    ds = SweepDataset(sequences[0], name="t", ground_truth=sequences[0] / "loops.npy")
    result = run_sweep(plan_sweep([ds], ["bow"]), tmp_path, SweepOptions(protocol="tolerance", tolerance=2,
                                                                         max_frames=12))
    (row,) = result.rows
    assert row["protocol"] == "tolerance" and row["tolerance"] == 2 and row["gt_file"].endswith("loops.npy")
    assert (tmp_path / "t__bow" / "eval_tolerance_2.json").is_file()
    with pytest.raises(DatasetError, match="not a folder"):
        run_sweep(plan_sweep([ds], ["bow"]), tmp_path / "sweep.csv")


def test_an_unreachable_scheduler_is_one_error() -> None:
    with pytest.raises(ClusterError, match="cannot reach the scheduler at tcp://127.0.0.1:1"), \
            open_client("tcp://127.0.0.1:1", timeout_s=1):
        pass


def _fake_service(reply: bytes | None) -> int:
    """A TCP service on 127.0.0.1 that is not Dask: it sends ``reply`` (or nothing) and holds the
    connection open."""
    srv = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []

    def serve() -> None:
        while True:
            conn, _ = srv.accept()
            held.append(conn)
            if reply:
                conn.sendall(reply)

    threading.Thread(target=serve, daemon=True).start()
    return int(srv.getsockname()[1])


@pytest.mark.parametrize("reply", [None, b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n"])
def test_a_service_that_is_not_dask_is_one_line_within_the_timeout(
    reply: bytes | None, sequences: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A silent service let the client wait past --timeout, an HTTP one was read as a frame
    length of exabytes (a traceback): both are one line, within the timeout (issue 34)."""
    port = _fake_service(reply)
    t = time.monotonic()
    assert main(["sweep", str(sequences[0]), "--out", str(tmp_path / "s"), "--preset", "bow",
                 "--scheduler", f"tcp://127.0.0.1:{port}", "--timeout", "2"]) == 1
    assert time.monotonic() - t < 10
    err = capsys.readouterr().err.strip()
    want = "no Dask scheduler answered within 2 s" if reply is None else "not as a Dask scheduler"
    assert err.count("\n") == 0 and want in err and f"127.0.0.1:{port}" in err, err

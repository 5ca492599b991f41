"""The node as a ROS 2 graph sees it (issue 36): a replay publisher, the node and a subscriber,
three real processes talking DDS on the loopback interface only (the shipped Cyclone DDS
configuration: interface ``lo``, multicast off, peer 127.0.0.1)."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cyclonedds", reason="the ros2 extra (cyclonedds) is not installed")

from rosdds import dds_env, decisions, stablecues, start, stop, synthetic_bag, wait_for_lines  # noqa: E402

from conftest import shared_path  # noqa: E402
from stablecues.cli.main import main  # noqa: E402
from stablecues.ros2 import messages as m  # noqa: E402
from stablecues.runs import load_run  # noqa: E402

#: a domain per session, so that sessions never hear one another (nor other tests' processes)
_DOMAINS = itertools.count(60 + (os.getpid() % 20) * 8)
SETTINGS = ("--preset", "fast", "--set", "query.exclude_recent=4")


@pytest.fixture(scope="module")
def synbag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthetic_bag(tmp_path_factory.mktemp("ros2") / "town")


@pytest.fixture(scope="module")
def eurocbag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A stereo ROS 2 bag of the EuRoC V1_01 micro sequence as PNG CompressedImage messages,
    CameraInfo of both cameras beside."""
    from stablecues.geometry import load_calibration
    from stablecues.imageio import read_image
    from stablecues.ros2.bagwrite import write_image_bag

    mav0 = shared_path("euroc", "V1_01_micro", "mav0")
    rows = [ln.split(",") for ln in (mav0 / "cam0" / "data.csv").read_text().splitlines()[1:] if ln.strip()]
    stamps = [int(s) for s, _ in rows]
    left = [read_image(mav0 / "cam0" / "data" / n.strip(), "8bit") for _, n in rows]
    right = [read_image(mav0 / "cam1" / "data" / n.strip(), "8bit") for _, n in rows]
    calib = load_calibration(mav0 / "cam0" / "sensor.yaml")
    return write_image_bag(
        tmp_path_factory.mktemp("ros2") / "v101", stamps, left, right, calibration=calib, compressed="png"
    )


def reference(bag: Path, out: Path) -> Any:
    """``stablecues run`` over the bag, with the node's settings."""
    assert main(["run", str(bag), *SETTINGS, "--out", str(out), "--no-progress", "--pictures", "0"]) == 0
    return load_run(out)


@dataclass
class Session:
    decisions: list[dict[str, Any]]
    summary: dict[str, Any]
    log: str
    raw: list[bytes]


@dataclass
class Processes:
    node: subprocess.Popen[bytes]
    echo: subprocess.Popen[bytes]
    env: dict[str, str]
    tmp: Path


def launch(tmp: Path, name: str, node_args: list[str], expect: int) -> Processes:
    """The subscriber, then the node (queueing every frame, reliable camera QoS)."""
    env = dds_env(next(_DOMAINS))
    echo = start(
        stablecues(
            "ros2", "echo", "--count", str(expect), "--timeout", "40", "--raw", str(tmp / f"{name}.raw")
        ),
        env,
        tmp / f"{name}.echo",
    )
    node = start(
        stablecues(
            "ros2",
            *SETTINGS,
            "--qos",
            "reliable",
            "--no-skip",
            "--exit-after-idle",
            "4",
            "--summary",
            str(tmp / f"{name}.summary.json"),
            *node_args,
        ),
        env,
        tmp / f"{name}.node.log",
    )
    return Processes(node, echo, env, tmp)


def play(procs: Processes, bag: Path, *args: str) -> None:
    out = subprocess.run(
        stablecues(
            "ros2",
            "play",
            str(bag),
            "--qos",
            "reliable",
            "--rate",
            "3",
            "--wait-subscribers",
            "1",
            "--wait-timeout",
            "30",
            *args,
        ),
        env=procs.env,
        capture_output=True,
        text=True,
        timeout=90,
    )
    assert out.returncode == 0, out.stderr


def finish(procs: Processes, name: str, expect: int) -> Session:
    try:
        wait_for_lines(procs.tmp / f"{name}.echo", expect, 40, procs.echo)
        procs.node.wait(timeout=30)
        procs.echo.wait(timeout=30)
    finally:
        stop(procs.node, procs.echo)
    tmp = procs.tmp
    summary_path = tmp / f"{name}.summary.json"
    return Session(
        decisions(tmp / f"{name}.echo"),
        json.loads(summary_path.read_text()) if summary_path.exists() else {},
        (tmp / f"{name}.node.log").read_text(),
        [bytes.fromhex(ln) for ln in (tmp / f"{name}.raw").read_text().split()]
        if (tmp / f"{name}.raw").exists()
        else [],
    )


@pytest.fixture
def sessions() -> Iterator[list[Processes]]:
    """Processes started by a test, killed at its end whatever happens."""
    started: list[Processes] = []
    yield started
    for p in started:
        stop(p.node, p.echo)


def assert_same_decisions(got: list[dict[str, Any]], run: Any, first: int = 0) -> None:
    extra = run.extra()
    assert [d["query_index"] for d in got] == [int(f) for f in run.frames[first:]]
    for d, k in zip(got, range(first, len(run)), strict=True):
        assert (d["status"], d["candidate_index"], d["accepted"]) == (
            run.status[k],
            int(run.candidates[k]),
            bool(run.accepted[k]),
        ), k
        want = run.scores[k]
        assert (
            (d["score"] is None) if not np.isfinite(want) else d["score"] == pytest.approx(want, rel=1e-9)
        ), k
        assert d["inliers"] == int(extra[k].get("inliers") or 0), k


def assert_payloads_are_rosbags_bytes(raw: list[bytes]) -> None:
    """What the node sent is byte for byte rosbags' CDR of the message it carries (then DDS's
    0-3 padding bytes)."""
    assert raw
    for payload in raw:
        ours = m.encode(m.decode(payload, m.LOOP_CLOSURE), m.LOOP_CLOSURE)
        assert payload[: len(ours)] == ours and set(payload[len(ours) :]) <= {0} and len(payload) % 4 == 0


def test_decisions_over_dds_equal_stablecues_run_synthetic(
    synbag: Path, tmp_path: Path, sessions: list[Processes]
) -> None:
    """Needs no shared data: a synthetic mono drive with CameraInfo, frame for frame."""
    run = reference(synbag, tmp_path / "run")
    procs = launch(tmp_path, "s", ["--image", "/cam0/image_raw"], len(run))
    sessions.append(procs)
    play(procs, synbag)
    got = finish(procs, "s", len(run))
    assert_same_decisions(got.decisions, run)
    assert run.accepted.sum() > 0  # the comparison covers accepted loops
    assert got.summary["processed"] == len(run) and got.summary["skipped"] == 0
    assert_payloads_are_rosbags_bytes(got.raw)


def test_stereo_decisions_over_dds_equal_stablecues_run_euroc(
    eurocbag: Path, tmp_path: Path, sessions: list[Processes]
) -> None:
    """Real EuRoC stereo pairs (CompressedImage), matched by stamp, calibrated from both CameraInfo
    topics."""
    run = reference(eurocbag, tmp_path / "run")
    procs = launch(
        tmp_path,
        "e",
        ["--image", "/cam0/image_raw/compressed", "--right", "/cam1/image_raw/compressed"],
        len(run),
    )
    sessions.append(procs)
    play(procs, eurocbag)
    got = finish(procs, "e", len(run))
    assert_same_decisions(got.decisions, run)
    assert got.summary["unpaired"] == 0 and got.summary["processed"] == len(run)
    assert {d["verifier"] for d in got.decisions} - {""}  # the stereo geometry ran


def test_killed_node_restarted_continues_the_map(
    synbag: Path, tmp_path: Path, sessions: list[Processes]
) -> None:
    run = reference(synbag, tmp_path / "run")
    half = len(run) // 2
    map_file = tmp_path / "map.sqlite"
    first = launch(tmp_path, "k1", ["--image", "/cam0/image_raw", "--map", str(map_file)], half)
    sessions.append(first)
    play(first, synbag, "--frames", str(half))
    got = wait_for_lines(tmp_path / "k1.echo", half, 40, first.echo)
    assert len(got) == half
    first.node.send_signal(signal.SIGKILL)  # mid-stream, no goodbye
    first.node.wait(timeout=10)
    stop(first.echo)

    second = launch(tmp_path, "k2", ["--image", "/cam0/image_raw", "--map", str(map_file)], len(run) - half)
    sessions.append(second)
    play(second, synbag, "--start", str(half))
    got2 = finish(second, "k2", len(run) - half)
    assert [d["query_index"] for d in got2.decisions] == list(range(half, len(run)))
    assert got2.summary["first_index"] == half and got2.summary["map_frames"] == len(run)
    assert f"numbering on from frame {half}" in got2.log or got2.summary["first_index"] == half
    # the continued map decides the second half as one uninterrupted run does
    assert_same_decisions(got2.decisions, run, first=half)


def test_a_node_restarted_with_new_session_stores_its_frames_in_another_session(
    synbag: Path, tmp_path: Path, sessions: list[Processes]
) -> None:
    """A robot's second run on a kept map (``--new-session``): its frames go to session 1, the
    first run's stay in session 0, and the map says so after both nodes exit."""
    from stablecues.database import Database
    from stablecues.vocabulary import default_vocabulary

    run = reference(synbag, tmp_path / "run")
    half = len(run) // 2
    map_file = tmp_path / "map.sqlite"
    args = ["--image", "/cam0/image_raw", "--map", str(map_file), "--new-session"]
    first = launch(tmp_path, "s1", args, half)
    sessions.append(first)
    play(first, synbag, "--frames", str(half))
    got1 = finish(first, "s1", half)
    assert got1.summary["session"] == 0  # a new map: its first session
    second = launch(tmp_path, "s2", args, len(run) - half)
    sessions.append(second)
    play(second, synbag, "--start", str(half))
    got2 = finish(second, "s2", len(run) - half)
    assert got2.summary["session"] == 1 and got2.summary["map_frames"] == len(run)
    assert "session 1" in got2.log
    with Database(default_vocabulary(), map_file) as db:
        assert db.index.sessions().tolist() == [0] * half + [1] * (len(run) - half)


MALFORMED = r"""
import sys, time
import numpy as np
from stablecues.ros2 import dds, messages as m
from stablecues.ros2.bagwrite import _image_msg
T = dds.topic_type(m.IMAGE, "opaque")
w = dds.writer(dds.domain_id(), "/cam0/image_raw", m.IMAGE, "reliable", "opaque")
assert dds.wait_for_readers([w], 30)
img = np.tile(np.arange(64, dtype=np.uint8), (48, 1))
good = _image_msg(1_000_000_000, "cam0", img)
payload = m.encode(good, m.IMAGE)
bad_step = _image_msg(2_000_000_000, "cam0", img); bad_step.step = 100
bad_enc = _image_msg(3_000_000_000, "cam0", img); bad_enc.encoding = "weird16"
for p in (payload[:40], m.encode(bad_step, m.IMAGE), m.encode(bad_enc, m.IMAGE),
          m.encode(_image_msg(4_000_000_000, "cam0", img), m.IMAGE)):
    w.write(T(p)); time.sleep(0.2)
time.sleep(1.0)
"""


def test_malformed_messages_are_one_line_each_and_the_node_goes_on(
    tmp_path: Path, sessions: list[Processes]
) -> None:
    procs = launch(tmp_path, "bad", ["--image", "/cam0/image_raw", "--camera-info", "none"], 1)
    sessions.append(procs)
    out = subprocess.run(
        [sys.executable, "-c", MALFORMED], env=procs.env, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    got = finish(procs, "bad", 1)
    skipped = [ln for ln in got.log.splitlines() if "skipped a malformed" in ln]
    assert len(skipped) == 3, got.log
    assert "not a valid sensor_msgs/msg/Image" in skipped[0]
    assert "step" in skipped[1] and "weird16" in skipped[2]
    assert "Traceback" not in got.log
    assert got.summary["malformed"] == 3 and got.summary["processed"] == 1
    assert [d["query_index"] for d in got.decisions] == [0]


POSES = r"""
import sys, time
import numpy as np
from stablecues.ros2 import dds, messages as m
positions = np.load(sys.argv[1])
w = dds.writer(dds.domain_id(), "/robot/pose", m.POSE_STAMPED, "reliable", "opaque", depth=100)
assert dds.wait_for_readers([w], 30)
T = dds.topic_type(m.POSE_STAMPED, "opaque")
t = m.typestore().types
for k, p in enumerate(positions):
    pose = np.eye(4); pose[:3, 3] = p
    msg = t[m.POSE_STAMPED](header=m.header_msg(1_600_000_000_000_000_000 + k * 100_000_000, "map"),
                           pose=m.pose_msg(pose))
    w.write(T(m.encode(msg, m.POSE_STAMPED)))
time.sleep(1.0)
"""


def test_loop_edges_for_rviz_with_a_pose_topic(
    synbag: Path, tmp_path: Path, sessions: list[Processes], monkeypatch: pytest.MonkeyPatch
) -> None:
    """With a PoseStamped topic, each accepted loop adds a line from the query frame's position to
    the candidate's, in the poses' frame, to one LINE_LIST marker (RViz's MarkerArray)."""
    from stablecues.ros2 import dds

    run = reference(synbag, tmp_path / "run")
    procs = launch(tmp_path, "p", ["--image", "/cam0/image_raw", "--pose", "/robot/pose"], len(run))
    sessions.append(procs)
    monkeypatch.setenv("CYCLONEDDS_URI", procs.env["CYCLONEDDS_URI"])
    did = int(procs.env["ROS_DOMAIN_ID"])
    markers = dds.reader(did, "/stablecues/loop_markers", m.MARKER_ARRAY, "reliable", "exact", depth=100)
    positions = np.load(synbag.with_suffix(".positions.npy"))
    out = subprocess.run(
        [sys.executable, "-c", POSES, str(synbag.with_suffix(".positions.npy"))],
        env=procs.env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    play(procs, synbag)
    got = finish(procs, "p", len(run))
    arrays = [m.decode(s.payload, m.MARKER_ARRAY) for s in markers.take(100) if getattr(s, "payload", None)]
    loops = [(d["query_index"], d["candidate_index"]) for d in got.decisions if d["accepted"]]
    assert loops and len(arrays) == len(loops)
    marker = arrays[-1].markers[0]
    assert (
        marker.type == marker.LINE_LIST
        and marker.header.frame_id == "map"
        and marker.ns == "stablecues_loops"
    )
    points = np.array([[p.x, p.y, p.z] for p in marker.points])
    want = np.array([positions[k] for q, c in loops for k in (q, c)])
    np.testing.assert_allclose(points, want)


def test_the_shell_example_replays_a_bag_to_the_node(synbag: Path, tmp_path: Path) -> None:
    """examples/ros2_replay.sh: publisher, node and subscriber by hand, on the loopback interface."""
    env = dds_env(next(_DOMAINS))
    del env["CYCLONEDDS_URI"]  # the script sets the loopback configuration itself
    env.update(
        PRESET="fast",
        NODE_ARGS="--set query.exclude_recent=4",
        PATH=f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}",
    )
    script = Path(__file__).resolve().parents[2] / "examples" / "ros2_replay.sh"
    out = subprocess.run(
        ["bash", str(script), str(synbag)], env=env, capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert out.returncode == 0, out.stderr
    loops = [json.loads(ln) for ln in out.stdout.splitlines() if ln.startswith("{")]
    assert loops and all(d["accepted"] for d in loops)
    assert "frames decided" in out.stderr and "Traceback" not in out.stderr

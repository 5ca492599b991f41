"""On the wire (issue 36, item 2): a publisher process sends one message of every type the node
and the replay publisher use, as they send it, and what this process receives over DDS (the
loopback interface only) is byte for byte rosbags' CDR of the same message."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("cyclonedds", reason="the ros2 extra (cyclonedds) is not installed")

from rosdds import dds_env  # noqa: E402
from test_ros2_messages import USED, samples  # noqa: E402

from stablecues.ros2 import dds  # noqa: E402
from stablecues.ros2 import messages as m  # noqa: E402

HERE = Path(__file__).resolve().parent
DOMAIN = 200 + os.getpid() % 30

#: how each type travels: the node's and the replay's inputs opaque, the node's outputs exact
DESCRIPTION: dict[str, dds.Description] = {t: "exact" for t in USED} | {
    m.IMAGE: "opaque",
    m.COMPRESSED: "opaque",
    m.CAMERA_INFO: "opaque",
    m.POSE_STAMPED: "opaque",
    m.ODOMETRY: "opaque",
}


def topic_of(msgtype: str) -> str:
    return "/wire/" + msgtype.split("/")[-1].lower()


PUBLISHER = f"""
import sys, time
sys.path.insert(0, {str(HERE)!r})
from test_ros2_messages import samples
from test_ros2_wire import DESCRIPTION, topic_of
from stablecues.ros2 import dds, messages as m
did = dds.domain_id()
writers = {{t: dds.writer(did, topic_of(t), t, "reliable", DESCRIPTION[t]) for t in DESCRIPTION}}
assert dds.wait_for_readers(list(writers.values()), 30), "no subscriber"
for t, msg in samples().items():
    writers[t].write(dds.topic_type(t, DESCRIPTION[t])(m.encode(msg, t)))
time.sleep(2.0)
"""


def test_every_type_arrives_as_rosbags_bytes(monkeypatch: pytest.MonkeyPatch) -> None:
    env = dds_env(DOMAIN)
    monkeypatch.setenv("CYCLONEDDS_URI", env["CYCLONEDDS_URI"])  # this process: loopback only too
    readers = {t: dds.reader(DOMAIN, topic_of(t), t, "reliable", DESCRIPTION[t]) for t in DESCRIPTION}
    pub = subprocess.Popen([sys.executable, "-c", PUBLISHER], env=env, stderr=subprocess.PIPE, text=True)
    try:
        got: dict[str, bytes] = {}
        end = time.monotonic() + 40
        while len(got) < len(readers) and time.monotonic() < end and pub.poll() in (None, 0):
            for t, r in readers.items():
                for s in r.take(4):
                    if getattr(s, "payload", None) is not None:
                        got[t] = s.payload
            time.sleep(0.05)
        pub.wait(timeout=30)
        assert pub.returncode == 0, pub.stderr.read() if pub.stderr else ""
    finally:
        if pub.poll() is None:
            pub.kill()
            pub.wait(timeout=10)
    assert set(got) == set(USED)
    for t, msg in samples().items():
        ours = m.encode(msg, t)
        assert got[t][: len(ours)] == ours, t
        assert set(got[t][len(ours) :]) <= {0} and len(got[t]) % 4 == 0 and len(got[t]) - len(ours) < 4, t
        assert m.dds_type_name(t) == dds.topic_type(t, DESCRIPTION[t]).__idl__.idl_transformed_typename

"""The node's parts that need no DDS: the newest-frame slot, depth images, topic defaults, the
domain id, and the shipped loopback configuration."""

from __future__ import annotations

import threading
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from stablecues.errors import ConfigError, ImageError
from stablecues.ros2 import messages as m
from stablecues.ros2.dds import LOOPBACK_CONFIG, domain_id
from stablecues.ros2.node import NodeConfig, _Image, _Pending, _Slot, beside_camera_info, depth_from_image


def _item(k: int) -> _Pending:
    return _Pending(_Image(k, b"", "", "", 0.0))


def test_the_slot_keeps_the_newest_frame_and_counts_the_rest() -> None:
    slot = _Slot(skip=True)
    for k in range(5):
        slot.put(_item(k))
    got = slot.get(0.0)
    assert got is not None and got.left.stamp_ns == 4 and slot.skipped == 4
    assert slot.get(0.0) is None
    queue = _Slot(skip=False)
    for k in range(5):
        queue.put(_item(k))
    assert [queue.get(0.0).left.stamp_ns for _ in range(5)] == list(range(5))  # type: ignore[union-attr]
    assert queue.skipped == 0


def test_a_waiting_detector_wakes_for_a_frame() -> None:
    slot = _Slot(skip=True)
    timer = threading.Timer(0.05, slot.put, args=(_item(7),))
    timer.start()
    try:
        got = slot.get(10.0)
    finally:
        timer.cancel()
    assert got is not None and got.left.stamp_ns == 7


def _depth_msg(values: np.ndarray, encoding: str, step_pad: int = 0) -> object:
    h, w = values.shape
    rows = values.reshape(h, -1).view(np.uint8).reshape(h, -1)
    rows = np.concatenate([rows, np.zeros((h, step_pad), np.uint8)], axis=1)
    return m.typestore().types[m.IMAGE](
        header=m.header_msg(1, "cam"),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=rows.shape[1],
        data=rows.ravel(),
    )


def test_depth_images_in_millimetres_and_metres() -> None:
    mm = np.array([[0, 1000], [2500, 65535]], np.uint16)
    got = depth_from_image(_depth_msg(mm, "16UC1", step_pad=4), "d")
    np.testing.assert_allclose(got, [[np.nan, 1.0], [2.5, 65.535]], rtol=1e-6)
    metres = np.array([[np.nan, 0.5], [-1.0, 3.25]], np.float32)
    got = depth_from_image(_depth_msg(metres, "32FC1"), "d")
    np.testing.assert_allclose(got, [[np.nan, 0.5], [np.nan, 3.25]])
    with pytest.raises(ImageError, match="depth encoding 'rgb8'"):
        depth_from_image(_depth_msg(mm, "rgb8"), "d")
    short = _depth_msg(mm, "16UC1")
    short.step = 40  # type: ignore[attr-defined]
    with pytest.raises(ImageError, match="step 40"):
        depth_from_image(short, "d")


def test_topic_defaults() -> None:
    assert beside_camera_info("/cam0/image_raw") == "/cam0/camera_info"
    assert beside_camera_info("/camera/left/image_rect/compressed") == "/camera/left/camera_info"
    c = NodeConfig(image="/l/image_rect/compressed", right="/r/image_rect/compressed")
    assert c.image_type == m.COMPRESSED and c.is_rectified
    assert c.info_topics() == ("/l/camera_info", "/r/camera_info")
    assert NodeConfig(camera_info=None, right="/r/image").info_topics() == (None, None)
    assert NodeConfig().image_type == m.IMAGE and not NodeConfig().is_rectified
    with pytest.raises(ConfigError, match="input QoS"):
        NodeConfig(input_qos="fast")  # type: ignore[arg-type]


def test_domain_id(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert domain_id() == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert domain_id() == 42 and domain_id("7") == 7
    for bad in ("233", "-1", "one"):
        with pytest.raises(ConfigError, match="0..232"):
            domain_id(bad)


def test_the_shipped_configuration_keeps_dds_on_the_loopback_interface() -> None:
    ns = {"c": "https://cdds.io/config"}
    root = ET.parse(LOOPBACK_CONFIG).getroot()
    interfaces = root.findall(".//c:General/c:Interfaces/c:NetworkInterface", ns)
    assert [i.get("name") for i in interfaces] == ["lo"]
    assert root.findtext(".//c:General/c:AllowMulticast", namespaces=ns) == "false"
    assert [p.get("address") for p in root.findall(".//c:Discovery/c:Peers/c:Peer", ns)] == ["127.0.0.1"]
    assert root.findtext(".//c:Discovery/c:ParticipantIndex", namespaces=ns) == "auto"


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["play", "missing_bag"], "missing_bag: ROS bag not found"),
        (["play", "old.bag"], "a ROS 1 bag; replay a ROS 2 bag"),
        (["play", "missing_bag", "--rate", "0"], "--rate: expected a speed factor > 0"),
        (["--image", "cam/image"], "expected an absolute ROS topic name"),
        (["--map", "/nonexistent/dir/m.sqlite"], "its folder does not exist"),
        (["--new-session"], "--new-session: needs --map"),
        (["--domain", "999"], "the domain id: expected a whole number in 0..232, got '999'"),
    ],
)
def test_command_line_mistakes_are_one_line(
    args: list[str], said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("cyclonedds", reason="the ros2 extra (cyclonedds) is not installed")
    from stablecues.cli.main import main

    assert main(["ros2", *args]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("stablecues ros2: error: ") and said in err[0], err

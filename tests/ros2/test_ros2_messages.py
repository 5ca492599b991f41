"""ROS 2 names and payloads (issue 36, item 2): the DDS names follow ROS 2's mangling, the type
descriptions mirror the ROS 2 definitions rosbags ships, and Cyclone DDS's own serialiser of
those descriptions makes the very bytes rosbags makes (no DDS traffic here)."""

from __future__ import annotations

import subprocess
import sys
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cyclonedds", reason="the ros2 extra (cyclonedds) is not installed")

from rosbags.typesys import Stores, get_typestore  # noqa: E402
from rosbags.typesys.base import Nodetype  # noqa: E402

from stablecues.errors import InputError  # noqa: E402
from stablecues.ros2 import dds  # noqa: E402
from stablecues.ros2 import messages as m  # noqa: E402
from stablecues.ros2.bagwrite import _image_msg, _info_msg  # noqa: E402

#: every message type the node and the replay publisher put on the wire, with its DDS name
USED = {
    m.IMAGE: "sensor_msgs::msg::dds_::Image_",
    m.COMPRESSED: "sensor_msgs::msg::dds_::CompressedImage_",
    m.CAMERA_INFO: "sensor_msgs::msg::dds_::CameraInfo_",
    m.POSE_STAMPED: "geometry_msgs::msg::dds_::PoseStamped_",
    m.ODOMETRY: "nav_msgs::msg::dds_::Odometry_",
    m.STRING: "std_msgs::msg::dds_::String_",
    m.MARKER_ARRAY: "visualization_msgs::msg::dds_::MarkerArray_",
    m.LOOP_CLOSURE: "stablecues_msgs::msg::dds_::LoopClosure_",
}


def test_type_and_topic_names_follow_ros2_mangling() -> None:
    for msgtype, name in USED.items():
        assert m.dds_type_name(msgtype) == name
        assert dds.topic_type(msgtype, "exact").__idl__.idl_transformed_typename == name
        assert dds.topic_type(msgtype, "opaque").__idl__.idl_transformed_typename == name
    assert m.dds_topic_name("/cam0/image_raw") == "rt/cam0/image_raw"
    assert m.dds_topic_name("/stablecues/loop_closure") == "rt/stablecues/loop_closure"
    for bad in ("cam0/image_raw", "/cam0//image", "/0cam/image", "/cam-0/image", "/"):
        with pytest.raises(InputError, match="absolute ROS topic"):
            m.dds_topic_name(bad)


def test_the_types_are_the_ros2_definitions_rosbags_ships() -> None:
    """Every type used is one of ROS 2 Humble's (ours aside), defined the same in Jazzy, and the
    exact description lists its fields in order, nested types by their DDS names."""
    humble, jazzy = get_typestore(Stores.ROS2_HUMBLE), get_typestore(Stores.ROS2_JAZZY)
    for msgtype in USED:
        if msgtype == m.LOOP_CLOSURE:
            continue
        assert humble.fielddefs[msgtype] == jazzy.fielddefs[msgtype], msgtype
        assert m.typestore().fielddefs[msgtype] == humble.fielddefs[msgtype]
        _check_description(msgtype)
    _check_description(m.LOOP_CLOSURE)


def _check_description(msgtype: str) -> None:
    cls = dds.topic_type(msgtype, "exact")
    hints = list(cls.__annotations__)
    assert hints == [name for name, _ in m.fields_of(msgtype)], msgtype
    for name, (kind, detail) in m.fields_of(msgtype):
        if kind == Nodetype.NAME:
            nested = cls.__annotations__[name]
            assert nested.__idl__.idl_transformed_typename == m.dds_type_name(detail)
            _check_description(detail)
    assert dds.topic_type(msgtype, "opaque").__annotations__ == {}


def test_loop_closure_msg_is_shipped_and_builds_as_a_ros2_package() -> None:
    pkg = m.LOOP_CLOSURE_MSG.parent.parent
    assert (pkg / "package.xml").is_file() and (pkg / "CMakeLists.txt").is_file()
    assert "msg/LoopClosure.msg" in (pkg / "CMakeLists.txt").read_text()
    names = [name for name, _ in m.fields_of(m.LOOP_CLOSURE)]
    assert names == [
        "header",
        "query_stamp",
        "candidate_stamp",
        "query_index",
        "candidate_index",
        "accepted",
        "status",
        "score",
        "raw_score",
        "inliers",
        "verifier",
        "has_pose",
        "has_covariance",
        "relative_pose",
    ]


# --- the bytes ------------------------------------------------------------------------------------


def _as_cyclone(value: Any, spec: tuple[Any, Any]) -> Any:
    """A rosbags value as the value of cyclonedds' mirrored dataclass."""
    kind, detail = spec
    if kind == Nodetype.NAME:
        cls = dds._nested_struct(detail)
        return cls(**{name: _as_cyclone(getattr(value, name), s) for name, s in m.fields_of(detail)})
    if kind == Nodetype.BASE:
        return value.item() if isinstance(value, np.generic) else value
    inner = detail[0]
    return [_as_cyclone(v, inner) for v in (value.tolist() if isinstance(value, np.ndarray) else value)]


def samples() -> dict[str, Any]:
    """One message of every type used, fields of every kind set."""
    t = m.typestore().types
    image = _image_msg(1_403_715_273_262_142_976, "cam0", np.arange(35, dtype=np.uint8).reshape(5, 7))
    info = _info_msg(
        7,
        "cam1",
        {
            "width": 752,
            "height": 480,
            "K": np.eye(3) * 458.0,
            "D": [0.1, -0.2, 0, 0, 0.01],
            "R": np.eye(3),
            "P": np.hstack([np.eye(3), np.ones((3, 1))]),
        },
    )
    pose = m.pose_msg(np.array([[0, -1, 0, 1.5], [1, 0, 0, -2], [0, 0, 1, 0.25], [0, 0, 0, 1]], float))
    odom = t[m.ODOMETRY](
        header=m.header_msg(9, "odom"),
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.linspace(0, 1, 36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](
                linear=t["geometry_msgs/msg/Vector3"](x=1.0, y=2.0, z=3.0),
                angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.5),
            ),
            covariance=np.zeros(36),
        ),
    )
    closure = m.loop_closure_msg(
        stamp=12_345,
        frame_id="cam0",
        query_index=41,
        candidate_index=3,
        candidate_stamp=999,
        accepted=True,
        status="loop_detected",
        score=75.999,
        raw_score=0.31,
        inliers=75,
        verifier="pnp",
        relative_pose=np.eye(4),
    )
    return {
        m.IMAGE: image,
        m.COMPRESSED: t[m.COMPRESSED](
            header=m.header_msg(5, "cam0"), format="jpeg", data=np.array([255, 216, 255, 1, 2], np.uint8)
        ),
        m.CAMERA_INFO: info,
        m.POSE_STAMPED: t[m.POSE_STAMPED](header=m.header_msg(3, "map"), pose=pose),
        m.ODOMETRY: odom,
        m.STRING: m.string_msg(m.loop_closure_dict(closure)),
        m.MARKER_ARRAY: m.loop_markers_msg([(np.zeros(3), np.array([1.0, 2.0, 3.0]))], 11, "map"),
        m.LOOP_CLOSURE: closure,
    }


@pytest.mark.parametrize("msgtype", list(USED))
def test_cyclone_serialises_the_description_to_rosbags_bytes(msgtype: str) -> None:
    """The description Cyclone DDS announces is the layout rosbags writes: Cyclone DDS's own
    serialiser, given the same message as its mirrored dataclass, makes byte for byte the
    payload rosbags makes (encapsulation header included; Cyclone pads to 4 bytes), and
    rosbags reads it back."""
    msg = samples()[msgtype]
    ours = m.encode(msg, msgtype)
    mirrored = _as_cyclone(msg, (Nodetype.NAME, msgtype))
    theirs = mirrored.serialize(use_version_2=False)
    assert ours[:4] == b"\x00\x01\x00\x00"  # little-endian plain CDR, as ROS 2 sends
    assert theirs[: len(ours)] == ours and set(theirs[len(ours) :]) <= {0} and len(theirs) - len(ours) < 4
    assert m.encode(m.decode(theirs, msgtype), msgtype) == ours


def test_truncated_and_foreign_payloads_are_one_message_error() -> None:
    payload = m.encode(samples()[m.IMAGE], m.IMAGE)
    for bad in (payload[:20], payload[:-8], b"\x00\x02\x00\x00" + payload[4:], b"", payload + bytes(16)):
        with pytest.raises(m.MessageError, match="not a valid sensor_msgs/msg/Image") as err:
            m.decode(bad, m.IMAGE, "/cam0/image_raw")
        assert "\n" not in str(err.value)


def test_missing_extra_is_one_line_with_the_install_command() -> None:
    code = (
        "import sys; sys.modules['cyclonedds'] = None\n"
        "from stablecues.cli.main import main\n"
        "sys.exit(main(['ros2', 'echo', '--count', '1']))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and 'pip install "stablecues[ros2]"' in lines[0], out.stderr

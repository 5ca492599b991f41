"""ROS 2 messages as bytes: names as ROS 2 puts them on DDS, and CDR through ``rosbags``.

ROS 2 maps a topic ``/camera/image_raw`` to the DDS topic ``rt/camera/image_raw`` and a message
type ``sensor_msgs/msg/Image`` to the DDS type ``sensor_msgs::msg::dds_::Image_``; a message is
the plain (XCDR1) CDR of its fields after a 4-byte encapsulation header (``00 01 00 00``:
little-endian CDR). Every payload here is made and read by ``rosbags``' serialiser, the one the
bag reader uses, from the message definitions rosbags ships (ROS 2 Humble's; the types used
here are the same in Jazzy), plus ``stablecues_msgs/msg/LoopClosure`` from the ``.msg`` file
shipped beside this module.

Nothing here imports ``cyclonedds``.
"""

from __future__ import annotations

import functools
import json
import math
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, reason

__all__ = [
    "CAMERA_INFO",
    "COMPRESSED",
    "IMAGE",
    "LOOP_CLOSURE",
    "LOOP_CLOSURE_MSG",
    "MARKER_ARRAY",
    "ODOMETRY",
    "POSE_STAMPED",
    "STRING",
    "MessageError",
    "dds_topic_name",
    "dds_type_name",
    "decode",
    "encode",
    "fields_of",
    "peek_stamp",
    "stamp_ns",
    "time_msg",
    "typestore",
]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
STRING = "std_msgs/msg/String"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
LOOP_CLOSURE = "stablecues_msgs/msg/LoopClosure"

#: the shipped definition of :data:`LOOP_CLOSURE` (inside a ROS 2 package a workspace can build)
LOOP_CLOSURE_MSG = Path(__file__).resolve().parent / "stablecues_msgs" / "msg" / "LoopClosure.msg"


class MessageError(InputError):
    """A payload that is not a valid CDR message of its type (truncated, of another layout)."""


@functools.cache
def typestore() -> Any:
    """The ``rosbags`` type store of ROS 2 Humble with :data:`LOOP_CLOSURE` registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(LOOP_CLOSURE_MSG.read_text(encoding="utf-8"), LOOP_CLOSURE))
    return store


def dds_topic_name(topic: str) -> str:
    """The DDS topic ROS 2 uses for a (fully qualified) ROS topic: ``/a/b`` -> ``rt/a/b``.

    Raises:
        InputError: a name that is not an absolute ROS topic (``/`` first, no empty part, letters,
            digits and underscores only, no part starting with a digit).
    """
    parts = topic.split("/")
    if (
        not topic.startswith("/")
        or len(parts) < 2
        or any(
            not p or not (p.replace("_", "a").isascii() and p.replace("_", "a").isalnum()) or p[0].isdigit()
            for p in parts[1:]
        )
    ):
        raise InputError(f"expected an absolute ROS topic name such as /camera/image_raw, got {topic!r}")
    return "rt" + topic


def dds_type_name(msgtype: str) -> str:
    """The DDS type name ROS 2 gives a message type: ``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def fields_of(msgtype: str) -> list[tuple[str, Any]]:
    """The fields of ``msgtype`` as ``rosbags`` defines it: ``(name, (nodetype, spec))`` each."""
    return list(typestore().fielddefs[msgtype][1])


def encode(message: Any, msgtype: str) -> bytes:
    """The CDR payload (little-endian, with its encapsulation header) of ``message``."""
    return bytes(typestore().serialize_cdr(message, msgtype, little_endian=True))


def decode(payload: bytes | memoryview, msgtype: str, where: str = "") -> Any:
    """The message a CDR payload holds.

    Raises:
        MessageError: a payload too short for its type, with an unknown encapsulation, with a
            string that is not UTF-8, or longer than its message (beyond DDS's 0-3 padding bytes).
    """
    try:
        return typestore().deserialize_cdr(payload, msgtype)
    except Exception as exc:  # rosbags raises SerdeError, struct.error, IndexError ... on bad bytes
        label = f"{where}: " if where else ""
        raise MessageError(f"{label}{len(payload)} bytes are not a valid {msgtype} ({reason(exc)})") from None


def peek_stamp(payload: bytes | memoryview, msgtype: str, where: str = "") -> int:
    """The header stamp (ns) of a message whose first field is a ``std_msgs/Header``, read from its
    first 12 bytes without decoding the rest (an image's pixels are decoded only if it is used).

    Raises:
        MessageError: fewer than 12 bytes, or not plain CDR.
    """
    head = bytes(payload[:12])
    if len(head) < 12 or head[:2] not in (b"\x00\x00", b"\x00\x01"):
        label = f"{where}: " if where else ""
        raise MessageError(f"{label}{len(payload)} bytes are not a valid {msgtype} (no CDR header and stamp)")
    sec, nanosec = struct.unpack_from("<iI" if head[1] else ">iI", head, 4)
    return sec * 1_000_000_000 + nanosec


def stamp_ns(stamp: Any) -> int:
    """A ``builtin_interfaces/Time`` as nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def time_msg(ns: int) -> Any:
    """``builtin_interfaces/msg/Time`` of ``ns`` nanoseconds (>= 0)."""
    ns = max(int(ns), 0)
    return typestore().types["builtin_interfaces/msg/Time"](
        sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000
    )


def header_msg(ns: int, frame_id: str) -> Any:
    """``std_msgs/msg/Header``."""
    return typestore().types["std_msgs/msg/Header"](stamp=time_msg(ns), frame_id=frame_id)


def _quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a (3, 3) rotation matrix (Shepperd's method)."""
    r = np.asarray(rotation, dtype=np.float64)
    trace = float(np.trace(r))
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 1e-12))
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = 0.25 * s
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return q[0], q[1], q[2], q[3]


def pose_msg(transform: np.ndarray | None) -> Any:
    """``geometry_msgs/msg/Pose`` of a (4, 4) transform (identity for None)."""
    types = typestore().types
    t = np.eye(4) if transform is None else np.asarray(transform, dtype=np.float64)
    x, y, z, w = _quaternion(t[:3, :3])
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(t[0, 3]), y=float(t[1, 3]), z=float(t[2, 3])),
        orientation=types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def loop_closure_msg(
    *,
    stamp: int,
    frame_id: str,
    query_index: int,
    candidate_index: int,
    candidate_stamp: int,
    accepted: bool,
    status: str,
    score: float,
    raw_score: float,
    inliers: int,
    verifier: str,
    relative_pose: np.ndarray | None,
    covariance: np.ndarray | None = None,
) -> Any:
    """A ``stablecues_msgs/msg/LoopClosure`` (see its ``.msg`` for the fields)."""
    types = typestore().types
    cov = np.zeros(36) if covariance is None else np.asarray(covariance, dtype=np.float64).ravel()
    return types[LOOP_CLOSURE](
        header=header_msg(stamp, frame_id),
        query_stamp=time_msg(stamp),
        candidate_stamp=time_msg(candidate_stamp if candidate_index >= 0 else 0),
        query_index=int(query_index),
        candidate_index=int(candidate_index),
        accepted=bool(accepted),
        status=str(status),
        score=float(score),
        raw_score=float(raw_score),
        inliers=int(inliers),
        verifier=str(verifier),
        has_pose=relative_pose is not None,
        has_covariance=covariance is not None,
        relative_pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose_msg(relative_pose), covariance=cov
        ),
    )


def loop_closure_dict(msg: Any) -> dict[str, Any]:
    """The fields of a LoopClosure message as JSON-ready values (what the String topic carries)."""
    pose = msg.relative_pose.pose
    return {
        "stamp_ns": stamp_ns(msg.header.stamp),
        "frame_id": msg.header.frame_id,
        "query_stamp_ns": stamp_ns(msg.query_stamp),
        "candidate_stamp_ns": stamp_ns(msg.candidate_stamp),
        "query_index": int(msg.query_index),
        "candidate_index": int(msg.candidate_index),
        "accepted": bool(msg.accepted),
        "status": msg.status,
        "score": _finite(msg.score),
        "raw_score": _finite(msg.raw_score),
        "inliers": int(msg.inliers),
        "verifier": msg.verifier,
        "relative_pose": None
        if not msg.has_pose
        else {
            "position": [pose.position.x, pose.position.y, pose.position.z],
            "orientation_xyzw": [
                pose.orientation.x,
                pose.orientation.y,
                pose.orientation.z,
                pose.orientation.w,
            ],
        },
        "covariance": [float(v) for v in msg.relative_pose.covariance] if msg.has_covariance else None,
    }


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def string_msg(data: dict[str, Any]) -> Any:
    """``std_msgs/msg/String`` holding ``data`` as one line of JSON."""
    return typestore().types[STRING](data=json.dumps(data, separators=(",", ":")))


def loop_markers_msg(edges: Sequence[tuple[np.ndarray, np.ndarray]], stamp: int, frame_id: str) -> Any:
    """``visualization_msgs/msg/MarkerArray`` of one LINE_LIST marker: a line per accepted loop,
    from the query frame's position to the candidate's (``edges``: (3,) pairs, in ``frame_id``)."""
    types = typestore().types
    point = types["geometry_msgs/msg/Point"]
    marker_type = types["visualization_msgs/msg/Marker"]
    points = [point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for edge in edges for p in edge]
    marker = marker_type(
        header=header_msg(stamp, frame_id),
        ns="stablecues_loops",
        id=0,
        type=marker_type.LINE_LIST,
        action=marker_type.ADD,
        pose=pose_msg(None),
        scale=types["geometry_msgs/msg/Vector3"](x=0.05, y=0.0, z=0.0),
        color=types["std_msgs/msg/ColorRGBA"](r=1.0, g=0.2, b=0.1, a=1.0),
        lifetime=types["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        frame_locked=False,
        points=points,
        colors=[],
        texture_resource="",
        texture=types["sensor_msgs/msg/CompressedImage"](
            header=header_msg(0, ""), format="", data=np.zeros(0, np.uint8)
        ),
        uv_coordinates=[],
        text="",
        mesh_resource="",
        mesh_file=types["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
        mesh_use_embedded_materials=False,
    )
    return types[MARKER_ARRAY](markers=[marker])

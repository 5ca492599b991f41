"""The DDS side: Cyclone DDS participants, ROS 2 topic types carrying ``rosbags`` payloads, QoS.

``cyclonedds`` (the ``ros2`` extra) is imported on first use; without it the first call says, in
one line, how to install it.

A topic type is a Cyclone DDS ``IdlStruct`` named as ROS 2 names the message on DDS
(``sensor_msgs::msg::dds_::Image_``), keyless as every ROS 2 type, whose samples are CDR payloads
made by ``rosbags`` (:mod:`.messages`) and handed to Cyclone DDS as they are: the bytes on the
wire are rosbags' bytes, followed by the zero to three zero bytes DDS pads a payload with. Its
XTypes description (what Cyclone DDS announces in discovery, and checks payloads against) is
either

* ``exact``: the message's fields, nested types and all, mirrored from the definitions rosbags
  ships; Cyclone DDS then refuses a payload that is not a valid CDR of the type before anyone
  sees it. The node's outputs use it.
* ``opaque``: no fields; Cyclone DDS hands any payload to the application, which checks it
  itself (a truncated message is then logged and skipped by the node instead of dropped
  silently). The node's inputs and the replay publisher use it.

Peers that announce no type description (ROS 2's ``rmw_cyclonedds_cpp``, and Fast DDS in ROS 2
Humble and Jazzy) match either by the type's name alone. A DDS application that announces a full
description of an input type matches only ``exact`` (``stablecues ros2 --exact-types``).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from ..errors import ConfigError
from .messages import dds_type_name, fields_of

__all__ = [
    "LOOPBACK_CONFIG",
    "Description",
    "QosProfile",
    "Sample",
    "domain_id",
    "participant",
    "qos",
    "reader",
    "topic_type",
    "use_loopback",
    "writer",
]

#: Cyclone DDS on the loopback interface only (multicast off, peer 127.0.0.1): tests, CI, the
#: benchmark and the examples run with it (``CYCLONEDDS_URI=file://...``)
LOOPBACK_CONFIG = Path(__file__).resolve().parent / "cyclonedds_loopback.xml"

INSTALL_HINT = 'the ROS 2 node needs Cyclone DDS\'s Python binding: pip install "stablecues[ros2]"'

Description = Literal["exact", "opaque"]
QosProfile = Literal["sensor", "reliable"]


def cyclonedds() -> Any:
    """The ``cyclonedds`` package.

    Raises:
        ImportError: it is not installed, with the install command.
    """
    try:
        import cyclonedds as cdds
        import cyclonedds.domain
        import cyclonedds.idl
        import cyclonedds.pub
        import cyclonedds.sub
        import cyclonedds.topic  # noqa: F401  (the submodules used here)
    except ImportError as exc:
        raise ImportError(INSTALL_HINT, name="cyclonedds") from exc
    return cdds


def use_loopback() -> str:
    """Point Cyclone DDS at :data:`LOOPBACK_CONFIG` (``CYCLONEDDS_URI``) for this process and the
    processes it starts; returns the URI. Must run before the first participant is made."""
    uri = LOOPBACK_CONFIG.as_uri()
    os.environ["CYCLONEDDS_URI"] = uri
    return uri


def domain_id(value: str | None = None) -> int:
    """The DDS domain: ``value``, else ``ROS_DOMAIN_ID``, else 0.

    Raises:
        ConfigError: not a whole number in 0..232 (the ids ROS 2 allows).
    """
    raw = value if value is not None else os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
    try:
        did = int(raw)
    except ValueError:
        did = -1
    if not 0 <= did <= 232:
        where = "the domain id" if value is not None else "ROS_DOMAIN_ID"
        raise ConfigError(f"{where}: expected a whole number in 0..232, got {raw!r}")
    return did


@functools.cache
def participant(did: int) -> Any:
    """The process's DomainParticipant of domain ``did`` (one per domain, as a ROS 2 context)."""
    return cyclonedds().domain.DomainParticipant(did)


# ----------------------------------------------------------------------------------------------
# topic types


class Sample:
    """A payload as a sample: what a topic type's ``serialize`` hands Cyclone DDS and its
    ``deserialize`` gets back. Its methods are those of every topic type.

    Attributes:
        payload: the CDR bytes, encapsulation header first.
        sample_info: set by Cyclone DDS on a received sample (``source_timestamp`` ns ...).
    """

    def __init__(self, payload: bytes) -> None:
        self.payload = bytes(payload)
        self.sample_info: Any = None

    def serialize(
        self, buffer: Any = None, endianness: Any = None, use_version_2: bool | None = None
    ) -> bytes:
        """The payload, as is."""
        return self.payload

    @classmethod
    def deserialize(cls, data: bytes, has_header: bool = True, use_version_2: bool | None = None) -> Sample:
        """A received payload, as is (padding included)."""
        return cls(data)


_BASE = {
    "bool": "bool", "byte": "byte", "char": "uint8", "int8": "int8", "uint8": "uint8", "int16": "int16",
    "uint16": "uint16", "int32": "int32", "uint32": "uint32", "int64": "int64", "uint64": "uint64",
    "float32": "float32", "float64": "float64",
}  # fmt: skip


def _idl_name(msgtype: str) -> str:
    """The IDL type name cyclonedds takes (``.`` for ``::``)."""
    return dds_type_name(msgtype).replace("::", ".")


def _field_type(spec: tuple[Any, Any], nested: Callable[[str], Any]) -> Any:
    """The cyclonedds type of a rosbags field spec ``(nodetype, detail)``."""
    from rosbags.typesys.base import Nodetype

    types = cyclonedds().idl.types
    kind, detail = spec
    if kind == Nodetype.BASE:
        name, bound = detail
        if name == "string":
            return types.bounded_str[bound] if bound else str
        if name == "bool":
            return bool
        return getattr(types, _BASE[name])
    if kind == Nodetype.NAME:
        return nested(detail)
    inner, size = detail
    if kind == Nodetype.ARRAY:
        return types.array[_field_type(inner, nested), size]
    return (
        types.sequence[_field_type(inner, nested), size]
        if size
        else types.sequence[_field_type(inner, nested)]
    )


@functools.cache
def _nested_struct(msgtype: str) -> Any:
    """A plain IdlStruct mirroring ``msgtype`` (for the description of a type that holds it)."""
    idl = cyclonedds().idl
    fields = {name: _field_type(spec, _nested_struct) for name, spec in fields_of(msgtype)}
    return idl.make_idl_struct(msgtype.rsplit("/", 1)[-1] + "_", _idl_name(msgtype), fields)


def topic_type(msgtype: str, description: Description = "exact") -> Any:
    """The topic type of a ROS 2 message type (see the module's docstring); its samples are
    :class:`Sample` (``type(payload)``). One class per type and description."""
    return _topic_type(msgtype, description)


@functools.cache
def _topic_type(msgtype: str, description: Description) -> Any:
    idl = cyclonedds().idl
    fields = (
        {}
        if description == "opaque"
        else {name: _field_type(spec, _nested_struct) for name, spec in fields_of(msgtype)}
    )
    cls = idl.make_idl_struct(
        msgtype.rsplit("/", 1)[-1] + "_", _idl_name(msgtype), fields, dataclassify=False
    )
    # a sample is its payload, whatever the fields say (set on the class, not inherited: a base
    # class would enter the type's XTypes description as its parent)
    cls.__init__ = Sample.__init__
    cls.serialize = Sample.serialize
    cls.deserialize = classmethod(Sample.deserialize.__func__)  # type: ignore[attr-defined]
    # the key of an invalid sample (a writer gone): keyless types have none
    cls.deserialize_key = classmethod(Sample.deserialize.__func__)  # type: ignore[attr-defined]
    return cls


# ----------------------------------------------------------------------------------------------
# QoS and endpoints


def qos(profile: QosProfile, depth: int | None = None) -> Any:
    """ROS 2's QoS profiles: ``sensor`` (``rmw_qos_profile_sensor_data``: best effort, keep the
    last 5, volatile) and ``reliable`` (the default profile: reliable, keep the last 10, volatile)."""
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.util import duration

    cyclonedds()
    if profile == "sensor":
        return Qos(
            Policy.Reliability.BestEffort, Policy.History.KeepLast(depth or 5), Policy.Durability.Volatile
        )
    return Qos(
        Policy.Reliability.Reliable(duration(milliseconds=100)),
        Policy.History.KeepLast(depth or 10),
        Policy.Durability.Volatile,
    )


def _topic(did: int, topic: str, msgtype: str, description: Description) -> Any:
    from .messages import dds_topic_name

    cdds = cyclonedds()
    return _topics(did, dds_topic_name(topic), msgtype, description, cdds)


@functools.cache
def _topics(did: int, dds_name: str, msgtype: str, description: Description, cdds: Any) -> Any:
    return cdds.topic.Topic(participant(did), dds_name, topic_type(msgtype, description))


def writer(
    did: int,
    topic: str,
    msgtype: str,
    profile: QosProfile = "reliable",
    description: Description = "exact",
    depth: int | None = None,
) -> Any:
    """A DataWriter of ROS topic ``topic`` (``/a/b``); ``write(topic_type(msgtype)(payload))``."""
    cdds = cyclonedds()
    return cdds.pub.DataWriter(
        participant(did), _topic(did, topic, msgtype, description), qos(profile, depth)
    )


def reader(
    did: int,
    topic: str,
    msgtype: str,
    profile: QosProfile = "reliable",
    description: Description = "exact",
    depth: int | None = None,
) -> Any:
    """A DataReader of ROS topic ``topic``; ``take(N)`` gives :class:`Sample`\\ s."""
    cdds = cyclonedds()
    return cdds.sub.DataReader(
        participant(did), _topic(did, topic, msgtype, description), qos(profile, depth)
    )


def wait_for_readers(writers: list[Any], timeout: float, count: int = 1) -> bool:
    """Wait (at most ``timeout`` seconds) until each writer has matched ``count`` readers."""
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if all(len(w.get_matched_subscriptions()) >= count for w in writers):
            return True
        time.sleep(0.05)
    return False

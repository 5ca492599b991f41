"""Replaying a ROS 2 bag's camera topics over DDS, and listening to the node's decisions.

:func:`play` publishes the image and CameraInfo messages of a ROS 2 bag (sqlite3 or MCAP) at
their recorded rate (or ``rate`` times it), each message's bytes as the bag stores them (a ROS 2
bag stores the CDR a publisher sent), so the node can be tried without a robot.
:func:`listen` subscribes to the node's LoopClosure topic and hands each decision over as JSON
fields.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import DatasetError
from . import dds
from .messages import CAMERA_INFO, COMPRESSED, IMAGE, LOOP_CLOSURE, MessageError, decode, loop_closure_dict

__all__ = ["PlaySummary", "listen", "play"]

log = logging.getLogger(__name__)

PLAYED_TYPES = (IMAGE, COMPRESSED, CAMERA_INFO)


@dataclass
class PlaySummary:
    """What a replay published.

    Attributes:
        messages: messages published, per topic.
        seconds: wall-clock seconds the replay took.
        published_ns: ``(topic, header stamp ns, publication time ns)`` of every image published.
    """

    messages: dict[str, int]
    seconds: float
    published_ns: list[tuple[str, int, int]]


def _bag_topics(reader: Any, bag: Path, topics: Sequence[str] | None) -> dict[str, str]:
    """The topics to replay (image and CameraInfo topics, or those named) -> their types.

    Raises:
        DatasetError: a named topic the bag lacks or that is not an image or CameraInfo topic.
    """
    present = {name: str(info.msgtype) for name, info in reader.topics.items()}
    playable = {t: typ for t, typ in present.items() if typ in PLAYED_TYPES}
    if not topics:
        if not playable:
            raise DatasetError(f"{bag}: no sensor_msgs/Image, CompressedImage or CameraInfo topic to replay")
        return playable
    for t in topics:
        if t not in playable:
            listed = ", ".join(sorted(playable)) or "none"
            raise DatasetError(
                f"{bag}: expected an image or CameraInfo topic, {t!r} is not one; playable topics: {listed}"
            )
    return {t: playable[t] for t in topics}


def play(
    bag: str | Path,
    *,
    topics: Sequence[str] | None = None,
    rate: float = 1.0,
    domain: int = 0,
    image_qos: dds.QosProfile = "sensor",
    wait_for_subscribers: int = 0,
    wait_timeout: float = 10.0,
    start: int = 0,
    count: int | None = None,
    linger: float = 0.5,
    stop: Callable[[], bool] = lambda: False,
    description: dds.Description = "opaque",
) -> PlaySummary:
    """Publish a ROS 2 bag's camera topics at their recorded rate.

    Args:
        bag: a ROS 2 bag folder (or its ``.db3`` / ``.mcap`` file).
        topics: the topics to replay (default: every Image, CompressedImage and CameraInfo topic).
        rate: speed factor of the bag's timing (2: twice as fast); > 0.
        domain: the DDS domain.
        image_qos: QoS of the image topics ("sensor": best effort, as camera drivers publish;
            "reliable"); CameraInfo is published reliably.
        wait_for_subscribers: wait (at most ``wait_timeout`` s) until every topic has this many
            subscribers before the first message.
        start: skip the messages before the ``start``-th message of the first image topic (the
            CameraInfo of the first played frame is kept).
        count: play this many messages of the first image topic (None: all).
        linger: seconds to stay after the last message, so reliable readers get it.
        stop: polled between messages; True ends the replay.
        description: the types' description announced (see :mod:`.dds`): "opaque", as the node's
            subscriptions announce it, or "exact" for a node run with ``--exact-types``.

    Raises:
        DatasetError: not a readable ROS 2 bag (a ROS 1 bag is refused: its messages are not CDR),
            or a topic that cannot be replayed.
        ConfigError: a rate that is not > 0.
    """
    from ..datasets.rosbag import _messages, _open_reader
    from ..errors import ConfigError

    if not rate > 0:
        raise ConfigError(f"--rate: expected a speed factor > 0, got {rate}")
    path = Path(bag)
    if path.suffix == ".bag":
        raise DatasetError(f"{path}: a ROS 1 bag; replay a ROS 2 bag (convert it with `rosbags-convert`)")
    reader = _open_reader(path)
    try:
        chosen = _bag_topics(reader, path, topics)
        first_image = min((t for t, typ in chosen.items() if typ != CAMERA_INFO), default=None)
        writers = {
            t: dds.writer(domain, t, typ, image_qos if typ != CAMERA_INFO else "reliable", description)
            for t, typ in chosen.items()
        }
        types = {t: dds.topic_type(typ, description) for t, typ in chosen.items()}
        if wait_for_subscribers and not dds.wait_for_readers(
            list(writers.values()), wait_timeout, wait_for_subscribers
        ):
            log.warning(
                "not every topic had %d subscribers after %g s; publishing anyway",
                wait_for_subscribers,
                wait_timeout,
            )
        conns = [c for c in reader.connections if c.topic in chosen]
        lo, hi = _window(reader, path, conns, first_image, start, count)
        counts = dict.fromkeys(chosen, 0)
        published: list[tuple[str, int, int]] = []
        t0_wall: float | None = None
        t0_bag = 0
        began = time.monotonic()
        for conn, bag_ns, raw in _messages(reader, path, conns):
            if bag_ns >= hi or stop():
                break
            is_info = chosen[conn.topic] == CAMERA_INFO
            if bag_ns < lo and not is_info:
                continue  # before the window; CameraInfo goes out at once, so the node has it
            if bag_ns >= lo:
                if t0_wall is None:
                    t0_wall, t0_bag = time.monotonic(), bag_ns
                delay = t0_wall + (bag_ns - t0_bag) * 1e-9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            payload = bytes(raw)
            writers[conn.topic].write(types[conn.topic](payload))
            counts[conn.topic] += 1
            if not is_info:
                published.append((conn.topic, _header_stamp(payload, chosen[conn.topic]), time.time_ns()))
        time.sleep(max(linger, 0.0))
        return PlaySummary(counts, time.monotonic() - began, published)
    finally:
        reader.close()


def _window(
    reader: Any, bag: Path, conns: list[Any], first_image: str | None, start: int, count: int | None
) -> tuple[float, float]:
    """The bag times [lo, hi) holding messages ``start`` .. ``start + count - 1`` of ``first_image``
    (bounds halfway between frames, so that a stereo pair's other half is inside with it)."""
    from ..datasets.rosbag import _messages

    if first_image is None or (start <= 0 and count is None):
        return float("-inf"), float("inf")
    times = [t for _, t, _ in _messages(reader, bag, [c for c in conns if c.topic == first_image])]

    def between(k: int) -> float:
        if k <= 0:
            return float("-inf")
        if k >= len(times):
            return float("inf")
        return (times[k - 1] + times[k]) / 2

    return between(start), between(start + count) if count is not None else float("inf")


def _header_stamp(payload: bytes, msgtype: str) -> int:
    """The header stamp of an image payload (-1 when it does not decode)."""
    from .messages import stamp_ns

    try:
        return stamp_ns(decode(payload, msgtype).header.stamp)
    except MessageError:
        return -1


def listen(
    on_decision: Callable[[dict[str, Any]], None],
    *,
    topic: str = "/stablecues/loop_closure",
    domain: int = 0,
    count: int | None = None,
    timeout: float | None = None,
    stop: Callable[[], bool] = lambda: False,
    raw: Callable[[bytes], None] | None = None,
) -> int:
    """Subscribe to a LoopClosure topic and call ``on_decision`` with each decision's JSON fields
    (plus ``source_timestamp_ns``, when the node published it, and ``received_ns``).

    ``raw``, when given, gets each payload as received (CDR, padding included) first.
    Returns after ``count`` decisions, ``timeout`` seconds without one, or when ``stop()`` says so;
    returns how many were received.
    """
    from cyclonedds.core import ReadCondition, SampleState, WaitSet
    from cyclonedds.util import duration

    reader = dds.reader(domain, topic, LOOP_CLOSURE, "reliable", "exact", depth=1000)
    waitset = WaitSet(dds.participant(domain))
    waitset.attach(ReadCondition(reader, SampleState.NotRead))
    received = 0
    last = time.monotonic()
    while not stop() and (count is None or received < count):
        if timeout is not None and time.monotonic() - last > timeout:
            break
        waitset.wait(duration(milliseconds=100))
        for sample in reader.take(64):
            if getattr(sample, "payload", None) is None:
                continue
            if raw is not None:
                raw(sample.payload)
            try:
                fields = loop_closure_dict(decode(sample.payload, LOOP_CLOSURE, topic))
            except MessageError as exc:
                log.warning("skipped a malformed message: %s", exc)
                continue
            fields["source_timestamp_ns"] = int(sample.sample_info.source_timestamp)
            fields["received_ns"] = time.time_ns()
            on_decision(fields)
            received += 1
            last = time.monotonic()
    return received

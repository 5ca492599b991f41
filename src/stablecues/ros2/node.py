"""The loop-closure node: camera topics in, a decision per frame out, over DDS as ROS 2 speaks it.

Threads: a receiver takes every sample as Cyclone DDS delivers it (decodes the CDR, pairs a
stereo pair's images by stamp, keeps the first CameraInfo of each camera and the poses), and
hands frames to the detector through a one-frame slot: when the detector falls behind, a new
frame replaces the one waiting, and the replaced one is counted as skipped (``skip=False``
queues every frame instead, for replays that must match ``stablecues run``). The detector runs
in the caller's thread and publishes each decision as a ``stablecues_msgs/msg/LoopClosure``, as
``std_msgs/msg/String`` JSON, and (with a pose topic) as RViz loop edges.

A message that cannot be used (truncated CDR, an image whose ``step`` and size disagree, an
unknown encoding, a corrupt JPEG) is logged in one line and skipped; the node goes on.
"""

from __future__ import annotations

import bisect
import logging
import resource
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from ..errors import CalibrationError, ConfigError, ImageError, StableCuesError
from . import dds
from .messages import (
    CAMERA_INFO,
    COMPRESSED,
    IMAGE,
    LOOP_CLOSURE,
    MARKER_ARRAY,
    ODOMETRY,
    POSE_STAMPED,
    STRING,
    MessageError,
    dds_topic_name,
    decode,
    encode,
    loop_closure_dict,
    loop_closure_msg,
    loop_markers_msg,
    peek_stamp,
    stamp_ns,
    string_msg,
)

if TYPE_CHECKING:
    from ..detection import LoopDecision, LoopDetector
    from ..geometry import Calibration

__all__ = ["NodeConfig", "NodeSummary", "LoopClosureNode", "beside_camera_info", "depth_from_image"]

log = logging.getLogger(__name__)

#: frames of a stereo pair waiting for their other half, at most (the oldest go first)
MAX_PENDING = 64
#: seconds frames may wait for the CameraInfo before the node warns
CAMERA_INFO_PATIENCE = 5.0
#: poses a pose topic's reader holds until the receiver takes them
POSE_HISTORY = 200


def beside_camera_info(image_topic: str) -> str:
    """The CameraInfo topic ROS puts beside an image topic: ``/cam0/image_raw[/compressed]`` ->
    ``/cam0/camera_info``."""
    base = image_topic.removesuffix("/compressed")
    return base.rsplit("/", 1)[0] + "/camera_info"


@dataclass(frozen=True)
class NodeConfig:
    """What the node subscribes to and publishes.

    Attributes:
        image: the (left) camera's topic; ``sensor_msgs/CompressedImage`` when it ends in
            ``/compressed`` (or ``compressed`` is True), ``sensor_msgs/Image`` otherwise.
        right: the right camera's topic of a stereo pair (same kind), or None.
        camera_info: the left camera's CameraInfo topic; "auto": the one beside ``image``;
            None: none (the detector's own calibration, if any, applies).
        right_camera_info: the right camera's; "auto": beside ``right``.
        depth: a depth image topic registered to ``image`` (16UC1 / mono16 millimetres or 32FC1
            metres), or None.
        pose: a topic of the robot's poses, for the RViz loop edges, or None.
        pose_type: ``geometry_msgs/PoseStamped`` ("pose") or ``nav_msgs/Odometry`` ("odometry").
        prefix: the namespace of the outputs: ``PREFIX/loop_closure`` (LoopClosure),
            ``PREFIX/loop_closure_json`` (String), ``PREFIX/loop_markers`` (MarkerArray).
        input_qos: "sensor" (best effort, keep last 5: ROS's sensor-data profile) or "reliable".
        skip: keep only the newest frame when the detector falls behind (False: queue them all).
        max_stereo_difference: largest stamp difference (s) of a stereo pair, and of an image and
            its depth image.
        rectified: the images are rectified (calibration from ``P``); None: when the topic is an
            ``image_rect*`` topic.
        compressed: force the image kind (None: from the topic name).
        exact_types: announce the inputs' full type descriptions (see :mod:`.dds`); Cyclone DDS
            then drops malformed payloads itself, unlogged.
        domain: the DDS domain (``ROS_DOMAIN_ID``).
    """

    image: str = "/camera/image_raw"
    right: str | None = None
    camera_info: str | None = "auto"
    right_camera_info: str | None = "auto"
    depth: str | None = None
    pose: str | None = None
    pose_type: Literal["pose", "odometry"] = "pose"
    prefix: str = "/stablecues"
    input_qos: dds.QosProfile = "sensor"
    skip: bool = True
    max_stereo_difference: float = 0.002
    rectified: bool | None = None
    compressed: bool | None = None
    exact_types: bool = False
    domain: int = 0

    def __post_init__(self) -> None:
        if self.input_qos not in ("sensor", "reliable"):
            raise ConfigError(f"input QoS: expected 'sensor' or 'reliable', got {self.input_qos!r}")
        if self.pose_type not in ("pose", "odometry"):
            raise ConfigError(f"pose type: expected 'pose' or 'odometry', got {self.pose_type!r}")
        for topic in (
            self.image,
            self.right,
            self.camera_info,
            self.right_camera_info,
            self.depth,
            self.pose,
            self.prefix.rstrip("/") + "/loop_closure",
        ):
            if topic is not None and topic != "auto":
                dds_topic_name(topic)  # an absolute ROS name, or InputError in one line
        if not self.max_stereo_difference >= 0:
            raise ConfigError(
                f"max stereo difference: expected seconds >= 0, got {self.max_stereo_difference}"
            )

    @property
    def image_type(self) -> str:
        """``sensor_msgs/msg/CompressedImage`` or ``sensor_msgs/msg/Image``."""
        compressed = self.image.endswith("/compressed") if self.compressed is None else self.compressed
        return COMPRESSED if compressed else IMAGE

    def info_topics(self) -> tuple[str | None, str | None]:
        """The CameraInfo topics of the left and right camera (None: not read)."""
        left = beside_camera_info(self.image) if self.camera_info == "auto" else self.camera_info
        right = None
        if self.right is not None and left is not None:
            right = (
                beside_camera_info(self.right) if self.right_camera_info == "auto" else self.right_camera_info
            )
        return left, right

    @property
    def is_rectified(self) -> bool:
        if self.rectified is not None:
            return self.rectified
        return self.image.removesuffix("/compressed").rsplit("/", 1)[-1].startswith("image_rect")


@dataclass
class NodeSummary:
    """What a node did, for its log line and ``--summary`` file.

    Attributes:
        received: images received (left images of a stereo pair).
        processed: frames the detector decided.
        skipped: frames replaced by a newer one before the detector got to them.
        malformed: messages logged and skipped (bad CDR, bad image, bad CameraInfo).
        unpaired: stereo images dropped without their other half.
        loops: loops accepted.
        first_index: the first frame index of this session (the map's next index), -1 if none.
        last_index: the last one decided, -1 if none.
        map_frames: frames in the map at exit.
        session: the map's session this run's frames were stored in (``--new-session``).
        cpu_s: CPU seconds of the process (user + system), all threads.
        wall_s: seconds the node ran.
        decide_ms: median milliseconds from a frame's arrival to its decision's publication.
        detect_ms: median milliseconds the detector took per frame (its ``total`` stage).
    """

    received: int = 0
    processed: int = 0
    skipped: int = 0
    malformed: int = 0
    unpaired: int = 0
    loops: int = 0
    first_index: int = -1
    last_index: int = -1
    map_frames: int = 0
    session: int = 0
    cpu_s: float = 0.0
    wall_s: float = 0.0
    decide_ms: float = float("nan")
    detect_ms: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def line(self) -> str:
        """One line for people."""
        return (
            f"{self.processed} frames decided ({self.loops} loops), {self.skipped} skipped while the "
            f"detector was busy, {self.malformed} malformed messages skipped, {self.unpaired} unpaired "
            f"stereo images; map holds {self.map_frames} frames; "
            f"CPU {self.cpu_s:.1f} s in {self.wall_s:.1f} s"
        )


@dataclass
class _Image:
    """A received image message: its stamp, and its CDR decoded only when the frame is used."""

    stamp_ns: int
    payload: bytes
    msgtype: str
    topic: str
    arrived: float  # time.monotonic() at arrival

    def message(self) -> Any:
        """The decoded message.

        Raises:
            MessageError: a payload that is not a valid message of its type.
        """
        return decode(self.payload, self.msgtype, self.topic)


@dataclass
class _Pending:
    """A frame waiting for the detector."""

    left: _Image
    right: _Image | None = None
    depth: _Image | None = None
    frame_id: str = ""  # the left image's, once decoded


@dataclass
class _Slot:
    """The frames between receiver and detector: the newest only (``skip``) or all of them."""

    skip: bool
    items: deque[_Pending] = field(default_factory=deque)
    cond: threading.Condition = field(default_factory=threading.Condition)
    skipped: int = 0

    def put(self, item: _Pending) -> None:
        with self.cond:
            if self.skip and self.items:
                self.skipped += len(self.items)
                if self.skipped == 1 or self.skipped % 50 == 0:
                    log.warning(
                        "the detector is behind the camera: keeping the newest frame (%d skipped so far)",
                        self.skipped,
                    )
                self.items.clear()
            self.items.append(item)
            self.cond.notify()

    def get(self, timeout: float) -> _Pending | None:
        with self.cond:
            if not self.items:
                self.cond.wait(timeout)
            return self.items.popleft() if self.items else None


def depth_from_image(msg: Any, where: str) -> np.ndarray:
    """(H, W) float32 metres of a depth ``sensor_msgs/Image`` (16UC1 / mono16 in millimetres,
    32FC1 in metres), NaN where unknown (zero, or not finite).

    Raises:
        ImageError: another encoding, or fewer bytes than ``step * height``.
    """
    encoding = str(msg.encoding).lower()
    kinds = {"16uc1": ("u2", 1e-3), "mono16": ("u2", 1e-3), "32fc1": ("f4", 1.0)}
    if encoding not in kinds:
        raise ImageError(
            f"{where}: depth encoding {msg.encoding!r} is not supported; expected 16UC1, mono16 "
            "(millimetres) or 32FC1 (metres)"
        )
    code, scale = kinds[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    dtype = np.dtype(code).newbyteorder(">" if msg.is_bigendian else "<")
    data = np.asarray(msg.data, dtype=np.uint8).ravel()
    if height <= 0 or width <= 0 or step < width * dtype.itemsize or data.size < step * height:
        raise ImageError(
            f"{where}: a {width} x {height} {msg.encoding} depth image needs step * height bytes; "
            f"found step {step} and {data.size} bytes"
        )
    rows = np.ascontiguousarray(data[: step * height].reshape(height, step)[:, : width * dtype.itemsize])
    depth = rows.view(dtype).astype(np.float32) * np.float32(scale)
    depth[~np.isfinite(depth) | (depth <= 0)] = np.nan
    return depth


class _Poses:
    """The robot's positions by stamp (for the loop edges), the latest ones kept."""

    def __init__(self, limit: int = 100_000) -> None:
        self.stamps: list[int] = []
        self.positions: list[np.ndarray] = []
        self.frame_id = ""
        self.limit = limit
        self.lock = threading.Lock()

    def add(self, stamp: int, position: np.ndarray, frame_id: str) -> None:
        with self.lock:
            self.frame_id = frame_id
            at = bisect.bisect(self.stamps, stamp)
            self.stamps.insert(at, stamp)
            self.positions.insert(at, position)
            if len(self.stamps) > self.limit:
                del self.stamps[0], self.positions[0]

    def near(self, stamp: int, tolerance_ns: int = 500_000_000) -> np.ndarray | None:
        with self.lock:
            at = bisect.bisect(self.stamps, stamp)
            best = [k for k in (at - 1, at) if 0 <= k < len(self.stamps)]
            if not best:
                return None
            k = min(best, key=lambda j: abs(self.stamps[j] - stamp))
            return self.positions[k] if abs(self.stamps[k] - stamp) <= tolerance_ns else None


class LoopClosureNode:
    """The node: readers, writers and the detector (see the module's docstring).

    Args:
        config: topics and QoS.
        detector: the loop detector (a persistent map continues at ``detector.next_index``).
        calibration: used when no CameraInfo topic is read (None: the detector's own).
    """

    def __init__(
        self, config: NodeConfig, detector: LoopDetector, calibration: Calibration | None = None
    ) -> None:
        self.config = config
        self.detector = detector
        self.summary = NodeSummary()
        self._slot = _Slot(config.skip)
        self._lock = threading.Lock()
        self._pending_left: dict[int, _Image] = {}
        self._pending_right: dict[int, _Image] = {}
        self._depths: dict[int, _Image] = {}
        self._infos: dict[str, Any] = {}  # CameraInfo topic -> its first usable message
        self._calibration = calibration
        self._calibration_ready = all(t is None for t in config.info_topics())
        self._poses = _Poses()
        self._positions: dict[int, np.ndarray] = {}  # entry id -> position, frames with a pose
        self._edges: list[tuple[np.ndarray, np.ndarray]] = []
        self._stamps: list[int] = [
            int(round(t * 1e9)) if np.isfinite(t) else 0
            for t in (detector.db.column("timestamp") if len(detector.db) else [])
        ]
        self._decide_ms: list[float] = []
        self._detect_ms: list[float] = []
        self._readers: list[tuple[Any, Callable[[Any], None]]] = []
        self._writers: dict[str, Any] = {}
        self._stop = threading.Event()
        self._waiting_said = False
        self._waiting_since: float | None = None
        self._open_endpoints()

    # ------------------------------------------------------------------------------------------
    # DDS

    def _open_endpoints(self) -> None:
        c = self.config
        did = c.domain
        description: dds.Description = "exact" if c.exact_types else "opaque"
        subs: list[tuple[str, str, dds.QosProfile, Callable[[Any], None]]] = [
            (c.image, c.image_type, c.input_qos, self._on_left)
        ]
        if c.right is not None:
            subs.append((c.right, c.image_type, c.input_qos, self._on_right))
        for topic in c.info_topics():
            if topic is not None:
                subs.append((topic, CAMERA_INFO, c.input_qos, self._info_handler(topic)))
        if c.depth is not None:
            subs.append((c.depth, IMAGE, c.input_qos, self._on_depth))
        if c.pose is not None:
            subs.append(
                (c.pose, POSE_STAMPED if c.pose_type == "pose" else ODOMETRY, c.input_qos, self._on_pose)
            )
        for topic, msgtype, profile, handler in subs:
            # every input at the camera's QoS: a best-effort reader matches best-effort and reliable
            # publishers alike (a reliable one would miss a driver's best-effort CameraInfo); poses
            # come in bursts faster than images, and each is wanted
            depth = POSE_HISTORY if msgtype in (POSE_STAMPED, ODOMETRY) else None
            reader = dds.reader(did, topic, msgtype, profile, description, depth)
            self._readers.append((reader, self._decoder(topic, msgtype, handler)))
        prefix = c.prefix.rstrip("/")
        self._writers[LOOP_CLOSURE] = dds.writer(did, f"{prefix}/loop_closure", LOOP_CLOSURE)
        self._writers[STRING] = dds.writer(did, f"{prefix}/loop_closure_json", STRING)
        if c.pose is not None:
            self._writers[MARKER_ARRAY] = dds.writer(did, f"{prefix}/loop_markers", MARKER_ARRAY)
        self._types = {t: dds.topic_type(t) for t in self._writers}

    def _decoder(self, topic: str, msgtype: str, handler: Callable[[Any], None]) -> Callable[[Any], None]:
        """A reader's sample handler: images go on as their stamp and bytes (decoded when used),
        other messages decoded; a malformed one is logged in one line and skipped."""
        image = msgtype in (IMAGE, COMPRESSED)

        def on_sample(sample: Any) -> None:
            try:
                if image:
                    stamp = peek_stamp(sample.payload, msgtype, topic)
                    handler(_Image(stamp, sample.payload, msgtype, topic, time.monotonic()))
                else:
                    handler(decode(sample.payload, msgtype, topic))
            except MessageError as exc:
                self.summary.malformed += 1
                log.warning("skipped a malformed message: %s", exc)

        return on_sample

    def _receive(self) -> None:
        """The receiver thread: take every sample of every reader as it arrives."""
        dds.cyclonedds()  # the install hint, should the imports below fail
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
        from cyclonedds.util import duration

        waitset = WaitSet(dds.participant(self.config.domain))
        mask = SampleState.Any | ViewState.Any | InstanceState.Any
        conditions = [ReadCondition(reader, mask) for reader, _ in self._readers]
        for cond in conditions:
            waitset.attach(cond)
        while not self._stop.is_set():
            waitset.wait(duration(milliseconds=100))
            for reader, handle in self._readers:
                while True:
                    samples = reader.take(64)
                    if not samples:
                        break
                    for sample in samples:
                        if getattr(sample, "payload", None) is None:
                            continue  # a writer gone (an invalid sample carries no message)
                        try:
                            handle(sample)
                        except Exception as exc:  # never let one message stop the receiver
                            self.summary.malformed += 1
                            log.warning(
                                "skipped a message that could not be used (%s: %s)", type(exc).__name__, exc
                            )

    # ------------------------------------------------------------------------------------------
    # what arrives

    def _on_left(self, img: _Image) -> None:
        self.summary.received += 1
        if self.config.right is None:
            self._deliver(_Pending(img))
            return
        with self._lock:
            right = self._match(self._pending_right, img.stamp_ns)
            if right is None:
                self._keep(self._pending_left, img)
                return
        self._deliver(_Pending(img, right))

    def _on_right(self, img: _Image) -> None:
        with self._lock:
            left = self._match(self._pending_left, img.stamp_ns)
            if left is None:
                self._keep(self._pending_right, img)
                return
        self._deliver(_Pending(left, img))

    def _match(self, pending: dict[int, _Image], stamp: int) -> _Image | None:
        """The waiting image nearest ``stamp`` within the stereo tolerance, taken out of ``pending``."""
        if not pending:
            return None
        tol = int(self.config.max_stereo_difference * 1e9)
        best = min(pending, key=lambda s: abs(s - stamp))
        if abs(best - stamp) > tol:
            return None
        # images older than the match never will be matched: a camera's stamps only increase
        for s in [s for s in pending if s < best]:
            del pending[s]
            self.summary.unpaired += 1
        return pending.pop(best)

    def _keep(self, pending: dict[int, _Image], img: _Image) -> None:
        pending[img.stamp_ns] = img
        while len(pending) > MAX_PENDING:
            del pending[min(pending)]
            self.summary.unpaired += 1

    def _on_depth(self, img: _Image) -> None:
        with self._lock:
            self._depths[img.stamp_ns] = img
            while len(self._depths) > MAX_PENDING:
                del self._depths[min(self._depths)]

    def _info_handler(self, topic: str) -> Callable[[Any], None]:
        def on_info(msg: Any) -> None:
            if topic not in self._infos:
                self._infos[topic] = msg
                self._calibrate()

        return on_info

    def _calibrate(self) -> None:
        """The calibration from the CameraInfo messages, once every one named has arrived."""
        from ..datasets.rosbag import CameraInfo, calibration_from_camera_info

        left_topic, right_topic = self.config.info_topics()
        names = [t for t in (left_topic, right_topic) if t is not None]
        if self._calibration_ready or not all(t in self._infos for t in names):
            return
        try:
            infos = [CameraInfo.from_message(self._infos[t], t) for t in names]
            if any(not i.calibrated for i in infos):
                log.warning("%s says the camera is uncalibrated (K is zero): no calibration", names[0])
                self._calibration = None
            else:
                self._calibration = calibration_from_camera_info(
                    infos[0],
                    infos[1] if len(infos) > 1 else None,
                    rectified=self.config.is_rectified,
                    source=names[0],
                )
        except (CalibrationError, ValueError, TypeError, AttributeError) as exc:
            self.summary.malformed += 1
            log.warning("skipped an unusable CameraInfo (%s): no calibration", exc)
            self._calibration = None
        self._calibration_ready = True

    def _on_pose(self, msg: Any) -> None:
        pose = msg.pose.pose if self.config.pose_type == "odometry" else msg.pose
        p = pose.position
        self._poses.add(
            stamp_ns(msg.header.stamp), np.array([p.x, p.y, p.z], np.float64), str(msg.header.frame_id)
        )

    def _deliver(self, item: _Pending) -> None:
        if self.config.depth is not None:
            with self._lock:
                item.depth = self._match(self._depths, item.left.stamp_ns)
        self._slot.put(item)

    # ------------------------------------------------------------------------------------------
    # deciding

    def run(
        self,
        *,
        max_frames: int | None = None,
        idle_timeout: float | None = None,
        on_decision: Callable[[dict[str, Any]], None] | None = None,
    ) -> NodeSummary:
        """Receive and decide until :meth:`stop`, ``max_frames`` frames, or ``idle_timeout`` seconds
        without a frame once one has come; returns the summary (the map is left open)."""
        receiver = threading.Thread(target=self._receive, name="stablecues-ros2-receiver", daemon=True)
        start = time.monotonic()
        cpu0 = _cpu_s()
        self.summary.first_index = -1
        self.summary.session = int(self.detector.db.session)
        index = self.detector.next_index
        log.info("map holds %d frames; numbering on from frame %d", len(self.detector.db), index)
        receiver.start()
        last_frame = time.monotonic()
        try:
            while not self._stop.is_set():
                if max_frames is not None and self.summary.processed >= max_frames:
                    break
                if not self._calibration_ready:
                    self._say_waiting()
                    time.sleep(0.02)
                    continue
                item = self._slot.get(0.1)
                if item is None:
                    if (
                        idle_timeout is not None
                        and self.summary.received
                        and time.monotonic() - last_frame > idle_timeout
                    ):
                        break
                    continue
                last_frame = time.monotonic()
                out = self._decide(item, index)
                if out is None:
                    continue
                if on_decision is not None:
                    on_decision(out)
                index += 1
        finally:
            self._stop.set()
            receiver.join(timeout=2.0)
            self.summary.skipped = self._slot.skipped
            self.summary.map_frames = len(self.detector.db)
            self.summary.cpu_s = _cpu_s() - cpu0
            self.summary.wall_s = time.monotonic() - start
            if self._decide_ms:
                self.summary.decide_ms = float(np.median(self._decide_ms))
                self.summary.detect_ms = float(np.median(self._detect_ms))
        return self.summary

    def stop(self) -> None:
        """Ask :meth:`run` to return (from a signal handler or another thread)."""
        self._stop.set()

    def _say_waiting(self) -> None:
        """Say, once, that frames wait for the CameraInfo: at once in the log's detail, and as a
        warning when it has not come 5 s after the first frame (a camera publishing none needs
        ``--camera-info none`` or ``--calib``)."""
        if self.summary.received and self._waiting_since is None:
            self._waiting_since = time.monotonic()
            log.info("waiting for CameraInfo on %s before deciding", " and ".join(self._info_names()))
        if (
            not self._waiting_said
            and self._waiting_since is not None
            and time.monotonic() - self._waiting_since > CAMERA_INFO_PATIENCE
        ):
            log.warning(
                "no CameraInfo on %s yet, %g s after the first frame: frames wait (kept as the "
                "skip policy says); give --camera-info none or --calib FILE for a camera without one",
                " and ".join(self._info_names()),
                CAMERA_INFO_PATIENCE,
            )
            self._waiting_said = True

    def _info_names(self) -> list[str]:
        return [t for t in self.config.info_topics() if t is not None]

    def _frame(self, item: _Pending, index: int) -> Any:
        """The detector's Frame of a pending item.

        Raises:
            ImageError: an image that cannot be read (logged and skipped by the caller).
        """
        from ..datasets.rosbag import image_from_compressed, image_from_raw
        from ..types import Frame

        read = image_from_compressed if self.config.image_type == COMPRESSED else image_from_raw
        left = item.left.message()
        item.frame_id = str(left.header.frame_id)
        image = read(left, f"{self.config.image} message at {item.left.stamp_ns} ns")
        right = None
        if item.right is not None and self.config.right is not None:
            right = read(item.right.message(), f"{self.config.right} message at {item.right.stamp_ns} ns")
        depth = None
        if item.depth is not None and self.config.depth is not None:
            depth = depth_from_image(
                item.depth.message(), f"{self.config.depth} message at {item.depth.stamp_ns} ns"
            )
        label = self.config.image.strip("/")
        return Frame(
            index=index,
            name=f"{label}/{item.left.stamp_ns}",
            timestamp=item.left.stamp_ns * 1e-9,
            image=image,
            right=right,
            depth=depth,
            calibration=self._calibration,
        )

    def _decide(self, item: _Pending, index: int) -> dict[str, Any] | None:
        """Decide one frame and publish the decision; the decision's JSON fields, or None when the
        frame could not be read (logged in one line)."""
        try:
            frame = self._frame(item, index)
            decision = self.detector.process(frame)
        except (ImageError, MessageError) as exc:
            self.summary.malformed += 1
            log.warning("skipped a malformed image: %s", exc)
            return None
        except StableCuesError as exc:  # an input the detector refuses: said, and the node goes on
            self.summary.malformed += 1
            log.warning("skipped a frame the detector refused: %s", exc)
            return None
        self._stamps.append(item.left.stamp_ns)
        if self.summary.first_index < 0:
            self.summary.first_index = index
        self.summary.last_index = index
        self.summary.processed += 1
        self.summary.loops += int(decision.accepted)
        out = self._publish(item, decision)
        self._decide_ms.append((time.monotonic() - item.left.arrived) * 1e3)
        self._detect_ms.append(float(decision.timings.get("total", float("nan"))))
        return out

    def _publish(self, item: _Pending, d: LoopDecision) -> dict[str, Any]:
        v = d.verification
        cand_stamp = self._stamps[d.candidate] if 0 <= d.candidate < len(self._stamps) else 0
        msg = loop_closure_msg(
            stamp=item.left.stamp_ns,
            frame_id=item.frame_id,
            query_index=d.frame_index,
            candidate_index=d.candidate_frame,
            candidate_stamp=cand_stamp,
            accepted=d.accepted,
            status=d.status.value,
            score=d.confidence if d.candidate >= 0 else float("nan"),
            raw_score=d.raw_score if d.candidate >= 0 else float("nan"),
            inliers=0 if v is None else int(v.n_inliers),
            verifier="" if v is None else str(v.method),
            relative_pose=d.relative_pose if d.accepted else None,
        )
        fields = loop_closure_dict(msg)
        self._write(LOOP_CLOSURE, encode(msg, LOOP_CLOSURE))
        self._write(STRING, encode(string_msg(fields), STRING))
        if MARKER_ARRAY in self._writers:
            self._publish_edges(item, d)
        return fields

    def _publish_edges(self, item: _Pending, d: LoopDecision) -> None:
        here = self._poses.near(item.left.stamp_ns)
        if here is not None and d.entry_id >= 0:
            self._positions[d.entry_id] = here
        there = self._positions.get(d.candidate)
        if d.accepted and here is not None and there is not None:
            self._edges.append((here, there))
            markers = loop_markers_msg(self._edges, item.left.stamp_ns, self._poses.frame_id or "map")
            self._write(MARKER_ARRAY, encode(markers, MARKER_ARRAY))

    def _write(self, msgtype: str, payload: bytes) -> None:
        try:
            self._writers[msgtype].write(self._types[msgtype](payload))
        except Exception as exc:  # a writer refusing (a full history under load): said, not fatal
            log.warning("could not publish a %s (%s)", msgtype, exc)


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return float(usage.ru_utime + usage.ru_stime)

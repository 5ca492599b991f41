"""ROS 1 and ROS 2 bags as a sequence of frames, read with the pure-Python ``rosbags`` package.

What opens (no ROS install needed; ``pip install "stablecues[rosbag]"``)::

    run.bag                     ROS 1 bag (any chunk compression)
    run/metadata.yaml + *.db3   ROS 2 bag folder, sqlite3 storage
    run/metadata.yaml + *.mcap  ROS 2 bag folder, MCAP storage
    run_0.db3, run_0.mcap       a ROS 2 storage file on its own

Frames come from ``sensor_msgs/Image`` (mono8, mono16, bgr8, rgb8, bgra8, rgba8, 8UC1/3/4,
16UC1, bgr16/rgb16, Bayer 8-bit, yuv422) or ``sensor_msgs/CompressedImage`` (JPEG, PNG ...,
decoded with ``cv2.imdecode`` after its header gave a size within
:data:`stablecues.limits.MAX_IMAGE_PIXELS`) topics. With no topic given, the one camera (a raw
topic preferred to its ``/compressed`` twin) or the one stereo pair (topics that differ only
in ``left``/``right``, ``0``/``1`` or ``1``/``2``) is taken; a bag with more cameras needs
``topic=``. A right image is matched to each left image by stamp, at most
``max_stereo_difference`` apart; left images without one are dropped (and counted).

Stamps are the messages' header stamps (``stamps="header"``), the time the bag recorded them
(``"bag"``), or (``"auto"``) the header stamps unless one of them is zero. The calibration comes
from the ``sensor_msgs/CameraInfo`` beside each image topic (``/cam0/image_raw`` ->
``/cam0/camera_info``): ``K`` and ``D`` (plumb_bob) for raw images, ``P`` for rectified ones
(a topic named ``image_rect*``), and for a stereo pair the right camera's ``P[0, 3] = -fx * B``
gives the baseline ``B`` and ``R``/``P`` of both give the rectification. The first message of
each CameraInfo topic is used. A camera whose ``K`` is zero (ROS's "uncalibrated") gives no
calibration; depth images of an RGB-D bag are not read as depth.

Opening reads every message of the chosen image topics once (to index their stamps); a frame
is then read from the bag when asked for.
"""

from __future__ import annotations

import functools
import logging
import math
import stat
import threading
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple

import cv2
import numpy as np

from ..errors import CalibrationError, ConfigError, DatasetError, ImageError, reason
from ..fileio import captured_stderr
from ..geometry.camera import Calibration, PinholeCamera, Rectification
from ..imageio import check_decoded_bytes, header_size, image_format, to_grey
from ..limits import MAX_BAG_METADATA_BYTES, MAX_IMAGE_PIXELS, check_file_size
from ..trajectory import nearest, ns_to_seconds
from ..types import Frame
from .base import FrameRecord, SequenceDataset

__all__ = [
    "BAG_SUFFIXES",
    "BagTopic",
    "CameraInfo",
    "RosbagDataset",
    "bag_summary",
    "bag_topics",
    "calibration_from_camera_info",
    "image_from_compressed",
    "image_from_raw",
    "is_bag",
    "open_rosbag",
]

logger = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE_TYPES = (IMAGE, COMPRESSED)
BAG_SUFFIXES = (".bag", ".db3", ".mcap")

StampSource = Literal["auto", "header", "bag"]

# ROS image encoding (lower case) -> (dtype, channels, OpenCV conversion to BGR or None)
_ENCODINGS: dict[str, tuple[type[np.unsignedinteger[Any]], int, int | None]] = {
    "mono8": (np.uint8, 1, None),
    "8uc1": (np.uint8, 1, None),
    "mono16": (np.uint16, 1, None),
    "16uc1": (np.uint16, 1, None),
    "bgr8": (np.uint8, 3, None),
    "8uc3": (np.uint8, 3, None),
    "rgb8": (np.uint8, 3, cv2.COLOR_RGB2BGR),
    "bgra8": (np.uint8, 4, cv2.COLOR_BGRA2BGR),
    "8uc4": (np.uint8, 4, cv2.COLOR_BGRA2BGR),
    "rgba8": (np.uint8, 4, cv2.COLOR_RGBA2BGR),
    "bgr16": (np.uint16, 3, None),
    "16uc3": (np.uint16, 3, None),
    "rgb16": (np.uint16, 3, cv2.COLOR_RGB2BGR),
    "bgra16": (np.uint16, 4, cv2.COLOR_BGRA2BGR),
    "rgba16": (np.uint16, 4, cv2.COLOR_RGBA2BGR),
    # OpenCV names a Bayer pattern after its second row (as cv_bridge maps them)
    "bayer_rggb8": (np.uint8, 1, cv2.COLOR_BayerBG2BGR),
    "bayer_bggr8": (np.uint8, 1, cv2.COLOR_BayerRG2BGR),
    "bayer_gbrg8": (np.uint8, 1, cv2.COLOR_BayerGR2BGR),
    "bayer_grbg8": (np.uint8, 1, cv2.COLOR_BayerGB2BGR),
    "yuv422": (np.uint8, 2, cv2.COLOR_YUV2BGR_UYVY),
    "uyvy": (np.uint8, 2, cv2.COLOR_YUV2BGR_UYVY),
    "yuv422_yuy2": (np.uint8, 2, cv2.COLOR_YUV2BGR_YUY2),
    "yuyv": (np.uint8, 2, cv2.COLOR_YUV2BGR_YUY2),
}

# YUV 4:2:2 conversions: two pixels share their chroma, so a row holds an even number of them
_PAIRED_PIXELS = (cv2.COLOR_YUV2BGR_UYVY, cv2.COLOR_YUV2BGR_YUY2)

# topic name parts that tell the two cameras of a stereo pair apart (left first)
_PAIR_TOKENS = (("left", "right"), ("Left", "Right"), ("LEFT", "RIGHT"), ("0", "1"), ("1", "2"))


def is_bag(path: str | Path) -> bool:
    """Whether ``path`` looks like a ROS bag: a ``.bag``, ``.db3`` or ``.mcap`` file, or a folder
    whose ``metadata.yaml`` is a ROS 2 bag's (only its first kilobytes are read)."""
    p = Path(path)
    if p.is_file():
        return p.suffix.lower() in BAG_SUFFIXES
    meta = p / "metadata.yaml"
    if not meta.is_file():
        return False
    try:
        with meta.open("rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return b"rosbag2_bagfile_information" in head


# ----------------------------------------------------------------------------------------------
# the bag reader and its errors


def _anyreader() -> Any:
    from rosbags.highlevel import AnyReader

    return AnyReader


def _open_reader(path: Path) -> Any:
    """An opened ``rosbags`` AnyReader of the bag at ``path``.

    Raises:
        DatasetError: the bag is missing, not a bag, truncated or corrupt (naming the file).
    """
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise DatasetError(f"{path}: ROS bag not found")
    if not is_bag(path):
        raise DatasetError(
            f"{path}: expected a ROS bag (a .bag, .db3 or .mcap file, or a ROS 2 bag folder with "
            "metadata.yaml)"
        )
    if path.is_dir():
        _check_bag_folder(path)
    # a bare .db3 of an older ROS 2 holds no message definitions: the standard ones are used
    default = get_typestore(Stores.ROS1_NOETIC if path.suffix == ".bag" else Stores.ROS2_HUMBLE)
    reader = None
    try:
        reader = _anyreader()([path], default_typestore=default)
        reader.open()
    except Exception as exc:  # rosbags raises assorted errors on a truncated or corrupt bag
        raise DatasetError(f"{path}: not a readable ROS bag ({reason(exc)})") from None
    return reader


def _check_bag_folder(path: Path) -> None:
    """A ROS 2 bag folder holds regular files only (a FIFO or a device named like its storage
    file would block the reader forever), and its ``metadata.yaml`` is of a sane size (real ones
    are a few kilobytes; parsing runs at about 1 s a megabyte)."""
    check_file_size(path / "metadata.yaml", MAX_BAG_METADATA_BYTES, "ROS 2 bag metadata")
    try:
        entries = sorted(path.iterdir())
    except OSError as exc:
        raise DatasetError(f"{path}: cannot list the bag folder ({exc.strerror or exc})") from None
    for entry in entries:
        try:
            mode = entry.stat().st_mode  # a link is judged by what it points to
        except OSError:
            continue  # a dangling link: the reader names it if the bag needs it
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            raise DatasetError(f"{entry}: not a regular file (a FIFO, device or socket) inside a ROS 2 bag "
                               "folder; a bag's files must be regular files")


def _messages(
    reader: Any, path: Path, connections: Sequence[Any], start: int | None = None, stop: int | None = None
) -> Iterator[tuple[Any, int, bytes]]:
    """``reader.messages`` with its errors (a truncated chunk, a bad record) as DatasetError."""
    try:
        for conn, t, raw in reader.messages(connections, start=start, stop=stop):
            if not isinstance(t, int) or isinstance(t, bool):  # a .db3's timestamp column is free-form
                raise DatasetError(f"{path}: {conn.topic}: a message's bag time is {t!r:.40}, not whole "
                                   "nanoseconds (a corrupt bag)")
            yield conn, t, raw
    except DatasetError:
        raise
    except Exception as exc:  # rosbags raises assorted errors on corrupt records
        raise DatasetError(f"{path}: a corrupt or truncated ROS bag ({reason(exc)})") from None


def _deserialize(reader: Any, path: Path, conn: Any, raw: bytes, bag_ns: int) -> Any:
    try:
        msg = reader.deserialize(raw, conn.msgtype)
    except Exception as exc:  # a message shorter than its type or of another layout
        raise DatasetError(
            f"{path}: {conn.topic} message at bag time {bag_ns} ns is not a valid {conn.msgtype} "
            f"({reason(exc)})"
        ) from None
    _check_fields(msg, path, conn)
    return msg


def _is_int(v: Any) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool)


def _is_bytes(v: Any) -> bool:
    return isinstance(v, np.ndarray) and v.dtype == np.uint8 and v.ndim == 1


def _is_floats(v: Any) -> bool:
    return isinstance(v, np.ndarray | list | tuple) and all(
        isinstance(x, float | int | np.floating | np.integer) and not isinstance(x, bool) for x in v)


#: the fields each message type the reader takes must carry, and what each must be: a bag may
#: carry its own definition of a type (ROS 1, MCAP and db3 all store them), and one that drops
#: a field or changes its type would otherwise fail deep inside the reader
_INT, _TEXT = (_is_int, "an integer"), (lambda v: isinstance(v, str), "text")
_FIELDS: dict[str, tuple[tuple[str, Callable[[Any], bool], str], ...]] = {
    IMAGE: (("height", *_INT), ("width", *_INT), ("step", *_INT), ("encoding", *_TEXT),
            ("is_bigendian", *_INT), ("data", _is_bytes, "uint8[]")),
    COMPRESSED: (("format", *_TEXT), ("data", _is_bytes, "uint8[]")),
    CAMERA_INFO: (("height", *_INT), ("width", *_INT), ("distortion_model", *_TEXT),
                  ("d", _is_floats, "float64[]"), ("k", _is_floats, "float64[9]"),
                  ("r", _is_floats, "float64[9]"), ("p", _is_floats, "float64[12]")),
}


def _check_fields(msg: Any, path: Path, conn: Any) -> None:
    """Refuse, in one line naming the topic and the field, a message of a type the reader takes
    whose (bag-defined) layout lacks a field it reads or gives it another type."""
    fields = _FIELDS.get(conn.msgtype)
    if fields is None:
        return
    where = f"{path}: {conn.topic}: {conn.msgtype}"
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if not (_is_int(getattr(stamp, "sec", None)) and _is_int(getattr(stamp, "nanosec", None))):
        raise DatasetError(f"{where} has no header.stamp of whole seconds and nanoseconds (the bag's "
                           "definition of the type differs from ROS's)")
    for name, ok, kind in fields:
        value = getattr(msg, name, None)
        if value is None and len(name) == 1:  # ROS 1's CameraInfo: D, K, R, P
            value = getattr(msg, name.upper(), None)
        if not ok(value):
            raise DatasetError(f"{where}: field {name!r} is missing or not {kind} (the bag's definition of "
                               "the type differs from ROS's)")


def _stamp_ns(msg: Any) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


# ----------------------------------------------------------------------------------------------
# images


def _as_bgr8(image: np.ndarray, grey: bool) -> np.ndarray:
    """uint8/uint16 (H, W[, C]) -> uint8 (H, W) or (H, W, 3) BGR (16 bits scaled down, alpha dropped)."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if grey and image.ndim == 3:
        image = to_grey(image)
    return np.ascontiguousarray(image)


def _check_size(where: str, width: int, height: int) -> None:
    if width <= 0 or height <= 0:
        raise ImageError(f"{where}: expected a positive image size, found {width} x {height}")
    if width * height > MAX_IMAGE_PIXELS:
        raise ImageError(
            f"{where}: a {width} x {height} image is larger than the {MAX_IMAGE_PIXELS} pixels accepted "
            "(stablecues.limits)"
        )


def image_from_raw(msg: Any, where: str, *, grey: bool = False) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` message.

    Args:
        msg: the deserialised message (``height``, ``width``, ``encoding``, ``is_bigendian``,
            ``step``, ``data``).
        where: the bag and topic, for messages.
        grey: convert colour to grey.

    Returns:
        (H, W) uint8 grey or (H, W, 3) uint8 BGR (16-bit images scaled down by 256, alpha
        dropped, Bayer and YUV converted to BGR).

    Raises:
        ImageError: an unsupported encoding, a size over the limit, or fewer bytes than
            ``step * height`` (or a ``step`` shorter than a row).
    """
    encoding = str(msg.encoding)
    spec = _ENCODINGS.get(encoding.lower())
    if spec is None:
        raise ImageError(
            f"{where}: image encoding {encoding!r} is not supported; expected one of {', '.join(_ENCODINGS)}"
        )
    dtype, channels, conversion = spec
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    _check_size(where, width, height)
    if conversion in _PAIRED_PIXELS and width % 2:
        raise ImageError(f"{where}: a {encoding} image stores pixels in pairs; its width must be even, "
                         f"found {width}")
    row = width * channels * np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8).ravel()
    if step < row or data.size < step * height:
        raise ImageError(
            f"{where}: a {width} x {height} {encoding} image needs rows of at least {row} bytes and "
            f"step * height bytes; found step {step} and {data.size} bytes"
        )
    rows = np.ascontiguousarray(data[: step * height].reshape(height, step)[:, :row])
    stored = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    pixels = rows.view(stored).astype(dtype)
    image = pixels.reshape(height, width, channels)
    if conversion is not None:
        image = cv2.cvtColor(image if channels > 1 else image[:, :, 0], conversion)
    return _as_bgr8(image, grey)


def image_from_compressed(msg: Any, where: str, *, grey: bool = False) -> np.ndarray:
    """The pixels of a ``sensor_msgs/CompressedImage`` message (JPEG, PNG, BMP, PNM, TIFF, WebP).

    The size is read from the image's header before anything is decoded.

    Returns:
        (H, W) uint8 grey or (H, W, 3) uint8 BGR, as :func:`image_from_raw`.

    Raises:
        ImageError: a ``compressedDepth`` message, an unknown or damaged image, a size over the
            limit, or data that does not decode.
    """
    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower():
        raise ImageError(f"{where}: format {fmt!r} is a depth image; expected a camera image (jpeg, png)")
    data = np.asarray(msg.data, dtype=np.uint8).ravel()
    buf = data.tobytes()
    kind = image_format(buf)
    if kind is None:
        raise ImageError(f"{where}: compressed image ({fmt!r}) is not a JPEG, PNG, BMP, PNM, TIFF or WebP")
    size = header_size(buf)
    if size is None:
        raise ImageError(f"{where}: compressed image with a damaged {kind} header")
    _check_size(where, *size)
    check_decoded_bytes(where, buf, size)
    with captured_stderr() as printed:
        try:
            image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        except cv2.error:
            image = None
    # a truncated image decodes to grey fill after the data ends (a 589-byte JPEG whose header
    # claims 65500 x 1000 gave a 65-megapixel frame): libjpeg says so, and the frame is refused
    cut = [line for line in printed.lines if "premature end" in line.lower()]
    if image is None or image.dtype not in (np.uint8, np.uint16) or cut:
        why = f"; {(cut or printed.lines)[0][:120]}" if printed.lines else ""
        raise ImageError(f"{where}: a corrupt {kind} image{why}")
    return _as_bgr8(image, grey)


# ----------------------------------------------------------------------------------------------
# calibration


@dataclass(frozen=True, eq=False)
class CameraInfo:
    """What a ``sensor_msgs/CameraInfo`` message says, as plain arrays.

    Attributes:
        topic: the topic it came from.
        width: image width in pixels (0 when unset).
        height: image height in pixels.
        distortion_model: ``plumb_bob``, ``rational_polynomial``, ``equidistant`` ...
        D: distortion coefficients, as many as the message holds.
        K: (3, 3) float64 intrinsics of the raw image (zero when uncalibrated).
        R: (3, 3) float64 rectification rotation (raw camera -> rectified camera).
        P: (3, 4) float64 projection of the rectified image (``P[0, 3] = -fx * B`` for the right
            camera of a stereo pair).
    """

    topic: str
    width: int
    height: int
    distortion_model: str
    D: tuple[float, ...]
    K: np.ndarray
    R: np.ndarray
    P: np.ndarray

    @staticmethod
    def from_message(msg: Any, topic: str) -> CameraInfo:
        """From a deserialised message of ROS 1 (``D K R P``) or ROS 2 (``d k r p``)."""

        def arr(name: str, n: int) -> np.ndarray:
            value = getattr(msg, name, None)
            if value is None:
                value = getattr(msg, name.lower())
            out = np.asarray(value, dtype=np.float64).ravel()
            if out.size != n:
                raise CalibrationError(f"{topic}: CameraInfo {name}: expected {n} numbers, found {out.size}")
            return out

        d = getattr(msg, "D", None)
        d = msg.d if d is None else d
        return CameraInfo(
            topic=topic,
            width=int(msg.width),
            height=int(msg.height),
            distortion_model=str(msg.distortion_model),
            D=tuple(float(v) for v in np.asarray(d, dtype=np.float64).ravel()),
            K=arr("K", 9).reshape(3, 3),
            R=arr("R", 9).reshape(3, 3),
            P=arr("P", 12).reshape(3, 4),
        )

    @property
    def calibrated(self) -> bool:
        """False for ROS's "uncalibrated camera" (``K[0, 0] == 0``)."""
        return bool(self.K[0, 0] != 0.0)


def _size(info: CameraInfo) -> tuple[int | None, int | None]:
    return (info.width or None, info.height or None) if info.width > 0 and info.height > 0 else (None, None)


def _distortion(info: CameraInfo, source: str) -> tuple[float, ...]:
    """The coefficients as OpenCV's ``k1 k2 p1 p2 [k3]``.

    Raises:
        CalibrationError: a model other than plumb_bob (or rational_polynomial reduced to it)
            with nonzero coefficients.
    """
    d = np.asarray(info.D, dtype=np.float64)
    if not np.isfinite(d).all():
        raise CalibrationError(f"{source}: {info.topic}: expected finite distortion numbers, found {info.D}")
    model = info.distortion_model.lower()
    if not d.any():
        return ()
    if model in ("plumb_bob", "radtan", "radial-tangential", "") and d.size in (4, 5):
        return tuple(d)
    if model in ("plumb_bob", "rational_polynomial") and d.size >= 5 and not d[5:].any():
        return tuple(d[:5])
    raise CalibrationError(
        f"{source}: {info.topic}: distortion model {info.distortion_model!r} with {d.size} coefficients "
        "is not supported; expected plumb_bob (k1 k2 p1 p2 [k3])"
    )


def _checked(info: CameraInfo, source: str) -> None:
    for name in ("K", "R", "P"):
        if not np.isfinite(getattr(info, name)).all():
            raise CalibrationError(f"{source}: {info.topic}: CameraInfo {name}: expected finite numbers")


def _rotation(info: CameraInfo, source: str) -> np.ndarray:
    r = info.R
    if not (np.allclose(r @ r.T, np.eye(3), atol=1e-4) and np.linalg.det(r) > 0):
        raise CalibrationError(f"{source}: {info.topic}: CameraInfo R: expected a rotation matrix")
    return r


def calibration_from_camera_info(
    left: CameraInfo, right: CameraInfo | None = None, *, rectified: bool = False, source: str = ""
) -> Calibration:
    """The calibration that one or two ``CameraInfo`` messages describe.

    Args:
        left: the left (or only) camera.
        right: the right camera of a stereo pair, or None.
        rectified: the images are rectified (``image_rect``): the cameras are ``P``'s, without
            distortion; otherwise they are ``K`` with ``D``.
        source: the bag, for messages.

    Returns:
        Monocular: the left camera. Stereo and rectified: :meth:`Calibration.rectified_stereo`
        with the baseline ``-P_right[0, 3] / P_right[0, 0]``. Stereo and raw: both cameras with
        the rig's rectification from ``R`` and ``P`` of both, and the left-to-right transform it
        implies (``X_r = R_r^T (R_l X_l - [B, 0, 0])``).

    Raises:
        CalibrationError: an uncalibrated camera (``K`` zero), non-finite numbers, an unsupported
            distortion model, a right camera whose ``P`` gives no positive baseline, or an ``R``
            that is not a rotation.
    """
    where = source or left.topic
    for info in (left, right):
        if info is None:
            continue
        _checked(info, where)
        if not info.calibrated:
            raise CalibrationError(f"{where}: {info.topic}: the camera is uncalibrated (K is zero)")
    width, height = _size(left)
    if rectified:
        cam = PinholeCamera.from_matrix(left.P[:, :3], width=width, height=height)
    else:
        cam = PinholeCamera.from_matrix(left.K, _distortion(left, where), width=width, height=height)
    if right is None:
        return Calibration(left=cam, source=where)
    baseline = float(-right.P[0, 3] / right.P[0, 0]) if right.P[0, 0] != 0 else float("nan")
    if not (math.isfinite(baseline) and baseline > 0):
        raise CalibrationError(
            f"{where}: {right.topic}: expected P[0, 3] = -fx * baseline < 0 for the right camera, "
            f"found P[0, 3] = {right.P[0, 3]}, fx = {right.P[0, 0]}"
        )
    if rectified:
        return Calibration.rectified_stereo(cam, baseline, source=where)
    r_width, r_height = _size(right)
    right_cam = PinholeCamera.from_matrix(right.K, _distortion(right, where), width=r_width, height=r_height)
    r1, r2 = _rotation(left, where), _rotation(right, where)
    rect = Rectification(R1=r1, R2=r2, P1=left.P, P2=right.P)
    return Calibration(
        left=cam,
        right=right_cam,
        rotation=r2.T @ r1,
        translation=-r2.T @ np.array([baseline, 0.0, 0.0]),
        rectified=False,
        rectification=rect,
        source=where,
    )


def _load_camera_info(
    _path: Path, left: CameraInfo, right: CameraInfo | None, rectified: bool, source: str
) -> Calibration:
    """``calibration_loader`` of a bag dataset: its calibration, built on first use."""
    return calibration_from_camera_info(left, right, rectified=rectified, source=source)


# ----------------------------------------------------------------------------------------------
# topics


@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag, for ``stablecues info``.

    Attributes:
        name: the topic.
        msgtype: its message type (``sensor_msgs/msg/Image``).
        count: number of messages.
        rate_hz: messages per second over the topic's span of bag time, or None (< 2 messages).
        image_size: (width, height) of its first message, for image and CameraInfo topics.
        encoding: the first image's encoding (Image) or format (CompressedImage), or None.
    """

    name: str
    msgtype: str
    count: int
    rate_hz: float | None = None
    image_size: tuple[int, int] | None = None
    encoding: str | None = None


def _first_image_details(msg: Any, msgtype: str) -> tuple[tuple[int, int] | None, str | None]:
    if msgtype == IMAGE:
        return (int(msg.width), int(msg.height)), str(msg.encoding)
    if msgtype == COMPRESSED:
        return header_size(np.asarray(msg.data, np.uint8).tobytes()), str(msg.format)
    if msgtype == CAMERA_INFO:
        return (int(msg.width), int(msg.height)), str(msg.distortion_model)
    return None, None


def bag_topics(path: str | Path) -> list[BagTopic]:
    """Every topic of a bag with its type, message count, rate and (images) size.

    Reads every message once (the rates need each message's bag time); deserialises only the
    first message of image and CameraInfo topics.

    Raises:
        DatasetError: a missing, truncated or corrupt bag.
    """
    bag = Path(path)
    reader = _open_reader(bag)
    try:
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        details: dict[str, tuple[tuple[int, int] | None, str | None]] = {}
        for conn, t, raw in _messages(reader, bag, reader.connections):
            first.setdefault(conn.topic, t)
            last[conn.topic] = t
            if conn.topic not in details and conn.msgtype in (*IMAGE_TYPES, CAMERA_INFO):
                msg = _deserialize(reader, bag, conn, raw, t)
                details[conn.topic] = _first_image_details(msg, conn.msgtype)
        out = []
        for name, info in sorted(reader.topics.items()):
            span = (last.get(name, 0) - first.get(name, 0)) * 1e-9
            rate = (info.msgcount - 1) / span if info.msgcount > 1 and span > 0 else None
            size, encoding = details.get(name, (None, None))
            out.append(BagTopic(name, str(info.msgtype), int(info.msgcount), rate, size, encoding))
        return out
    finally:
        reader.close()


def _base(topic: str) -> str:
    """The camera stream a topic belongs to: ``/cam0/image_raw/compressed`` -> ``/cam0/image_raw``."""
    for suffix in ("/compressed", "/theora"):
        if topic.endswith(suffix):
            return topic[: -len(suffix)]
    return topic


def _streams(image_topics: dict[str, str]) -> list[str]:
    """One topic per camera stream (raw preferred to compressed), depth topics left out."""
    chosen: dict[str, str] = {}
    for topic in sorted(image_topics):
        if "depth" in topic.lower():
            continue
        base = _base(topic)
        if base not in chosen or image_topics[topic] == IMAGE:
            chosen[base] = topic
    return sorted(chosen.values())


def _pair(a: str, b: str) -> tuple[str, str] | None:
    """(left, right) when topics ``a`` and ``b`` differ only in one left/right token."""
    for x, y in ((a, b), (b, a)):
        for lt, rt in _PAIR_TOKENS:
            at = x.find(lt)
            while at >= 0:
                if x[:at] + rt + x[at + len(lt) :] == y:
                    return x, y
                at = x.find(lt, at + 1)
    return None


def _partner(topic: str, streams: list[str]) -> str | None:
    """The one other stream that pairs with ``topic`` as its right camera, or None."""
    found = [s for s in streams if s != topic and _pair(topic, s) == (topic, s)]
    return found[0] if len(found) == 1 else None


def _choose_topics(
    bag: Path, image_topics: dict[str, str], topic: str | None, right_topic: str | None, stereo: bool
) -> tuple[str, str | None]:
    """(left topic, right topic or None) given what was asked and what the bag holds.

    Raises:
        DatasetError: a named topic that is not an image topic of the bag, no image topic, or
            several cameras and no topic named.
    """
    listed = ", ".join(f"{t} ({image_topics[t].rsplit('/', 1)[-1]})" for t in sorted(image_topics)) or "none"
    for t in (topic, right_topic):
        if t is not None and t not in image_topics:
            raise DatasetError(f"{bag}: expected an image topic, {t!r} is not one; image topics: {listed}")
    streams = _streams(image_topics)
    if topic is not None:
        right = right_topic if right_topic is not None else (_partner(topic, streams) if stereo else None)
        return topic, right
    if not streams:
        raise DatasetError(f"{bag}: expected a sensor_msgs/Image or CompressedImage topic, found {listed}")
    if len(streams) == 1:
        return streams[0], right_topic
    if len(streams) == 2 and (pair := _pair(*streams)) is not None:
        return pair if stereo else (pair[0], None)
    raise DatasetError(
        f"{bag}: {len(streams)} cameras, expected one (or one stereo pair); name the topic to use "
        f"(topic=, right_topic=); image topics: {listed}"
    )


def _info_topic(image_topic: str, info_topics: list[str]) -> str | None:
    """The CameraInfo topic beside an image topic (same namespace), or the only one there is."""
    base = _base(image_topic)
    namespace = base.rsplit("/", 1)[0]
    for cand in (f"{namespace}/camera_info", f"{base}/camera_info"):
        if cand in info_topics:
            return cand
    return None


# ----------------------------------------------------------------------------------------------
# the dataset


class _Message(NamedTuple):
    """Where a message is: its bag time, and its rank among the topic's messages of that time."""

    bag_ns: int
    ordinal: int
    stamp_ns: int


@dataclass
class RosbagDataset(SequenceDataset):
    """Frames of one image topic (or a stereo pair of them) of a ROS bag; see :func:`open_rosbag`.

    ``root`` is the bag (file or folder). The bag stays open while frames are read (``close()``
    or ``with`` closes it; a pickled copy reopens it on first use).

    Attributes:
        topic: the left (or only) image topic.
        right_topic: the right image topic of a stereo pair, or None.
        stamps: "header" or "bag", which time the frames carry.
        info_topics: the CameraInfo topics the calibration comes from (empty: none).
        rectified: whether the images are taken as rectified.
        unmatched: left images dropped because no right image was within the tolerance.
    """

    topic: str = ""
    right_topic: str | None = None
    stamps: str = "header"
    info_topics: tuple[str, ...] = ()
    rectified: bool = False
    unmatched: int = 0
    left_messages: list[_Message] = field(default_factory=list, repr=False)
    right_messages: list[_Message] = field(default_factory=list, repr=False)
    _reader: Any = field(default=None, init=False, repr=False)
    _lock: Any = field(default_factory=threading.Lock, init=False, repr=False)

    def __getitem__(self, index: int) -> Frame:
        index = self.frame_index(index)
        rec = self.records[index]
        with self._lock:
            reader = self._open()
            image = self._image(reader, self.topic, self.left_messages[index])
            right = None
            if self.right_topic is not None:
                right = self._image(reader, self.right_topic, self.right_messages[index])
        return Frame(
            index=index,
            name=rec.name or f"{self.topic}/{index}",
            timestamp=float(rec.timestamp),
            image=image,
            right=right,
            calibration=self.calibration,
            calibration_path=self.calibration_path,
        )

    def _open(self) -> Any:
        if self._reader is None:
            self._reader = _open_reader(self.root)
        return self._reader

    def _image(self, reader: Any, topic: str, where: _Message) -> np.ndarray:
        conns = [c for c in reader.connections if c.topic == topic]
        found = None
        for k, (conn, _, raw) in enumerate(
            _messages(reader, self.root, conns, start=where.bag_ns, stop=where.bag_ns + 1)
        ):
            if k == where.ordinal:
                found = (conn, raw)
                break
        if found is None:
            raise DatasetError(
                f"{self.root}: {topic} has no message at bag time {where.bag_ns} ns any more "
                "(the bag changed since it was opened)"
            )
        conn, raw = found
        msg = _deserialize(reader, self.root, conn, raw, where.bag_ns)
        label = f"{self.root}: {topic} message at {where.stamp_ns} ns"
        if conn.msgtype == COMPRESSED:
            return image_from_compressed(msg, label, grey=self.grey)
        return image_from_raw(msg, label, grey=self.grey)

    def close(self) -> None:
        """Close the bag (reading a frame opens it again)."""
        with self._lock:
            if self._reader is not None:
                reader, self._reader = self._reader, None
                reader.close()

    def __enter__(self) -> RosbagDataset:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_reader"] = None
        state["_lock"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def describe(self) -> dict[str, Any]:
        """As :meth:`SequenceDataset.describe`, plus the topics, the stamps and the dropped frames."""
        return {
            **super().describe(),
            "stereo": self.right_topic is not None,
            "topic": self.topic,
            "right_topic": self.right_topic,
            "stamps": self.stamps,
            "camera_info": list(self.info_topics),
            "rectified": self.rectified,
            "unmatched_left_images": self.unmatched,
        }


def _index_topic(reader: Any, bag: Path, topic: str) -> tuple[list[_Message], bool]:
    """Every message of ``topic`` in bag order, and whether all carry a nonzero header stamp."""
    conns = [c for c in reader.connections if c.topic == topic]
    seen: Counter[int] = Counter()
    out = []
    all_stamped = True
    for conn, t, raw in _messages(reader, bag, conns):
        stamp = _stamp_ns(_deserialize(reader, bag, conn, raw, t))
        all_stamped = all_stamped and stamp > 0
        out.append(_Message(t, seen[t], stamp))
        seen[t] += 1
    if not out:
        raise DatasetError(f"{bag}: topic {topic} holds no message")
    return out, all_stamped


def _first_camera_info(reader: Any, bag: Path, topic: str) -> CameraInfo:
    conns = [c for c in reader.connections if c.topic == topic]
    for conn, t, raw in _messages(reader, bag, conns):
        msg = _deserialize(reader, bag, conn, raw, t)
        try:
            return CameraInfo.from_message(msg, topic)
        except CalibrationError as exc:
            raise CalibrationError(f"{bag}: {exc}") from None
        except (TypeError, ValueError, AttributeError) as exc:
            raise DatasetError(f"{bag}: {topic}: not a usable CameraInfo ({reason(exc)})") from None
    raise DatasetError(f"{bag}: topic {topic} holds no message")


def _times(messages: list[_Message], stamps: str) -> np.ndarray:
    ns = np.array([m.stamp_ns if stamps == "header" else m.bag_ns for m in messages], dtype=np.int64)
    return ns_to_seconds(ns)


def _camera_infos(
    reader: Any, bag: Path, topics: dict[str, str], left: str, right: str | None, named: Sequence[str | None]
) -> list[CameraInfo]:
    """The CameraInfo of each camera (named, else found beside its topic); empty when one is missing
    or uncalibrated."""
    info_topics = sorted(t for t, typ in topics.items() if typ == CAMERA_INFO)
    cams = [left] if right is None else [left, right]
    out = []
    for cam, given in zip(cams, named, strict=False):
        if given is not None and topics.get(given) != CAMERA_INFO:
            raise DatasetError(
                f"{bag}: expected a CameraInfo topic, {given!r} is not one; CameraInfo topics: {info_topics}"
            )
        name = given if given is not None else _info_topic(cam, info_topics)
        if name is None and right is None and len(info_topics) == 1:
            name = info_topics[0]
        if name is None:
            logger.info("%s: no CameraInfo topic for %s: no calibration", bag, cam)
            return []
        info = _first_camera_info(reader, bag, name)
        if not info.calibrated:
            logger.info("%s: %s says the camera is uncalibrated (K is zero): no calibration", bag, name)
            return []
        out.append(info)
    return out


def open_rosbag(
    path: str | Path,
    *,
    topic: str | None = None,
    right_topic: str | None = None,
    stereo: bool = True,
    stamps: StampSource = "auto",
    max_stereo_difference: float = 0.002,
    info_topic: str | None = None,
    right_info_topic: str | None = None,
    rectified: bool | None = None,
    grey: bool = False,
) -> RosbagDataset:
    """Open a ROS 1 bag, a ROS 2 bag folder, or a ROS 2 ``.db3`` / ``.mcap`` file.

    Args:
        path: the bag.
        topic: the image topic (left camera); None picks the bag's one camera or stereo pair.
        right_topic: the right camera's image topic; None: the topic pairing with ``topic``
            (``left``/``right``, ``cam0``/``cam1``) when there is exactly one and ``stereo``.
        stereo: attach right images when a pair is found (False: left images only).
        stamps: "header" (the messages' header stamps), "bag" (when the bag recorded them), or
            "auto" (header stamps unless one is zero).
        max_stereo_difference: largest gap (s) between a left image and its right image.
        info_topic: CameraInfo topic of the left camera; None: the one beside the image topic.
        right_info_topic: CameraInfo topic of the right camera.
        rectified: whether the images are rectified; None: when the topic is an ``image_rect*``.
        grey: read images as (H, W) grey.

    Returns:
        The dataset; ``dataset.close()`` (or ``with``) closes the bag.

    Raises:
        DatasetError: a missing, truncated or corrupt bag, an unknown topic, several cameras
            and no topic named, no right image within ``max_stereo_difference`` of any left one.
        ConfigError: an unknown ``stamps``, a negative ``max_stereo_difference``.
    """
    if stamps not in ("auto", "header", "bag"):
        raise ConfigError(f"stamps: expected 'auto', 'header' or 'bag', got {stamps!r}")
    if not (math.isfinite(max_stereo_difference) and max_stereo_difference >= 0):
        raise ConfigError(f"max_stereo_difference: expected seconds >= 0, got {max_stereo_difference}")
    bag = Path(path)
    reader = _open_reader(bag)
    try:
        topics = {name: str(info.msgtype) for name, info in reader.topics.items()}
        image_topics = {t: typ for t, typ in topics.items() if typ in IMAGE_TYPES}
        left, right = _choose_topics(bag, image_topics, topic, right_topic, stereo)
        left_msgs, stamped = _index_topic(reader, bag, left)
        right_msgs: list[_Message] = []
        if right is not None:
            right_msgs, right_stamped = _index_topic(reader, bag, right)
            stamped = stamped and right_stamped
        if stamps == "header" and not stamped:
            raise DatasetError(f"{bag}: {left}: expected header stamps, found a zero one; use stamps='bag'")
        source = "header" if stamps == "header" or (stamps == "auto" and stamped) else "bag"
        infos = _camera_infos(reader, bag, topics, left, right, (info_topic, right_info_topic))
    finally:
        reader.close()

    times = _times(left_msgs, source)
    unmatched = 0
    if right is not None:
        idx = nearest(times, _times(right_msgs, source), max_stereo_difference)
        keep = np.flatnonzero(idx >= 0)
        if keep.size == 0:
            raise DatasetError(
                f"{bag}: no {right} image within {max_stereo_difference} s of any {left} image "
                "(max_stereo_difference)"
            )
        unmatched = len(left_msgs) - keep.size
        if unmatched:
            logger.warning(
                "%s: %d %s images without a %s image within %g s dropped",
                bag,
                unmatched,
                left,
                right,
                max_stereo_difference,
            )
        right_msgs = [right_msgs[int(idx[k])] for k in keep]
        left_msgs = [left_msgs[int(k)] for k in keep]
        times = times[keep]
    is_rect = rectified if rectified is not None else _base(left).rsplit("/", 1)[-1].startswith("image_rect")
    label = left.strip("/")
    by_header = source == "header"
    records = [
        FrameRecord(image=bag, timestamp=float(t), name=f"{label}/{m.stamp_ns if by_header else m.bag_ns}")
        for t, m in zip(times, left_msgs, strict=True)
    ]
    calib_infos = infos if right is None or len(infos) == 2 else []
    loader = None
    if calib_infos:
        loader = functools.partial(
            _load_camera_info,
            left=calib_infos[0],
            right=calib_infos[1] if len(calib_infos) == 2 else None,
            rectified=is_rect,
            source=str(bag),
        )
    return RosbagDataset(
        root=bag,
        records=records,
        name=bag.stem if bag.is_file() else bag.name,
        format="rosbag",
        calibration_path=bag if loader is not None else None,
        calibration_loader=loader,
        grey=grey,
        topic=left,
        right_topic=right,
        stamps=source,
        info_topics=tuple(i.topic for i in calib_infos),
        rectified=is_rect,
        unmatched=unmatched,
        left_messages=left_msgs,
        right_messages=right_msgs,
    )


def _calibration_summary(calib: Calibration) -> dict[str, Any]:
    cam = calib.left
    return {
        "kind": "stereo" if calib.is_stereo else "mono",
        "rectified": calib.rectified,
        "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
        "size": list(cam.image_size) if cam.image_size else None,
        "distortion": list(cam.distortion),
        "baseline_m": calib.baseline,
    }  # fmt: skip


def bag_summary(path: str | Path, **options: Any) -> dict[str, Any]:
    """What ``stablecues info`` shows of a bag: its topics, and the frames and calibration that
    :func:`open_rosbag` (with ``options``) would give.

    Returns:
        JSON-ready ``{"bag", "topics": [BagTopic fields...], "frames": describe() + first/last
        time, or None, "frames_error": why not, or None, "calibration": camera summary or None,
        "calibration_error": why not, or None}``. A bag whose topics can be listed but whose
        frames cannot be chosen (several cameras) or whose CameraInfo is refused still gives
        the topics, with the reason in ``frames_error`` / ``calibration_error``.

    Raises:
        DatasetError: a missing, truncated or corrupt bag.
    """
    from dataclasses import asdict

    bag = Path(path)
    out: dict[str, Any] = {
        "bag": str(bag),
        "topics": [asdict(t) for t in bag_topics(bag)],
        "frames": None,
        "frames_error": None,
        "calibration": None,
        "calibration_error": None,
    }
    try:
        ds = open_rosbag(bag, **options)
    except (DatasetError, ImageError) as exc:
        out["frames_error"] = str(exc)
        return out
    times = ds.times
    out["frames"] = {**ds.describe(), "first_time": float(times[0]), "last_time": float(times[-1])}
    try:
        calib = ds.calibration
    except CalibrationError as exc:
        out["calibration_error"] = str(exc)
    else:
        out["calibration"] = None if calib is None else _calibration_summary(calib)
    return out

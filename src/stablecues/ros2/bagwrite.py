"""Writing a small ROS 2 bag of camera images (and their CameraInfo), to try the node and the
replay publisher on your own frames without a robot (the tests and the benchmark use it)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InputError
from .messages import CAMERA_INFO, COMPRESSED, IMAGE, encode, header_msg, typestore

if TYPE_CHECKING:
    from ..geometry import Calibration

__all__ = ["camera_info_fields", "write_image_bag"]


def camera_info_fields(calibration: Calibration, right: bool = False) -> dict[str, Any]:
    """CameraInfo fields (``width height K D R P``) of one camera of ``calibration``: ``K`` and
    plumb_bob ``D`` of the raw camera, and for a stereo rig its rectification's ``R`` and ``P``
    (as ROS's stereo calibration writes them; the right ``P[0, 3] = -fx * baseline``)."""
    from ..geometry.rectify import rectification_of

    cam = calibration.right if right else calibration.left
    if cam is None:
        raise InputError("the calibration has no right camera")
    if calibration.is_stereo:
        rect = rectification_of(calibration)
        r, p = (rect.R2, rect.P2) if right else (rect.R1, rect.P1)
    else:
        r, p = np.eye(3), np.hstack([cam.K, np.zeros((3, 1))])
    dist = np.zeros(5)
    dist[: len(cam.dist)] = cam.dist
    return {"width": cam.width or 0, "height": cam.height or 0, "K": cam.K, "D": dist, "R": r, "P": p}


def _image_msg(stamp: int, frame_id: str, image: np.ndarray) -> Any:
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise InputError(f"expected (H, W) or (H, W, 3) uint8 images, got {image.dtype} {image.shape}")
    h, w = image.shape[:2]
    encoding = "mono8" if image.ndim == 2 else "bgr8"
    rows = np.ascontiguousarray(image).reshape(h, -1)
    return typestore().types[IMAGE](
        header=header_msg(stamp, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=rows.shape[1],
        data=rows.ravel(),
    )


def _compressed_msg(stamp: int, frame_id: str, image: np.ndarray, fmt: str) -> Any:
    import cv2

    ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", image)
    if not ok:
        raise InputError(f"could not encode a {image.shape} image as {fmt}")
    return typestore().types[COMPRESSED](header=header_msg(stamp, frame_id), format=fmt, data=buf.ravel())


def _info_msg(stamp: int, frame_id: str, info: dict[str, Any]) -> Any:
    types = typestore().types
    roi = types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return types[CAMERA_INFO](
        header=header_msg(stamp, frame_id),
        height=int(info["height"]),
        width=int(info["width"]),
        distortion_model="plumb_bob",
        d=np.asarray(info["D"], np.float64).ravel(),
        k=np.asarray(info["K"], np.float64).ravel(),
        r=np.asarray(info["R"], np.float64).ravel(),
        p=np.asarray(info["P"], np.float64).ravel(),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def write_image_bag(
    path: str | Path,
    stamps_ns: Sequence[int],
    left: Sequence[np.ndarray],
    right: Sequence[np.ndarray] | None = None,
    *,
    calibration: Calibration | None = None,
    prefix: str = "",
    storage: str = "sqlite3",
    compressed: str | None = None,
) -> Path:
    """Write a ROS 2 bag (a folder) of ``PREFIX/cam0/image_raw`` (and ``PREFIX/cam1/image_raw``;
    ``.../compressed`` when ``compressed``)
    with a ``camera_info`` beside each (when ``calibration`` is given), one message per image at
    its stamp (the bag time is the stamp).

    Args:
        path: the bag folder to make (must not exist).
        stamps_ns: header stamps, increasing.
        left: (H, W) uint8 grey (mono8) or (H, W, 3) uint8 BGR (bgr8) images.
        right: the right images of a stereo pair, or None.
        calibration: the camera(s), for the CameraInfo messages.
        prefix: a namespace in front of the topics.
        storage: "sqlite3" or "mcap".
        compressed: None (``sensor_msgs/Image``), or "png" / "jpeg": ``sensor_msgs/CompressedImage``
            on ``.../image_raw/compressed``.

    Returns:
        ``path``.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    ts = typestore()
    cams = [("cam0", left)] + ([("cam1", right)] if right is not None else [])
    messages: list[tuple[int, Any, bytes]] = []
    with Writer(Path(path), version=9, storage_plugin=plugin) as writer:
        for k, (name, images) in enumerate(cams):
            kind = COMPRESSED if compressed else IMAGE
            suffix = "/compressed" if compressed else ""
            conn = writer.add_connection(f"{prefix}/{name}/image_raw{suffix}", kind, typestore=ts)
            info_conn = (
                writer.add_connection(f"{prefix}/{name}/camera_info", CAMERA_INFO, typestore=ts)
                if calibration is not None
                else None
            )
            info = camera_info_fields(calibration, right=k == 1) if calibration is not None else None
            for stamp, image in zip(stamps_ns, images, strict=True):
                if info_conn is not None and info is not None:
                    messages.append(
                        (int(stamp), info_conn, encode(_info_msg(int(stamp), name, info), CAMERA_INFO))
                    )
                msg = (
                    _compressed_msg(int(stamp), name, image, compressed)
                    if compressed
                    else _image_msg(int(stamp), name, image)
                )
                messages.append((int(stamp), conn, encode(msg, kind)))
        messages.sort(key=lambda item: item[0])  # stable: per stamp, left before right, info first
        for stamp, conn, payload in messages:
            writer.write(conn, stamp, payload)
    return Path(path)

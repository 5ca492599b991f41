"""stablecues.datasets.rosbag on bags written here with rosbags' own writers from real EuRoC frames.

EuRoC V1_01_micro (19 stereo pairs, 752x480 grey) goes into a ROS 2 bag (sqlite3 and MCAP
storage) and a ROS 1 bag, raw and PNG-compressed, with the two cameras' CameraInfo made from the
EuRoC sensor.yaml files (K, D, and R/P of the rig's rectification); the bags are read back frame
for frame against the EuRoC folder.
"""

from __future__ import annotations

import os
import pickle
import shutil
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from conftest import shared_path
from stablecues.datasets import detect_format, open_dataset
from stablecues.datasets.rosbag import (
    CameraInfo,
    bag_topics,
    calibration_from_camera_info,
    image_from_compressed,
    image_from_raw,
    open_rosbag,
)
from stablecues.errors import CalibrationError, ConfigError, DatasetError, ImageError
from stablecues.geometry import load_calibration
from stablecues.geometry.camera import Calibration
from stablecues.geometry.rectify import rectification_of
from stablecues.imageio import read_image

rosbags = pytest.importorskip("rosbags")

from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
BAG_DELAY_NS = 3_000_000  # the bag records each message 3 ms after its header stamp


# ----------------------------------------------------------------------------------------------
# writing bags


@dataclass
class Cam:
    """One camera's frames: topic, stamps (ns), images, and its CameraInfo fields."""

    topic: str
    stamps: list[int]
    images: list[np.ndarray]
    info: dict[str, Any] | None = None
    info_topic: str | None = None
    compressed: str | None = None  # None: sensor_msgs/Image; "png" / "jpeg": CompressedImage
    encoding: str = "mono8"


def _time(ts: Any, ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(ts: Any, ns: int, ros1: bool, frame: str = "cam") -> Any:
    header = ts.types["std_msgs/msg/Header"]
    if ros1:
        return header(seq=0, stamp=_time(ts, ns), frame_id=frame)
    return header(stamp=_time(ts, ns), frame_id=frame)


def raw_message(
    ts: Any, ns: int, image: np.ndarray, encoding: str, ros1: bool, *, bigendian: bool = False, pad: int = 0
) -> Any:
    """A sensor_msgs/Image of ``image`` (its bytes as stored, rows padded by ``pad`` bytes)."""
    h, w = image.shape[:2]
    rows = image.reshape(h, -1)
    if image.dtype == np.uint16:
        rows = image.astype(">u2" if bigendian else "<u2").reshape(h, -1).view(np.uint8)
    rows = np.concatenate([rows, np.zeros((h, pad), np.uint8)], axis=1) if pad else rows
    return ts.types[IMAGE](
        header=_header(ts, ns, ros1),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=int(bigendian),
        step=rows.shape[1],
        data=np.ascontiguousarray(rows).ravel(),
    )


def compressed_message(ts: Any, ns: int, image: np.ndarray, fmt: str, ros1: bool) -> Any:
    ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", image)
    assert ok
    return ts.types[COMPRESSED](header=_header(ts, ns, ros1), format=fmt, data=buf.ravel())


def info_message(ts: Any, ns: int, info: dict[str, Any], ros1: bool) -> Any:
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    names = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
    arrays = {n: np.asarray(info[n.upper()], np.float64).ravel() for n in names}
    return ts.types[CAMERA_INFO](
        header=_header(ts, ns, ros1),
        height=info["height"],
        width=info["width"],
        distortion_model=info.get("model", "plumb_bob"),
        binning_x=0,
        binning_y=0,
        roi=roi,
        **arrays,
    )


def camera_info_fields(calib: Calibration, right: bool) -> dict[str, Any]:
    """CameraInfo fields of one camera of a raw EuRoC rig: K, D (plumb_bob, 5), and the
    rectification's R and P, as ROS's stereo calibration writes them."""
    cam = calib.right if right else calib.left
    assert cam is not None and cam.width is not None
    rect = rectification_of(calib)
    return {
        "width": cam.width,
        "height": cam.height,
        "K": cam.K,
        "D": cam.dist,
        "R": rect.R2 if right else rect.R1,
        "P": rect.P2 if right else rect.P1,
    }


def write_bag(path: Path, cams: Iterable[Cam], kind: str) -> Path:
    """Write ``cams`` into a bag: kind "ros1" (.bag), "sqlite3" or "mcap" (ROS 2 folders)."""
    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    serialize: Callable[[Any, str], bytes] = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        writer: Any = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    messages: list[tuple[int, Any, Any, str]] = []
    with writer:
        for k, cam in enumerate(cams):
            msgtype = COMPRESSED if cam.compressed else IMAGE
            conn = writer.add_connection(cam.topic, msgtype, typestore=ts)
            info_conn = (
                writer.add_connection(cam.info_topic, CAMERA_INFO, typestore=ts)
                if cam.info is not None and cam.info_topic
                else None
            )
            for ns, image in zip(cam.stamps, cam.images, strict=True):
                if cam.compressed:
                    msg = compressed_message(ts, ns, image, cam.compressed, ros1)
                else:
                    msg = raw_message(ts, ns, image, cam.encoding, ros1)
                bag_ns = ns + BAG_DELAY_NS + k * 1_000_000
                messages.append((bag_ns, conn, msg, msgtype))
                if info_conn is not None and cam.info is not None:
                    messages.append((bag_ns, info_conn, info_message(ts, ns, cam.info, ros1), CAMERA_INFO))
        for bag_ns, conn, msg, msgtype in sorted(messages, key=lambda m: m[0]):
            writer.write(conn, bag_ns, serialize(msg, msgtype))
    return path


@dataclass
class Euroc:
    """The EuRoC micro sequence as read from its folder."""

    root: Path
    stamps: list[int]
    left: list[np.ndarray]
    right: list[np.ndarray]
    calib: Calibration


@pytest.fixture(scope="module")
def euroc() -> Euroc:
    root = shared_path("euroc", "V1_01_micro")
    mav0 = root / "mav0"
    lines = [ln.split(",") for ln in (mav0 / "cam0" / "data.csv").read_text().splitlines()[1:] if ln.strip()]
    stamps = [int(s) for s, _ in lines]
    left = [read_image(mav0 / "cam0" / "data" / n.strip(), "8bit") for _, n in lines]
    right = [read_image(mav0 / "cam1" / "data" / n.strip(), "8bit") for _, n in lines]
    return Euroc(root, stamps, left, right, load_calibration(mav0 / "cam0" / "sensor.yaml"))


def stereo_cams(e: Euroc, compressed: str | None = None, prefix: str = "") -> list[Cam]:
    return [
        Cam(
            f"{prefix}/cam0/image_raw",
            e.stamps,
            e.left,
            camera_info_fields(e.calib, False),
            f"{prefix}/cam0/camera_info",
            compressed,
        ),
        Cam(
            f"{prefix}/cam1/image_raw",
            e.stamps,
            e.right,
            camera_info_fields(e.calib, True),
            f"{prefix}/cam1/camera_info",
            compressed,
        ),
    ]


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory, euroc: Euroc) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bags")
    return {
        "sqlite3": write_bag(d / "v101_sqlite3", stereo_cams(euroc), "sqlite3"),
        "mcap": write_bag(d / "v101_mcap", stereo_cams(euroc, "png"), "mcap"),
        "ros1": write_bag(d / "v101.bag", stereo_cams(euroc, "png"), "ros1"),
        "ros1_raw": write_bag(d / "v101_raw.bag", stereo_cams(euroc)[:1], "ros1"),
    }


def assert_same_calibration(got: Calibration | None, want: Calibration) -> None:
    """The bag's calibration is the EuRoC folder's: same cameras, same rig, and the rig's own
    rectification (which cv2.stereoRectify computes for the folder's)."""
    assert got is not None and got.right is not None and want.right is not None
    assert got.left == want.left and got.right == want.right
    assert want.rotation is not None and want.translation is not None
    np.testing.assert_allclose(got.rotation, want.rotation, atol=1e-9)
    np.testing.assert_allclose(got.translation, want.translation, atol=1e-9)
    assert got.baseline == pytest.approx(want.baseline, rel=1e-12)
    assert got.rectification is not None and not got.rectified
    rect = rectification_of(want)
    for name in ("R1", "R2", "P1", "P2"):
        np.testing.assert_array_equal(getattr(got.rectification, name), getattr(rect, name))


# ----------------------------------------------------------------------------------------------
# reading back


@pytest.mark.parametrize("kind", ["sqlite3", "mcap", "ros1"])
def test_stereo_bag_reads_back_frame_for_frame(kind: str, bags: dict[str, Path], euroc: Euroc) -> None:
    """Raw (sqlite3) and PNG-compressed (MCAP, ROS 1) stereo bags give the EuRoC folder's pixels,
    timestamps and calibration."""
    ds = open_dataset(bags[kind])
    folder = open_dataset(euroc.root)
    assert ds.format == "rosbag" and len(ds) == len(folder) == 19
    assert ds.topic == "/cam0/image_raw" and ds.right_topic == "/cam1/image_raw"  # type: ignore[attr-defined]
    assert ds.stamps == "header"  # type: ignore[attr-defined]
    np.testing.assert_array_equal(ds.times, folder.times)
    for i in range(len(ds)):
        f, g = ds[i], folder[i]
        assert f.index == i and f.timestamp == g.timestamp
        assert f.name == f"cam0/image_raw/{euroc.stamps[i]}"
        assert f.image.dtype == np.uint8 and f.image.shape == (480, 752)
        np.testing.assert_array_equal(f.image, g.image)
        assert f.right is not None and g.right is not None
        np.testing.assert_array_equal(f.right, g.right)
    assert_same_calibration(ds.calibration, folder.calibration)  # type: ignore[arg-type]
    assert ds[0].calibration is ds.calibration and ds[-1].index == 18
    described = ds.describe()
    assert described["stereo"] and described["camera_info"] == ["/cam0/camera_info", "/cam1/camera_info"]
    ds.close()  # type: ignore[attr-defined]
    np.testing.assert_array_equal(ds[3].image, euroc.left[3])  # reopens
    with pytest.raises(IndexError):
        ds[19]


@pytest.mark.parametrize("kind", ["sqlite3", "mcap"])
def test_bare_storage_file_opens(kind: str, bags: dict[str, Path], euroc: Euroc) -> None:
    """The .db3 / .mcap file of a ROS 2 bag folder opens on its own."""
    (storage,) = sorted(bags[kind].glob(f"*.{'db3' if kind == 'sqlite3' else 'mcap'}"))
    assert detect_format(storage) == "rosbag"
    ds = open_dataset(storage, grey=True)
    assert len(ds) == 19 and ds.name == storage.stem
    np.testing.assert_array_equal(ds[5].image, euroc.left[5])
    assert_same_calibration(ds.calibration, euroc.calib)


def test_ros1_mono_raw_bag_and_bag_time(bags: dict[str, Path], euroc: Euroc) -> None:
    ds = open_rosbag(bags["ros1_raw"])
    assert ds.right_topic is None and len(ds) == 19 and ds[0].right is None
    np.testing.assert_array_equal(ds[7].image, euroc.left[7])
    calib = ds.calibration
    assert calib is not None and calib.right is None and calib.left == euroc.calib.left
    by_bag = open_rosbag(bags["ros1_raw"], stamps="bag")
    assert by_bag.stamps == "bag"
    np.testing.assert_allclose(by_bag.times - ds.times, BAG_DELAY_NS * 1e-9, atol=1e-6)


def test_stereo_option_and_topics_named(bags: dict[str, Path], euroc: Euroc) -> None:
    mono = open_rosbag(bags["mcap"], stereo=False)
    assert mono.right_topic is None and mono[0].right is None
    cam1 = open_rosbag(bags["mcap"], topic="/cam1/image_raw", stereo=False, info_topic="/cam1/camera_info")
    np.testing.assert_array_equal(cam1[2].image, euroc.right[2])
    assert cam1.right_topic is None and cam1.info_topics == ("/cam1/camera_info",)
    assert cam1.calibration is not None and cam1.calibration.left == euroc.calib.right
    # the pair swapped: its calibration (cam0 is left of cam1) is refused when first used
    swapped = open_rosbag(
        bags["mcap"],
        topic="/cam1/image_raw",
        right_topic="/cam0/image_raw",
        info_topic="/cam1/camera_info",
        right_info_topic="/cam0/camera_info",
    )
    assert len(swapped) == 19 and swapped.info_topics == ("/cam1/camera_info", "/cam0/camera_info")
    with pytest.raises(CalibrationError, match=r"v101_mcap: /cam0/camera_info: expected P\[0, 3\] = -fx"):
        swapped[2]
    # cam0 named alone finds cam1 as its partner
    assert open_rosbag(bags["mcap"], topic="/cam0/image_raw").right_topic == "/cam1/image_raw"
    with pytest.raises(DatasetError, match=r"v101_mcap: expected an image topic, '/cam2/image_raw'"):
        open_rosbag(bags["mcap"], topic="/cam2/image_raw")
    with pytest.raises(DatasetError, match="expected a CameraInfo topic"):
        open_rosbag(bags["mcap"], info_topic="/cam0/image_raw")
    with pytest.raises(ConfigError, match="stamps: expected 'auto', 'header' or 'bag', got 'frame'"):
        open_dataset(bags["mcap"], stamps="frame")
    with pytest.raises(ConfigError, match="max_stereo_difference"):
        open_dataset(bags["mcap"], format="rosbag", max_stereo_difference=-1.0)


def test_dataset_pickles_and_reopens(bags: dict[str, Path], euroc: Euroc) -> None:
    ds = open_rosbag(bags["sqlite3"])
    _ = ds[0]  # the bag is open now
    copy = pickle.loads(pickle.dumps(ds))
    np.testing.assert_array_equal(copy[4].right, euroc.right[4])
    assert_same_calibration(copy.calibration, euroc.calib)
    ds.close()
    copy.close()


def test_topic_choice(tmp_path: Path, euroc: Euroc) -> None:
    """Raw topics are preferred to their /compressed twins and depth topics are left out; three
    cameras need a topic; stereo frames without a right image in tolerance are dropped."""
    e = euroc
    few, imgs = e.stamps[:4], e.left[:4]
    cams = [
        Cam("/stereo/left/image_raw", few, imgs),
        Cam("/stereo/left/image_raw/compressed", few, imgs, compressed="png"),
        Cam("/stereo/right/image_raw", [s + (0 if k else 5_000_000) for k, s in enumerate(few)], e.right[:4]),
        Cam("/camera/depth/image", few, [i.astype(np.uint16) for i in imgs], encoding="16UC1"),
    ]
    ds = open_rosbag(write_bag(tmp_path / "two", cams, "mcap"))
    assert (ds.topic, ds.right_topic) == ("/stereo/left/image_raw", "/stereo/right/image_raw")
    assert len(ds) == 3 and ds.unmatched == 1  # frame 0's right image is 5 ms late
    np.testing.assert_array_equal(ds[0].right, e.right[1])
    assert ds.calibration is None and ds.calibration_path is None  # no CameraInfo
    assert len(open_rosbag(tmp_path / "two", max_stereo_difference=0.01)) == 4
    cams.append(Cam("/front/image_raw", few, imgs))
    with pytest.raises(DatasetError, match=r"three: 3 cameras, expected one .*/front/image_raw \(Image\)"):
        open_rosbag(write_bag(tmp_path / "three", cams, "sqlite3"))
    depth = open_rosbag(tmp_path / "three", topic="/camera/depth/image")
    assert depth[1].image.dtype == np.uint8 and depth.right_topic is None
    np.testing.assert_array_equal(depth[1].image, (imgs[1].astype(np.uint16) >> 8).astype(np.uint8))


# ----------------------------------------------------------------------------------------------
# images and calibration of single messages


@pytest.fixture(scope="module")
def colour() -> np.ndarray:
    """A real colour frame (TUM fr2/desk), cut to 64 x 48 to keep the messages small."""
    image = read_image(sorted(shared_path("tum", "fr2_desk").glob("*.png"))[0], "bgr")
    return np.ascontiguousarray(image[200:248, 300:364])


@pytest.mark.parametrize("ros1", [False, True])
def test_raw_encodings(colour: np.ndarray, ros1: bool) -> None:
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    grey = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
    cases = {
        "bgr8": (colour, colour),
        "rgb8": (cv2.cvtColor(colour, cv2.COLOR_BGR2RGB), colour),
        "bgra8": (cv2.cvtColor(colour, cv2.COLOR_BGR2BGRA), colour),
        "rgba8": (cv2.cvtColor(colour, cv2.COLOR_BGR2RGBA), colour),
        "mono8": (grey, grey),
        "8UC3": (colour, colour),
        "mono16": (grey.astype(np.uint16) * 257, grey),
    }
    for encoding, (stored, want) in cases.items():
        for bigendian in (False, True):
            msg = raw_message(ts, 1, stored, encoding, ros1, bigendian=bigendian, pad=3)
            # through the wire format and back, as a bag holds it
            serial = ts.serialize_ros1(msg, IMAGE) if ros1 else ts.serialize_cdr(msg, IMAGE)
            back = ts.deserialize_ros1(serial, IMAGE) if ros1 else ts.deserialize_cdr(serial, IMAGE)
            np.testing.assert_array_equal(image_from_raw(back, "t"), want, err_msg=encoding)
    got = image_from_raw(raw_message(ts, 1, colour, "bgr8", ros1), "t", grey=True)
    np.testing.assert_array_equal(got, grey)
    # Bayer: a BGGR mosaic of the frame demosaics to the frame's colours, roughly
    bayer = np.empty(grey.shape, np.uint8)
    bayer[0::2, 0::2], bayer[0::2, 1::2] = colour[0::2, 0::2, 0], colour[0::2, 1::2, 1]
    bayer[1::2, 0::2], bayer[1::2, 1::2] = colour[1::2, 0::2, 1], colour[1::2, 1::2, 2]
    demosaiced = image_from_raw(raw_message(ts, 1, bayer, "bayer_bggr8", ros1), "t")
    assert demosaiced.shape == colour.shape
    assert np.abs(demosaiced.astype(int) - colour.astype(int))[4:-4, 4:-4].mean() < 12


def test_compressed_images(colour: np.ndarray) -> None:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    np.testing.assert_array_equal(
        image_from_compressed(compressed_message(ts, 1, colour, "png", False), "t"), colour
    )
    jpeg = image_from_compressed(compressed_message(ts, 1, colour, "bgr8; jpeg compressed bgr8", False), "t")
    assert jpeg.shape == colour.shape and np.abs(jpeg.astype(int) - colour.astype(int)).mean() < 6
    grey = image_from_compressed(compressed_message(ts, 1, colour, "png", False), "t", grey=True)
    assert grey.shape == colour.shape[:2]


def test_bad_image_messages(colour: np.ndarray) -> None:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msg = raw_message(ts, 1, colour, "bgr8", False)
    with pytest.raises(ImageError, match=r"^bag: /t: image encoding '32FC1' is not supported"):
        image_from_raw(ts.types[IMAGE](**{**vars_of(msg), "encoding": "32FC1"}), "bag: /t")
    short = ts.types[IMAGE](**{**vars_of(msg), "data": msg.data[:-10]})
    with pytest.raises(ImageError, match=r"step \* height bytes; found step 192 and 9206 bytes"):
        image_from_raw(short, "bag: /t")
    huge = ts.types[IMAGE](**{**vars_of(msg), "height": 1 << 20, "width": 1 << 20})
    with pytest.raises(ImageError, match="larger than the 67108864 pixels accepted"):
        image_from_raw(huge, "bag: /t")
    bad = compressed_message(ts, 1, colour, "png", False)
    with pytest.raises(ImageError, match="not a JPEG, PNG"):
        image_from_compressed(ts.types[COMPRESSED](header=bad.header, format="png", data=bad.data[8:]), "t")
    with pytest.raises(ImageError, match="damaged PNG header"):
        data = bad.data.copy()
        data[20] ^= 0xFF  # the IHDR no longer matches its CRC
        image_from_compressed(ts.types[COMPRESSED](header=bad.header, format="png", data=data), "t")
    with pytest.raises(ImageError, match="a corrupt JPEG image"):
        jpeg = compressed_message(ts, 1, colour, "jpeg", False)
        image_from_compressed(
            ts.types[COMPRESSED](header=bad.header, format="jpeg", data=jpeg.data[:300]), "t"
        )
    with pytest.raises(ImageError, match="is a depth image"):
        image_from_compressed(
            ts.types[COMPRESSED](header=bad.header, format="16UC1; compressedDepth png", data=bad.data), "t"
        )
    # a small JPEG whose header claims 65500 x 1000: libjpeg fills the rest with grey
    small = compressed_message(ts, 1, colour[:16, :16], "jpeg", False)
    claims = small.data.copy()
    sof = bytes(claims).find(b"\xff\xc0")
    claims[sof + 5: sof + 9] = np.frombuffer(struct.pack(">HH", 1000, 65500), np.uint8)
    with pytest.raises(ImageError, match="a corrupt JPEG image; Corrupt JPEG data: premature end"):
        image_from_compressed(ts.types[COMPRESSED](header=small.header, format="jpeg", data=claims), "t")
    # YUV 4:2:2 with an odd width: cv2.error before
    odd = raw_message(ts, 1, np.zeros((4, 5, 2), np.uint8), "uyvy", False)
    with pytest.raises(ImageError, match="uyvy image stores pixels in pairs; .* even, found 5"):
        image_from_raw(odd, "t")


def vars_of(msg: Any) -> dict[str, Any]:
    return {k: getattr(msg, k) for k in msg.__dataclass_fields__ if k != "__msgtype__"}


def _info(fields: dict[str, Any], topic: str = "/cam0/camera_info", model: str = "plumb_bob") -> CameraInfo:
    return CameraInfo(
        topic,
        fields["width"],
        fields["height"],
        model,
        tuple(np.ravel(fields["D"])),
        np.reshape(fields["K"], (3, 3)),
        np.reshape(fields["R"], (3, 3)),
        np.reshape(fields["P"], (3, 4)),
    )


def test_camera_info_calibration(euroc: Euroc) -> None:
    left = _info(camera_info_fields(euroc.calib, False))
    right = _info(camera_info_fields(euroc.calib, True), "/cam1/camera_info")
    assert_same_calibration(calibration_from_camera_info(left, right, source="b"), euroc.calib)
    # rectified images: the cameras are P's, and the baseline -P[0,3]/P[0,0] of the right one
    rect = calibration_from_camera_info(left, right, rectified=True, source="b")
    assert rect.rectified and rect.left.distortion == () and rect.left.fx == left.P[0, 0]
    assert rect.baseline == pytest.approx(euroc.calib.baseline, rel=1e-12)
    assert rect.baseline == pytest.approx(0.110, abs=0.001)  # EuRoC's stereo baseline
    # rational_polynomial with only k1..k3 set is plumb_bob; equidistant is not supported
    eight = _info(
        {**camera_info_fields(euroc.calib, False), "D": [*euroc.calib.left.dist, 0, 0, 0]},
        model="rational_polynomial",
    )
    assert calibration_from_camera_info(eight).left == euroc.calib.left
    fisheye = _info(
        {**camera_info_fields(euroc.calib, False), "D": [0.1, 0.01, 0.0, 0.0]}, model="equidistant"
    )
    with pytest.raises(CalibrationError, match=r"^b: /cam0/camera_info: distortion model 'equidistant'"):
        calibration_from_camera_info(fisheye, source="b")
    no_baseline = _info({**camera_info_fields(euroc.calib, True), "P": np.zeros((3, 4))}, "/cam1/camera_info")
    with pytest.raises(
        CalibrationError, match=r"/cam1/camera_info: expected P\[0, 3\] = -fx \* baseline < 0"
    ):
        calibration_from_camera_info(left, no_baseline, source="b")
    uncalibrated = _info({**camera_info_fields(euroc.calib, False), "K": np.zeros(9)})
    assert not uncalibrated.calibrated
    with pytest.raises(CalibrationError, match="uncalibrated"):
        calibration_from_camera_info(uncalibrated, source="b")


def test_uncalibrated_and_rectified_topics(tmp_path: Path, euroc: Euroc) -> None:
    e = euroc
    fields = camera_info_fields(e.calib, False)
    zero_k = Cam("/cam/image_raw", e.stamps[:2], e.left[:2], {**fields, "K": np.zeros(9)}, "/cam/camera_info")
    ds = open_rosbag(write_bag(tmp_path / "uncal.bag", [zero_k], "ros1"))
    assert ds.calibration is None and ds.info_topics == ()
    rect = [
        Cam(
            f"/stereo/{side}/image_rect",
            e.stamps[:2],
            imgs[:2],
            camera_info_fields(e.calib, side == "right"),
            f"/stereo/{side}/camera_info",
        )
        for side, imgs in (("left", e.left), ("right", e.right))
    ]
    ds = open_rosbag(write_bag(tmp_path / "rect", rect, "mcap"))
    assert ds.rectified and ds.calibration is not None and ds.calibration.rectified
    assert ds.calibration.baseline == pytest.approx(e.calib.baseline, rel=1e-12)


def test_bag_topics(bags: dict[str, Path]) -> None:
    topics = {t.name: t for t in bag_topics(bags["ros1"])}
    assert sorted(topics) == ["/cam0/camera_info", "/cam0/image_raw", "/cam1/camera_info", "/cam1/image_raw"]
    img = topics["/cam1/image_raw"]
    assert (
        img.msgtype == COMPRESSED
        and img.count == 19
        and img.image_size == (752, 480)
        and img.encoding == "png"
    )
    assert img.rate_hz == pytest.approx(4.0, rel=0.01)  # every 5th frame of a 20 Hz camera
    assert topics["/cam0/camera_info"].encoding == "plumb_bob"


# ----------------------------------------------------------------------------------------------
# malformed bags


def test_malformed_bags(tmp_path: Path, bags: dict[str, Path]) -> None:
    data = bags["ros1_raw"].read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=r"cut\.bag: not a readable ROS bag \("):
        open_dataset(cut)
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 8)
    with pytest.raises(DatasetError, match=r"garbage\.mcap: not a readable ROS bag"):
        open_dataset(garbage)
    empty = tmp_path / "empty.db3"
    empty.write_bytes(b"")
    with pytest.raises(DatasetError, match=r"empty\.db3: not a readable ROS bag"):
        open_rosbag(empty)
    folder = tmp_path / "meta"
    folder.mkdir()
    (folder / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: [\n"
    )
    assert detect_format(folder) == "rosbag"
    with pytest.raises(DatasetError, match=r"meta: not a readable ROS bag"):
        open_dataset(folder)
    with pytest.raises(DatasetError, match=r"nothing\.bag: ROS bag not found"):
        open_rosbag(tmp_path / "nothing.bag")
    with pytest.raises(DatasetError, match="expected a ROS bag"):
        open_rosbag(tmp_path)
    # a chunk of the MCAP bag damaged after its index was read: the frame fails with one line
    (storage,) = bags["mcap"].glob("*.mcap")
    damaged = tmp_path / "damaged.mcap"
    raw = bytearray(storage.read_bytes())
    ds = open_rosbag(storage.parent)
    start = raw.find(b"\x89PNG", len(raw) // 2)
    raw[start : start + 64] = bytes(64)
    damaged.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match=r"damaged\.mcap"):
        broken = open_rosbag(damaged)
        for i in range(len(broken)):
            broken[i]
    assert len(ds) == 19


def test_zero_header_stamps(tmp_path: Path, euroc: Euroc) -> None:
    cam = Cam("/cam/image_raw", [0, 0, 0], euroc.left[:3])
    bag = write_bag(tmp_path / "zero.bag", [cam], "ros1")
    ds = open_rosbag(bag)  # auto: the bag's times
    assert ds.stamps == "bag" and ds.times[0] == pytest.approx(BAG_DELAY_NS * 1e-9)
    with pytest.raises(
        DatasetError, match=r"zero\.bag: /cam/image_raw: expected header stamps, found a zero"
    ):
        open_rosbag(bag, stamps="header")


@pytest.mark.parametrize("kind", ["sqlite3", "mcap"])
def test_a_fifo_in_a_bag_folder_and_huge_metadata_are_refused_without_hanging(
    kind: str, tmp_path: Path, bags: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """A FIFO in place of the bag's storage file blocked `info` and `run` forever (issue 34): it
    is refused in one line before the reader opens anything; a metadata.yaml over
    MAX_BAG_METADATA_BYTES is refused before it is parsed."""
    from stablecues.cli.main import main
    from stablecues.limits import MAX_BAG_METADATA_BYTES

    folder = tmp_path / "bag"
    shutil.copytree(bags[kind], folder)
    (storage,) = [p for p in folder.iterdir() if p.suffix in (".db3", ".mcap")]
    storage.unlink()
    os.mkfifo(storage)
    with pytest.raises(DatasetError, match=f"{storage.name}: not a regular file .* inside a ROS 2 bag"):
        open_rosbag(folder)
    assert main(["info", str(folder)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not a regular file" in err
    storage.unlink()
    shutil.copy(next(bags[kind].glob(f"*{storage.suffix}")), storage)
    meta = folder / "metadata.yaml"
    text = meta.read_text()
    meta.write_text(text + "#" * (MAX_BAG_METADATA_BYTES + 1) + "\n")
    with pytest.raises(DatasetError, match="ROS 2 bag metadata"):
        open_rosbag(folder)
    meta.write_text(text)
    assert len(open_rosbag(folder)) > 0  # the same folder, repaired, opens


@pytest.mark.parametrize("definition, field", [
    ("std_msgs/Header header\nuint32 height\nuint32 width\nuint8 is_bigendian\nuint32 step\nuint8[] data\n",
     "'encoding'"),
    ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\n"
     "float64[] data\n", "'data'"),
    ("uint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n",
     "header.stamp"),
])
def test_a_bag_defining_image_its_own_way_is_one_line(
    definition: str, field: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bag carries its own message definitions: an Image without `encoding` or `header`, or
    with `float64[] data`, gave AttributeErrors or garbage pixels in `info` and `run` (issue 34);
    each is one line naming the topic and the field."""
    from rosbags.typesys import get_types_from_msg

    from stablecues.cli.main import main

    base = get_typestore(Stores.ROS2_HUMBLE)
    ts = get_typestore(Stores.EMPTY)
    for name in ("builtin_interfaces/msg/Time", "std_msgs/msg/Header"):
        ts.register({name: base.fielddefs[name]})
    ts.register(get_types_from_msg(definition, IMAGE))
    bag = tmp_path / "bag"
    fields = {"height": 4, "width": 4, "is_bigendian": 0, "step": 4}
    if "string encoding" in definition:
        fields["encoding"] = "mono8"
    if "std_msgs/Header" in definition:
        fields["header"] = ts.types["std_msgs/msg/Header"](
            stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam")
    with Writer2(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/cam/image_raw", IMAGE, typestore=ts)
        for i in range(3):
            data = np.zeros(16, np.float64 if "float64[]" in definition else np.uint8)
            w.write(conn, (i + 1) * 10**9, ts.serialize_cdr(ts.types[IMAGE](**fields, data=data), IMAGE))
    for argv in (["info", str(bag)], ["run", str(bag), "--out", str(tmp_path / "run"), "--preset", "bow"]):
        assert main(argv) == 1
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "/cam/image_raw" in err and field in err, err


@pytest.mark.parametrize("value", ["'abc'", "1.5"])  # NULL: this schema refuses it
def test_a_db3_message_time_that_is_not_an_integer_is_one_line(
    value: str, tmp_path: Path, bags: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """SQLite keeps whatever a column is given: a message whose bag time is text or a
    fraction made `info` a TypeError traceback (issue 34)."""
    import sqlite3

    from stablecues.cli.main import main

    bag = shutil.copytree(bags["sqlite3"], tmp_path / "bag")
    (db3,) = bag.glob("*.db3")
    with sqlite3.connect(db3) as con:
        con.execute(f"UPDATE messages SET timestamp = {value} WHERE id = 2")
    con.close()
    assert main(["info", str(bag)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "bag time is" in err and "not whole nanoseconds" in err, err

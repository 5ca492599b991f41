"""Bounded fuzzing of every parser that reads bytes or text: each returns or raises a
:class:`~stablecues.errors.StableCuesError`, never anything else (no traceback in the CLI).

Inputs are random bytes, random text built from the format's own tokens, and valid files with
bytes changed, inserted or cut. The runs are reproducible (a fixed seed) and small by default;
``STABLECUES_FUZZ_EXAMPLES=2000 pytest tests/test_fuzz_parsers.py`` fuzzes longer.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from stablecues.errors import StableCuesError

EXAMPLES = int(os.environ.get("STABLECUES_FUZZ_EXAMPLES", "25"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


@contextmanager
def _file(data: bytes, name: str) -> Iterator[Path]:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / name
        path.write_bytes(data)
        yield path


def _only_known_errors(fn: Callable[[], Any]) -> None:
    """Call ``fn``: it may return or raise a StableCuesError, nothing else."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with contextlib.suppress(StableCuesError):
            fn()


@st.composite
def mutated(draw: st.DrawFn, valid: bytes) -> bytes:
    """``valid`` with a few bytes replaced, a block inserted, and maybe cut short."""
    data = bytearray(valid)
    for _ in range(draw(st.integers(0, 6))):
        if data:
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    if draw(st.booleans()):
        at = draw(st.integers(0, len(data)))
        data[at:at] = draw(st.binary(max_size=16))
    if draw(st.booleans()):
        data = data[: draw(st.integers(0, len(data)))]
    return bytes(data)


def lines_of(tokens: list[str], *, max_lines: int = 8) -> st.SearchStrategy[str]:
    """Text of lines made of the format's own tokens, numbers and odd characters."""
    token = st.one_of(
        st.sampled_from(tokens),
        st.floats(allow_nan=True, allow_infinity=True).map(repr),
        st.integers(-(10**20), 10**20).map(str),
        st.text(alphabet="0123456789.,-+eE:#%[]{}/\\ \t\x00\x0c\r\u2028", max_size=8),
    )
    line = st.lists(token, max_size=14).map(lambda ts: " ".join(ts))
    return st.lists(line, max_size=max_lines).map(lambda ls: "\n".join(ls))


TEXT_BYTES = st.one_of(
    st.binary(max_size=300),
    st.text(max_size=200).map(lambda t: t.encode("utf-8")),
    st.text(max_size=100).map(lambda t: t.encode("utf-16")),
)


def _npy_bytes(array: np.ndarray, allow_pickle: bool = False) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=allow_pickle)
    return buf.getvalue()


# ---------------------------------------------------------------------------------------------
# trajectories and times


@seed(1201)
@FUZZ
@given(st.one_of(TEXT_BYTES, lines_of(["0", "1", "0.5", "nan", "inf", "1e308", "-0"]).map(str.encode)))
def test_trajectory_readers(data: bytes) -> None:
    from stablecues import trajectory

    with _file(data, "poses.txt") as p:
        readers = (trajectory.read_tum, trajectory.read_kitti, trajectory.read_euroc, trajectory.read_times,
                   trajectory.read_poses)
        for reader in readers:
            _only_known_errors(lambda r=reader: r(p))  # type: ignore[misc]


# ---------------------------------------------------------------------------------------------
# calibration


ORBSLAM = (
    b"%YAML:1.0\nCamera.fx: 400.0\nCamera.fy: 400.0\nCamera.cx: 80.0\nCamera.cy: 60.0\nCamera.k1: 0.0\n"
    b"Camera.k2: 0.0\nCamera.p1: 0.0\nCamera.p2: 0.0\nCamera.width: 160\nCamera.height: 120\n"
    b"Camera.bf: 40.0\n"
)
EUROC = (
    b"%YAML:1.0\ncamera_model: pinhole\nintrinsics: [458.6, 457.3, 367.2, 248.4]\n"
    b"distortion_model: radial-tangential\ndistortion_coefficients: [-0.28, 0.07, 0.0002, 1.8e-05]\n"
    b"resolution: [752, 480]\nT_BS:\n  cols: 4\n  rows: 4\n"
    b"  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n"
)
KITTI = b"P0: 400 0 80 0 0 400 60 0 0 0 1 0\nP1: 400 0 80 -200 0 400 60 0 0 0 1 0\n"
CAL_TOKENS = ["Camera.fx:", "Camera.bf:", "intrinsics:", "T_BS:", "data:", "P0:", "P1:", "&a", "*a",
              "!!opencv-matrix", "[", "]", "{", "}", "-", ".nan", ".inf", "Stereo.T_c1_c2:", "LEFT.K:",
              "Camera1.fx:", "Camera2.fx:"]


@seed(1202)
@FUZZ
@given(st.one_of(TEXT_BYTES, mutated(ORBSLAM), mutated(EUROC), mutated(KITTI),
                 lines_of(CAL_TOKENS).map(str.encode)))
def test_calibration_loader(data: bytes) -> None:
    from stablecues.geometry import load_calibration

    with _file(data, "cam.yaml") as p:
        _only_known_errors(lambda: load_calibration(p))


@seed(1203)
@FUZZ
@given(st.one_of(TEXT_BYTES, mutated(EUROC)))
def test_euroc_sensor_yaml(data: bytes) -> None:
    from stablecues.datasets.euroc import sensor_extrinsics

    with _file(data, "sensor.yaml") as p:
        _only_known_errors(lambda: sensor_extrinsics(p))


# ---------------------------------------------------------------------------------------------
# ground truth


GT = np.tril(np.eye(12, k=-5, dtype=bool) | np.eye(12, k=-6, dtype=bool))
TABLE = np.empty((3, 2), dtype=object)
TABLE[:] = [[0, [0, 1]], [1, [2]], [2, []]]


def _mat_bytes() -> bytes:
    import scipy.io

    buf = io.BytesIO()
    scipy.io.savemat(buf, {"gt": GT.astype(np.uint8)})
    return buf.getvalue()


def _mat73_bytes() -> bytes:
    """A MATLAB v7.3 (HDF5) loop matrix, or a v5 one when h5py is not installed."""
    try:
        import h5py
    except ImportError:
        return _mat_bytes()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "gt.mat"
        with h5py.File(path, "w", userblock_size=512) as fh:
            fh.create_dataset("gt", data=GT.T.astype(np.uint8), compression="gzip")
        head = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, HDF5 schema 1.00 ."
        with path.open("r+b") as fh:
            fh.write(head.ljust(116) + b"\x00" * 8 + b"\x00\x02IM")
        return path.read_bytes()


def _png_bytes() -> bytes:
    return cv2.imencode(".png", GT.astype(np.uint8) * 255)[1].tobytes()


@seed(1204)
@FUZZ
@given(st.one_of(st.binary(max_size=300), mutated(_npy_bytes(GT)), mutated(_npy_bytes(GT.astype(np.float64))),
                 mutated(_npy_bytes(TABLE, allow_pickle=True))))
def test_ground_truth_npy(data: bytes) -> None:
    from stablecues.groundtruth import load_ground_truth

    with _file(data, "ground_truth_new.npy") as p:
        _only_known_errors(lambda: load_ground_truth(p))


@seed(1205)
@FUZZ
@given(st.one_of(st.binary(max_size=300), mutated(_mat_bytes()), mutated(_mat73_bytes())))
def test_ground_truth_mat(data: bytes) -> None:
    from stablecues.groundtruth import load_ground_truth

    with _file(data, "gt.mat") as p:
        _only_known_errors(lambda: load_ground_truth(p))


@seed(1206)
@FUZZ
@given(st.one_of(st.binary(max_size=300), mutated(_png_bytes())))
def test_ground_truth_image(data: bytes) -> None:
    from stablecues.groundtruth import load_ground_truth

    with _file(data, "gt.png") as p:
        _only_known_errors(lambda: load_ground_truth(p))


# reference ids: small ones, and ones past every limit (the matrix must never be allocated)
IDS = st.one_of(st.integers(-2, 60), st.integers(10**9, 10**19))


@seed(1207)
@FUZZ
@given(st.lists(st.tuples(st.one_of(st.integers(-3, 5), st.floats(), st.text(max_size=3)),
                          st.one_of(IDS, st.floats(), st.lists(IDS, max_size=4),
                                    st.lists(st.lists(st.integers(), max_size=2), max_size=2),
                                    st.text(max_size=3))), max_size=5),
       st.one_of(st.none(), st.integers(-2, 50)))
def test_vprbench_table(rows: list[tuple[Any, Any]], n_ref: int | None) -> None:
    from stablecues.groundtruth import vprbench_matrix

    table = np.empty((len(rows), 2), dtype=object)
    for k, (q, ids) in enumerate(rows):
        table[k, 0], table[k, 1] = q, ids
    _only_known_errors(lambda: vprbench_matrix(table, n_ref))


# ---------------------------------------------------------------------------------------------
# images


@seed(1208)
@FUZZ
@given(st.one_of(st.binary(max_size=200), mutated(_png_bytes()),
                 mutated(cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))[1].tobytes()),
                 mutated(cv2.imencode(".bmp", np.zeros((8, 8), np.uint8))[1].tobytes()),
                 mutated(cv2.imencode(".tiff", np.zeros((8, 8), np.uint8))[1].tobytes())))
def test_image_reader(data: bytes) -> None:
    from stablecues.imageio import header_size, read_image

    header_size(data)  # never raises
    with _file(data, "a.png") as p:
        _only_known_errors(lambda: read_image(p, "8bit"))


# ---------------------------------------------------------------------------------------------
# dataset manifests


@seed(1209)
@FUZZ
@given(st.one_of(TEXT_BYTES, lines_of(["0.0", "rgb/a.png", "../a.png", "/etc/passwd", "#", "rgb\\a.png"])
                 .map(str.encode)))
def test_tum_rgb_txt(data: bytes) -> None:
    from stablecues.datasets import open_tum

    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "rgb").mkdir()
        cv2.imwrite(str(Path(d) / "rgb" / "a.png"), np.zeros((4, 4), np.uint8))
        (Path(d) / "rgb.txt").write_bytes(data)
        _only_known_errors(lambda: open_tum(d))


@seed(1210)
@FUZZ
@given(st.one_of(TEXT_BYTES, lines_of(["1403715273262142976,a.png", "#timestamp", ",", "../a.png", "12"])
                 .map(str.encode)))
def test_euroc_data_csv(data: bytes) -> None:
    from stablecues.datasets.euroc import read_euroc_list

    with _file(data, "data.csv") as p:
        _only_known_errors(lambda: read_euroc_list(p))


@seed(1211)
@FUZZ
@given(st.one_of(TEXT_BYTES, mutated(KITTI + b"P2: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n")))
def test_kitti_calib_txt(data: bytes) -> None:
    from stablecues.datasets.kitti import read_kitti_calib

    with _file(data, "calib.txt") as p:
        _only_known_errors(lambda: read_kitti_calib(p))


@seed(1212)
@FUZZ
@given(st.one_of(TEXT_BYTES, lines_of(["DepthMapFactor:", "5000", "abc", "-1"]).map(str.encode)))
def test_folder_settings_and_times(data: bytes) -> None:
    from stablecues.datasets import open_folder

    with tempfile.TemporaryDirectory() as d:
        for k in range(2):
            cv2.imwrite(str(Path(d) / f"{k}.png"), np.zeros((4, 4), np.uint8))
        (Path(d) / "calib.yaml").write_bytes(data)
        (Path(d) / "times.txt").write_bytes(data)
        _only_known_errors(lambda: open_folder(d))


# ---------------------------------------------------------------------------------------------
# run directories


@seed(1213)
@FUZZ
@given(st.one_of(TEXT_BYTES, mutated(
    b"frame,timestamp,status,candidate,score,raw_score,accepted,t_total_ms\n"
    b"0,0.0,no_db_results,-1,nan,nan,0,1.5\n1,0.1,loop_detected,0,0.5,0.1,1,2.5\n")),
    st.one_of(st.binary(max_size=100), st.just(b'{"complete": true}'), st.just(b"[1]")))
def test_run_directory(decisions: bytes, meta: bytes) -> None:
    from stablecues.runs import load_run

    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "config.json").write_text("{}")
        (Path(d) / "meta.json").write_bytes(meta)
        (Path(d) / "decisions.csv").write_bytes(decisions)
        (Path(d) / "extra.jsonl").write_bytes(decisions)
        (Path(d) / "timings.json").write_bytes(meta)

        def read() -> None:
            run = load_run(d)
            run.extra()
            run.timings()

        _only_known_errors(read)


# ---------------------------------------------------------------------------------------------
# flight logs


def _df_text() -> bytes:
    lines = [
        "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns",
        "FMT, 129, 23, GPS, QBIHBcLLeeff, TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ",
        "FMT, 130, 31, IMU, Qffffff, TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ",
        "FMT, 131, 14, MODE, QMBB, TimeUS,Mode,ModeNum,Rsn",
        "FMT, 133, 31, PARM, QNf, TimeUS,Name,Value",
        "PARM, 1000, GAIN, 1.5",
        "MODE, 1000000, 2, 2, 1",
        "IMU, 1000000, 0, 0, 0, 0, 0, -9.8",
        "GPS, 1000000, 3, 100000, 2000, 10, 1.0, 52.1, -4.1, 50.0, 0, 0, 0",
        "GPS, 3000000, 3, 102000, 2000, 10, 1.0, 52.2, -4.1, 50.0, 0, 0, 0",
    ]
    return ("\n".join(lines) + "\n").encode()


def _df_binary() -> bytes:
    import sys

    sys.path.insert(0, str(Path(__file__).parent / "mav"))
    from flight_synth import make_log

    return make_log(0.4)


def _ulog() -> bytes:
    def msg(kind: bytes, payload: bytes) -> bytes:
        return struct.pack("<HB", len(payload), kind[0]) + payload

    fmt = b"vehicle_attitude:uint64_t timestamp;float[4] q;"
    out = b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 1000)
    out += msg(b"F", fmt)
    key = b"char[3] sys_name"
    out += msg(b"I", bytes([len(key)]) + key + b"PX4")
    out += msg(b"P", bytes([10]) + b"float GAIN" + struct.pack("<f", 2.0))
    out += msg(b"A", struct.pack("<BH", 0, 1) + b"vehicle_attitude")
    for k in range(3):
        out += msg(b"D", struct.pack("<HQ4f", 1, 1000 + k, 1.0, 0.0, 0.0, 0.0))
    return out


@seed(1214)
@FUZZ
@given(st.one_of(mutated(_df_text()), mutated(_df_binary()),
                 lines_of(["FMT,", "IMU,", "GPS,", "PARM,", "MODE,", "128", "89", "Qffffff", ","]).map(
                     lambda t: b"FMT, " + t.encode())))
def test_dataflash_reader(data: bytes) -> None:
    from stablecues.mav import read_log

    with _file(data, "flight.bin") as p:
        _only_known_errors(lambda: read_log(p))


@seed(1215)
@FUZZ
@given(st.one_of(mutated(_ulog()), st.binary(max_size=200).map(lambda b: b"ULog\x01\x12\x35\x01" + b)))
def test_ulog_reader(data: bytes) -> None:
    pytest.importorskip("pyulog")
    from stablecues.mav import read_log

    with _file(data, "flight.ulg") as p:
        _only_known_errors(lambda: read_log(p))


@seed(1216)
@FUZZ
@given(st.one_of(TEXT_BYTES, lines_of(["timestamp,lat,lon,alt", "1.0,52.0,-4.0,10", "nan", ",", ";", '"'])
                 .map(lambda t: b"timestamp,lat,lon\n" + t.encode())))
def test_gnss_track_and_frame_times(data: bytes) -> None:
    from stablecues.mav import read_log
    from stablecues.mav.frames import read_frames

    with _file(data, "track.csv") as p:
        _only_known_errors(lambda: read_log(p))
        _only_known_errors(lambda: read_frames(None, p))


# ---------------------------------------------------------------------------------------------
# settings


JSON = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=5)),
    lambda inner: st.one_of(
        st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=8), inner, max_size=3)
    ),
    max_leaves=8,
)


@seed(1217)
@FUZZ
@given(st.dictionaries(st.sampled_from(["query", "features", "masking", "verification", "similarity",
                                        "confidence", "semantic_source", "alpha"]),
                       st.one_of(JSON, st.dictionaries(st.sampled_from(["alpha", "exclude_recent", "name",
                                                                         "n_features", "mode", "use_nss"]),
                                                       JSON, max_size=3)), max_size=3))
def test_detector_settings(overrides: dict[str, Any]) -> None:
    from stablecues.detection import preset

    _only_known_errors(lambda: preset("default", overrides))

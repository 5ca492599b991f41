"""A hand-written ArduPilot dataflash log (binary and text) through the reader (no shared data)."""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymavlink")
pytest.importorskip("pymap3d")

from stablecues.errors import DatasetError  # noqa: E402
from stablecues.mav import TruncatedLogWarning, detect_format, read_log  # noqa: E402

HEAD = b"\xa3\x95"
# name -> (type id, struct format after the header, dataflash format, columns)
FORMATS = {
    "MSG": (140, "<Q64s", "QZ", "TimeUS,Message"),
    "PARM": (141, "<Q16sf", "QNf", "TimeUS,Name,Value"),
    "GPS": (142, "<QBIHBhiiffff", "QBIHBcLLffff", "TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ"),
    "IMU": (143, "<QBffffff", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
    "BARO": (144, "<QBff", "QBff", "TimeUS,I,Alt,Press"),
    "MAG": (145, "<QBhhh", "QBhhh", "TimeUS,I,MagX,MagY,MagZ"),
    "ATT": (146, "<Qfff", "Qfff", "TimeUS,Roll,Pitch,Yaw"),
    "MODE": (147, "<QBBB", "QMBB", "TimeUS,Mode,ModeNum,Rsn"),
    "XKF1": (148, "<QBfffffffff", "QBfffffffff", "TimeUS,C,Roll,Pitch,Yaw,VN,VE,VD,PN,PE,PD"),
    "ORGN": (149, "<QBiif", "QBLLf", "TimeUS,Type,Lat,Lng,Alt"),
}
FMT_STRUCT = struct.Struct("<BB4s16s64s")


def _fmt_record(name: str) -> bytes:
    tid, fmt, df, cols = FORMATS[name]
    length = 3 + struct.calcsize(fmt)
    return HEAD + bytes([128]) + FMT_STRUCT.pack(tid, length, name.encode(), df.encode(), cols.encode())


def _record(name: str, *values: object) -> bytes:
    tid, fmt, _, _ = FORMATS[name]
    vals = [v.encode() if isinstance(v, str) else v for v in values]
    if name == "MSG":
        vals[1] = vals[1].ljust(64, b"\0")  # type: ignore[union-attr]
    return HEAD + bytes([tid]) + struct.pack(fmt, *vals)


def make_log(seconds: float = 10.0) -> bytes:
    """A copter hovering 1 s, then flying north at 2 m/s; LOITER, BRAKE at 4 s, RTL at 7 s."""
    out = bytearray()
    # FMT of FMT itself, as ArduPilot writes it
    out += (
        HEAD + bytes([128]) + FMT_STRUCT.pack(128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")
    )
    for name in FORMATS:
        out += _fmt_record(name)
    t0 = 50_000_000  # 50 s after boot
    out += _record("MSG", t0, "ArduCopter V4.3.6 (abcdef12)")
    out += _record("PARM", t0, "COMPASS_DEC", 0.0)
    out += _record("ORGN", t0, 0, int(52.0 * 1e7), int(-4.0 * 1e7), 100.0)
    out += _record("MODE", t0, 5, 5, 1)
    lat0, lon0 = 52.0, -4.0
    for k in range(int(seconds * 50)):
        t = t0 + k * 20_000
        ts = k * 0.02
        out += _record("IMU", t, 0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.80665)
        out += _record("IMU", t, 1, 0.0, 0.0, 0.0, 0.0, 0.0, -9.7)  # second IMU: ignored
        if k % 5 == 0:
            out += _record("BARO", t, 0, 0.5, 101000.0)
            out += _record("MAG", t, 0, 200, 0, 400)
            out += _record("ATT", t, 0.0, 0.0, 0.0)
            north = max(0.0, ts - 1.0) * 2.0
            speed = 2.0 if ts > 1.0 else 0.0
            out += _record("XKF1", t, 0, 0.0, 0.0, 0.0, speed, 0.0, 0.0, north, 0.0, 0.0)
        if k % 10 == 0:
            north = max(0.0, ts - 1.0) * 2.0
            lat = lat0 + north / 6_371_000.0 * 180.0 / np.pi
            gms = 300_000_000 + k * 20
            speed = 2.0 if ts > 1.0 else 0.0
            out += _record(
                "GPS", t, 3, gms, 2269, 15, 80, int(round(lat * 1e7)), int(lon0 * 1e7), 100.0, speed, 0.0, 0.0
            )
        if k == 200:
            out += _record("MODE", t, 17, 17, 1)
        if k == 350:
            out += _record("MODE", t, 6, 6, 1)
    return bytes(out)


def test_synthetic_dataflash_reads(tmp_path: Path) -> None:
    path = tmp_path / "synth.bin"
    path.write_bytes(make_log())
    assert detect_format(path) == "dataflash"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complete log: no warning at all
        log = read_log(path)
    assert log.vehicle == "ArduCopter V4.3.6 (abcdef12)" and not log.truncated
    assert log.boot_time_offset == pytest.approx(50.0)
    assert log.duration == pytest.approx(9.98, abs=1e-6)
    assert log.counts["IMU"] == 1000 and len(log.imu) == 500  # instance 0 only
    np.testing.assert_allclose(log.imu.accel[0], [0, 0, -9.80665], rtol=1e-6)
    assert len(log.gnss) == 50 and np.all(log.gnss.fix == 3)
    np.testing.assert_allclose(log.gnss.vel_ned[-1], [2.0, 0.0, 0.0], atol=1e-6)
    assert log.gnss.lat[0] == pytest.approx(52.0) and log.gnss.lon[0] == pytest.approx(-4.0)  # 'L': 1e-7 deg
    np.testing.assert_allclose(log.mag.field[0], [0.2, 0.0, 0.4])  # milligauss -> gauss
    # GPS week 2269, 300000 s into the week, 18 leap seconds
    assert log.utc_offset == pytest.approx(315964800 + 2269 * 604800 + 300_000 - 18, abs=1e-3)
    assert [(c.name, round(c.t, 2)) for c in log.mode_changes] == [
        ("LOITER", 0.0),
        ("BRAKE", 4.0),
        ("RTL", 7.0),
    ]
    assert log.onboard is not None and log.onboard.origin == pytest.approx((52.0, -4.0, 100.0))
    np.testing.assert_allclose(log.onboard.position[-1], [0.0, 17.8, 0.0], atol=1e-4)  # ENU: north is y


def test_synthetic_dataflash_truncated_and_corrupt(tmp_path: Path) -> None:
    data = make_log()
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[: len(data) - 5])
    with pytest.warns(TruncatedLogWarning, match="ends inside a record"):
        log = read_log(cut)
    assert log.truncated and len(log.gnss) == 50
    # garbage in the middle: skipped with a warning, the rest still reads
    mid = len(data) // 2
    bad = tmp_path / "bad.bin"
    bad.write_bytes(data[:mid] + b"\x00\x01\x02garbage" * 20 + data[mid:])
    with pytest.warns(UserWarning):
        log = read_log(bad)
    assert len(log.gnss) >= 45
    # a dataflash header followed by nothing usable
    junk = tmp_path / "junk.bin"
    junk.write_bytes(HEAD + bytes(range(200)))
    with pytest.raises(DatasetError, match="no record with a timestamp"):
        read_log(junk)
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    with pytest.raises(DatasetError, match="not a flight log"):
        read_log(empty)
    with pytest.raises(DatasetError, match="not found"):
        read_log(tmp_path / "missing.bin")


def test_text_dataflash_log(tmp_path: Path) -> None:
    lines = [
        "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns",
        "FMT, 129, 23, GPS, QBIHBcLLeeff, TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ",
        "FMT, 130, 31, IMU, Qffffff, TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ",
        "FMT, 131, 14, MODE, QMBB, TimeUS,Mode,ModeNum,Rsn",
        "FMT, 132, 75, MSG, QZ, TimeUS,Message",
        "MSG, 1000000, ArduCopter V4.0.0",
        "MODE, 1000000, 2, 2, 1",
        "IMU, 1000000, 0, 0, 0, 0, 0, -9.8",
        "GPS, 1000000, 3, 100000, 2000, 10, 1.0, 52.1, -4.1, 50.0, 0, 0, 0",
        "IMU, 2000000, 0, 0, 0, 0, 0, -9.8",
        "MODE, 2500000, 5, 5, 1",
        "GPS, 3000000, 3, 102000, 2000, 10, 1.0, 52.2, -4.1, 50.0, 0, 0, 0",
    ]
    path = tmp_path / "flight.log"
    path.write_text("\n".join(lines) + "\n")
    assert detect_format(path) == "dataflash_text"
    log = read_log(path)
    assert log.duration == pytest.approx(2.0)
    np.testing.assert_allclose(log.gnss.lat, [52.1, 52.2])
    assert [(c.name, c.t) for c in log.mode_changes] == [("ALT_HOLD", 0.0), ("LOITER", 1.5)]

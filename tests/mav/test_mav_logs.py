"""Flight-log readers: a hand-written ArduPilot dataflash log (binary and text), and the real
logs of ../shared/data/mav against the facts in its MANIFEST.md (those skip when it is absent)."""

from __future__ import annotations

import re
import warnings
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path

pytest.importorskip("pymavlink")
pytest.importorskip("pyulog")
pytest.importorskip("pymap3d")

from flight_synth import DF_HEAD, make_log  # noqa: E402

from stablecues.errors import DatasetError  # noqa: E402
from stablecues.geometry.rotations import quat_to_matrix  # noqa: E402
from stablecues.mav import FlightLog, TruncatedLogWarning, detect_format, read_log  # noqa: E402

# ---------------------------------------------------------------------------------------------
# synthetic logs


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
    junk.write_bytes(DF_HEAD + bytes(range(200)))
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


# ---------------------------------------------------------------------------------------------
# real logs


@cache
def _log(*parts: str) -> FlightLog:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_log(shared_path("mav", *parts))


def _spans(log: FlightLog) -> list[tuple[str, float, float]]:
    return [(s.name, round(s.start, 1), round(s.end, 1)) for s in log.mode_spans()]


LOGS = [
    ("uob_ardupilot_copter_2023", "2023-07-06_10-12-18.bin", 98.0),
    ("uob_ardupilot_copter_2023", "2023-07-06_10-18-44.bin", 104.2),
    ("erlerobot_ardupilot_copter_2014", "118.BIN", 303.0),
    ("erlerobot_ardupilot_copter_2014", "Loiter_RTL.bin", 258.0),
    ("pymavlink_test_bin", "test.BIN", 1.0),
    ("methodic_configurator_truncated_v46", "backend_log_80k.bin", 0.4),
    ("pyulog_samples", "sample.ulg", 69.0),
    ("pyulog_samples", "sample_appended_multiple.ulg", 9.8),
    ("pyulog_samples", "sample_log_small.ulg", 1174.0),
    ("pyulog_samples", "sample_logging_tagged_and_default_params.ulg", 10.8),
    ("pyulog_samples", "sample_px4_events.ulg", 31.0),
    ("px4ulogtests_sitl_groundtruth", "14_19_29.ulg", 57.6),
    ("roboto_px4_fmuv5_ground", "test.ulg", 9.0),
]


@pytest.mark.parametrize(("folder", "name", "duration"), LOGS, ids=[n for _, n, _ in LOGS])
def test_every_log_reads_with_its_duration(folder: str, name: str, duration: float) -> None:
    log = _log(folder, name)
    assert log.duration == pytest.approx(duration, abs=0.5 if duration > 5 else 0.1)
    assert log.kind == ("px4" if name.endswith(".ulg") else "ardupilot")
    assert sum(log.counts.values()) > 0
    assert len(log.imu) > 0 and np.isfinite(log.imu.accel).all()
    assert np.all(np.diff(log.imu.t) >= 0)
    # at rest or hovering, the mean specific force is about one g
    assert np.linalg.norm(np.median(log.imu.accel, axis=0)) == pytest.approx(9.8, abs=1.5)


def test_uob_flights_messages_and_modes() -> None:
    a = _log("uob_ardupilot_copter_2023", "2023-07-06_10-12-18.bin")
    b = _log("uob_ardupilot_copter_2023", "2023-07-06_10-18-44.bin")
    for log in (a, b):
        for msg in (
            "GPS",
            "GPA",
            "BARO",
            "IMU",
            "ATT",
            "AHR2",
            "MAG",
            "MODE",
            "ORGN",
            "POS",
            "XKF1",
            "XKQ",
            "PARM",
        ):
            assert log.counts.get(msg, 0) > 0, msg
        assert log.vehicle.startswith("ArduCopter V4.3")
        assert log.onboard is not None and log.onboard.name == "XKF1[0]"
        assert not log.onboard.origin_estimated
    # MANIFEST: GPS Status 3 (490 fixes, 5 Hz) / Status 4 (DGPS, 521 fixes)
    assert len(a.gnss) == 490 and np.all(a.gnss.fix == 3)
    assert len(b.gnss) == 521 and np.all(b.gnss.fix == 4)
    assert np.median(np.diff(a.gnss.t)) == pytest.approx(0.2, abs=0.01)
    # BARO: 2 instances at 10 Hz each; the first one is used
    assert a.counts["BARO"] == 1960 and len(a.baro) == 980
    assert np.median(np.diff(a.baro.t)) == pytest.approx(0.1, abs=0.01)
    # 52.807 N, -4.122 E, about 33 x 33 m and 17 m of height
    assert np.median(a.gnss.lat) == pytest.approx(52.807, abs=0.001)
    assert np.median(a.gnss.lon) == pytest.approx(-4.122, abs=0.001)
    assert np.ptp(a.gnss.alt) == pytest.approx(17, abs=2.5)
    # LOITER 0.1-32.4 s, then RTL 32.4-98.0 s; the other flight is AUTO throughout
    assert _spans(a) == [("LOITER", 0.1, 32.4), ("RTL", 32.4, 98.0)]
    assert _spans(b) == [("AUTO", 0.1, 104.2)]
    # GNSS time gives UTC: the file name is the local (BST = UTC+1) start time 10:12:18
    import datetime as dt

    start = dt.datetime.fromtimestamp(a.utc_offset, dt.UTC)
    assert (start.hour, start.minute) == (9, 12) and abs(start.second - 18) <= 1


def test_118_has_thirteen_mode_records_and_twelve_spans() -> None:
    log = _log("erlerobot_ardupilot_copter_2014", "118.BIN")
    # 13 MODE records; the first two both say ALT_HOLD (logged at the start of the log), so the
    # flight has 12 distinct mode spans (the MANIFEST's "13 segments" counts the records)
    assert len(log.mode_changes) == 13
    assert [c.name for c in log.mode_changes[:2]] == ["ALT_HOLD", "ALT_HOLD"]
    spans = _spans(log)
    names = [s[0] for s in spans]
    assert names == [
        "ALT_HOLD", "LOITER", "RTL", "ALT_HOLD", "LOITER", "STABILIZE", "ALT_HOLD",
        "STABILIZE", "ALT_HOLD", "LOITER", "RTL", "STABILIZE",
    ]  # fmt: skip
    starts = [s[1] for s in spans]
    for want in (0.0, 18.0, 60.1, 107.5, 124.3, 162.8, 236.0, 278.9, 299.8):
        assert any(abs(s - want) < 0.11 for s in starts), want
    assert spans[-1][2] == pytest.approx(303.2, abs=0.1)
    assert int(np.sum(log.gnss.fix >= 3)) == 1309  # MANIFEST: 3D fix throughout (1309 fixes)
    # |roll| > 60 deg at 166.8 s (the tip-over)
    roll = np.degrees(np.abs(log.attitude.rpy[:, 0]))
    assert np.any((roll > 60) & (np.abs(log.attitude.t - 166.8) < 1.0))
    # the 2014 EKF1 has no logged origin: it is fitted to GNSS, and says so
    assert log.onboard is not None and log.onboard.name == "EKF1" and log.onboard.origin_estimated
    assert any("ORGN" in w for w in log.warnings)


def test_loiter_rtl_modes() -> None:
    log = _log("erlerobot_ardupilot_copter_2014", "Loiter_RTL.bin")
    spans = _spans(log)
    assert [s[0] for s in spans] == [
        "ALT_HOLD", "LOITER", "LAND", "ALT_HOLD", "LOITER", "LAND", "ALT_HOLD", "LOITER", "RTL",
    ]  # fmt: skip
    assert spans[1][1:] == pytest.approx((20.4, 24.0), abs=0.11)
    assert spans[2][1:] == pytest.approx((24.0, 30.9), abs=0.11)
    assert spans[-2][1:] == pytest.approx((105.7, 206.6), abs=0.11)
    assert spans[-1][1] == pytest.approx(206.6, abs=0.11)
    assert int(np.sum(log.gnss.fix >= 3)) == 990


def test_px4_modes_and_topics() -> None:
    ev = _log("pyulog_samples", "sample_px4_events.ulg")
    spans = _spans(ev)
    assert [s[0] for s in spans] == ["AUTO_LOITER", "AUTO_TAKEOFF", "AUTO_LOITER", "AUTO_RTL", "AUTO_LOITER"]
    assert spans[1][1:] == pytest.approx((14.9, 21.3), abs=0.11)
    assert spans[3][1:] == pytest.approx((22.1, 30.1), abs=0.11)
    assert len(ev.gnss) > 0 and len(ev.baro) > 0 and len(ev.mag) > 0 and len(ev.attitude) > 0
    assert ev.onboard is not None and ev.onboard.name == "vehicle_local_position"

    sitl = _log("px4ulogtests_sitl_groundtruth", "14_19_29.ulg")
    assert [s[0] for s in _spans(sitl)] == ["AUTO_LOITER", "AUTO_TAKEOFF", "AUTO_LOITER", "AUTO_RTL"]
    assert _spans(sitl)[1][1] == pytest.approx(44.8, abs=0.1)
    assert _spans(sitl)[3][1] == pytest.approx(47.8, abs=0.1)
    assert sitl.counts["sensor_combined"] / sitl.duration == pytest.approx(217, abs=3)
    assert sitl.ground_truth is not None
    assert np.ptp(sitl.ground_truth.position[:, 2]) == pytest.approx(2.5, abs=1.0)  # "only a 2.5 m hop"

    small = _log("pyulog_samples", "sample_log_small.ulg")
    assert len(small.gnss) == 32 and np.all(small.gnss.fix == 3)
    assert np.median(small.gnss.lat) == pytest.approx(63.417, abs=0.01)
    ground = _log("roboto_px4_fmuv5_ground", "test.ulg")
    assert _spans(ground)[0][0] == "STAB"
    assert np.median(ground.gnss.lat) == pytest.approx(31.753, abs=0.01)


def test_truncated_logs_warn_and_still_read(tmp_path: Path) -> None:
    src = shared_path("mav", "methodic_configurator_truncated_v46", "backend_log_80k.bin")
    with pytest.warns(TruncatedLogWarning, match="ends inside a record"):
        log = read_log(src)
    assert log.truncated and log.vehicle.startswith("ArduCopter V4.6")
    assert log.counts["PARM"] > 1000 and len(log.gnss) == 2 and log.onboard is not None
    # a ULog cut in the middle of a message
    ulg = shared_path("mav", "pyulog_samples", "sample_px4_events.ulg").read_bytes()
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(ulg[: len(ulg) * 3 // 4 + 37])
    with pytest.warns(TruncatedLogWarning):
        log = read_log(cut)
    assert log.truncated and 5.0 < log.duration < 31.0
    assert "AUTO_TAKEOFF" in [c.name for c in log.mode_changes]
    # a complete ULog does not warn
    with warnings.catch_warnings():
        warnings.simplefilter("error", TruncatedLogWarning)
        assert not read_log(shared_path("mav", "pyulog_samples", "sample_appended_multiple.ulg")).truncated


def test_files_that_are_not_logs_raise(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not a flight log"):
        read_log(shared_path("mav", "MANIFEST.md"))
    with pytest.raises(DatasetError, match="not a flight log"):
        read_log(shared_path("mav", "zr10_aerial_camera_gnss", "images", "IMG_0011.jpg"))


def _parse_dump(path: Path) -> list[tuple[str, dict[str, str]]]:
    out = []
    for line in path.read_text().splitlines():
        m = re.match(r"^\S+ \S+: (\w+) \{(.*)\}$", line)
        if not m:
            continue
        fields = dict(kv.split(" : ", 1) for kv in m.group(2).split(", ") if " : " in kv)
        out.append((m.group(1), fields))
    return out


def test_pymavlink_test_bin_agrees_with_golden_dump() -> None:
    folder = shared_path("mav", "pymavlink_test_bin")
    with pytest.warns(TruncatedLogWarning):
        log = read_log(folder / "test.BIN")
    dump = _parse_dump(folder / "test.BIN.py3.dumped")
    counts: dict[str, int] = {}
    for name, _ in dump:
        counts[name] = counts.get(name, 0) + 1
    assert dict(log.counts) == counts  # every message type, every record
    assert log.vehicle.startswith("ArduPlane V3.8.2")

    def column(name: str, key: str) -> np.ndarray:
        return np.array([float(f[key]) for n, f in dump if n == name])

    t0 = log.boot_time_offset
    np.testing.assert_allclose(log.gnss.t, column("GPS", "TimeUS") * 1e-6 - t0, atol=1e-9)
    np.testing.assert_allclose(log.gnss.lat, column("GPS", "Lat"), atol=1e-9)
    np.testing.assert_allclose(log.gnss.lon, column("GPS", "Lng"), atol=1e-9)
    np.testing.assert_allclose(log.gnss.alt, column("GPS", "Alt"), atol=1e-6)
    np.testing.assert_allclose(log.gnss.h_acc, column("GPA", "HAcc"), atol=1e-6)
    np.testing.assert_allclose(log.imu.accel[:, 2], column("IMU", "AccZ"), rtol=1e-6)
    np.testing.assert_allclose(log.imu.gyro[:, 0], column("IMU", "GyrX"), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(log.baro.alt, column("BARO", "Alt"), rtol=1e-6)
    np.testing.assert_allclose(log.mag.field[:, 0], column("MAG", "MagX") * 1e-3)
    np.testing.assert_allclose(np.degrees(log.attitude.rpy[:, 0]), column("ATT", "Roll"), atol=1e-6)
    assert log.onboard is not None and log.onboard.name == "NKF1[0]"
    # NKF1 is NED; the structure holds ENU: east = PE, north = PN, up = -PD
    np.testing.assert_allclose(log.onboard.position[:, 0], column("NKF1", "PE"), rtol=1e-6)
    np.testing.assert_allclose(log.onboard.position[:, 1], column("NKF1", "PN"), rtol=1e-6)
    np.testing.assert_allclose(log.onboard.position[:, 2], -column("NKF1", "PD"), rtol=1e-6)
    assert [c.name for c in log.mode_changes] == ["MANUAL"]
    assert log.mode_changes[0].t == pytest.approx(column("MODE", "TimeUS")[0] * 1e-6 - t0)
    assert log.params["SERIAL5_BAUD"] == 921600.0
    # the attitude comes from NKQ1 (logged w, x, y, z): NKF1's Euler angles are the same attitude
    # with the AHRS trim (AHRS_TRIM_X / _Y, radians) applied, to the 0.01 deg NKF1 is logged in
    rpy = np.degrees(log.onboard.rpy)
    trim = np.degrees([log.params["AHRS_TRIM_X"], log.params["AHRS_TRIM_Y"]])
    np.testing.assert_allclose(rpy[:, 0] - trim[0], column("NKF1", "Roll"), atol=0.02)
    np.testing.assert_allclose(rpy[:, 1] - trim[1], column("NKF1", "Pitch"), atol=0.02)
    yaw_err = (rpy[:, 2] - column("NKF1", "Yaw") + 180.0) % 360.0 - 180.0
    np.testing.assert_allclose(yaw_err, 0.0, atol=0.02)
    # ENU quaternions (x, y, z, w): the body's nose (FRD x) points along the logged yaw
    nose = quat_to_matrix(log.onboard.quaternion)[:, :, 0]
    heading_cw_from_north = np.degrees(np.arctan2(nose[:, 0], nose[:, 1]))
    err = (heading_cw_from_north - column("NKF1", "Yaw") + 180.0) % 360.0 - 180.0
    assert np.abs(err).max() < 0.5


def test_dataflash_attitude_quaternion_is_read_scalar_first(tmp_path: Path) -> None:
    # XKQ logs (w, x, y, z); 90 degrees about NED down: the nose points east
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    path = tmp_path / "xkq.bin"
    path.write_bytes(make_log(2.0, xkq_wxyz=(c, 0.0, 0.0, s)))
    log = read_log(path)
    assert log.onboard is not None
    np.testing.assert_allclose(
        np.degrees(log.onboard.rpy), np.tile([0.0, 0.0, 90.0], (len(log.onboard), 1)), atol=1e-4
    )
    # body -> ENU, (x, y, z, w): the nose is along ENU x (east), the right wing along -y (south)
    np.testing.assert_allclose(log.onboard.quaternion[0], [1.0, 0.0, 0.0, 0.0], atol=1e-6)  # 180 deg about x
    r = quat_to_matrix(log.onboard.quaternion[0])
    np.testing.assert_allclose(r[:, 0], [1.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(r[:, 1], [0.0, -1.0, 0.0], atol=1e-6)


def test_px4_attitude_quaternions_are_read_scalar_first() -> None:
    # the onboard solution's attitude is vehicle_attitude's q (logged w, x, y, z), slerped to its
    # times: its Euler angles agree with the attitude series read from the same topic
    log = _log("pyulog_samples", "sample_px4_events.ulg")
    assert log.onboard is not None
    known = np.isfinite(log.onboard.quaternion).all(axis=1)
    assert known.sum() > 100
    on = log.onboard.rpy[known]
    t = log.onboard.t[known]
    for k in range(2):
        np.testing.assert_allclose(on[:, k], np.interp(t, log.attitude.t, log.attitude.rpy[:, k]), atol=0.02)
    yaw_err = np.angle(
        np.exp(1j * (on[:, 2] - np.interp(t, log.attitude.t, np.unwrap(log.attitude.rpy[:, 2]))))
    )
    assert np.abs(yaw_err).max() < 0.02

"""Real flight logs of ../shared/data/mav against the facts in its MANIFEST.md (skips when absent)."""

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

from stablecues.errors import DatasetError  # noqa: E402
from stablecues.mav import FlightLog, TruncatedLogWarning, read_log  # noqa: E402


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

#!/usr/bin/env python
"""MAV benchmark (issue 7): this package's EKF against the autopilots' own navigation solutions.

Acceptance figures: on the two real ArduCopter 4.3 flights of ``uob_ardupilot_copter_2023`` the
fused trajectory must stay within 0.5 m horizontal and 0.3 m vertical RMS of the onboard EKF3
(``XKF1``, core 0) after removing a constant offset. One configuration (the defaults of
:class:`stablecues.mav.EkfConfig`) is used for every log.

Also reported, for context (not acceptance):

* the raw GNSS against XKF1 (the floor a GNSS-only trajectory would reach);
* the 2014 ArduCopter 3.3 flights against their EKF1 (no logged origin: fitted to GNSS; the
  vehicle tips over in both, so large local errors are expected);
* the PX4 SITL log against its simulator ground truth, and the PX4 onboard EKF against it;
* run time per flight.

Prints a table and writes ``bench/results/mav.json`` (``ekf_h_rmse_m`` / ``ekf_v_rmse_m`` per
flight and overall, where overall pools all compared samples of both flights).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from stablecues.config import to_dict
from stablecues.mav import EkfConfig, FlightLog, NavSolution, compare_solutions, geo, read_log, run_ekf

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data" / "mav"

ACCEPTANCE = [
    ("uob_ardupilot_copter_2023", "2023-07-06_10-12-18.bin"),
    ("uob_ardupilot_copter_2023", "2023-07-06_10-18-44.bin"),
]
CONTEXT = [
    ("erlerobot_ardupilot_copter_2014", "118.BIN"),
    ("erlerobot_ardupilot_copter_2014", "Loiter_RTL.bin"),
    ("px4ulogtests_sitl_groundtruth", "14_19_29.ulg"),
]
SHORT = {"vehicle_local_position": "PX4 EKF2", "vehicle_local_position_groundtruth": "SITL truth"}


def _read(path: Path) -> FlightLog:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_log(path)


def _gnss_vs(log: FlightLog, reference: NavSolution) -> dict[str, float]:
    """Raw GNSS fixes against a reference (constant offset removed)."""
    g = log.gnss.subset(log.gnss.fix >= 3)
    enu = geo.geodetic_to_enu(g.lat, g.lon, g.alt, reference.origin)
    at = reference.interpolate(g.t)
    ok = np.isfinite(at.position).all(axis=1)
    d = enu[ok] - at.position[ok]
    d -= d.mean(axis=0)
    return {
        "h_rmse_m": float(np.sqrt(np.mean(d[:, 0] ** 2 + d[:, 1] ** 2))),
        "v_rmse_m": float(np.sqrt(np.mean(d[:, 2] ** 2))),
    }


def evaluate(path: Path, config: EkfConfig) -> dict[str, object]:
    log = _read(path)
    t0 = time.perf_counter()
    solution, report = run_ekf(log, config)
    seconds = time.perf_counter() - t0
    out: dict[str, object] = {
        "log": f"{path.parent.name}/{path.name}",
        "duration_s": round(log.duration, 2),
        "imu_samples": len(log.imu),
        "ekf_seconds": round(seconds, 3),
        "gnss_lag_s": report.gnss_lag_s,
        "accel_noise": round(report.accel_noise, 4),
        "gyro_noise": round(report.gyro_noise, 5),
        "accepted": report.accepted,
        "rejected": report.rejected,
        "resets": report.resets,
    }
    for label, ref in (("onboard", log.onboard), ("ground_truth", log.ground_truth)):
        if ref is None:
            continue
        c = compare_solutions(solution, ref)
        out[label] = {
            "reference": c.reference,
            "origin_estimated": ref.origin_estimated,
            "n": c.n,
            "ekf_h_rmse_m": round(c.h_rmse_m, 4),
            "ekf_v_rmse_m": round(c.v_rmse_m, 4),
            "offset_enu_m": [round(x, 3) for x in c.offset_enu],
            "roll_rmse_deg": round(c.roll_rmse_deg, 3),
            "pitch_rmse_deg": round(c.pitch_rmse_deg, 3),
            "yaw_rmse_deg": round(c.yaw_rmse_deg, 3),
            "gnss": {k: round(v, 4) for k, v in _gnss_vs(log, ref).items()},
        }
    if log.onboard is not None and log.ground_truth is not None:
        c = compare_solutions(log.onboard, log.ground_truth)
        out["onboard_vs_ground_truth"] = {"h_rmse_m": round(c.h_rmse_m, 4), "v_rmse_m": round(c.v_rmse_m, 4)}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="the shared mav data folder")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "mav.json")
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        print(f"bench_mav: {args.data} is absent; nothing to measure", file=sys.stderr)
        return 1
    config = EkfConfig()

    flights = [evaluate(args.data / f / n, config) for f, n in ACCEPTANCE]
    for f in flights:  # the acceptance figures, at the top of each flight's entry
        f["ekf_h_rmse_m"] = f["onboard"]["ekf_h_rmse_m"]  # type: ignore[index]
        f["ekf_v_rmse_m"] = f["onboard"]["ekf_v_rmse_m"]  # type: ignore[index]
    context = [evaluate(args.data / f / n, config) for f, n in CONTEXT if (args.data / f / n).is_file()]

    def pooled(key: str) -> float:
        num = sum(f["onboard"]["n"] * f["onboard"][key] ** 2 for f in flights)  # type: ignore[index]
        den = sum(f["onboard"]["n"] for f in flights)  # type: ignore[index]
        return float(np.sqrt(num / den))

    overall = {
        "ekf_h_rmse_m": round(pooled("ekf_h_rmse_m"), 4),
        "ekf_v_rmse_m": round(pooled("ekf_v_rmse_m"), 4),
        "worst_h_rmse_m": max(f["onboard"]["ekf_h_rmse_m"] for f in flights),  # type: ignore[index]
        "worst_v_rmse_m": max(f["onboard"]["ekf_v_rmse_m"] for f in flights),  # type: ignore[index]
    }
    passed = overall["worst_h_rmse_m"] < 0.5 and overall["worst_v_rmse_m"] < 0.3
    result = {
        "benchmark": "mav",
        "what": "stablecues EKF vs the autopilot's EKF (XKF1 core 0), constant offset removed",
        "acceptance": {"h_rmse_m_below": 0.5, "v_rmse_m_below": 0.3, "passed": bool(passed)},
        "flights": {f["log"]: f for f in flights},
        "overall": overall,
        "context": {c["log"]: c for c in context},
        "config": to_dict(config),
        "machine": {"python": platform.python_version(), "platform": platform.platform()},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")

    print("stablecues EKF against the onboard EKF (constant offset removed)")
    print(
        f"{'log':58s} {'ref':12s} {'h RMS m':>8s} {'v RMS m':>8s} {'yaw deg':>8s} {'GNSS h/v':>12s} {'s':>6s}"
    )
    for f in flights + context:
        for label in ("onboard", "ground_truth"):
            r = f.get(label)
            if not isinstance(r, dict):
                continue
            g = r["gnss"]
            ref = SHORT.get(str(r["reference"]), str(r["reference"]))
            print(
                f"{f['log']:58s} {ref:12.12s} {r['ekf_h_rmse_m']:8.3f} {r['ekf_v_rmse_m']:8.3f} "
                f"{r['yaw_rmse_deg']:8.2f} {g['h_rmse_m']:5.2f}/{g['v_rmse_m']:<5.2f} {f['ekf_seconds']:6.2f}"
            )
    print(
        f"overall (uob flights pooled): h {overall['ekf_h_rmse_m']:.3f} m, v {overall['ekf_v_rmse_m']:.3f} m "
        f"-> acceptance (< 0.5 m / < 0.3 m) {'passed' if passed else 'FAILED'}"
    )
    print(f"wrote {args.out}")
    return 0 if passed else 2


if __name__ == "__main__":
    sys.exit(main())

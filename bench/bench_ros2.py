"""The ROS 2 node's latency on a 20 Hz EuRoC replay (issue 36): from an image's publication to
its decision's publication, the frames it skipped, and its CPU, with ``fast`` and the default.

A ROS 2 bag is made of the real EuRoC V1_01 micro stereo pairs (``../shared/data``), repeated
``--laps`` times (a lap revisits the places of the one before) with stamps 50 ms apart: 20 Hz,
the EuRoC camera's rate. Three processes talk DDS on the loopback interface only (the shipped
``cyclonedds_loopback.xml``): ``stablecues ros2 play`` publishes the bag as a camera driver would
(sensor-data QoS: best effort, keep last 5; each image's publication time recorded),
``stablecues ros2`` decides with its defaults (keeps the newest frame when it falls behind) and
``stablecues ros2 echo`` records each decision with its publication time (the writer's source
timestamp). The latency of a decision is its publication time minus its left image's; the
first decided frame (it loads the features and the network) is reported apart; the node loads
its compiled kernels before its first frame (``STABLECUES_COMPILE=wait``), so the figures are
those of a node that has been running a while. CPU is the
node process's user + system time over the replay (100 % = one core), sampled with psutil.

    python bench/bench_ros2.py                  # writes bench/results/ros2.json
    python bench/bench_ros2.py --laps 2 --presets fast

Another benchmark may share the machine: the load averages before and after are recorded.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "ros2.json"
SHARED = Path(os.environ.get("STABLECUES_SHARED_DATA", HERE.parent.parent / "shared" / "data"))
PERIOD_NS = 50_000_000  # 20 Hz


def make_bag(path: Path, laps: int) -> tuple[Path, int]:
    """The replayed bag: EuRoC V1_01 micro stereo pairs, ``laps`` times, 50 ms apart."""
    from stablecues.geometry import load_calibration
    from stablecues.imageio import read_image
    from stablecues.ros2.bagwrite import write_image_bag

    mav0 = SHARED / "euroc" / "V1_01_micro" / "mav0"
    if not mav0.is_dir():
        sys.exit(f"bench_ros2: the EuRoC micro sequence is not at {mav0} (see docs/data.md)")
    names = [
        ln.split(",")[1].strip()
        for ln in (mav0 / "cam0" / "data.csv").read_text().splitlines()[1:]
        if ln.strip()
    ]
    left = [read_image(mav0 / "cam0" / "data" / n, "8bit") for n in names] * laps
    right = [read_image(mav0 / "cam1" / "data" / n, "8bit") for n in names] * laps
    stamps = [1_403_715_273_000_000_000 + k * PERIOD_NS for k in range(len(left))]
    calib = load_calibration(mav0 / "cam0" / "sensor.yaml")
    return write_image_bag(path, stamps, left, right, calibration=calib), len(left)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "stablecues.cli.main", *args]


def _lines(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(ln) for ln in path.read_text().splitlines() if ln.startswith("{")]


def measure(bag: Path, frames: int, preset: str, work: Path, domain: int) -> dict[str, Any]:
    """One replay of ``bag`` to a node of ``preset``; the figures."""
    import psutil

    from stablecues.ros2.dds import LOOPBACK_CONFIG

    env = dict(
        os.environ,
        CYCLONEDDS_URI=LOOPBACK_CONFIG.as_uri(),
        ROS_DOMAIN_ID=str(domain),
        PYTHONUNBUFFERED="1",
        STABLECUES_COMPILE="wait",  # compiled kernels loaded before the first frame: the steady state
    )
    echo_out, published = work / f"{preset}.echo", work / f"{preset}.published.json"
    summary = work / f"{preset}.summary.json"
    echo = subprocess.Popen(
        _cli("ros2", "echo", "--timeout", "60"),
        env=env,
        stdout=echo_out.open("wb"),
        stderr=subprocess.DEVNULL,
    )
    node = subprocess.Popen(
        _cli(
            "ros2",
            "--image",
            "/cam0/image_raw",
            "--right",
            "/cam1/image_raw",
            "--preset",
            preset,
            "--exit-after-idle",
            "3",
            "--summary",
            str(summary),
        ),
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=(work / f"{preset}.node.log").open("wb"),
    )
    samples: list[tuple[int, float]] = []  # (time.time_ns(), node CPU seconds)
    done = threading.Event()

    def sample_cpu() -> None:
        proc = psutil.Process(node.pid)
        while not done.is_set():
            try:
                samples.append((time.time_ns(), sum(proc.cpu_times()[:2])))
            except psutil.Error:
                return
            time.sleep(0.05)

    sampler = threading.Thread(target=sample_cpu, daemon=True)
    sampler.start()
    try:
        t0 = time.monotonic()
        subprocess.run(
            _cli(
                "ros2",
                "play",
                str(bag),
                "--wait-subscribers",
                "1",
                "--wait-timeout",
                "60",
                "--published",
                str(published),
            ),
            env=env,
            check=True,
            timeout=600,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        n, still = -1, time.monotonic()
        while time.monotonic() - still < 1.0 and time.monotonic() - t0 < 600:  # until the node is done
            now = len(_lines(echo_out))
            if now != n:
                n, still = now, time.monotonic()
            time.sleep(0.1)
        done.set()
        sampler.join(timeout=5)
        node.wait(timeout=60)
    finally:
        for p in (node, echo):
            if p.poll() is None:
                p.terminate()
        for p in (node, echo):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
    pub = {stamp: t for topic, stamp, t in json.loads(published.read_text()) if topic == "/cam0/image_raw"}
    decisions = _lines(echo_out)
    lat = np.array(
        [
            (d["source_timestamp_ns"] - pub[d["query_stamp_ns"]]) * 1e-6
            for d in decisions
            if d["query_stamp_ns"] in pub
        ]
    )
    node_summary = json.loads(summary.read_text())
    # CPU over the replay: from the first image's publication to the last decision's
    first_pub = min(pub.values())
    last_dec = max(d["source_timestamp_ns"] for d in decisions)
    cpu = np.array(samples)
    cpu_s = float(np.interp(last_dec, cpu[:, 0], cpu[:, 1]) - np.interp(first_pub, cpu[:, 0], cpu[:, 1]))
    span_s = (last_dec - first_pub) * 1e-9
    rest = lat[1:] if lat.size > 1 else lat
    return {
        "preset": preset,
        "frames_published": frames,
        "decisions": len(decisions),
        "loops": int(sum(d["accepted"] for d in decisions)),
        "frames_skipped": node_summary["skipped"],
        "frames_lost_before_the_node": frames - node_summary["received"],
        "latency_ms": {
            "median": round(float(np.median(rest)), 1),
            "p99": round(float(np.percentile(rest, 99)), 1),
            "max": round(float(rest.max()), 1),
            "first_frame": round(float(lat[0]), 1),
            "note": "median, p99 and max leave the first decided frame out (it loads the detector); "
            f"{rest.size} decisions counted",
        },
        "node_cpu_percent_of_one_core": round(100 * cpu_s / span_s, 1),
        "replay_s": round(span_s, 2),
        "node_summary": node_summary,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--laps", type=int, default=8, help="times the 19-pair sequence is replayed (default 8)"
    )
    parser.add_argument("--presets", nargs="+", default=["fast", "default"])
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    load_before = os.getloadavg()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        bag, frames = make_bag(work / "euroc20hz", args.laps)
        for k, preset in enumerate(args.presets):
            r = measure(bag, frames, preset, work, domain=180 + k)
            results.append(r)
            lat = r["latency_ms"]
            print(
                f"{preset:8s} latency median {lat['median']} ms, p99 {lat['p99']} ms (first frame "
                f"{lat['first_frame']} ms); {r['decisions']} decisions of {frames} frames, "
                f"{r['frames_skipped']} skipped, {r['frames_lost_before_the_node']} lost on the way; "
                f"node CPU {r['node_cpu_percent_of_one_core']} % of a core"
            )
    out = {
        "what": "stablecues ros2 on a 20 Hz EuRoC V1_01 micro stereo replay (752x480 raw mono8 pairs + "
        "CameraInfo), publisher, node and subscriber as processes over Cyclone DDS on the loopback "
        "interface; latency = decision publication - left image publication",
        "laps": args.laps,
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
        "loadavg_before": [round(v, 2) for v in load_before],
        "loadavg_after": [round(v, 2) for v in os.getloadavg()],
        "date": time.strftime("%Y-%m-%d"),
        "results": results,
    }
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

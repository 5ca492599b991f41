"""Helpers of the ROS 2 tests: bags of real and synthetic frames, and the node, replay and
subscriber as real processes on the loopback interface."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from stablecues.ros2.bagwrite import write_image_bag
from stablecues.ros2.dds import LOOPBACK_CONFIG


def dds_env(domain: int) -> dict[str, str]:
    """The environment of a test process: the shipped loopback-only Cyclone DDS configuration and
    a domain of the test's own (tests running side by side do not hear each other)."""
    env = dict(os.environ)
    env["CYCLONEDDS_URI"] = LOOPBACK_CONFIG.as_uri()
    env["ROS_DOMAIN_ID"] = str(domain)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def stablecues(*args: str) -> list[str]:
    return [sys.executable, "-m", "stablecues.cli.main", *args]


def start(cmd: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    """A process whose output goes to ``log`` (stderr with it)."""
    fh = log.open("wb")
    return subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT)


def stop(*procs: subprocess.Popen[bytes]) -> None:
    """Terminate (then kill) the processes still running."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)


def wait_for_lines(
    path: Path, n: int, timeout: float, proc: subprocess.Popen[bytes] | None = None
) -> list[str]:
    """The first ``n`` non-empty lines of ``path``, waiting at most ``timeout`` s (fewer if it
    times out or ``proc`` ends)."""
    end = time.monotonic() + timeout
    lines: list[str] = []
    while time.monotonic() < end:
        lines = [ln for ln in path.read_text().splitlines() if ln.strip()] if path.exists() else []
        if len(lines) >= n or (proc is not None and proc.poll() is not None):
            break
        time.sleep(0.1)
    return lines[:n] if len(lines) >= n else lines


def decisions(path: Path) -> list[dict[str, Any]]:
    out = []
    for ln in path.read_text().splitlines():
        ln = ln.strip()
        if ln.startswith("{"):
            out.append(json.loads(ln))
    return out


def synthetic_bag(path: Path, frames: int = 24) -> Path:
    """A mono ROS 2 bag of a small synthetic town drive (no shared data needed), with CameraInfo;
    the camera's positions (frames x 3, world frame) beside it in ``<path>.positions.npy``."""
    from stablecues.geometry import Calibration, PinholeCamera
    from stablecues.synthetic import SyntheticTown, SyntheticTownConfig

    cfg = SyntheticTownConfig(frames=frames, width=256, height=192, loops=1, seed=3)
    town = SyntheticTown(cfg)
    images, positions = [], []
    for k in range(frames):
        frame = town.frame(k)
        images.append(np.ascontiguousarray(frame.image))
        positions.append(np.asarray(frame.pose, np.float64)[:3, 3])
    np.save(path.with_suffix(".positions.npy"), np.array(positions))
    fx = float(cfg.width)
    cam = PinholeCamera.from_matrix(
        np.array([[fx, 0, cfg.width / 2], [0, fx, cfg.height / 2], [0, 0, 1]]),
        width=cfg.width,
        height=cfg.height,
    )
    stamps = [1_600_000_000_000_000_000 + k * 100_000_000 for k in range(frames)]
    return write_image_bag(path, stamps, images, calibration=Calibration(left=cam))

"""Compiled kernels loading in the background (issue 38): the first frames run on NumPy while
numba loads or compiles, and the decisions are the same as when the kernels load first."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from conftest import write_wall_drive
from stablecues.engine import Kernels


def test_kernels_load_once_in_the_background() -> None:
    gate = threading.Event()
    calls: list[int] = []

    def load() -> str:
        calls.append(1)
        gate.wait(10)
        return "kernels"

    k: Kernels[str] = Kernels(load, "test kernels")
    assert k.get(wait=False) is None and k.loaded() is None  # started, not there yet: NumPy meanwhile
    assert k.get(wait=False) is None
    gate.set()
    assert k.get(wait=True) == "kernels" and k.loaded() == "kernels" and not k.failed()
    assert k.get(wait=False) == "kernels" and calls == [1]


def test_kernels_that_cannot_load_mean_numpy_for_good() -> None:
    def no_numba() -> str:
        raise ImportError("No module named 'numba'")

    k: Kernels[str] = Kernels(no_numba, "test kernels")
    assert k.get(wait=False) is None
    assert k.get(wait=True) is None and k.failed()


def test_waiting_returns_the_kernels_and_never_blocks_the_others(monkeypatch: pytest.MonkeyPatch) -> None:
    """``STABLECUES_COMPILE=wait`` (or wait=True) returns the kernels once loaded; meanwhile a
    caller that does not wait gets None at once (the load runs in its own thread)."""
    gate = threading.Event()
    k: Kernels[str] = Kernels(lambda: (gate.wait(10), "k")[1], "test")
    got: list[str | None] = []
    waiter = threading.Thread(target=lambda: got.append(k.get(wait=True)))
    waiter.start()
    assert k.get(wait=False) is None  # not behind the waiting caller
    gate.set()
    waiter.join(10)
    assert got == ["k"]
    monkeypatch.setenv("STABLECUES_COMPILE", "wait")
    other: Kernels[str] = Kernels(lambda: "k2", "test")
    assert other.get(wait=False) == "k2"


RUN = r"""
import json, os, sys, threading
from pathlib import Path
import cv2
from stablecues import Frame, LoopDetector, preset
from stablecues.engine import Kernels
from stablecues.vocabulary import engine
gate = threading.Event()
if os.environ.get("STABLECUES_COMPILE") != "wait":  # the kernels arrive after frame 5, mid-run
    real = engine._load
    engine._KERNELS = Kernels(lambda: (gate.wait(60), real())[1], "the vocabulary transform")
detector = LoopDetector(preset("fast", {"query": {"exclude_recent": 3}}))
out, compiled = [], []
for i, path in enumerate(sorted(Path(sys.argv[1]).glob("*.png"))):
    d = detector.process(Frame(index=i, name=path.name, timestamp=float(i), image=cv2.imread(str(path), 0)))
    compiled.append(detector.vocabulary.engine == "compiled")
    out.append([d.status.value, d.candidate_frame, round(d.score, 9), d.n_features])
    if i == 5:
        gate.set()
        engine.compiled_kernels(wait=True)
print(json.dumps({"decisions": out, "compiled": compiled}))
"""


def test_decisions_do_not_depend_on_when_the_kernels_arrive(tmp_path: Path) -> None:
    frames = write_wall_drive(tmp_path, 16)
    got = {}
    for mode in ("background", "wait"):
        env = {k: v for k, v in os.environ.items() if k != "STABLECUES_COMPILE"}
        if mode == "wait":
            env["STABLECUES_COMPILE"] = "wait"
        run = subprocess.run([sys.executable, "-c", RUN, str(frames)], env=env, capture_output=True,
                             text=True, timeout=300, check=True)
        got[mode] = json.loads(run.stdout.strip().splitlines()[-1])
    assert got["background"]["decisions"] == got["wait"]["decisions"]
    assert any(d[0] == "loop_detected" for d in got["wait"]["decisions"])
    if importlib.util.find_spec("numba") is not None:  # the switch happened, mid-run
        background = got["background"]["compiled"]
        assert not any(background[:6]) and all(background[6:]), background
        assert all(got["wait"]["compiled"])

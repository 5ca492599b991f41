"""Compiled kernels loading in the background (issue 38): the first frames run on NumPy while
numba loads or compiles, and the decisions are the same as when the kernels load first."""

from __future__ import annotations

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


def test_waiting_loads_in_the_calling_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    """``STABLECUES_COMPILE=wait`` (or wait=True) loads where the kernels are first needed."""
    where: list[str] = []
    k: Kernels[str] = Kernels(lambda: where.append(threading.current_thread().name) or "k", "test")
    monkeypatch.setenv("STABLECUES_COMPILE", "wait")
    assert k.get(wait=False) == "k" and where == [threading.current_thread().name]


RUN = r"""
import json, sys
from pathlib import Path
import cv2
from stablecues import Frame, LoopDetector, preset
from stablecues.vocabulary.engine import loaded_kernels
detector = LoopDetector(preset("fast", {"query": {"exclude_recent": 3}}))
out = []
for i, path in enumerate(sorted(Path(sys.argv[1]).glob("*.png"))):
    d = detector.process(Frame(index=i, name=path.name, timestamp=float(i), image=cv2.imread(str(path), 0)))
    if i == 0:
        first = loaded_kernels() is not None
    out.append([d.status.value, d.candidate_frame, round(d.score, 9), d.n_features])
print(json.dumps({"decisions": out, "compiled_at_first_frame": first}))
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
    assert got["wait"]["compiled_at_first_frame"] or "numba" not in sys.modules
    assert any(d[0] == "loop_detected" for d in got["wait"]["decisions"])

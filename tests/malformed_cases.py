"""Malformed inputs through the CLI: one case per reader and per way a file can be wrong.

Each case builds its files in a fresh folder and names the command to run. The expectation:

* ``error``: exit status 1 and exactly one line on stderr that names the file (``names``) and
  says what was expected; nothing else changed (``check``, when given, says what was not).
* ``ok``: exit status 0 and ``check`` finds the result right (a silently wrong result fails).

Whatever the expectation, a crafted file must never run code: the canary file that the
crafted inputs would create (:func:`canary`) must not exist afterwards.

``tests/test_malformed_inputs.py`` runs every case in-process; ``bench/bench_robustness.py``
runs them in subprocesses with a memory cap and counts clear errors, tracebacks, memory
blow-ups, silent results and executions. To add a case, write a builder decorated with
:func:`case` (the vocabulary and database cases of other areas go here too).
"""

from __future__ import annotations

import json
import math
import os
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

# ---------------------------------------------------------------------------------------------
# the table


@dataclass(frozen=True)
class Setup:
    """What a case runs and how its outcome is judged.

    Attributes:
        argv: the command's arguments (without ``stablecues``).
        names: text the error line must contain (the file's name); None for ``ok`` cases.
        check: called after the command with the case's folder; returns what is wrong, or None.
        block: modules made unimportable for the command (a missing optional dependency).
    """

    argv: list[str]
    names: str | None = None
    check: Callable[[Path], str | None] | None = None
    block: tuple[str, ...] = ()


@dataclass(frozen=True)
class Case:
    name: str
    area: str
    build: Callable[[Path], Setup]
    expect: str = "error"
    tags: tuple[str, ...] = field(default=())


CASES: list[Case] = []


def case(name: str, *, expect: str = "error", tags: tuple[str, ...] = ()) -> Callable:
    """Register a builder ``fn(folder) -> Setup`` as the case ``name`` ("area/what")."""

    def register(fn: Callable[[Path], Setup]) -> Callable[[Path], Setup]:
        if any(c.name == name for c in CASES):
            raise ValueError(f"duplicate case {name}")
        CASES.append(Case(name, name.split("/")[0], fn, expect, tags))
        return fn

    return register


def canary(folder: Path) -> Path:
    """The file a crafted input would create if it ran code."""
    return folder / "CANARY_code_ran"


# ---------------------------------------------------------------------------------------------
# helpers that write files


def images(folder: Path, n: int, size: tuple[int, int] = (160, 120), seed: int = 0) -> list[Path]:
    """``n`` textured grey PNGs 000.png ... in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        img = cv2.GaussianBlur(rng.integers(0, 256, (size[1], size[0]), dtype=np.uint8), (3, 3), 0)
        p = folder / f"{i:03d}.png"
        cv2.imwrite(str(p), img)
        out.append(p)
    return out


def loop_matrix(n: int) -> np.ndarray:
    gt = np.zeros((n, n), bool)
    for i in range(n // 2 + 2, n):
        gt[i, i - n // 2] = True
    return gt


def fake_run(folder: Path, n: int = 30, *, meta: dict | None = None, complete: bool = True) -> Path:
    """A run directory written with RunWriter (no detector): loops at i -> i - n/2."""
    from stablecues.runs import RunWriter

    run = folder / "run"
    base = {"dataset": str(folder / "data"), "format": "folder", "preset": "fake", "exclude": 2,
            "dataset_frames": n}
    w = RunWriter(run, {"fake": True}, {**base, **(meta or {})}, stages=["query", "total"])
    for i in range(n):
        cand = i - n // 2 if i >= n // 2 + 2 else -1
        ok = cand >= 0
        w.add(i, float(i), "loop_detected" if ok else "no_db_results", cand, 0.5 if ok else math.nan,
              0.1 if ok else math.nan, ok, {"query": 1.0, "total": 2.0})
    if complete:
        w.close()
    return run


class _Exec:
    """Pickles as a call of ``os.system`` (what a crafted ground-truth file carries)."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self) -> tuple:
        return (os.system, (self.command,))


def evil_table(path: Path, folder: Path, rows: int = 4) -> Path:
    """A VPR-Bench style ``.npy`` object table whose unpickling would create the canary."""
    table = np.empty((rows, 2), dtype=object)
    for q in range(rows):
        table[q, 0], table[q, 1] = q, [q]
    table[0, 1] = _Exec(f"touch {canary(folder)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, table, allow_pickle=True)
    return path


def vpr_table(path: Path, rows: list[tuple[int, object]]) -> Path:
    table = np.empty((len(rows), 2), dtype=object)
    for k, (q, ids) in enumerate(rows):
        table[k, 0], table[k, 1] = q, ids
    np.save(path, table, allow_pickle=True)
    return path


def npy_with_header(path: Path, header: str, payload: bytes = b"") -> Path:
    """A ``.npy`` version 1.0 file with this header text (padded as numpy pads it)."""
    text = header.encode("latin1")
    pad = 64 - (10 + len(text) + 1) % 64
    body = text + b" " * pad + b"\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(body)) + body + payload)
    return path


def png_header(path: Path, width: int, height: int) -> Path:
    """A PNG whose IHDR claims ``width`` x ``height`` (the pixel data is a few bytes)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))
    return path


def big_png(path: Path, side: int) -> Path:
    """A real, highly compressible ``side`` x ``side`` grey PNG (a few hundred kB at 25000)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    comp = zlib.compressobj(9)
    row = b"\0" + b"\0" * side
    parts = [comp.compress(row) for _ in range(side)]
    data = b"".join(parts) + comp.flush()
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", data) + chunk(b"IEND", b""))
    return path


def tum_poses(path: Path, n: int, *, step: float = 1.0, quat: str = "0 0 0 1") -> Path:
    lines = [f"{i * 0.1:.6f} {i * step:.3f} 0 0 {quat}" for i in range(n)]
    path.write_text("\n".join(lines) + "\n")
    return path


def orbslam_yaml(path: Path, **fields: object) -> Path:
    base: dict[str, object] = {"Camera.fx": 400.0, "Camera.fy": 400.0, "Camera.cx": 80.0, "Camera.cy": 60.0,
                               "Camera.k1": 0.0, "Camera.k2": 0.0, "Camera.p1": 0.0, "Camera.p2": 0.0,
                               "Camera.width": 160, "Camera.height": 120}
    base.update(fields)
    body = "\n".join(f"{k}: {v}" for k, v in base.items() if v is not None)
    path.write_text("%YAML:1.0\n" + body + "\n")
    return path


def euroc_sensor(path: Path, *, t_bs: list[float] | None = None, intrinsics: str = "[400, 400, 80, 60]",
                 distortion: str = "[0.0, 0.0, 0.0, 0.0]") -> Path:
    t = t_bs if t_bs is not None else [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        "%YAML:1.0\nsensor_type: camera\ncamera_model: pinhole\n"
        f"intrinsics: {intrinsics}\ndistortion_model: radial-tangential\n"
        f"distortion_coefficients: {distortion}\nresolution: [160, 120]\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: {t}\n"
    )
    return path


def kitti_calib(path: Path, p0: str | None = None, p1: str | None = None, p2: str | None = None) -> Path:
    ok0 = "400 0 80 0 0 400 60 0 0 0 1 0"
    ok1 = "400 0 80 -200 0 400 60 0 0 0 1 0"
    lines = [f"P0: {p0 or ok0}", f"P1: {p1 or ok1}", f"P2: {p2 or ok0}", f"P3: {ok1}"]
    path.write_text("\n".join(lines) + "\n")
    return path


def tampered_vocabulary(src: Path, dst: Path, edit: str) -> None:
    """``src`` with its payload or header changed and the payload CRC made to fit again: what
    the CRC alone cannot tell from the original."""
    raw = bytearray(src.read_bytes())
    _, version, hlen = struct.unpack_from("<8sII", raw)
    header = json.loads(raw[16:16 + hlen])
    start = 16 + hlen + (-(16 + hlen)) % 64
    if edit == "centroid":
        at = start + header["arrays"]["descriptors"]["offset"] + 4 * 64 * 7  # a centroid's first value
        raw[at:at + 4] = struct.pack("<f", 3e38)
    elif edit == "relabel":  # float words read as 256-byte binary words: the same bytes
        header["descriptor"] = {"kind": "binary", "size": 256}
        header["arrays"]["descriptors"]["dtype"] = "|u1"
        header["arrays"]["descriptors"]["shape"][1] = 256
    payload = bytes(raw[start:start + header["payload_bytes"]])
    header["payload_crc32"] = zlib.crc32(payload)
    text = json.dumps(header, sort_keys=True).encode()
    head = struct.pack("<8sII", b"SCVOCAB\0", version, len(text)) + text
    dst.write_bytes(head + b"\0" * ((-len(head)) % 64) + payload)


def verify_argv(folder: Path, calib: Path | str, *extra: str) -> list[str]:
    a, b = images(folder / "pair", 2)
    return ["verify", str(a), str(b), "--calib", str(calib), *extra]


def run_argv(dataset: Path, folder: Path, *extra: str) -> list[str]:
    return ["run", str(dataset), "--out", str(folder / "out"), "--max-frames", "2", "--pictures", "0",
            "--no-progress", *extra]


def ulog(path: Path, messages: list[tuple[bytes, bytes]], *, header: bool = True) -> Path:
    """A ULog file: the 16-byte header, then (type, payload) messages."""
    out = bytearray(b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 1_000_000) if header else b"")
    for kind, payload in messages:
        out += struct.pack("<HB", len(payload), kind[0]) + payload
    path.write_bytes(bytes(out))
    return path


def ulog_info(key: str, value: bytes) -> tuple[bytes, bytes]:
    k = key.encode()
    return b"I", bytes([len(k)]) + k + value


def ulog_param(key: str, value: bytes) -> tuple[bytes, bytes]:
    k = key.encode()
    return b"P", bytes([len(k)]) + k + value


DF_TEXT_HEAD = [
    "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns",
    "FMT, 129, 23, GPS, QBIHBcLLeeff, TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ",
    "FMT, 130, 31, IMU, Qffffff, TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ",
    "FMT, 131, 14, MODE, QMBB, TimeUS,Mode,ModeNum,Rsn",
]


def not_changed(path: Path, content: bytes) -> Callable[[Path], str | None]:
    def check(_: Path) -> str | None:
        if not path.exists():
            return f"{path} was deleted"
        return None if path.read_bytes() == content else f"{path} was changed"

    return check


def all_of(*checks: Callable[[Path], str | None]) -> Callable[[Path], str | None]:
    def check(folder: Path) -> str | None:
        for c in checks:
            problem = c(folder)
            if problem:
                return problem
        return None

    return check


# ---------------------------------------------------------------------------------------------
# ground truth: code execution


@case("groundtruth/npy-pickle-exec-via-eval-gt")
def _(d: Path) -> Setup:
    run = fake_run(d)
    gt = evil_table(d / "gt.npy", d)
    return Setup(["eval", str(run), "--gt", str(gt)], "gt.npy")


@case("groundtruth/npy-pickle-exec-via-run-meta")
def _(d: Path) -> Setup:
    gt = evil_table(d / "theirs.npy", d)
    run = fake_run(d, meta={"ground_truth": str(gt)})
    return Setup(["eval", str(run)], "theirs.npy")


@case("groundtruth/npy-pickle-exec-via-report", expect="ok")
def _(d: Path) -> Setup:
    gt = evil_table(d / "theirs.npy", d)
    run = fake_run(d)
    doc = {"protocol": "exact", "tolerance": 0, "exclude": 2, "recall_at_100p": 0.5, "auc": 0.5, "tp": 1,
           "fp": 0, "fn": 1, "positives": 2, "gt_file": str(gt), "gt_view": "all"}
    (run / "eval_exact.json").write_text(json.dumps(doc))

    def check(folder: Path) -> str | None:
        html = (folder / "r.html").read_text()
        said = "ground truth not shown" in html
        return None if said else "the report does not say the ground truth was refused"

    return Setup(["report", str(run), "--out", str(d / "r.html")], check=check)


@case("groundtruth/npy-pickle-exec-via-vprbench-dataset")
def _(d: Path) -> Setup:
    data = d / "set"
    images(data / "ref", 3)
    images(data / "query", 4, seed=1)
    evil_table(data / "ground_truth_new.npy", d)
    run = fake_run(d, 7, meta={"format": "vprbench", "dataset": str(data),
                               "ground_truth": str(data / "ground_truth_new.npy")})
    return Setup(["eval", str(run)], "ground_truth_new.npy")


@case("groundtruth/npy-pickle-other-global")
def _(d: Path) -> Setup:
    run = fake_run(d)
    payload = b"\x80\x02cbuiltins\neval\nX\x04\x00\x00\x001+1q\x00\x85q\x01Rq\x02."
    gt = npy_with_header(d / "gt.npy", "{'descr': '|O', 'fortran_order': False, 'shape': (2, 2), }", payload)
    return Setup(["eval", str(run), "--gt", str(gt)], "gt.npy")


@case("groundtruth/npy-pickle-nested-list-bomb")
def _(d: Path) -> Setup:
    # a row's ids: a list of two references to a list of two references to ... (2^40 ints
    # once expanded; the pickle shares them, so the file is small)
    run = fake_run(d)
    ids: list = [1]
    for _ in range(40):
        ids = [ids, ids]
    gt = vpr_table(d / "gt.npy", [(0, [0]), (1, ids)])
    return Setup(["eval", str(run), "--gt", str(gt)], "gt.npy")


# ---------------------------------------------------------------------------------------------
# ground truth: tracebacks and memory


@case("groundtruth/npy-header-huge-shape")
def _(d: Path) -> Setup:
    run = fake_run(d)
    header = "{'descr': '|b1', 'fortran_order': False, 'shape': (1000000, 1000000), }"
    gt = npy_with_header(d / "gt.npy", header,
                         b"\0" * 900)
    return Setup(["eval", str(run), "--gt", str(gt)], "gt.npy")


@case("groundtruth/npy-header-unbalanced")
def _(d: Path) -> Setup:
    run = fake_run(d)
    gt = npy_with_header(d / "gt.npy", "{'descr': '|b1', 'fortran_order': False, 'shape': ((30, 30), }",
                         b"\0" * 900)
    return Setup(["eval", str(run), "--gt", str(gt)], "gt.npy")


@case("groundtruth/npy-header-not-a-dict")
def _(d: Path) -> Setup:
    run = fake_run(d)
    gt = npy_with_header(d / "gt.npy", "__import__('os').system('touch CANARY')", b"\0" * 900)
    return Setup(["eval", str(run), "--gt", str(gt)], "gt.npy")


@case("groundtruth/npy-truncated-data")
def _(d: Path) -> Setup:
    run = fake_run(d)
    np.save(d / "full.npy", loop_matrix(30))
    data = (d / "full.npy").read_bytes()
    (d / "gt.npy").write_bytes(data[: len(data) - 100])
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "gt.npy")


@case("groundtruth/npy-garbage")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (d / "gt.npy").write_bytes(os.urandom(2000))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "gt.npy")


@case("groundtruth/npy-all-nan")
def _(d: Path) -> Setup:
    run = fake_run(d)
    np.save(d / "gt.npy", np.full((30, 30), np.nan))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "gt.npy")


@case("groundtruth/npy-three-dimensional")
def _(d: Path) -> Setup:
    run = fake_run(d)
    np.save(d / "gt.npy", np.zeros((30, 30, 2), bool))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "gt.npy")


@case("groundtruth/npy-not-square")
def _(d: Path) -> Setup:
    run = fake_run(d)
    np.save(d / "gt.npy", np.zeros((30, 31), bool))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "gt.npy")


@case("groundtruth/npy-text-dtype")
def _(d: Path) -> Setup:
    run = fake_run(d)
    np.save(d / "gt.npy", np.full((30, 30), "x"))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "gt.npy")


@case("groundtruth/larger-than-run")
def _(d: Path) -> Setup:
    run = fake_run(d, 30)
    np.save(d / "gt.npy", loop_matrix(160))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "gt.npy")


@case("groundtruth/smaller-than-run")
def _(d: Path) -> Setup:
    run = fake_run(d, 30)
    np.save(d / "gt.npy", loop_matrix(20))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "gt.npy")


@case("groundtruth/npz-corrupt")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (d / "gt.npz").write_bytes(b"PK\x03\x04" + os.urandom(500))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npz")], "gt.npz")


@case("groundtruth/npz-member-huge-header")
def _(d: Path) -> Setup:
    import zipfile

    run = fake_run(d)
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (200000, 200000), }"
    member = npy_with_header(d / "m.npy", header,
                             b"\0" * 64)
    with zipfile.ZipFile(d / "gt.npz", "w") as zf:
        zf.write(member, "gt.npy")
    return Setup(["eval", str(run), "--gt", str(d / "gt.npz")], "gt.npz")


@case("groundtruth/npz-object-array")
def _(d: Path) -> Setup:
    run = fake_run(d)
    table = np.empty((2, 2), dtype=object)
    table[:] = [[0, _Exec(f"touch {canary(d)}")], [1, [0]]]
    np.savez(d / "gt.npz", gt=table)
    return Setup(["eval", str(run), "--gt", str(d / "gt.npz")], "gt.npz")


@case("groundtruth/mat-garbage")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (d / "gt.mat").write_bytes(b"MATLAB 5.0 MAT-file" + b" " * 97 + b"\x00\x01IM" + os.urandom(400))
    return Setup(["eval", str(run), "--gt", str(d / "gt.mat")], "gt.mat")


@case("groundtruth/mat-truncated")
def _(d: Path) -> Setup:
    import scipy.io

    run = fake_run(d)
    scipy.io.savemat(d / "full.mat", {"gt": loop_matrix(30).astype(float)})
    data = (d / "full.mat").read_bytes()
    (d / "gt.mat").write_bytes(data[: len(data) // 2])
    return Setup(["eval", str(run), "--gt", str(d / "gt.mat")], "gt.mat")


@case("groundtruth/mat-dims-huge")
def _(d: Path) -> Setup:
    import scipy.io

    run = fake_run(d)
    scipy.io.savemat(d / "full.mat", {"gt": np.zeros((30, 30))}, do_compression=False)
    data = bytearray((d / "full.mat").read_bytes())
    at = data.find(struct.pack("<ii", 30, 30))
    data[at : at + 8] = struct.pack("<ii", 1_000_000, 1_000_000)
    (d / "gt.mat").write_bytes(bytes(data))
    return Setup(["eval", str(run), "--gt", str(d / "gt.mat")], "gt.mat")


@case("groundtruth/mat-v73-broken-hdf5")
def _(d: Path) -> Setup:
    run = fake_run(d)
    head = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    head = head.ljust(116, b" ") + b"\0" * 8 + b"\x00\x02IM"
    (d / "gt.mat").write_bytes(head + b"\x89HDF\r\n\x1a\n" + os.urandom(2000))
    return Setup(["eval", str(run), "--gt", str(d / "gt.mat")], "gt.mat")


@case("groundtruth/mat-v73-without-h5py")
def _(d: Path) -> Setup:
    run = fake_run(d)
    head = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    head = head.ljust(116, b" ") + b"\0" * 8 + b"\x00\x02IM"
    (d / "gt.mat").write_bytes(head + os.urandom(500))
    return Setup(["eval", str(run), "--gt", str(d / "gt.mat")], "gt.mat", block=("h5py",))


@case("groundtruth/png-header-65535")
def _(d: Path) -> Setup:
    run = fake_run(d)
    return Setup(["eval", str(run), "--gt", str(png_header(d / "gt.png", 65535, 65535))], "gt.png")


@case("groundtruth/png-25000-decoded", tags=("slow",))
def _(d: Path) -> Setup:
    run = fake_run(d)
    return Setup(["eval", str(run), "--gt", str(big_png(d / "gt.png", 25000))], "gt.png")


@case("groundtruth/vprbench-ref-id-huge")
def _(d: Path) -> Setup:
    run = fake_run(d, 4)
    gt = vpr_table(d / "ground_truth_new.npy", [(0, [0]), (1, [10**9]), (2, [1])])
    return Setup(["eval", str(run), "--gt", str(gt)], "ground_truth_new.npy")


@case("groundtruth/vprbench-row-not-ids")
def _(d: Path) -> Setup:
    run = fake_run(d, 4)
    gt = vpr_table(d / "ground_truth_new.npy", [(0, [0]), (1, "abc"), (2, [1])])
    return Setup(["eval", str(run), "--gt", str(gt)], "ground_truth_new.npy")


@case("groundtruth/unknown-suffix")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (d / "gt.txt").write_text("1 0\n")
    return Setup(["eval", str(run), "--gt", str(d / "gt.txt")], "gt.txt")


# ---------------------------------------------------------------------------------------------
# evaluation traps


@case("evaluation/incomplete-run")
def _(d: Path) -> Setup:
    run = fake_run(d, complete=False)
    np.save(d / "gt.npy", loop_matrix(30))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "run")


@case("evaluation/tolerance-without-n")
def _(d: Path) -> Setup:
    run = fake_run(d)
    np.save(d / "gt.npy", loop_matrix(30))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy"), "--protocol", "tolerance"], "--tolerance")


@case("evaluation/report-mixes-protocols")
def _(d: Path) -> Setup:
    np.save(d / "gt.npy", loop_matrix(30))
    a, b = fake_run(d / "a"), fake_run(d / "b")
    from stablecues.cli.main import main

    main(["eval", str(a), "--gt", str(d / "gt.npy")])
    main(["eval", str(b), "--gt", str(d / "gt.npy"), "--protocol", "tolerance", "--tolerance", "2"])
    return Setup(["report", str(a), str(b), "--out", str(d / "r.html")], "protocol")


@case("evaluation/unscored-detections-said", expect="ok")
def _(d: Path) -> Setup:
    data = d / "set"
    images(data / "ref", 15)
    images(data / "query", 15, seed=1)
    vpr_table(data / "ground_truth_new.npy", [(q, [q]) for q in range(15)])
    run = fake_run(d, 30, meta={"ground_truth": str(data / "ground_truth_new.npy")}, complete=False)
    from stablecues.runs import RunWriter

    # the reference pass (frames 0..14) accepts loops too: they are not scored, and eval says so
    w = RunWriter(run, {"fake": True}, {"ground_truth": str(data / "ground_truth_new.npy"), "exclude": 2,
                                        "dataset_frames": 30}, stages=["query", "total"], mode="overwrite")
    for i in range(30):
        w.add(i, float(i), "loop_detected" if i >= 5 else "no_db_results", i - 5 if i >= 5 else -1,
              0.5 if i >= 5 else math.nan, 0.1, i >= 5, {"query": 1.0, "total": 2.0})
    w.close()

    def check(folder: Path) -> str | None:
        doc = json.loads((folder / "e.json").read_text())
        n = doc.get("unscored_detections")
        return None if n else f"accepted loops of the reference pass left out silently ({n})"

    return Setup(["eval", str(run), "--json", str(d / "e.json")], check=check)


@case("evaluation/meta-exclude-not-a-number")
def _(d: Path) -> Setup:
    run = fake_run(d, meta={"exclude": "abc"})
    np.save(d / "gt.npy", loop_matrix(30))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "meta.json")


@case("evaluation/eval-json-malformed")
def _(d: Path) -> Setup:
    run = fake_run(d)
    doc = {"protocol": "exact", "tolerance": "x", "recall_at_100p": "high", "auc": 0.5, "tp": 1, "fp": 0,
           "fn": 1, "positives": 2}
    (run / "eval_exact.json").write_text(json.dumps(doc))
    return Setup(["results", str(run)], "eval_exact.json")


@case("evaluation/timings-malformed")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (run / "timings.json").write_text(json.dumps({"total": 5}))
    return Setup(["results", str(run)], "timings.json")


@case("evaluation/decisions-binary")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (run / "decisions.csv").write_bytes(b"\xff\xfe" + "frame,timestamp".encode("utf-16-le"))
    return Setup(["results", str(run)], "decisions.csv")


# ---------------------------------------------------------------------------------------------
# run directories


@case("runs/out-exists-with-notes")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    out = d / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "matches").mkdir()
    (out / "matches" / "sketch.png").write_bytes(b"mine")
    (out / "eval_exact.json").write_text("{}")
    keep = all_of(not_changed(out / "notes.txt", b"mine"),
                  not_changed(out / "matches" / "sketch.png", b"mine"),
                  not_changed(out / "eval_exact.json", b"{}"))
    return Setup(run_argv(d / "data", d), "out", check=keep)


@case("runs/overwrite-keeps-user-files", expect="ok")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    from stablecues.cli.main import main

    main(run_argv(d / "data", d))
    out = d / "out"
    (out / "notes.txt").write_text("mine")
    (out / "matches").mkdir(exist_ok=True)
    (out / "matches" / "notes.md").write_text("mine")
    keep = all_of(not_changed(out / "notes.txt", b"mine"), not_changed(out / "matches" / "notes.md", b"mine"))
    return Setup([*run_argv(d / "data", d), "--overwrite"], check=keep)


@case("runs/resume-symlinked-extra")
def _(d: Path) -> Setup:
    run = fake_run(d, complete=False)
    outside = d / "outside.txt"
    outside.write_text("theirs\n")
    (run / "extra.jsonl").unlink(missing_ok=True)
    (run / "extra.jsonl").symlink_to(outside)
    images(d / "data", 40)
    return Setup(["run", str(d / "data"), "--out", str(run), "--resume", "--pictures", "0", "--no-progress"],
                 "extra.jsonl", check=not_changed(outside, b"theirs\n"))


@case("runs/resume-symlinked-decisions")
def _(d: Path) -> Setup:
    run = fake_run(d, complete=False)
    outside = d / "outside.csv"
    outside.write_bytes((run / "decisions.csv").read_bytes())
    (run / "decisions.csv").unlink()
    (run / "decisions.csv").symlink_to(outside)
    content = outside.read_bytes()
    images(d / "data", 40)
    return Setup(["run", str(d / "data"), "--out", str(run), "--resume", "--pictures", "0", "--no-progress"],
                 "decisions.csv", check=not_changed(outside, content))


@case("runs/overwrite-symlinked-matches", expect="ok")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    from stablecues.cli.main import main

    main(run_argv(d / "data", d))
    theirs = d / "theirs"
    theirs.mkdir()
    (theirs / "photo.png").write_bytes(b"theirs")
    out = d / "out"
    if (out / "matches").exists():
        for p in (out / "matches").iterdir():
            p.unlink()
        (out / "matches").rmdir()
    (out / "matches").symlink_to(theirs)
    keep = not_changed(theirs / "photo.png", b"theirs")
    return Setup([*run_argv(d / "data", d), "--overwrite"], check=keep)


@case("runs/report-symlinked-picture", expect="ok")
def _(d: Path) -> Setup:
    run = fake_run(d)
    secret = d / "secret.png"
    secret.write_bytes(b"\x89PNG secret-bytes-" + b"S" * 64)
    (run / "matches").mkdir()
    (run / "matches" / "loop_00020_00005.png").symlink_to(secret)

    def check(folder: Path) -> str | None:
        import base64

        html = (folder / "r.html").read_text()
        return "the report embedded a file outside the run" if base64.b64encode(secret.read_bytes()).decode()[
            :40] in html else None

    return Setup(["report", str(run), "--out", str(d / "r.html")], check=check)


@case("runs/symlinked-meta")
def _(d: Path) -> Setup:
    run = fake_run(d)
    outside = d / "outside.json"
    outside.write_bytes((run / "meta.json").read_bytes())
    (run / "meta.json").unlink()
    (run / "meta.json").symlink_to(outside)
    return Setup(["results", str(run)], "meta.json")


@case("runs/resume-finished-run", expect="ok")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    from stablecues.cli.main import main

    main(run_argv(d / "data", d))
    before = (d / "out" / "decisions.csv").read_bytes()

    def check(folder: Path) -> str | None:
        if (folder / "out" / "decisions.csv").read_bytes() != before:
            return "resuming a finished run changed it"
        return None

    return Setup([*run_argv(d / "data", d), "--resume"], check=check)


@case("runs/db-folder-missing")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    return Setup([*run_argv(d / "data", d), "--db", str(d / "nope" / "dir" / "map.sqlite")], "map.sqlite",
                 check=lambda f: "the database's folder was created" if (f / "nope").exists() else None)


@case("runs/db-entry-log-is-a-folder")
def _(d: Path) -> Setup:
    """The database's entry log (``map.sqlite-entries``) is a folder: refused before the run
    folder is made (an earlier version wrote the run's files, then failed)."""
    images(d / "data", 3)
    (d / "map.sqlite-entries").mkdir()
    return Setup([*run_argv(d / "data", d), "--db", str(d / "map.sqlite")], "map.sqlite-entries",
                 check=lambda f: "the run folder was written" if (f / "out").exists() else None)


@case("runs/similarity-too-large")
def _(d: Path) -> Setup:
    images(d / "data", 1)
    lines = "\n".join(f"{i}.0 000.png" for i in range(40_000))
    (d / "data" / "rgb.txt").write_text(lines + "\n")
    argv = ["run", str(d / "data"), "--out", str(d / "out"), "--no-progress", "--format", "tum"]
    return Setup(argv, "similarity")


# ---------------------------------------------------------------------------------------------
# configuration


@case("config/set-float-not-a-number")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    return Setup([*run_argv(d / "data", d), "--set", "query.alpha=abc"], "query.alpha")


@case("config/set-int-as-text")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    return Setup([*run_argv(d / "data", d), "--set", 'query.exclude_recent="5"'], "query.exclude_recent")


@case("config/set-unknown-key")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    return Setup([*run_argv(d / "data", d), "--set", "query.alfa=0.2"], "alfa")


@case("config/set-without-value")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    return Setup([*run_argv(d / "data", d), "--set", "query.alpha"], "query.alpha")


@case("config/set-section-as-number")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    return Setup([*run_argv(d / "data", d), "--set", "query=5"], "query")


# ---------------------------------------------------------------------------------------------
# images


def image_dataset(d: Path, make: Callable[[Path], Path]) -> list[str]:
    """A folder dataset of three images whose second is made by ``make(path)``; run over it."""
    paths = images(d / "data", 3)
    paths[1].unlink()
    make(paths[1])
    return run_argv(d / "data", d, "--max-frames", "3")


@case("images/png-header-65535")
def _(d: Path) -> Setup:
    return Setup(image_dataset(d, lambda p: png_header(p, 65535, 65535)), "001.png")


@case("images/png-header-zero-size")
def _(d: Path) -> Setup:
    return Setup(image_dataset(d, lambda p: png_header(p, 0, 0)), "001.png")


@case("images/png-25000-decoded", tags=("slow",))
def _(d: Path) -> Setup:
    return Setup(image_dataset(d, lambda p: big_png(p, 25000)), "001.png")


@case("images/png-9000-decoded")
def _(d: Path) -> Setup:
    return Setup(image_dataset(d, lambda p: big_png(p, 9000)), "001.png")


@case("images/empty-file")
def _(d: Path) -> Setup:
    def make(p: Path) -> Path:
        p.write_bytes(b"")
        return p

    return Setup(image_dataset(d, make), "001.png")


@case("images/truncated-png")
def _(d: Path) -> Setup:
    def make(p: Path) -> Path:
        (full,) = images(d / "full", 1)
        p.write_bytes(full.read_bytes()[:300])
        return p

    return Setup(image_dataset(d, make), "001.png")


@case("images/not-an-image")
def _(d: Path) -> Setup:
    def make(p: Path) -> Path:
        p.write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(100))
        return p

    return Setup(image_dataset(d, make), "001.png")


@case("images/jpeg-header-huge")
def _(d: Path) -> Setup:
    def make(p: Path) -> Path:
        sof = b"\xff\xc0\x00\x11\x08" + struct.pack(">HH", 60000, 60000)
        sof += b"\x03\x01\x22\x00\x02\x11\x01\x03\x11\x01"
        q = p.with_suffix(".jpg")
        q.write_bytes(b"\xff\xd8" + sof + b"\xff\xd9")
        return q

    return Setup(image_dataset(d, make), "001.jpg")


@case("images/bmp-header-huge")
def _(d: Path) -> Setup:
    def make(p: Path) -> Path:
        info = struct.pack("<IiiHHIIiiII", 40, 50000, 50000, 1, 24, 0, 0, 0, 0, 0, 0)
        q = p.with_suffix(".bmp")
        q.write_bytes(b"BM" + struct.pack("<IHHI", 54, 0, 0, 54) + info + b"\0" * 64)
        return q

    return Setup(image_dataset(d, make), "001.bmp")


@case("images/tiff-header-huge")
def _(d: Path) -> Setup:
    def make(p: Path) -> Path:
        entries = [(256, 4, 1, 40000), (257, 4, 1, 40000), (258, 3, 1, 8), (259, 3, 1, 1), (262, 3, 1, 1),
                   (273, 4, 1, 8), (277, 3, 1, 1), (278, 4, 1, 40000), (279, 4, 1, 1600000000)]
        ifd = struct.pack("<H", len(entries))
        for tag, kind, count, value in entries:
            ifd += struct.pack("<HHII", tag, kind, count, value)
        q = p.with_suffix(".tif")
        q.write_bytes(b"II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0) + b"\0" * 64)
        return q

    return Setup(image_dataset(d, make), "001.tif")


@case("images/pgm-header-huge")
def _(d: Path) -> Setup:
    def make(p: Path) -> Path:
        q = p.with_suffix(".pgm")
        q.write_bytes(b"P5\n# a comment\n60000 60000\n255\n" + b"\0" * 64)
        return q

    return Setup(image_dataset(d, make), "001.pgm")


@case("images/depth-colour-image")
def _(d: Path) -> Setup:
    paths = images(d / "data", 3)
    (d / "data" / "depth").mkdir()
    for p in paths:
        cv2.imwrite(str(d / "data" / "depth" / p.name), np.zeros((120, 160, 3), np.uint8))
    (d / "data" / "calib.yaml").write_text("%YAML:1.0\nDepthMapFactor: 1000.0\n")
    return Setup(run_argv(d / "data", d), "000.png")


@case("images/labels-16-bit")
def _(d: Path) -> Setup:
    paths = images(d / "data", 3)
    (d / "data" / "labels").mkdir()
    for p in paths:
        cv2.imwrite(str(d / "data" / "labels" / p.name), np.zeros((120, 160), np.uint16))
    return Setup(run_argv(d / "data", d), "000.png")


@case("images/verify-wrong-size")
def _(d: Path) -> Setup:
    (a,) = images(d / "a", 1, size=(320, 240))
    (b,) = images(d / "b", 1, size=(320, 240))
    calib = orbslam_yaml(d / "cam.yaml")  # says 160 x 120
    return Setup(["verify", str(a), str(b), "--calib", str(calib)], "000.png")


# ---------------------------------------------------------------------------------------------
# calibration


@case("calibration/yaml-nested-20000")
def _(d: Path) -> Setup:
    (d / "cam.yaml").write_text("Camera.fx: " + "[" * 20000 + "]" * 20000 + "\n")
    return Setup(verify_argv(d, d / "cam.yaml"), "cam.yaml")


@case("calibration/yaml-alias-bomb")
def _(d: Path) -> Setup:
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for k in range(1, 12):
        lines.append(f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * 10) + "]")
    lines.append("intrinsics: *a11")
    (d / "cam.yaml").write_text("\n".join(lines) + "\n")
    return Setup(verify_argv(d, d / "cam.yaml"), "cam.yaml")


@case("calibration/yaml-not-yaml")
def _(d: Path) -> Setup:
    (d / "cam.yaml").write_text("Camera.fx: [1, 2\n  : : :\n")
    return Setup(verify_argv(d, d / "cam.yaml"), "cam.yaml")


@case("calibration/binary-file")
def _(d: Path) -> Setup:
    (d / "cam.yaml").write_bytes(os.urandom(3000))
    return Setup(verify_argv(d, d / "cam.yaml"), "cam.yaml")


@case("calibration/utf16-file")
def _(d: Path) -> Setup:
    orbslam_yaml(d / "ok.yaml")
    (d / "cam.yaml").write_bytes((d / "ok.yaml").read_text().encode("utf-16"))
    return Setup(verify_argv(d, d / "cam.yaml"), "cam.yaml")


@case("calibration/euroc-T_BS-singular")
def _(d: Path) -> Setup:
    euroc_sensor(d / "cam0" / "sensor.yaml")
    euroc_sensor(d / "cam1" / "sensor.yaml", t_bs=[0.0] * 16)
    return Setup(verify_argv(d, d / "cam0" / "sensor.yaml"), "sensor.yaml")


@case("calibration/euroc-T_BS-text")
def _(d: Path) -> Setup:
    euroc_sensor(d / "cam0" / "sensor.yaml", t_bs=["a"] * 16)  # type: ignore[list-item]
    return Setup(verify_argv(d, d / "cam0" / "sensor.yaml"), "sensor.yaml")


@case("calibration/euroc-nan-distortion")
def _(d: Path) -> Setup:
    euroc_sensor(d / "cam0" / "sensor.yaml", distortion="[.nan, 0.0, 0.0, 0.0]")
    return Setup(verify_argv(d, d / "cam0" / "sensor.yaml"), "sensor.yaml")


@case("calibration/euroc-zero-focal")
def _(d: Path) -> Setup:
    euroc_sensor(d / "cam0" / "sensor.yaml", intrinsics="[0, 0, 80, 60]")
    return Setup(verify_argv(d, d / "cam0" / "sensor.yaml"), "sensor.yaml")


@case("calibration/euroc-inf-focal")
def _(d: Path) -> Setup:
    euroc_sensor(d / "cam0" / "sensor.yaml", intrinsics="[.inf, .inf, 80, 60]")
    return Setup(verify_argv(d, d / "cam0" / "sensor.yaml"), "sensor.yaml")


@case("calibration/orbslam-T_c1_c2-singular")
def _(d: Path) -> Setup:
    p = d / "cam.yaml"
    fields = {k.replace("Camera.", "Camera1."): v for k, v in
              {"Camera.fx": 400.0, "Camera.fy": 400.0, "Camera.cx": 80.0, "Camera.cy": 60.0, "Camera.k1": 0.0,
               "Camera.k2": 0.0, "Camera.p1": 0.0, "Camera.p2": 0.0}.items()}
    fields.update({k.replace("Camera1.", "Camera2."): v for k, v in fields.items()})
    body = "\n".join(f"{k}: {v}" for k, v in fields.items())
    body += "\nCamera.width: 160\nCamera.height: 120\nStereo.T_c1_c2: !!opencv-matrix\n  rows: 4\n  cols: 4\n"
    body += "  dt: f\n  data: [0,0,0,0, 0,0,0,0, 0,0,0,0, 0,0,0,0]\n"
    p.write_text("%YAML:1.0\n" + body)
    return Setup(verify_argv(d, p), "cam.yaml")


@case("calibration/orbslam-nan-distortion")
def _(d: Path) -> Setup:
    return Setup(verify_argv(d, orbslam_yaml(d / "cam.yaml", **{"Camera.k1": ".nan"})), "cam.yaml")


@case("calibration/orbslam-zero-focal")
def _(d: Path) -> Setup:
    return Setup(verify_argv(d, orbslam_yaml(d / "cam.yaml", **{"Camera.fx": 0.0})), "cam.yaml")


@case("calibration/orbslam-inf-bf")
def _(d: Path) -> Setup:
    return Setup(verify_argv(d, orbslam_yaml(d / "cam.yaml", **{"Camera.bf": ".inf"})), "cam.yaml")


@case("calibration/orbslam-huge-size")
def _(d: Path) -> Setup:
    return Setup(verify_argv(d, orbslam_yaml(d / "cam.yaml", **{"Camera.width": 1e30})), "cam.yaml")


@case("calibration/kitti-P1-zero-focal")
def _(d: Path) -> Setup:
    p = kitti_calib(d / "calib.txt", p1="0 0 80 -200 0 0 60 0 0 0 1 0")
    return Setup(verify_argv(d, p), "calib.txt")


@case("calibration/kitti-P2-singular")
def _(d: Path) -> Setup:
    data = d / "seq"
    images(data / "image_2", 3)
    kitti_calib(data / "calib.txt", p2="0 0 0 5 0 0 0 0 0 0 0 0")
    (data / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    return Setup(run_argv(data, d, "--format", "kitti"), "calib.txt")


@case("calibration/kitti-P0-text")
def _(d: Path) -> Setup:
    p = kitti_calib(d / "calib.txt", p0="400 0 80 0 0 400 abc 0 0 0 1 0")
    return Setup(verify_argv(d, p), "calib.txt")


@case("calibration/too-large")
def _(d: Path) -> Setup:
    p = d / "cam.yaml"
    p.write_text("%YAML:1.0\n" + "# padding\n" * 200_000 + "Camera.fx: 400\n")
    return Setup(verify_argv(d, p), "cam.yaml")


# ---------------------------------------------------------------------------------------------
# trajectories (mav gt reads TUM and KITTI poses)


@case("trajectory/binary")
def _(d: Path) -> Setup:
    (d / "poses.txt").write_bytes(os.urandom(4000))
    return Setup(["mav", "gt", str(d / "poses.txt"), "--out", str(d / "gt.png")], "poses.txt")


@case("trajectory/utf16")
def _(d: Path) -> Setup:
    tum_poses(d / "ok.txt", 10)
    (d / "poses.txt").write_bytes((d / "ok.txt").read_text().encode("utf-16"))
    return Setup(["mav", "gt", str(d / "poses.txt"), "--out", str(d / "gt.png")], "poses.txt")


@case("trajectory/zero-quaternion")
def _(d: Path) -> Setup:
    tum_poses(d / "poses.txt", 10, quat="0 0 0 0")
    return Setup(["mav", "gt", str(d / "poses.txt"), "--out", str(d / "gt.png"), "--max-angle", "30"],
                 "poses.txt")


@case("trajectory/wrong-columns")
def _(d: Path) -> Setup:
    (d / "poses.txt").write_text("0 1 2 3 4\n1 1 2 3 4\n")
    return Setup(["mav", "gt", str(d / "poses.txt"), "--out", str(d / "gt.png")], "poses.txt")


@case("trajectory/text-value")
def _(d: Path) -> Setup:
    tum_poses(d / "poses.txt", 5)
    with (d / "poses.txt").open("a") as fh:
        fh.write("9.0 1 2 abc 0 0 0 1\n")
    return Setup(["mav", "gt", str(d / "poses.txt"), "--out", str(d / "gt.png")], "poses.txt")


@case("trajectory/kitti-poses-gt", expect="ok")
def _(d: Path) -> Setup:
    lines = [f"1 0 0 {float(i % 10)} 0 1 0 0 0 0 1 0" for i in range(40)]
    (d / "poses.txt").write_text("\n".join(lines) + "\n")

    def check(folder: Path) -> str | None:
        gt = np.load(folder / "gt.npy")
        return None if gt.shape == (40, 40) and gt.any() else f"loop truth from KITTI poses is {gt.shape}"

    return Setup(["mav", "gt", str(d / "poses.txt"), "--out", str(d / "gt.png"), "--max-distance", "0.5",
                  "--min-gap-s", "0", "--min-gap-frames", "5"], check=check)


@case("trajectory/gt-10000-poses", expect="ok", tags=("slow",))
def _(d: Path) -> Setup:
    t = np.arange(10_000) * 0.1
    x = 5 * np.cos(t / 10)
    y = 5 * np.sin(t / 10)
    lines = [f"{t[i]:.3f} {x[i]:.3f} {y[i]:.3f} 0 0 0 0 1" for i in range(t.size)]
    (d / "poses.txt").write_text("\n".join(lines) + "\n")

    def check(folder: Path) -> str | None:
        gt = np.load(folder / "gt.npy", mmap_mode="r")
        return None if gt.shape == (10_000, 10_000) else f"shape {gt.shape}"

    return Setup(["mav", "gt", str(d / "poses.txt"), "--out", str(d / "gt.png")], check=check)


@case("trajectory/folder-times-text")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    (d / "data" / "times.txt").write_text("0.0\nabc\n0.2\n")
    return Setup(run_argv(d / "data", d), "times.txt")


@case("trajectory/folder-poses-binary")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    (d / "data" / "poses.txt").write_bytes(b"\x00\x01" * 300)
    return Setup(run_argv(d / "data", d), "poses.txt")


@case("trajectory/euroc-gt-zero-quaternion")
def _(d: Path) -> Setup:
    seq = _euroc(d)
    gt = seq / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    gt.parent.mkdir(parents=True)
    gt.write_text("#t,px,py,pz,qw,qx,qy,qz\n" + "".join(f"{1000 + i},0,0,0,0,0,0,0\n" for i in range(3)))
    return Setup(run_argv(seq, d, "--format", "euroc"), "data.csv")


# ---------------------------------------------------------------------------------------------
# dataset manifests


def _euroc(d: Path, names: list[str] | None = None) -> Path:
    seq = d / "seq"
    paths = images(seq / "mav0" / "cam0" / "data", 3)
    listed = names if names is not None else [p.name for p in paths]
    (seq / "mav0" / "cam0" / "data.csv").write_text(
        "#timestamp [ns],filename\n" + "".join(f"{1000 + i},{n}\n" for i, n in enumerate(listed))
    )
    return seq


@case("manifest/tum-rgb-escapes-dataset")
def _(d: Path) -> Setup:
    images(d / "outside", 1)
    data = d / "data"
    images(data / "rgb", 2)
    (data / "rgb.txt").write_text("0.0 rgb/000.png\n0.1 ../outside/000.png\n")
    return Setup(run_argv(data, d, "--format", "tum"), "rgb.txt")


@case("manifest/tum-rgb-absolute-path")
def _(d: Path) -> Setup:
    (outside,) = images(d / "outside", 1)
    data = d / "data"
    images(data / "rgb", 2)
    (data / "rgb.txt").write_text(f"0.0 rgb/000.png\n0.1 {outside}\n")
    return Setup(run_argv(data, d, "--format", "tum"), "rgb.txt")


@case("manifest/tum-depth-escapes-dataset")
def _(d: Path) -> Setup:
    data = d / "data"
    images(data / "rgb", 2)
    (data / "rgb.txt").write_text("0.0 rgb/000.png\n0.1 rgb/001.png\n")
    (data / "depth.txt").write_text("0.0 ../../../../etc/passwd\n")
    return Setup(run_argv(data, d, "--format", "tum"), "depth.txt")


@case("manifest/tum-rgb-binary")
def _(d: Path) -> Setup:
    data = d / "data"
    images(data / "rgb", 2)
    (data / "rgb.txt").write_bytes(os.urandom(500))
    return Setup(run_argv(data, d, "--format", "tum"), "rgb.txt")


@case("manifest/tum-rgb-text-time")
def _(d: Path) -> Setup:
    data = d / "data"
    images(data / "rgb", 2)
    (data / "rgb.txt").write_text("0.0 rgb/000.png\nabc rgb/001.png\n")
    return Setup(run_argv(data, d, "--format", "tum"), "rgb.txt")


@case("manifest/euroc-data-csv-escapes")
def _(d: Path) -> Setup:
    images(d / "outside", 1)
    seq = _euroc(d, ["000.png", "../../../../outside/000.png", "002.png"])
    return Setup(run_argv(seq, d, "--format", "euroc"), "data.csv")


@case("manifest/euroc-data-csv-absolute")
def _(d: Path) -> Setup:
    (outside,) = images(d / "outside", 1)
    seq = _euroc(d, ["000.png", str(outside), "002.png"])
    return Setup(run_argv(seq, d, "--format", "euroc"), "data.csv")


@case("manifest/euroc-data-csv-binary")
def _(d: Path) -> Setup:
    seq = _euroc(d)
    (seq / "mav0" / "cam0" / "data.csv").write_bytes(os.urandom(400))
    return Setup(run_argv(seq, d, "--format", "euroc"), "data.csv")


@case("manifest/euroc-sensor-yaml-nested")
def _(d: Path) -> Setup:
    seq = _euroc(d)
    (seq / "mav0" / "cam0" / "sensor.yaml").write_text("T_BS: " + "[" * 20000 + "]" * 20000 + "\n")
    return Setup(run_argv(seq, d, "--format", "euroc"), "sensor.yaml")


@case("manifest/euroc-sensor-T_BS-text")
def _(d: Path) -> Setup:
    seq = _euroc(d)
    euroc_sensor(seq / "mav0" / "cam0" / "sensor.yaml", t_bs=["x"] * 16)  # type: ignore[list-item]
    return Setup(run_argv(seq, d, "--format", "euroc"), "sensor.yaml")


@case("manifest/kitti-times-count")
def _(d: Path) -> Setup:
    data = d / "seq"
    images(data / "image_0", 3)
    (data / "times.txt").write_text("0.0\n0.1\n")
    return Setup(run_argv(data, d, "--format", "kitti"), "times.txt")


@case("manifest/kitti-poses-text")
def _(d: Path) -> Setup:
    data = d / "seq"
    images(data / "image_0", 3)
    (data / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2 + "a b c d e f g h i j k l\n")
    return Setup(run_argv(data, d, "--format", "kitti"), "poses.txt")


@case("manifest/kitti-calib-binary")
def _(d: Path) -> Setup:
    data = d / "seq"
    images(data / "image_0", 3)
    (data / "calib.txt").write_bytes(os.urandom(300))
    return Setup(run_argv(data, d, "--format", "kitti"), "calib.txt")


@case("manifest/vprbench-table-pickle-exec")
def _(d: Path) -> Setup:
    data = d / "set"
    images(data / "ref", 2)
    images(data / "query", 2, seed=1)
    evil_table(data / "ground_truth_new.npy", d, rows=2)
    from stablecues.cli.main import main

    main(["run", str(data), "--out", str(d / "out"), "--pictures", "0", "--no-progress"])
    return Setup(["eval", str(d / "out")], "ground_truth_new.npy")


@case("manifest/folder-depth-factor-text")
def _(d: Path) -> Setup:
    images(d / "data", 3)
    (d / "data" / "calib.yaml").write_text("%YAML:1.0\nCamera.fx: 400\nDepthMapFactor: abc\n")
    return Setup(run_argv(d / "data", d), "calib.yaml")


# ---------------------------------------------------------------------------------------------
# flight logs


@case("mav/dataflash-text-field-in-number")
def _(d: Path) -> Setup:
    lines = [*DF_TEXT_HEAD, "IMU, 1000000, abc, 0, 0, 0, 0, -9.8", "IMU, 2000000, 0, 0, 0, 0, 0, -9.8"]
    (d / "f.log").write_text("\n".join(lines) + "\n")
    return Setup(["mav", "info", str(d / "f.log")], "f.log")


@case("mav/dataflash-text-gps-text-field")
def _(d: Path) -> Setup:
    lines = [*DF_TEXT_HEAD, "GPS, 1000000, 3, 100000, 2000, 10, 1.0, north, -4.1, 50.0, 0, 0, 0",
             "IMU, 2000000, 0, 0, 0, 0, 0, -9.8"]
    (d / "f.log").write_text("\n".join(lines) + "\n")
    return Setup(["mav", "info", str(d / "f.log")], "f.log")


@case("mav/dataflash-binary-garbage")
def _(d: Path) -> Setup:
    (d / "f.bin").write_bytes(b"\xa3\x95\x80" + os.urandom(3000))
    return Setup(["mav", "info", str(d / "f.bin")], "f.bin")


@case("mav/gnss-csv-field-over-limit")
def _(d: Path) -> Setup:
    (d / "track.csv").write_text("timestamp,lat,lon,alt\n1.0,52.0,-4.0," + "9" * 200_000 + "\n2.0,52,-4,1\n")
    return Setup(["mav", "info", str(d / "track.csv")], "track.csv")


@case("mav/gnss-csv-all-nan-times")
def _(d: Path) -> Setup:
    rows = "".join(f"nan,52.{i},-4.0,10\n" for i in range(5))
    (d / "track.csv").write_text("timestamp,lat,lon,alt\n" + rows)
    return Setup(["mav", "info", str(d / "track.csv")], "track.csv")


@case("mav/gnss-csv-text-latitude")
def _(d: Path) -> Setup:
    (d / "track.csv").write_text("timestamp,lat,lon,alt\n1.0,north,-4.0,10\n2.0,52,-4,10\n")
    return Setup(["mav", "info", str(d / "track.csv")], "track.csv")


@case("mav/ulog-header-only")
def _(d: Path) -> Setup:
    return Setup(["mav", "info", str(ulog(d / "f.ulg", []))], "f.ulg")


@case("mav/ulog-parameter-raw-bytes")
def _(d: Path) -> Setup:
    msgs = [ulog_info("char[4] sys_name", b"PX4\0"), ulog_param("char[4] BAD_PARAM", b"\xff\xfe\x00\x01"),
            ulog_param("float GOOD", struct.pack("<f", 1.5))]
    return Setup(["mav", "info", str(ulog(d / "f.ulg", msgs))], "f.ulg")


@case("mav/ulog-garbage")
def _(d: Path) -> Setup:
    (d / "f.ulg").write_bytes(b"ULog\x01\x12\x35\x01" + os.urandom(3000))
    return Setup(["mav", "info", str(d / "f.ulg")], "f.ulg")


@case("mav/ulog-without-pyulog")
def _(d: Path) -> Setup:
    return Setup(["mav", "info", str(ulog(d / "f.ulg", []))], "pyulog", block=("pyulog",))


@case("mav/not-a-log")
def _(d: Path) -> Setup:
    (d / "f.bin").write_bytes(b"hello world\n")
    return Setup(["mav", "info", str(d / "f.bin")], "f.bin")


@case("mav/frames-times-csv-binary")
def _(d: Path) -> Setup:
    rows = "".join(f"{100 + i},{52 + i * 1e-5:.7f},-4.0,10\n" for i in range(20))
    (d / "track.csv").write_text("timestamp,lat,lon,alt\n" + rows)
    (d / "times.csv").write_bytes(b"time,name\n" + os.urandom(300))
    return Setup(["mav", "poses", str(d / "track.csv"), "--times", str(d / "times.csv"), "--out",
                  str(d / "p.txt")], "times.csv")


@case("mav/dataflash-parameter-text")
def _(d: Path) -> Setup:
    lines = [*DF_TEXT_HEAD, "FMT, 133, 31, PARM, QNf, TimeUS,Name,Value", "PARM, 1000000, GAIN, high",
             "IMU, 2000000, 0, 0, 0, 0, 0, -9.8"]
    (d / "f.log").write_text("\n".join(lines) + "\n")
    return Setup(["mav", "info", str(d / "f.log")], "f.log")


@case("mav/dataflash-without-pymavlink")
def _(d: Path) -> Setup:
    lines = [*DF_TEXT_HEAD, "IMU, 2000000, 0, 0, 0, 0, 0, -9.8"]
    (d / "f.log").write_text("\n".join(lines) + "\n")
    return Setup(["mav", "info", str(d / "f.log")], "pymavlink", block=("pymavlink",))


@case("mav/gnss-without-pymap3d")
def _(d: Path) -> Setup:
    rows = "".join(f"{100 + i},{52 + i * 1e-5:.7f},-4.0,10\n" for i in range(20))
    (d / "track.csv").write_text("timestamp,lat,lon,alt\n" + rows)
    return Setup(["mav", "poses", str(d / "track.csv"), "--out", str(d / "p.txt")], "pymap3d",
                 block=("pymap3d",))


@case("mav/gnss-csv-binary")
def _(d: Path) -> Setup:
    (d / "track.csv").write_bytes(b"timestamp,lat,lon\n" + os.urandom(400).replace(b"\0", b"\1") + b"\0")
    return Setup(["mav", "info", str(d / "track.csv")], "track.csv")


@case("mav/gnss-csv-rows-ragged")
def _(d: Path) -> Setup:
    (d / "track.csv").write_text("timestamp,lat,lon,alt\n1.0,52.0,-4.0,10\n2.0,52.1\n")
    return Setup(["mav", "info", str(d / "track.csv")], "track.csv")


# ---------------------------------------------------------------------------------------------
# more run directories and evaluation


@case("runs/decisions-frames-not-increasing")
def _(d: Path) -> Setup:
    run = fake_run(d)
    lines = (run / "decisions.csv").read_text().splitlines()
    (run / "decisions.csv").write_text("\n".join([lines[0], lines[3], lines[2], *lines[4:]]) + "\n")
    return Setup(["results", str(run)], "decisions.csv")


@case("runs/extra-jsonl-garbage")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (run / "extra.jsonl").write_text('{"frame": 0}\nnot json\n{"frame": 2}\n')
    images(d / "data", 30)
    return Setup(["run", str(d / "data"), "--out", str(run), "--resume", "--pictures", "0", "--no-progress"],
                 "extra.jsonl")


@case("runs/similarity-header-huge")
def _(d: Path) -> Setup:
    run = fake_run(d)
    npy_with_header(run / "similarity.npy",
                    "{'descr': '<f4', 'fortran_order': False, 'shape': (100000, 100000), }", b"\0" * 64)
    np.save(d / "gt.npy", loop_matrix(30))
    from stablecues.cli.main import main

    main(["eval", str(run), "--gt", str(d / "gt.npy")])
    return Setup(["report", str(run), "--out", str(d / "r.html")], "similarity.npy")


@case("runs/similarity-sparse-larger-than-run")
def _(d: Path) -> Setup:
    """Issue 34: a sparse 20000^2 similarity.npy under a 30-frame run cost report 1.7 GB."""
    run = fake_run(d)
    with (run / "similarity.npy").open("wb") as f:
        header = {"descr": "<f4", "fortran_order": False, "shape": (20000, 20000)}
        np.lib.format.write_array_header_1_0(f, header)
        f.truncate(f.tell() + 20000 * 20000 * 4)
    return Setup(["report", str(run), "--out", str(d / "r.html")], "similarity.npy")


@case("runs/decisions-more-rows-than-frames")
def _(d: Path) -> Setup:
    """More rows in decisions.csv than meta.json gives the run: refused before the rows are parsed."""
    run = fake_run(d)
    meta = json.loads((run / "meta.json").read_text())
    meta.update(frames=10, dataset_frames=10)
    (run / "meta.json").write_text(json.dumps(meta))
    return Setup(["results", str(run)], "decisions.csv")


@case("runs/extra-line-of-megabytes")
def _(d: Path) -> Setup:
    """Issue 34: a 210 MB extra.jsonl line cost 1.5 GB; a frame's record is a few kB."""
    run = fake_run(d)
    (run / "extra.jsonl").write_text(json.dumps({"frame": 20, "results": [[1, 0.5]] * 300_000}) + "\n")
    np.save(d / "gt.npy", loop_matrix(30))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "extra.jsonl")


@case("map/segment-body-flipped")
def _(d: Path) -> Setup:
    """Issue 34: a damaged index file body answered queries; `map check` names it (exit 1)."""
    from dbkit import fill
    from stablecues.database import Database, DatabaseConfig
    from stablecues.database.files import index_dir
    from stablecues.vocabulary import default_vocabulary

    voc = default_vocabulary("orb")
    rng = np.random.default_rng(0)
    with Database(voc, d / "map.sqlite", DatabaseConfig(tail_postings=2000, store_descriptors=False)) as db:
        fill(db, voc, [rng.integers(0, 256, (100, 32), dtype=np.uint8) for _ in range(60)])
        db.flush()
    seg = sorted(index_dir(d / "map.sqlite").glob("seg-*.sci"))[0]
    raw = bytearray(seg.read_bytes())
    raw[128 + 40] ^= 0x20
    seg.write_bytes(bytes(raw))
    return Setup(["map", "check", str(d / "map.sqlite")], seg.name)


@case("runs/resume-map-ahead")
def _(d: Path) -> Setup:
    images(d / "data", 4)
    from stablecues.cli.main import main

    main(run_argv(d / "data", d, "--max-frames", "4"))
    out = d / "out"
    lines = (out / "decisions.csv").read_text().splitlines()
    (out / "decisions.csv").write_text("\n".join(lines[:2]) + "\n")  # the map holds 4, the rows 1
    meta = json.loads((out / "meta.json").read_text())
    (out / "meta.json").write_text(json.dumps({**meta, "complete": False}))
    return Setup([*run_argv(d / "data", d, "--max-frames", "4"), "--resume"], "decisions.csv")


KILL_CHILD = r"""
import os, signal, sys
from stablecues.cli.main import main
from stablecues.detection import run as run_mod
orig = run_mod._DeferredCommit.commit
def commit_then_die(self):
    out = orig(self)
    if len(self._db) == int(sys.argv[1]):
        os.kill(os.getpid(), signal.SIGKILL)
    return out
run_mod._DeferredCommit.commit = commit_then_die
sys.exit(main(sys.argv[2:]))
"""


@case("runs/resume-after-kill-at-commit", expect="ok")
def _(d: Path) -> Setup:
    """Killed between the map's commit and the row of frame 5: resume must finish the run, its
    similarity rows all there (none silently zero) and meta.json complete."""
    import subprocess
    import sys

    images(d / "data", 8)
    argv = run_argv(d / "data", d, "--max-frames", "8", "--preset", "bow")
    subprocess.run([sys.executable, "-c", KILL_CHILD, "6", *argv], capture_output=True, check=False)

    def check(folder: Path) -> str | None:
        from stablecues.runs import load_run

        run = load_run(folder / "out")
        sim = run.similarity
        if not run.complete or len(run) != 8 or sim is None:
            return f"resumed run: complete {run.complete}, {len(run)} frames"
        zero_rows = [i for i in range(1, 8) if not np.any(sim[i, :i])]
        return f"similarity rows {zero_rows} are zero after the resume" if zero_rows else None

    return Setup([*argv, "--resume"], check=check)


@case("evaluation/gt-view-in-meta-unknown")
def _(d: Path) -> Setup:
    run = fake_run(d, meta={"gt_view": "middle"})
    np.save(d / "gt.npy", loop_matrix(30))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "gt_view")


@case("evaluation/negative-exclude")
def _(d: Path) -> Setup:
    run = fake_run(d)
    np.save(d / "gt.npy", loop_matrix(30))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy"), "--exclude", "-5"], "exclu")


@case("evaluation/results-not-a-run")
def _(d: Path) -> Setup:
    (d / "somewhere").mkdir()
    return Setup(["results", str(d / "somewhere")], "somewhere")


@case("evaluation/gt-variable-missing")
def _(d: Path) -> Setup:
    import scipy.io

    run = fake_run(d)
    scipy.io.savemat(d / "gt.mat", {"truth": loop_matrix(30).astype(float)})
    return Setup(["eval", str(run), "--gt", str(d / "gt.mat"), "--gt-variable", "GT"], "gt.mat")


# ---------------------------------------------------------------------------------------------
# issue 34: output paths, settings, run folders, vocabularies


@case("outputs/vocab-convert-onto-a-symlink")
def _(d: Path) -> Setup:
    target = d / "precious.bin"
    target.write_bytes(b"keep")
    (d / "out.scv").symlink_to(target)
    return Setup(["vocab", "convert", "default:xfeat", str(d / "out.scv")], "out.scv",
                 check=all_of(not_changed(target, b"keep"),
                              lambda f: None if (f / "out.scv").is_symlink() else "the link was replaced"))


@case("outputs/eval-json-onto-a-link-to-a-descriptor")
def _(d: Path) -> Setup:
    run = fake_run(d)
    np.save(d / "gt.npy", loop_matrix(30))
    (d / "e.json").symlink_to("/proc/self/fd/1")
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy"), "--json", str(d / "e.json")], "e.json",
                 check=lambda f: None if (f / "e.json").is_symlink() else "the link was replaced")


@case("outputs/results-json-into-a-folder")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (d / "table").mkdir()
    return Setup(["results", str(run), "--json", str(d / "table")], "table")


@case("outputs/info-json-onto-a-device")
def _(d: Path) -> Setup:
    images(d / "frames", 3)
    return Setup(["info", str(d / "frames"), "--json", "/dev/null"], "/dev/null")


@case("outputs/run-rerun-through-a-symlink")
def _(d: Path) -> Setup:
    images(d / "frames", 3)
    target = d / "precious.rrd"
    target.write_bytes(b"keep")
    (d / "rec.rrd").symlink_to(target)
    return Setup(["run", str(d / "frames"), "--out", str(d / "run"), "--preset", "bow", "--rerun",
                  str(d / "rec.rrd")], "rec.rrd", check=not_changed(target, b"keep"))


@case("config/set-a-non-finite-number")
def _(d: Path) -> Setup:
    images(d / "frames", 3)
    return Setup(["run", str(d / "frames"), "--out", str(d / "run"), "--set", "query.alpha=NaN"], "NaN")


@case("config/sweep-a-million-cells")
def _(d: Path) -> Setup:
    images(d / "frames", 3)
    vary = [x for k in range(10) for x in ("--vary", f"query.alpha=[0.1, 0.2, 0.3, {k}]")]
    return Setup(["sweep", str(d / "frames"), "--out", str(d / "s"), "--serial", *vary], "--vary")


@case("config/sweep-timeout-nan")
def _(d: Path) -> Setup:
    images(d / "frames", 3)
    return Setup(["sweep", str(d / "frames"), "--out", str(d / "s"), "--timeout", "nan"], "--timeout")


@case("runs/extra-line-is-a-list")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (run / "extra.jsonl").write_text('[1, 2]\n{"frame": 3}\n')
    np.save(d / "gt.npy", loop_matrix(30))
    return Setup(["eval", str(run), "--gt", str(d / "gt.npy")], "extra.jsonl")


@case("runs/extra-results-not-pairs")
def _(d: Path) -> Setup:
    run = fake_run(d)
    (run / "extra.jsonl").write_text('{"frame": 20, "results": [1, 2, 3]}\n{"frame": 21}\n')
    np.save(d / "gt.npy", loop_matrix(30))
    return Setup(["report", str(run), "--out", str(d / "r.html")], "extra.jsonl")


@case("runs/decisions-frame-2-to-the-70")
def _(d: Path) -> Setup:
    run = fake_run(d)
    lines = (run / "decisions.csv").read_text().splitlines()
    lines[1] = str(2**70) + lines[1][lines[1].index(","):]
    (run / "decisions.csv").write_text("\n".join(lines) + "\n")
    return Setup(["results", str(run)], "decisions.csv")


@case("vocabulary/float-centroid-tampered-crc-fixed")
def _(d: Path) -> Setup:
    from stablecues.vocabulary import default_vocabulary_path

    tampered_vocabulary(default_vocabulary_path("xfeat"), d / "v.scv", "centroid")
    return Setup(["vocab", "info", str(d / "v.scv")], "v.scv")


@case("outputs/report-onto-a-symlink")
def _(d: Path) -> Setup:
    run = fake_run(d)
    target = d / "precious.html"
    target.write_bytes(b"keep")
    (d / "r.html").symlink_to(target)
    return Setup(["report", str(run), "--out", str(d / "r.html")], "r.html",
                 check=not_changed(target, b"keep"))


@case("groundtruth/sparse-npy-60000-square")
def _(d: Path) -> Setup:
    run = fake_run(d)
    gt = npy_with_header(d / "gt.npy", "{'descr': '|b1', 'fortran_order': False, 'shape': (60000, 60000), }")
    with gt.open("r+b") as fh:  # a sparse file of the size the header claims: nothing on disk
        fh.truncate(fh.seek(0, 2) + 60000 * 60000)
    return Setup(["eval", str(run), "--gt", str(gt)], "gt.npy")

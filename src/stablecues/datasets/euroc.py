"""EuRoC MAV sequences in the ASL folder layout.

Layout (``DIR`` may be the sequence folder or its ``mav0``)::

    DIR/mav0/cam0/data.csv     "#timestamp [ns],filename" then one "ns,name.png" line per image
    DIR/mav0/cam0/data/        left images (752x480 grey)
    DIR/mav0/cam0/sensor.yaml  intrinsics, distortion and T_BS (camera-to-body)
    DIR/mav0/cam1/...          right camera, same form (NOT rectified)
    DIR/mav0/state_groundtruth_estimate0/data.csv
                               ns, p_x, p_y, p_z, q_w, q_x, q_y, q_z, ... (body-to-world)

Ground truth may instead be a TUM-format body trajectory (``t x y z qx qy qz qw``): passed as
``groundtruth=``, or found as the only ``*groundtruth*.txt`` in ``DIR``, or in ``DIR``'s parent
named after the sequence (``V1_01_groundtruth_tum.txt`` for ``V1_01_easy``). Frame poses are
the camera's: body pose at the nearest ground-truth time composed with cam0's ``T_BS``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..fileio import load_yaml, read_text
from ..limits import MAX_CALIBRATION_BYTES
from ..trajectory import nearest, ns_to_seconds, read_euroc, read_tum
from .base import FrameRecord, SequenceDataset, inside


def read_euroc_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Read a camera ``data.csv``: ((N,) int64 nanoseconds, N file names).

    Raises:
        DatasetError: missing file, or a line that is not ``ns,filename``.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: EuRoC image list not found")
    stamps: list[int] = []
    names: list[str] = []
    for lineno, line in enumerate(read_text(path, "EuRoC image list").splitlines(), 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = [p.strip() for p in text.split(",")]
        if len(parts) != 2 or not parts[0].isdigit():
            raise DatasetError(
                f"{path}: expected 'timestamp_ns,filename' per line, line {lineno} is {text[:60]!r}"
            )
        stamps.append(int(parts[0]))
        inside(path.parent, parts[1], path, lineno)  # the names are files of data/ beside it
        names.append(parts[1])
    if not names:
        raise DatasetError(f"{path}: expected at least one image line, found none")
    return np.asarray(stamps, dtype=np.int64), names


def read_sensor_yaml(path: Path) -> dict[str, object]:
    """Read an EuRoC / Kalibr ``sensor.yaml`` (its ``%YAML:1.0`` line is skipped).

    Raises:
        DatasetError: missing or unparsable file.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: EuRoC sensor.yaml not found")
    raw = read_text(path, "EuRoC sensor.yaml", limit=MAX_CALIBRATION_BYTES)
    text = "\n".join(ln for ln in raw.splitlines() if not ln.startswith("%"))
    data = load_yaml(text, path)
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a mapping of sensor fields, found {type(data).__name__}")
    return data


def sensor_extrinsics(path: Path) -> np.ndarray:
    """(4, 4) float64 ``T_BS`` (sensor-to-body) of an EuRoC ``sensor.yaml``.

    Raises:
        DatasetError: T_BS missing or not 16 numbers.
    """
    data = read_sensor_yaml(path)
    tbs = data.get("T_BS")
    values = tbs.get("data") if isinstance(tbs, dict) else None
    if not isinstance(values, list) or len(values) != 16:
        raise DatasetError(f"{path}: expected T_BS with 16 numbers in 'data', found {values!r:.60}")
    try:
        t_bs = np.asarray(values, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{path}: expected T_BS with 16 numbers in 'data', found {values!r:.60}") from None
    if not np.isfinite(t_bs).all():
        raise DatasetError(f"{path}: expected 16 finite numbers in T_BS, found {values!r:.60}")
    return t_bs


def _find_tum_groundtruth(seq: Path) -> Path | None:
    own = sorted(p for p in seq.glob("*groundtruth*.txt") if p.is_file())
    if len(own) == 1:
        return own[0]
    m = re.match(r"^([A-Za-z0-9]+_[0-9]+)", seq.name)
    if m:
        near = sorted(p for p in seq.parent.glob(f"{m.group(1)}*groundtruth*") if p.is_file())
        if len(near) == 1:
            return near[0]
    return None


def _find_groundtruth(mav0: Path, seq: Path) -> Path | None:
    """The sequence's body ground truth: ``state_groundtruth_estimate0`` or ``vicon0``, else TUM."""
    for cand in (mav0 / "state_groundtruth_estimate0" / "data.csv", mav0 / "vicon0" / "data.csv"):
        if cand.is_file():
            return cand
    return _find_tum_groundtruth(seq)


def _cam0_records(cam0: Path) -> tuple[np.ndarray, list[FrameRecord]]:
    """(N,) float64 seconds and one record per image listed in ``cam0/data.csv``.

    Raises:
        DatasetError: a malformed list, or a listed image that is not in ``cam0/data``.
    """
    stamps, names = read_euroc_list(cam0 / "data.csv")
    times = ns_to_seconds(stamps)
    records = []
    for t, name in zip(times, names, strict=True):
        img = cam0 / "data" / name
        if not img.is_file():
            raise DatasetError(f"{cam0 / 'data.csv'}: lists {name}, which is not in {cam0 / 'data'}")
        records.append(FrameRecord(image=img, timestamp=float(t), name=f"cam0/{name}"))
    return times, records


def _attach_right(records: list[FrameRecord], times: np.ndarray, cam1: Path) -> None:
    """Attach cam1's image taken within 2 ms of each frame (at ``times``) as its right image.

    Raises:
        DatasetError: a malformed list, or a frame without a right image within 2 ms.
    """
    stamps1, names1 = read_euroc_list(cam1 / "data.csv")
    idx = nearest(times, ns_to_seconds(stamps1), 0.002)
    for rec, k in zip(records, idx, strict=True):
        if k < 0:
            raise DatasetError(f"{cam1 / 'data.csv'}: no right image within 2 ms of {rec.name}")
        rec.right = cam1 / "data" / names1[k]


def _attach_groundtruth(
    records: list[FrameRecord], times: np.ndarray, gt_file: Path, t_bs: np.ndarray, max_difference: float
) -> None:
    """Give each frame (at ``times``) the camera pose: nearest body pose composed with ``t_bs``.

    Raises:
        DatasetError: a malformed ground-truth file (EuRoC ``.csv`` or TUM otherwise).
    """
    gtimes, gposes = read_euroc(gt_file) if gt_file.suffix == ".csv" else read_tum(gt_file)
    idx = nearest(times, gtimes, max_difference)
    for rec, k in zip(records, idx, strict=True):
        if k >= 0:
            rec.pose = gposes[k] @ t_bs


def open_euroc(
    path: str | Path,
    *,
    groundtruth: str | Path | None = None,
    max_difference: float = 0.02,
    stereo: bool = True,
    grey: bool = False,
) -> SequenceDataset:
    """Open a EuRoC MAV sequence (ASL layout).

    Args:
        path: the sequence folder or its ``mav0``.
        groundtruth: body trajectory overriding the one found: EuRoC ``data.csv`` or TUM ``.txt``.
        max_difference: largest time gap (s) between a frame and its ground-truth pose.
        stereo: attach cam1's images as ``right``.
        grey: read images as (H, W) grey.

    Raises:
        DatasetError: missing ``mav0/cam0``, list or image files, or malformed files.
    """
    root = Path(path)
    mav0 = root if root.name == "mav0" else root / "mav0"
    seq = mav0.parent
    cam0 = mav0 / "cam0"
    if not cam0.is_dir():
        raise DatasetError(f"{root}: expected a EuRoC sequence with mav0/cam0/, found none")
    times, records = _cam0_records(cam0)
    cam1 = mav0 / "cam1"
    if stereo and (cam1 / "data.csv").is_file():
        _attach_right(records, times, cam1)

    sensor = cam0 / "sensor.yaml"
    t_bs = sensor_extrinsics(sensor) if sensor.is_file() else np.eye(4)
    gt_file = Path(groundtruth) if groundtruth is not None else _find_groundtruth(mav0, seq)
    if gt_file is not None:
        _attach_groundtruth(records, times, gt_file, t_bs, max_difference)

    loops = seq / "loops.npy"
    return SequenceDataset(
        root=seq,
        records=records,
        format="euroc",
        calibration_path=sensor if sensor.is_file() else None,
        gt_path=loops if loops.is_file() else None,
        grey=grey,
        poses_path=gt_file,
    )

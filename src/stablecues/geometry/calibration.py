"""Calibration readers: EuRoC/Kalibr ``sensor.yaml``, KITTI ``calib.txt``, ORB-SLAM settings, TUM.

:func:`load_calibration` detects the format from the file's content. Every missing field raises
:class:`~stablecues.errors.CalibrationError` naming the field and the file.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ..errors import CalibrationError
from ..fileio import load_yaml, read_text
from ..limits import MAX_CALIBRATION_BYTES
from .camera import Calibration, PinholeCamera, Rectification

_F = TypeVar("_F", bound=Callable[..., Calibration])


def _names_file(loader: _F) -> _F:
    """Errors from validating the values read (a zero focal length, a wrong distortion count)
    are prefixed with the file, so every calibration error names it."""

    @functools.wraps(loader)
    def wrapper(path: str | Path, *args: Any, **kwargs: Any) -> Calibration:
        try:
            return loader(path, *args, **kwargs)
        except CalibrationError as exc:
            if str(Path(path)) in str(exc) or Path(path).name in str(exc):
                raise
            raise CalibrationError(f"{path}: {exc}") from None

    return wrapper  # type: ignore[return-value]


__all__ = [
    "TUM_CAMERAS",
    "load_calibration",
    "load_euroc",
    "load_euroc_stereo",
    "load_kitti",
    "load_orbslam",
    "tum_calibration",
]

# TUM RGB-D intrinsics, from the benchmark's "file formats" page (Freiburg 1/2/3 Kinects).
# Distortion in OpenCV order k1 k2 p1 p2 k3. Depth images store metres * 5000.
TUM_CAMERAS: dict[str, tuple[float, float, float, float, tuple[float, ...]]] = {
    "fr1": (517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": (520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": (535.4, 539.2, 320.1, 247.6, ()),
}
TUM_DEPTH_SCALE = 5000.0
_TUM_ALIASES = {
    "fr1": "fr1",
    "freiburg1": "fr1",
    "tum1": "fr1",
    "fr2": "fr2",
    "freiburg2": "fr2",
    "tum2": "fr2",
    "fr3": "fr3",
    "freiburg3": "fr3",
    "tum3": "fr3",
}


def tum_calibration(name: str) -> Calibration:
    """Calibration of a TUM RGB-D camera by name.

    Args:
        name: ``fr1``, ``fr2`` or ``fr3`` (also ``freiburg1``, ``tum:fr2`` ...).

    Returns:
        A monocular + depth calibration (640x480, depth scale 5000).
    """
    key = _TUM_ALIASES.get(name.lower().removeprefix("tum:").removeprefix("tum-"))
    if key is None:
        raise CalibrationError(f"unknown TUM camera {name!r}: expected one of fr1, fr2, fr3")
    fx, fy, cx, cy, dist = TUM_CAMERAS[key]
    cam = PinholeCamera(fx, fy, cx, cy, 640, 480, dist)
    return Calibration(left=cam, depth_scale=TUM_DEPTH_SCALE, source=f"TUM {key}")


def _is_tum_name(name: str) -> bool:
    return name.lower().removeprefix("tum:").removeprefix("tum-") in _TUM_ALIASES


@_names_file
def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration file, detecting its format.

    Supported:

    * EuRoC/Kalibr ``sensor.yaml`` (``intrinsics``, ``distortion_coefficients``, ``T_BS``).
      Give the left camera's file; the right one is found beside it (``sensorLeft.yaml`` ->
      ``sensorRight.yaml``, ``cam0/sensor.yaml`` -> ``cam1/sensor.yaml``). Without it the
      calibration is monocular. See :func:`load_euroc_stereo` to name both files.
    * KITTI ``calib.txt`` (``P0: ...`` to ``P3: ...``; raw ``P_rect_00`` also accepted).
    * ORB-SLAM(2/3) settings yaml (``%YAML:1.0``, ``Camera.fx`` ... ``Camera.bf``,
      ``DepthMapFactor``, optionally ``LEFT.K/D/R/P`` and ``RIGHT.*`` for raw stereo).
    * A TUM camera name instead of a path: ``fr1``, ``fr2``, ``fr3``.

    Args:
        path: the file, or a TUM camera name.

    Returns:
        The calibration.

    Raises:
        CalibrationError: missing file, unknown format, or a missing/invalid field.
    """
    path = Path(path)
    if not path.exists():
        if _is_tum_name(str(path)):
            return tum_calibration(str(path))
        raise CalibrationError(f"calibration file {path} does not exist")
    text = _read_text(path)
    if re.search(r"^\s*(P0|P_rect_00)\s*:", text, re.MULTILINE):
        return _parse_kitti(text, path)
    data = _parse_yaml(text, path)
    if "intrinsics" in data:
        right = _find_euroc_right(path)
        if right is not None:
            return load_euroc_stereo(path, right)
        return load_euroc(path)
    if any(k in data for k in ("Camera.fx", "Camera1.fx")):
        return _parse_orbslam(data, path)
    raise CalibrationError(
        f"{path}: unknown calibration format: expected EuRoC sensor.yaml (intrinsics), KITTI calib.txt "
        f"(P0:), or ORB-SLAM settings (Camera.fx)"
    )


# --- file helpers ---------------------------------------------------------------------------------


def _read_text(path: Path) -> str:
    try:
        return read_text(path, "calibration file", limit=MAX_CALIBRATION_BYTES, error=CalibrationError)
    except OSError as exc:
        raise CalibrationError(f"cannot read calibration file {path}: {exc}") from exc


def _parse_yaml(text: str, path: Path) -> dict[str, Any]:
    """YAML as OpenCV writes it: drop the ``%YAML:1.0`` directive and ``!!opencv-matrix`` tags."""
    lines = text.splitlines()
    if lines and lines[0].lstrip().startswith("%YAML"):
        lines = lines[1:]
    cleaned = "\n".join(lines).replace("!!opencv-matrix", "")
    data = load_yaml(cleaned, path, CalibrationError)
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a YAML mapping at the top level")
    return data


def _field(data: Mapping[str, Any], key: str, path: Path) -> Any:
    if key not in data or data[key] is None:
        raise CalibrationError(f"{path}: missing field {key!r}")
    return data[key]


def _number(data: Mapping[str, Any], key: str, path: Path) -> float:
    value = _field(data, key, path)
    try:
        out = float(value)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: field {key!r}: expected a number, got {value!r}") from exc
    if not np.isfinite(out):
        raise CalibrationError(f"{path}: field {key!r}: expected a finite number, got {value!r}")
    return out


def _numbers(data: Mapping[str, Any], key: str, path: Path, count: int | None = None) -> np.ndarray:
    value = _field(data, key, path)
    if isinstance(value, Mapping):  # an opencv-matrix or {rows, cols, data}
        value = _field(value, "data", path)
    try:
        arr = np.asarray(value, np.float64).ravel()
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{path}: field {key!r}: expected numbers, got {value!r:.60}") from None
    if not np.isfinite(arr).all():
        raise CalibrationError(f"{path}: field {key!r}: expected finite numbers, got {value!r:.60}")
    if count is not None and arr.size != count:
        raise CalibrationError(f"{path}: field {key!r}: expected {count} numbers, got {arr.size}")
    return arr


def _rigid(t: np.ndarray, path: Path, key: str) -> np.ndarray:
    """``t`` after checking it is a 4x4 rigid transform (rotation block orthonormal, last row
    0 0 0 1).

    Raises:
        CalibrationError: naming the file and the field.
    """
    rot = t[:3, :3]
    ok = np.allclose(rot @ rot.T, np.eye(3), atol=1e-4) and np.allclose(t[3], [0.0, 0.0, 0.0, 1.0])
    if not ok or not np.linalg.det(rot) > 0:
        raise CalibrationError(
            f"{path}: field {key!r}: expected a rigid transform (orthonormal rotation, last row 0 0 0 1)"
        )
    return t


def _rigid_inverse(t: np.ndarray, path: Path, key: str) -> np.ndarray:
    """The inverse of the rigid transform ``t`` (checked first: a singular matrix is refused)."""
    t = _rigid(t, path, key)
    return np.linalg.inv(t)


# --- EuRoC / Kalibr -------------------------------------------------------------------------------


def _find_euroc_right(left: Path) -> Path | None:
    name = left.name
    for a, b in (("Left", "Right"), ("left", "right"), ("LEFT", "RIGHT")):
        if a in name:
            cand = left.with_name(name.replace(a, b))
            if cand.exists():
                return cand
    if left.parent.name == "cam0":
        cand = left.parent.parent / "cam1" / name
        if cand.exists():
            return cand
    return None


def _euroc_camera(path: Path) -> tuple[PinholeCamera, np.ndarray]:
    data = _parse_yaml(_read_text(path), path)
    fx, fy, cx, cy = _numbers(data, "intrinsics", path, 4)
    model = str(data.get("camera_model", "pinhole"))
    if model != "pinhole":
        raise CalibrationError(f"{path}: camera_model {model!r} is not supported, expected 'pinhole'")
    dist_model = str(data.get("distortion_model", "radial-tangential"))
    if dist_model not in ("radial-tangential", "radtan", "plumb_bob"):
        raise CalibrationError(
            f"{path}: distortion_model {dist_model!r} is not supported, expected 'radial-tangential'"
        )
    dist = _numbers(data, "distortion_coefficients", path)
    if dist.size not in (4, 5):
        raise CalibrationError(
            f"{path}: field 'distortion_coefficients': expected 4 or 5 numbers, got {dist.size}"
        )
    res = _numbers(data, "resolution", path, 2)
    t_bs = _numbers(data, "T_BS", path, 16).reshape(4, 4)
    cam = PinholeCamera(
        float(fx), float(fy), float(cx), float(cy), int(res[0]), int(res[1]), tuple(float(d) for d in dist)
    )
    return cam, t_bs


@_names_file
def load_euroc(path: str | Path) -> Calibration:
    """Monocular calibration from one EuRoC/Kalibr ``sensor.yaml``."""
    path = Path(path)
    cam, _ = _euroc_camera(path)
    return Calibration(left=cam, source=str(path))


@_names_file
def load_euroc_stereo(left_path: str | Path, right_path: str | Path) -> Calibration:
    """Stereo calibration from the left and right cameras' EuRoC ``sensor.yaml`` files.

    ``T_BS`` maps sensor (camera) coordinates to the body frame, so the left-to-right transform
    is ``inv(T_BS_right) @ T_BS_left``.

    Args:
        left_path: the left camera's file (``cam0/sensor.yaml`` or ``sensorLeft.yaml``).
        right_path: the right camera's file.

    Returns:
        A raw (unrectified) stereo calibration; rectify it with
        :class:`stablecues.geometry.StereoRectifier`.
    """
    left_path, right_path = Path(left_path), Path(right_path)
    if not right_path.exists():
        raise CalibrationError(f"right calibration file {right_path} does not exist")
    left, t_bl = _euroc_camera(left_path)
    right, t_br = _euroc_camera(right_path)
    t_rl = _rigid_inverse(t_br, right_path, "T_BS") @ _rigid(t_bl, left_path, "T_BS")
    return Calibration(
        left=left,
        right=right,
        rotation=t_rl[:3, :3],
        translation=t_rl[:3, 3],
        rectified=False,
        source=f"{left_path} + {right_path.name}",
    )


# --- KITTI ----------------------------------------------------------------------------------------


@_names_file
def load_kitti(path: str | Path, *, pair: str = "grey") -> Calibration:
    """Rectified stereo calibration from a KITTI ``calib.txt``.

    Args:
        path: the file (odometry ``P0:`` ... ``P3:`` lines, or raw ``P_rect_00:`` ...).
        pair: ``"grey"`` (cameras 0 and 1) or ``"colour"`` (cameras 2 and 3).

    Returns:
        A rectified stereo calibration. Image size is unknown (None): KITTI's file omits it.
    """
    path = Path(path)
    if not path.exists():
        raise CalibrationError(f"calibration file {path} does not exist")
    return _parse_kitti(_read_text(path), path, pair=pair)


def _parse_kitti(text: str, path: Path, pair: str = "grey") -> Calibration:
    rows: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if ":" not in line:
            continue
        key, _, rest = line.partition(":")
        key = key.strip()
        try:
            rows[key] = np.array([float(v) for v in rest.split()])
        except ValueError:
            if re.fullmatch(r"P\d|P_rect_\d\d", key):
                raise CalibrationError(f"{path}: line {lineno} ({key}): expected 12 numbers") from None
    if pair in ("grey", "gray"):
        names = [("P0", "P_rect_00"), ("P1", "P_rect_01")]
    elif pair in ("colour", "color"):
        names = [("P2", "P_rect_02"), ("P3", "P_rect_03")]
    else:
        raise CalibrationError(f"KITTI camera pair {pair!r}: expected 'grey' or 'colour'")
    mats = []
    for alts in names:
        found = next((k for k in alts if k in rows), None)
        if found is None:
            raise CalibrationError(f"{path}: missing field {alts[0]!r}")
        if rows[found].size != 12:
            raise CalibrationError(f"{path}: field {found!r}: expected 12 numbers, got {rows[found].size}")
        mats.append(rows[found].reshape(3, 4))
    p_left, p_right = mats
    cam = PinholeCamera.from_matrix(p_left[:, :3])
    if not np.isfinite(np.stack(mats)).all() or not p_right[0, 0] > 0:
        raise CalibrationError(
            f"{path}: {names[1][0]}: expected finite numbers and a focal length > 0, fx = {p_right[0, 0]}"
        )
    baseline = float((p_left[0, 3] - p_right[0, 3]) / p_right[0, 0])
    if not (baseline > 0 and math.isfinite(baseline)):
        raise CalibrationError(
            f"{path}: stereo baseline from {names[0][0]}/{names[1][0]} is {baseline}, expected > 0"
        )
    return Calibration.rectified_stereo(cam, baseline, source=str(path))


# --- ORB-SLAM settings ----------------------------------------------------------------------------


@_names_file
def load_orbslam(path: str | Path) -> Calibration:
    """Calibration from an ORB-SLAM(2/3) settings yaml.

    ``Camera.fx`` ... ``Camera.p2`` (optional ``Camera.k3``), ``Camera.width/height``; ``Camera.bf``
    (``fx * baseline``) makes it a rectified stereo rig unless ``LEFT.K``/``RIGHT.K`` (raw
    stereo with ORB-SLAM's rectification ``LEFT.R``, ``LEFT.P`` ...) are given; ``DepthMapFactor``
    gives the depth scale of an RGB-D camera. ORB-SLAM3's ``Camera1.*``/``Camera2.*``,
    ``Stereo.b``, ``Stereo.T_c1_c2`` and ``RGBD.DepthMapFactor`` are read too.
    """
    path = Path(path)
    if not path.exists():
        raise CalibrationError(f"calibration file {path} does not exist")
    return _parse_orbslam(_parse_yaml(_read_text(path), path), path)


def _orb_camera(data: Mapping[str, Any], prefix: str, path: Path) -> PinholeCamera:
    fx = _number(data, f"{prefix}.fx", path)
    fy = _number(data, f"{prefix}.fy", path)
    cx = _number(data, f"{prefix}.cx", path)
    cy = _number(data, f"{prefix}.cy", path)
    dist = [_number(data, f"{prefix}.{k}", path) for k in ("k1", "k2", "p1", "p2")]
    if f"{prefix}.k3" in data:
        dist.append(_number(data, f"{prefix}.k3", path))
    size_prefix = "Camera" if "Camera.width" in data else prefix
    width = int(_number(data, f"{size_prefix}.width", path))
    height = int(_number(data, f"{size_prefix}.height", path))
    if not any(dist):
        dist = []
    return PinholeCamera(fx, fy, cx, cy, width, height, tuple(dist))


def _parse_orbslam(data: Mapping[str, Any], path: Path) -> Calibration:
    prefix = "Camera" if "Camera.fx" in data else "Camera1"
    cam = _orb_camera(data, prefix, path)
    source = str(path)
    depth_scale = None
    for key in ("DepthMapFactor", "RGBD.DepthMapFactor"):
        if key in data:
            depth_scale = _number(data, key, path)
    bf = _number(data, "Camera.bf", path) if "Camera.bf" in data else None
    if bf is None and "Stereo.b" in data:
        bf = _number(data, "Stereo.b", path) * cam.fx

    if "LEFT.K" in data or "RIGHT.K" in data:  # raw stereo with ORB-SLAM's own rectification
        left = PinholeCamera.from_matrix(
            _numbers(data, "LEFT.K", path, 9).reshape(3, 3),
            _numbers(data, "LEFT.D", path),
            int(_number(data, "LEFT.width", path)),
            int(_number(data, "LEFT.height", path)),
        )
        right = PinholeCamera.from_matrix(
            _numbers(data, "RIGHT.K", path, 9).reshape(3, 3),
            _numbers(data, "RIGHT.D", path),
            int(_number(data, "RIGHT.width", path)),
            int(_number(data, "RIGHT.height", path)),
        )
        rect = Rectification(
            R1=_numbers(data, "LEFT.R", path, 9).reshape(3, 3),
            R2=_numbers(data, "RIGHT.R", path, 9).reshape(3, 3),
            P1=_numbers(data, "LEFT.P", path, 12).reshape(3, 4),
            P2=_numbers(data, "RIGHT.P", path, 12).reshape(3, 4),
        )
        if not rect.baseline > 0:
            raise CalibrationError(f"{path}: field 'RIGHT.P': baseline -P[0,3]/P[0,0] must be positive")
        # rectified frames differ by the baseline along x: X_r = R2^T (R1 X_l - [B, 0, 0])
        rotation = rect.R2.T @ rect.R1
        translation = -rect.R2.T @ np.array([rect.baseline, 0.0, 0.0])
        return Calibration(
            left=left,
            right=right,
            rotation=rotation,
            translation=translation,
            depth_scale=depth_scale,
            rectified=False,
            rectification=rect,
            bf=bf,
            source=source,
        )
    if prefix == "Camera1" and "Camera2.fx" in data and "Stereo.T_c1_c2" in data:
        right = _orb_camera(data, "Camera2", path)
        t_c1_c2 = _numbers(data, "Stereo.T_c1_c2", path, 16).reshape(4, 4)
        t_c2_c1 = _rigid_inverse(t_c1_c2, path, "Stereo.T_c1_c2")
        return Calibration(
            left=cam,
            right=right,
            rotation=t_c2_c1[:3, :3],
            translation=t_c2_c1[:3, 3],
            depth_scale=depth_scale,
            rectified=False,
            bf=bf,
            source=source,
        )
    if bf is not None and depth_scale is None:
        if cam.has_distortion:
            raise CalibrationError(
                f"{path}: Camera.bf describes a rectified stereo pair, but Camera.k1..p2 are not zero"
            )
        return Calibration.rectified_stereo(cam, bf / cam.fx, source=source)
    return Calibration(left=cam, depth_scale=depth_scale, bf=bf, source=source)

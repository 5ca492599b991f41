"""A synthetic sequence: the town, the drive, rendering frames, ground truth, and writing a folder."""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import DatasetError, InputError, check_array
from ..groundtruth import save_ground_truth
from ..trajectory import write_times
from . import textures as tx
from .config import SyntheticTownConfig
from .render import Intrinsics, Renderer, View, cull
from .route import Lap, lap_lanes, lap_path, plan_laps
from .route import Path as LapPath
from .scene import (
    CAMVID_CLASSES,
    LANDMARK_CLASSES,
    LOD_ALWAYS,
    LOD_PIECE,
    LOD_WHOLE,
    Lighting,
    QuadSet,
    TextureBank,
    make_lighting,
    sky_colours,
)
from .town import K_LAP, Decals, Movers, Town, grid_size_for
from .truth import LoopTruthConfig, Visibility, loop_truth

logger = logging.getLogger(__name__)

SKY_SIZE = (2048, 320)  # panorama width (360 degrees) and height (40 degrees)
LOD_NEAR = 30.0  # metres: long quads nearer than this are drawn in pieces
SHADOW_FAR = 90.0  # metres: cast shadows beyond this are not drawn
VISIBILITY_FAR = 100.0  # metres: landmarks beyond this do not count for the loop ground truth


@dataclass
class SyntheticFrame:
    """One rendered frame.

    Attributes:
        index: frame number.
        timestamp: seconds (laps are hours apart: each is a drive at another time of day).
        lap: which drive the frame belongs to (0: the first pass).
        image: (H, W, 3) uint8 BGR left image.
        right: (H, W, 3) uint8 BGR rectified right image, or None.
        depth: (H, W) float32 metric depth of the left image along its optical axis, 0 for sky.
        labels: (H, W) uint8 CamVid 11-class ids (0 Sky ... 10 Bicyclist, 11 Unlabelled), or None.
        pose: (4, 4) float64 camera-to-world of the left camera (x right, y down, z forward).
    """

    index: int
    timestamp: float
    lap: int
    image: np.ndarray
    right: np.ndarray | None
    depth: np.ndarray | None
    labels: np.ndarray | None
    pose: np.ndarray


def camera_rotation(heading: float) -> np.ndarray:
    """(3, 3) camera-to-world rotation of a level camera looking along ``heading`` (radians from +x)."""
    c, s = math.cos(heading), math.sin(heading)
    return np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])


class SyntheticTown:
    """A procedural town and a drive through it; renders any frame on demand.

    Args:
        config: the settings (validated here).

    Attributes:
        config: the settings.
        intrinsics: the (undistorted, rectified) camera.
        poses: (N, 4, 4) camera-to-world poses of the left camera.
        times: (N,) timestamps in seconds.
        lap_of: (N,) int lap of each frame.
        headings: (N,) yaw of each frame, radians.
        step: metres between consecutive frames of a lap.
    """

    def __init__(self, config: SyntheticTownConfig = SyntheticTownConfig()) -> None:  # noqa: B008
        config.validate()
        self.config = config
        w, h = config.route_size()
        nbx, nby = grid_size_for((w, h))
        self.bank = TextureBank()
        self.town = Town(config.seed, nbx, nby, config.clutter, self.bank)
        self.laps: list[Lap] = plan_laps(1 + config.loops, (2, 2, w, h), config.seed)
        self.paths: list[LapPath] = [lap_path(self.town, lap) for lap in self.laps]
        lengths = np.array([p.length for p in self.paths])
        n = config.frames
        self.step = float(lengths.sum() / n)
        arc_all = np.arange(n) * self.step
        starts = np.concatenate([[0.0], np.cumsum(lengths)])
        self.lap_of = np.clip(np.searchsorted(starts, arc_all, side="right") - 1, 0, len(self.laps) - 1)
        self.arc = arc_all - starts[self.lap_of]
        pos2 = np.zeros((n, 2))
        self.headings = np.zeros(n)
        for k, path in enumerate(self.paths):
            sel = self.lap_of == k
            if sel.any():
                pos2[sel], self.headings[sel] = path.sample(self.arc[sel])
        self.positions = np.column_stack([pos2, np.full(n, config.camera_height)])
        self.poses = np.zeros((n, 4, 4))
        for i in range(n):
            self.poses[i, :3, :3] = camera_rotation(float(self.headings[i]))
            self.poses[i, :3, 3] = self.positions[i]
            self.poses[i, 3, 3] = 1.0
        # each lap starts at its hour of the day; days are added to keep time increasing
        t0 = []
        prev_end = -math.inf
        for lap, length in zip(self.laps, lengths, strict=True):
            t = lap.hour * 3600.0
            while t <= prev_end + 600.0:
                t += 86400.0
            t0.append(t)
            prev_end = t + length / config.speed
        self.lap_t0 = np.array(t0)
        self.lap_time = self.arc / config.speed
        self.times = self.lap_t0[self.lap_of] + self.lap_time
        self.intrinsics = Intrinsics.from_fov(config.width, config.height, config.fov_deg)
        self.renderer = Renderer(self.intrinsics, self.bank, far=config.max_depth)
        self.lights: list[Lighting] = []
        for lap in self.laps:
            horizon, zenith, cloud, cloud_c = sky_colours(lap.hour, lap.overcast)
            sky = self.bank.register(
                tx.sky_panorama,
                SKY_SIZE[0],
                SKY_SIZE[1],
                horizon,
                zenith,
                cloud,
                cloud_c,
                seed=(config.seed, K_LAP, lap.index, 99999),
            )
            self.lights.append(make_lighting(lap.hour, lap.overcast, sky))
        self._movers: dict[int, Movers] = {}
        self._decals: dict[int, Decals] = {}

    def __len__(self) -> int:
        return self.config.frames

    # ------------------------------------------------------------------ calibration

    @property
    def bf(self) -> float:
        """fx times the baseline (pixels x metres): disparity = bf / depth."""
        return self.intrinsics.fx * self.config.baseline

    def calibration_yaml(self, depth: bool = True) -> str:
        """ORB-SLAM settings text for this camera (stereo rectified; the depth PNG factor when
        ``depth``: a settings file with one is read as an RGB-D camera, whose right images
        would then never be used)."""
        c, cfg = self.intrinsics, self.config
        fps = cfg.speed / self.step
        lines = (

            [
                "%YAML:1.0",
                f"# stablecues synthetic town: seed {cfg.seed}, {cfg.frames} frames, {cfg.loops} revisits",
                "# rectified stereo pair without distortion; right camera = left + baseline along x",
                'Camera.type: "PinHole"',
                f"Camera.fx: {c.fx:.9f}",
                f"Camera.fy: {c.fy:.9f}",
                f"Camera.cx: {c.cx:.9f}",
                f"Camera.cy: {c.cy:.9f}",
                "Camera.k1: 0.0",
                "Camera.k2: 0.0",
                "Camera.p1: 0.0",
                "Camera.p2: 0.0",
                "Camera.k3: 0.0",
                f"Camera.width: {c.width}",
                f"Camera.height: {c.height}",
                f"Camera.fps: {fps:.6f}",
                f"Camera.bf: {self.bf:.9f}",
                f"Stereo.b: {cfg.baseline:.9f}",
                "Camera.RGB: 1",
                "ThDepth: 40.0",
                *([f"DepthMapFactor: {cfg.depth_map_factor:.6f}"] if depth else []),
                "",
            ]
        )
        return "\n".join(lines)

    # ------------------------------------------------------------------ per lap

    def movers(self, lap: int) -> Movers:
        """Cars, cyclists and people of a lap (made on first use)."""
        if lap not in self._movers:
            self._movers[lap] = self.town.lap_movers(lap, lap_lanes(self.laps[lap]))
        return self._movers[lap]

    def decals(self, lap: int) -> Decals:
        """Cast shadows of a lap (made on first use)."""
        if lap not in self._decals:
            self._decals[lap] = self.town.lap_decals(self.lights[lap])
        return self._decals[lap]

    # ------------------------------------------------------------------ rendering

    def _gather(
        self,
        R: np.ndarray,
        C: np.ndarray,
        lap: int,
        t: float,
        margin: float,
        far: float,
        cam: Intrinsics,
        cameras: list[np.ndarray] | None = None,
        lod_near: float = LOD_NEAR,
    ) -> tuple[QuadSet, np.ndarray]:
        """Quads that may be seen from a camera (or from all ``cameras`` of a stereo pair), with normals.

        Long quads come in pieces when any part of them is within ``lod_near`` metres, else whole.
        """
        town = self.town
        st = town.static
        idx = cull(R, C, town.static_centre, town.static_radius, cam, far, margin)
        lod = st.lod[idx]
        par = np.maximum(st.parent[idx], 0)
        near = np.linalg.norm(town.static_centre[par] - C, axis=1) - town.static_radius[par] < lod_near
        idx = idx[(lod == LOD_ALWAYS) | ((lod == LOD_PIECE) & near) | ((lod == LOD_WHOLE) & ~near)]
        parts = [town.static.subset(idx)]
        normals = [town.static_normal[idx]]
        mv = self.movers(lap)
        if len(mv):
            pos = mv.positions(t)
            d = pos - C
            flat = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)
            # objects never run into the camera: one that would hold it is left out
            keep = (flat < min(far, 120.0)) & ~mv.contains(t, C)
            keep[keep] &= np.isin(
                np.arange(len(mv))[keep],
                cull(
                    R, C, pos[keep] + np.array([0, 0, 1.0]), np.full(int(keep.sum()), 3.0), cam, far, margin
                ),
            )
            dyn = mv.world_quads(t, keep)
            if len(dyn):
                parts.append(dyn)
                normals.append(dyn.normals())
        quads, nrm = QuadSet.concat(parts), np.concatenate(normals)
        hidden = town.occluded(quads.corners(), cameras if cameras is not None else [C])
        keep = np.nonzero(~hidden)[0]
        return quads.subset(keep), nrm[keep]

    def render_pose(
        self,
        pose: np.ndarray,
        *,
        lap: int = 0,
        t: float = 0.0,
        right: bool = True,
        labels: bool = True,
        noise_seed: tuple[int, ...] | None = None,
    ) -> tuple[View, View | None]:
        """Render the town from any camera pose, with the traffic and light of ``lap`` at time ``t``.

        Args:
            pose: (4, 4) camera-to-world of the left camera.
            lap: whose cars, people and time of day to show.
            t: seconds into that lap (where the moving objects are).
            right: also render the right camera (``baseline`` to the right).
            labels: produce label and visibility images for the left view.
            noise_seed: seed of the sensor noise (None: no noise).

        Returns:
            (left view, right view or None).
        """
        check_array("pose", pose, shape=(4, 4))
        if not 0 <= lap < len(self.laps):
            raise InputError(f"lap: expected 0..{len(self.laps) - 1}, got {lap}")
        cfg = self.config
        R = np.asarray(pose[:3, :3], float)
        C = np.asarray(pose[:3, 3], float)
        C_right = C + cfg.baseline * R[:, 0]
        cams = [C, C_right] if right else [C]
        quads, normals = self._gather(R, C, lap, t, cfg.baseline + 0.5, cfg.max_depth, self.intrinsics, cams)
        light, decals = self.lights[lap], self.decals(lap)
        if len(decals):
            di = cull(R, C, decals.centre, decals.radius, self.intrinsics, SHADOW_FAR, cfg.baseline + 0.5)
            decals = decals.subset(di)
            decals = decals.subset(np.nonzero(~self.town.occluded(decals.quads.corners(), cams))[0])
        noise = cfg.noise if noise_seed is not None else 0.0
        rng_l = np.random.default_rng([*noise_seed, 0]) if noise_seed is not None else None
        left = self.renderer.render(
            R, C, quads, normals, light, decals, labels=labels, noise=noise, noise_rng=rng_l
        )
        rv = None
        if right:
            rng_r = np.random.default_rng([*noise_seed, 1]) if noise_seed is not None else None
            rv = self.renderer.render(
                R,
                C_right,
                quads,
                normals,
                light,
                decals,
                labels=False,
                levels=left.levels,
                noise=noise,
                noise_rng=rng_r,
            )
        return left, rv

    def frame(self, i: int, *, right: bool = True, depth: bool = True, labels: bool = True) -> SyntheticFrame:
        """Render frame ``i`` (0 <= i < frames)."""
        if not 0 <= i < len(self):
            raise InputError(f"frame index: expected 0..{len(self) - 1}, got {i}")
        lap = int(self.lap_of[i])
        left, rv = self.render_pose(
            self.poses[i],
            lap=lap,
            t=float(self.lap_time[i]),
            right=right,
            labels=labels,
            noise_seed=(self.config.seed, 3, i),
        )
        return SyntheticFrame(
            index=i,
            timestamp=float(self.times[i]),
            lap=lap,
            image=left.image,
            right=rv.image if rv is not None else None,
            depth=left.depth if depth else None,
            labels=left.labels if labels else None,
            pose=self.poses[i].copy(),
        )

    def __iter__(self) -> Iterator[SyntheticFrame]:
        for i in range(len(self)):
            yield self.frame(i)

    # ------------------------------------------------------------------ ground truth

    def visibility(self, frames: range | None = None) -> Visibility:
        """Which static landmark surfaces each frame sees, and how large they appear.

        Computed from the geometry, not by rendering: a landmark piece (building, tree, pole,
        sign or fence quad, long ones in 4 m pieces) counts when it lies in the view frustum
        within 100 m, faces the camera, and is not hidden behind a block
        (:meth:`Town.occluded`); its weight is its projected area in pixels (corners clamped
        to the image). Nearer objects of the same street side may still hide parts of it.
        """
        cfg = self.config
        town = self.town
        st = town.static
        cand = np.nonzero(np.isin(st.label, LANDMARK_CLASSES) & (st.lod != LOD_WHOLE))[0]
        corners_all = st.corners()[cand]
        normals = town.static_normal[cand]
        two = st.two_sided[cand]
        cam = self.intrinsics
        far = min(cfg.max_depth, VISIBILITY_FAR)
        frames = frames if frames is not None else range(len(self))
        ids: list[np.ndarray] = []
        weights: list[np.ndarray] = []
        for i in frames:
            R = self.poses[i, :3, :3]
            C = self.poses[i, :3, 3]
            k = cull(R, C, town.static_centre[cand], town.static_radius[cand], cam, far)
            facing = two[k] | ((normals[k] * (C - corners_all[k, 0])).sum(axis=1) > 0)
            k = k[facing]
            pc = (corners_all[k] - C) @ R
            front = pc[:, :, 2].min(axis=1) > 0.1
            k, pc = k[front], pc[front]
            k_keep = ~town.occluded(corners_all[k], [C])
            k, pc = k[k_keep], pc[k_keep]
            x = np.clip(cam.fx * pc[:, :, 0] / pc[:, :, 2] + cam.cx, -0.5, cam.width - 0.5)
            y = np.clip(cam.fy * pc[:, :, 1] / pc[:, :, 2] + cam.cy, -0.5, cam.height - 0.5)
            area = 0.5 * np.abs((x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y).sum(axis=1))
            pos = area > 0.5
            order = np.argsort(k[pos])
            ids.append(cand[k[pos]][order].astype(np.int32))
            weights.append(area[pos][order])
        return Visibility(ids, weights, town.static_centre)

    def ground_truth(self, config: LoopTruthConfig = LoopTruthConfig()) -> np.ndarray:  # noqa: B008
        """The (N, N) bool lower-triangular loop matrix (see :mod:`.truth` for the rule)."""
        vis = self.visibility() if config.opposite == "covisible" else None
        return loop_truth(self.positions, self.headings, config, vis)


def generate(config: SyntheticTownConfig = SyntheticTownConfig()) -> Iterator[SyntheticFrame]:  # noqa: B008
    """Render the frames of a synthetic sequence one by one (left, right, depth, labels, pose)."""
    yield from SyntheticTown(config)


def _tum_line(t: float, pose: np.ndarray) -> str:
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(pose[:3, :3]).as_quat()  # x, y, z, w
    x, y, z = pose[:3, 3]
    return f"{t:.6f} {x:.6f} {y:.6f} {z:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"


def write_sequence(
    config: SyntheticTownConfig,
    out_dir: str | Path,
    *,
    truth: LoopTruthConfig = LoopTruthConfig(),  # noqa: B008
    right: bool = True,
    depth: bool = True,
    labels: bool = True,
    progress: bool = True,
    overwrite: bool = False,
) -> Path:
    """Generate a sequence and write it in the project's image-folder format.

    Writes ``images/``, ``right/``, ``depth/`` (16-bit PNG, metres = value / DepthMapFactor, 0 for
    none), ``labels/`` (uint8 CamVid ids), ``times.txt``, ``poses.txt`` (TUM, camera-to-world),
    ``calib.yaml`` (ORB-SLAM settings with Camera.bf and DepthMapFactor), ``loops.npy`` and
    ``synthetic.json`` (the settings, lap of each frame, step and counts).

    Args:
        config: the sequence.
        out_dir: folder to write (created).
        truth: the loop ground-truth rule.
        right, depth, labels: which optional outputs to write.
        progress: show a tqdm progress bar.
        overwrite: allow writing into a folder that already holds images.

    Returns:
        The folder.

    Raises:
        DatasetError: the folder already holds a sequence and ``overwrite`` is False.
    """
    from tqdm import tqdm

    out = Path(out_dir)
    if (out / "images").is_dir() and any((out / "images").iterdir()) and not overwrite:
        raise DatasetError(f"{out}: already holds images/; choose an empty folder or overwrite")
    t_start = time.perf_counter()
    seq = SyntheticTown(config)
    subdirs = (
        ["images"]
        + (["right"] if right else [])
        + (["depth"] if depth else [])
        + (["labels"] if labels else [])
    )
    if overwrite:
        # an earlier sequence's frames (other count, other outputs) must not mix with this one
        for sub in ("images", "right", "depth", "labels"):
            for old in (out / sub).glob("*.png") if (out / sub).is_dir() else ():
                old.unlink()
    for sub in subdirs:
        (out / sub).mkdir(parents=True, exist_ok=True)
    png = [cv2.IMWRITE_PNG_COMPRESSION, 1]
    factor = config.depth_map_factor
    render_s = 0.0
    for i in tqdm(range(len(seq)), desc="synth", unit="frame", disable=not progress):
        t0 = time.perf_counter()
        f = seq.frame(i, right=right, depth=depth, labels=labels)
        render_s += time.perf_counter() - t0
        name = f"{i:06d}.png"
        _imwrite(out / "images" / name, f.image, png)
        if f.right is not None:
            _imwrite(out / "right" / name, f.right, png)
        if f.depth is not None:
            raw = np.round(f.depth.astype(np.float64) * factor)
            raw[(raw > 65535) | ~np.isfinite(raw)] = 0
            _imwrite(out / "depth" / name, raw.astype(np.uint16), png)
        if f.labels is not None:
            _imwrite(out / "labels" / name, f.labels, png)
    gt = seq.ground_truth(truth)
    save_ground_truth(out / "loops.npy", gt)
    write_times(out / "times.txt", seq.times)
    # its own TUM lines, not trajectory.write_tum: poses.txt has 6 and 9 decimals, write_tum writes 4 and 7
    (out / "poses.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw (camera-to-world)\n"
        + "".join(_tum_line(float(t), p) + "\n" for t, p in zip(seq.times, seq.poses, strict=True))
    )
    (out / "calib.yaml").write_text(seq.calibration_yaml(depth=depth))
    meta = {
        "generator": "stablecues.synthetic",
        "config": asdict(config),
        "truth": asdict(truth),
        "frames": len(seq),
        "laps": [
            {
                "index": lap.index,
                "clockwise": lap.clockwise,
                "lane_offset_m": lap.offset,
                "hour": round(lap.hour, 3),
                "overcast": lap.overcast,
                "detour_edge": lap.detour,
            }
            for lap in seq.laps
        ],
        "lap_of_frame": seq.lap_of.tolist(),
        "step_m": seq.step,
        "route_blocks": list(config.route_size()),
        "bf": seq.bf,
        "loop_pairs": int(gt.sum()),
        "loop_queries": int(gt.any(axis=1).sum()),
        "classes": list(CAMVID_CLASSES),
        "render_s": render_s,
        "total_s": time.perf_counter() - t_start,
    }
    (out / "synthetic.json").write_text(json.dumps(meta, indent=1))
    logger.info("wrote %d frames to %s", len(seq), out)
    return out


def _imwrite(path: Path, img: np.ndarray, params: list[int]) -> None:
    if not cv2.imwrite(str(path), img, params):
        raise DatasetError(f"{path}: could not write the image")

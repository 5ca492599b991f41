"""SyntheticTown and write_sequence: determinism, exact geometry (depth, poses, stereo), labels,
visibility, ORB revisits, and the written image folder read back."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.errors import DatasetError, InputError
from stablecues.synthetic import (
    CAMVID_CLASSES,
    SyntheticTown,
    SyntheticTownConfig,
    camera_rotation,
    write_sequence,
)

SMALL = SyntheticTownConfig(frames=24, width=160, height=120, loops=2, seed=3, noise=0.0)


@pytest.fixture(scope="module")
def town() -> SyntheticTown:
    return SyntheticTown(SMALL)


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Sample an (H, W[, C]) image at float positions (x, y) (all inside), (n, C) float."""
    im = img.reshape(img.shape[0], img.shape[1], -1).astype(np.float64)
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    top = im[y0, x0] * (1 - fx) + im[y0, x0 + 1] * fx
    bot = im[y0 + 1, x0] * (1 - fx) + im[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bot * fy


def _moved(pose: np.ndarray, forward: float, yaw_deg: float) -> np.ndarray:
    """A level camera ``forward`` metres ahead of ``pose``, turned by ``yaw_deg`` to the left."""
    heading = math.atan2(pose[1, 2], pose[0, 2])
    out = np.eye(4)
    out[:3, :3] = camera_rotation(heading + math.radians(yaw_deg))
    out[:3, 3] = pose[:3, 3] + forward * pose[:3, 2]
    return out


def test_frame_contents(town: SyntheticTown) -> None:
    f = town.frame(5)
    h, w = SMALL.height, SMALL.width
    assert f.image.shape == (h, w, 3) and f.image.dtype == np.uint8
    assert f.right is not None and f.right.shape == (h, w, 3)
    assert f.depth is not None and f.depth.shape == (h, w) and f.depth.dtype == np.float32
    assert f.labels is not None and f.labels.dtype == np.uint8
    assert f.labels.max() < len(CAMVID_CLASSES) == 12
    present = set(np.unique(f.labels).tolist())
    assert {0, 1, 3} <= present  # sky, buildings and road are always in a street view
    # sky has no depth, everything else has some
    assert np.all(f.depth[f.labels == 0] == 0)
    assert np.all(f.depth[f.labels != 0] > 0)
    # the pose is a rigid camera-to-world transform of a level camera at the set height
    R = f.pose[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-12)  # image y points down
    assert f.pose[2, 3] == pytest.approx(SMALL.camera_height)
    assert f.timestamp == pytest.approx(town.times[5])


def test_deterministic_for_a_seed(town: SyntheticTown) -> None:
    again = SyntheticTown(SMALL)
    np.testing.assert_array_equal(again.poses, town.poses)
    np.testing.assert_array_equal(again.times, town.times)
    a, b = town.frame(9), again.frame(9)
    np.testing.assert_array_equal(a.image, b.image)
    assert a.right is not None and b.right is not None
    np.testing.assert_array_equal(a.right, b.right)
    assert a.depth is not None and b.depth is not None
    np.testing.assert_array_equal(a.depth, b.depth)
    other = SyntheticTown(SyntheticTownConfig(**{**SMALL.__dict__, "seed": 4}))
    assert np.abs(other.frame(9).image.astype(int) - a.image.astype(int)).mean() > 10


def test_noise_is_seeded_per_frame() -> None:
    cfg = SyntheticTownConfig(frames=6, width=96, height=72, loops=0, seed=1, noise=3.0)
    a, b = SyntheticTown(cfg), SyntheticTown(cfg)
    np.testing.assert_array_equal(a.frame(2).image, b.frame(2).image)


def test_depth_and_poses_reproject_within_a_pixel(town: SyntheticTown) -> None:
    """Corners of frame A, lifted with A's depth and moved with the poses, land where LK finds them in B."""
    pa = town.poses[7]
    pb = _moved(pa, forward=0.8, yaw_deg=2.0)
    a, _ = town.render_pose(pa, lap=1, t=3.0, right=False)
    b, _ = town.render_pose(pb, lap=1, t=3.0, right=False)
    assert a.labels is not None
    K = town.intrinsics.K
    ga = cv2.cvtColor(a.image, cv2.COLOR_BGR2GRAY)
    gb = cv2.cvtColor(b.image, cv2.COLOR_BGR2GRAY)
    static = np.isin(a.labels, [1, 2, 4, 5, 6, 7]).astype(np.uint8)
    pts = cv2.goodFeaturesToTrack(ga, 300, 0.01, 4, mask=static)
    assert pts is not None and len(pts) > 40
    pts = pts.reshape(-1, 2)
    u, v = pts[:, 0], pts[:, 1]
    z = a.depth[np.round(v).astype(int), np.round(u).astype(int)].astype(np.float64)
    # lift (depth at the nearest pixel centre is exact for that centre, so use the centres)
    uc, vc = np.round(u), np.round(v)
    Xa = np.stack([(uc - K[0, 2]) / K[0, 0] * z, (vc - K[1, 2]) / K[1, 1] * z, z], axis=1)
    Xw = Xa @ pa[:3, :3].T + pa[:3, 3]
    Tb = np.linalg.inv(pb)
    Xb = Xw @ Tb[:3, :3].T + Tb[:3, 3]
    pred = np.stack(
        [K[0, 0] * Xb[:, 0] / Xb[:, 2] + K[0, 2], K[1, 1] * Xb[:, 1] / Xb[:, 2] + K[1, 2]], axis=1
    )
    # depth agrees where the point stays visible
    h, w = gb.shape
    inside = (pred[:, 0] > 3) & (pred[:, 0] < w - 4) & (pred[:, 1] > 3) & (pred[:, 1] < h - 4)
    zb = np.zeros(len(pred))
    zb[inside] = b.depth[np.round(pred[inside, 1]).astype(int), np.round(pred[inside, 0]).astype(int)]
    seen = inside & (np.abs(zb - Xb[:, 2]) < 0.02 * Xb[:, 2] + 0.05)
    assert seen.sum() > 25
    # track the pixel centres from A to B and compare with the prediction
    start = np.stack([uc, vc], axis=1).astype(np.float32)[seen]
    tracked, st, _ = cv2.calcOpticalFlowPyrLK(
        ga,
        gb,
        start,
        pred[seen].astype(np.float32).copy(),
        winSize=(9, 9),
        maxLevel=2,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    ok = st.ravel() == 1
    err = np.linalg.norm(tracked[ok] - pred[seen][ok], axis=1)
    assert np.median(err) < 0.5
    assert np.mean(err < 1.0) > 0.8
    # and photometrically: the colours at the predicted spots match A's, far better than 2 px off
    ca = a.image[vc[seen].astype(int), uc[seen].astype(int)].astype(np.float64)
    cb = _bilinear(b.image, pred[seen, 0], pred[seen, 1])
    cb_off = _bilinear(b.image, pred[seen, 0] + 2.0, pred[seen, 1])
    good = np.median(np.abs(cb - ca).mean(axis=1))
    off = np.median(np.abs(cb_off - ca).mean(axis=1))
    assert good < 0.5 * off


def test_stereo_disparity_is_bf_over_depth(town: SyntheticTown) -> None:
    f = town.frame(11)
    assert f.right is not None and f.depth is not None and f.labels is not None
    assert town.bf == pytest.approx(town.intrinsics.fx * SMALL.baseline)
    gl = cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY)
    gr = cv2.cvtColor(f.right, cv2.COLOR_BGR2GRAY)
    pts = cv2.goodFeaturesToTrack(gl, 300, 0.01, 4, mask=(f.depth > 0).astype(np.uint8))
    assert pts is not None
    pts = np.round(pts.reshape(-1, 2))
    z = f.depth[pts[:, 1].astype(int), pts[:, 0].astype(int)].astype(np.float64)
    disp = town.bf / z
    pred = pts - np.stack([disp, np.zeros_like(disp)], axis=1)
    keep = (pred[:, 0] > 4) & (disp < 40)
    tracked, st, _ = cv2.calcOpticalFlowPyrLK(
        gl,
        gr,
        pts[keep].astype(np.float32),
        pred[keep].astype(np.float32).copy(),
        winSize=(9, 9),
        maxLevel=1,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    ok = st.ravel() == 1
    assert ok.sum() > 30
    err = tracked[ok] - pred[keep][ok]
    assert np.median(np.abs(err[:, 0])) < 0.3  # disparity = fx * baseline / depth
    assert np.median(np.abs(err[:, 1])) < 0.2  # rectified: same row
    # dense check: the right image at u - bf/z shows the left pixel's colour
    h, w = gl.shape
    v, u = np.mgrid[0:h, 0:w]
    m = (f.depth > 0) & (u - town.bf / np.maximum(f.depth, 1e-3) > 1) & (v < h - 1)
    ur = (u - town.bf / np.maximum(f.depth, 1e-3))[m]
    col = _bilinear(f.right, ur, v[m].astype(float))
    diff = np.abs(col - f.image[m]).mean(axis=1)
    assert np.median(diff) < 2.0


def test_revisits_change_lane_light_and_direction(town: SyntheticTown) -> None:
    laps = town.laps
    assert len(laps) == 3
    assert laps[0].clockwise and laps[1].clockwise and not laps[2].clockwise
    assert laps[1].offset != laps[0].offset
    assert len({round(lap.hour, 2) for lap in laps}) == 3
    assert np.all(np.diff(town.times) > 0)
    # other cars and people every lap
    m0, m1 = town.movers(0), town.movers(1)
    assert len(m0) and len(m1)
    assert not (len(m0) == len(m1) and np.allclose(m0.start, m1.start))


def test_render_pose_rejects_bad_input(town: SyntheticTown) -> None:
    with pytest.raises(InputError):
        town.render_pose(np.eye(3))
    with pytest.raises(InputError):
        town.render_pose(town.poses[0], lap=7)
    with pytest.raises(InputError):
        town.frame(len(town))


def test_orb_recognises_a_revisit() -> None:
    """A revisit (other lane, time, cars) matches its first visit far better than another place."""
    cfg = SyntheticTownConfig(frames=90, width=320, height=240, loops=1, seed=5)
    town = SyntheticTown(cfg)
    gt = town.ground_truth()
    queries = np.nonzero(gt.any(axis=1) & (town.lap_of == 1))[0]
    assert len(queries) > 5
    orb = cv2.ORB_create(800)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)

    def desc(i: int) -> np.ndarray:
        g = cv2.cvtColor(town.frame(int(i), right=False, labels=False).image, cv2.COLOR_BGR2GRAY)
        kp, d = orb.detectAndCompute(g, None)
        assert len(kp) > 300  # plenty of corners
        return d

    def good(da: np.ndarray, db: np.ndarray) -> int:
        return sum(1 for m in bf.match(da, db) if m.distance < 40)

    revisit, unrelated = [], []
    for i in queries[::2]:
        js = np.nonzero(gt[i])[0]
        j = js[np.argmin(np.linalg.norm(town.positions[js] - town.positions[i], axis=1))]
        k = int(np.argmax(np.linalg.norm(town.positions[: i - 10] - town.positions[i], axis=1)))
        di = desc(i)
        revisit.append(good(di, desc(j)))
        unrelated.append(good(di, desc(k)))
    rv, un = np.array(revisit), np.array(unrelated)
    # small images and a dusk revisit from another lane: some pairs match weakly, so ask for the
    # typical revisit to stand out and for nearly every one to beat the unrelated frame
    assert np.median(rv) > 3 * np.median(un) + 10
    assert np.mean(rv > un) > 0.8


def test_visibility_sees_landmarks() -> None:
    town = SyntheticTown(SyntheticTownConfig(frames=10, width=64, height=48, loops=0, seed=2))
    vis = town.visibility(range(3))
    assert len(vis.ids) == 3
    for ids, counts in zip(vis.ids, vis.counts, strict=True):
        assert len(ids) > 10 and np.all(np.diff(ids) > 0) and np.all(counts > 0)
    assert vis.centres.shape[1] == 3


# ------------------------------------------------------------------------------------------ writing a folder

CFG = SyntheticTownConfig(frames=6, width=96, height=72, loops=1, seed=11, noise=0.0)


def _settings(path: Path) -> dict[str, str]:
    out = {}
    for line in path.read_text().splitlines()[1:]:
        if ":" in line and not line.startswith("#"):
            k, v = line.split(":", 1)
            out[k.strip()] = v.strip()
    return out


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_sequence(CFG, tmp_path_factory.mktemp("synth") / "seq", progress=False)


def test_written_folder_round_trips(written: Path) -> None:
    out = written
    town = SyntheticTown(CFG)
    names = sorted(p.name for p in (out / "images").iterdir())
    assert names == [f"{i:06d}.png" for i in range(CFG.frames)]
    for sub in ("right", "depth", "labels"):
        assert sorted(p.name for p in (out / sub).iterdir()) == names
    img = cv2.imread(str(out / "images" / names[2]), cv2.IMREAD_UNCHANGED)
    right = cv2.imread(str(out / "right" / names[2]), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(out / "depth" / names[2]), cv2.IMREAD_UNCHANGED)
    labels = cv2.imread(str(out / "labels" / names[2]), cv2.IMREAD_UNCHANGED)
    assert img.shape == right.shape == (72, 96, 3) and img.dtype == np.uint8
    assert depth.shape == (72, 96) and depth.dtype == np.uint16
    assert labels.shape == (72, 96) and labels.dtype == np.uint8 and labels.max() <= 11
    # the files hold what the generator renders
    f = town.frame(2)
    np.testing.assert_array_equal(img, f.image)
    np.testing.assert_array_equal(labels, f.labels)
    assert f.depth is not None
    factor = CFG.depth_map_factor
    np.testing.assert_allclose(depth / factor, f.depth, atol=0.5 / factor + 1e-6)
    # calibration
    s = _settings(out / "calib.yaml")
    assert (out / "calib.yaml").read_text().startswith("%YAML:1.0")
    assert float(s["Camera.fx"]) == pytest.approx(town.intrinsics.fx)
    assert float(s["Camera.bf"]) == pytest.approx(town.intrinsics.fx * CFG.baseline)
    assert float(s["DepthMapFactor"]) == factor
    assert int(s["Camera.width"]) == 96 and int(s["Camera.height"]) == 72
    # times and poses
    times = np.loadtxt(out / "times.txt")
    np.testing.assert_allclose(times, town.times, atol=1e-6)
    rows = np.loadtxt(out / "poses.txt")
    assert rows.shape == (CFG.frames, 8)
    np.testing.assert_allclose(rows[:, 1:4], town.poses[:, :3, 3], atol=1e-6)
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(rows[:, 4:8]).as_matrix()
    np.testing.assert_allclose(R, town.poses[:, :3, :3], atol=1e-6)
    # loops
    gt = np.load(out / "loops.npy")
    assert gt.shape == (CFG.frames, CFG.frames) and gt.dtype == bool and not np.triu(gt).any()
    np.testing.assert_array_equal(gt, town.ground_truth())
    meta = json.loads((out / "synthetic.json").read_text())
    assert meta["frames"] == CFG.frames and meta["lap_of_frame"] == town.lap_of.tolist()


def test_folder_loader_reads_it(written: Path) -> None:
    from stablecues.datasets.folder import open_folder

    out = written
    ds = open_folder(out)
    assert len(ds) == CFG.frames
    assert ds.depth_factor == CFG.depth_map_factor
    assert ds.gt_path == out / "loops.npy"
    rec = ds.records[3]
    assert rec.right is not None and rec.depth is not None and rec.labels is not None
    assert rec.pose is not None
    np.testing.assert_allclose(rec.pose, SyntheticTown(CFG).poses[3], atol=1e-6)


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    small = SyntheticTownConfig(frames=2, width=48, height=36, loops=0, clutter=0.0)
    write_sequence(small, tmp_path, progress=False, right=False, depth=False, labels=False)
    assert not (tmp_path / "right").exists()
    with pytest.raises(DatasetError, match="already holds"):
        write_sequence(small, tmp_path, progress=False)
    write_sequence(small, tmp_path, progress=False, overwrite=True)
    assert (tmp_path / "right").is_dir()

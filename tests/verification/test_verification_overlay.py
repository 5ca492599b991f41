"""A burnt-in overlay (a dashcam's timestamp) on real frames: fixed to the camera, it must not
make two places one."""

from __future__ import annotations

import cv2
import numpy as np

from conftest import shared_path
from stablecues.config import merge
from stablecues.features import OrbExtractor
from stablecues.imageio import read_image
from stablecues.verification import Verifier, View, preset


def _stamp(img: np.ndarray) -> np.ndarray:
    out = img.copy()
    cv2.rectangle(out, (8, 8), (300, 70), 0, -1)
    cv2.putText(out, "2026-12-02 16:41:07", (14, 34), cv2.FONT_HERSHEY_SIMPLEX, 0.75, 255, 2)
    cv2.putText(out, "CAM 03  58 km/h", (14, 62), cv2.FONT_HERSHEY_SIMPLEX, 0.75, 255, 2)
    return out


def test_a_timestamp_overlay_does_not_make_two_places_one() -> None:
    camvid = shared_path("camvid")
    a = read_image(sorted((camvid / "train").glob("0001TP*.jpg"))[10], "grey")  # two drives
    b = read_image(sorted((camvid / "val").glob("0016E5*.jpg"))[40], "grey")
    ex = OrbExtractor()
    fundamental = merge(preset("default"), {"method": "fundamental"})  # no calibration here
    keep_all = merge(fundamental, {"static_px": None})
    plain = View(ex.extract(a)), View(ex.extract(b))
    assert not Verifier(keep_all).verify(*plain).accepted
    stamped = View(ex.extract(_stamp(a))), View(ex.extract(_stamp(b)))
    fooled = Verifier(keep_all).verify(*stamped)
    assert fooled.accepted and fooled.n_inliers > 100  # the overlay fits any fundamental matrix
    res = Verifier(fundamental).verify(*stamped)
    assert not res.accepted


def test_a_true_loop_with_the_overlay_is_still_found() -> None:
    pairs = shared_path("euroc", "loop_pairs")
    ex = OrbExtractor()
    q, c = (View(ex.extract(_stamp(read_image(pairs / f"left_img_{i}.png", "grey")))) for i in (1, 0))
    res = Verifier(merge(preset("default"), {"method": "fundamental"})).verify(q, c)
    assert res.accepted and res.n_inliers >= 40
    pq, pc = res.pixels_query, res.pixels_candidate
    assert pq is not None and pc is not None
    assert np.linalg.norm(pq - pc, axis=1).min() > 0.5  # no match of the stamp to itself is left
    with_stamp = Verifier(merge(preset("default"), {"method": "fundamental", "static_px": None})).verify(q, c)
    assert with_stamp.n_matches > res.n_matches + 100  # the stamp would have matched itself

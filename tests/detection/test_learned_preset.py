"""The ``learned`` preset end to end on a short real day -> night sequence (Gardens Point)."""

from __future__ import annotations

import math

import pytest

from conftest import shared_path
from stablecues.detection import LoopDetector, describe_preset, preset
from stablecues.errors import ConfigError
from stablecues.imageio import read_image
from stablecues.types import Frame


def test_learned_preset_settings() -> None:
    cfg = preset("learned")
    assert cfg.features.name == "xfeat" and cfg.verification is not None
    assert cfg.verification.matcher == "mnn"
    # every mutual match verified; of the 7 best islands the loop is the one with the most inliers x
    # its 10-frame sequence score, loops ranked by that product, under 20 refused
    v = cfg.verification
    assert (v.ratio, v.max_distance, v.min_fundamental_ratio) == (1.0, 256, 0.0)
    assert cfg.query.sequence == 10 and not cfg.query.sequence_rank and cfg.confidence == "sequence"
    assert cfg.query.sequence_choice and cfg.query.islands_verified == 7 and cfg.query.refine == 2
    assert cfg.min_confidence == 20.0
    assert cfg.query.vlad == 0.35 and cfg.query.vlad_codebook == "default"  # the VLAD vote
    assert "XFeat" in describe_preset("learned")
    with pytest.raises(ConfigError, match="lighterglue"):
        preset("default", {"verification": {"matcher": "lighterglue"}})  # ORB features
    glued = preset("learned", {"verification": {"matcher": "lighterglue"}}).verification
    assert glued is not None and glued.matcher == "lighterglue"


def test_learned_preset_closes_day_night_loops_on_real_frames() -> None:
    """Places 0-19 by day, then the same places by night: ORB's default accepts no loop there
    (bench_learned.py); the learned preset accepts loops, all of them within 8 places of the
    true one, and says which matcher and verifier decided."""
    gp = shared_path("gardens_point_dev")
    names = [gp / "day_right" / f"Image{k:03d}.jpg" for k in range(20)]
    names += [gp / "night_right" / f"Image{k:03d}.jpg" for k in range(20)]
    det = LoopDetector(preset("learned"))
    accepted = []
    for i, path in enumerate(names):
        d = det.process(Frame(index=i, name=path.name, timestamp=math.nan, image=read_image(path, "bgr")))
        assert d.n_features == 1000
        if d.accepted:
            assert d.verification is not None and d.verification.matcher == "mnn"
            assert d.extras()["verifier"] == "fundamental" and d.extras()["matcher"] == "mnn"
            accepted.append((i, d.candidate_frame))
    det.close()
    assert len(accepted) >= 5, accepted
    assert all(i >= 20 and abs((i - 20) - c) <= 8 for i, c in accepted), accepted

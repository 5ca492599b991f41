"""A procedural 3D town with loops: stereo, depth, semantic labels, exact poses and loop ground truth.

The town is a grid of blocks lined with textured facades, trees, poles, signs and fences, with
sidewalks, roads and sky; cars, cyclists and pedestrians change from one visit to the next. A
camera drives laps around a rectangle of blocks, revisiting streets in another lane, the other
way round, at other times of day. Every frame comes with the rectified right image, metric
depth, CamVid labels and its exact pose; the loop matrix follows from poses and visibility.

Typical use::

    from stablecues.synthetic import SyntheticTownConfig, SyntheticTown, write_sequence

    cfg = SyntheticTownConfig(frames=300, width=384, height=288, loops=2, seed=0)
    write_sequence(cfg, "town/")          # image-folder format, loops.npy included
    town = SyntheticTown(cfg)             # or render frames in memory
    frame = town.frame(0)                 # .image, .right, .depth, .labels, .pose
"""

from .config import SyntheticTownConfig
from .render import Intrinsics
from .scene import CAMVID_CLASSES, LANDMARK_CLASSES
from .sequence import SyntheticFrame, SyntheticTown, camera_rotation, generate, write_sequence
from .truth import LoopTruthConfig, Visibility, loop_truth

__all__ = [
    "CAMVID_CLASSES",
    "LANDMARK_CLASSES",
    "Intrinsics",
    "LoopTruthConfig",
    "SyntheticFrame",
    "SyntheticTown",
    "SyntheticTownConfig",
    "Visibility",
    "camera_rotation",
    "generate",
    "loop_truth",
    "write_sequence",
]

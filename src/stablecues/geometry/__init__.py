"""Cameras, calibration files, stereo rectification, 3D lifting of keypoints, triangles and PnP.

Frames and directions are stated in :mod:`.camera` (``X_b = R @ X_a + t`` for a transform from
a to b) and :mod:`.pose` (the loop's pose takes candidate-camera points to the query camera).
"""

from typing import TYPE_CHECKING

from .._lazy import lazy_names

if TYPE_CHECKING:
    from .calibration import (
        TUM_CAMERAS,
        load_calibration,
        load_euroc,
        load_euroc_stereo,
        load_kitti,
        load_orbslam,
        tum_calibration,
    )
    from .camera import Calibration, PinholeCamera, Rectification
    from .depth import DepthConfig, depth_to_metres, lift_depth, lift_map_points
    from .points import KINECT_DEPTH_COEFF, STEREO_DISPARITY_SIGMA, NoiseModel, Points3D
    from .pose import PnPConfig, PoseEstimate, estimate_pose_pnp, fundamental_ransac, rotation_angle_deg
    from .rectify import StereoRectifier, rectification_of
    from .stereo import StereoConfig, StereoLifter, stereo_disparities
    from .triangles import Triangle, TriangleCheck, TriangleConfig, check_triangles, side_sigma

__getattr__, __dir__ = lazy_names(
    __name__,
    {
        "calibration": (
            "TUM_CAMERAS",
            "load_calibration",
            "load_euroc",
            "load_euroc_stereo",
            "load_kitti",
            "load_orbslam",
            "tum_calibration",
        ),
        "camera": (
            "Calibration",
            "PinholeCamera",
            "Rectification",
        ),
        "depth": (
            "DepthConfig",
            "depth_to_metres",
            "lift_depth",
            "lift_map_points",
        ),
        "points": (
            "KINECT_DEPTH_COEFF",
            "STEREO_DISPARITY_SIGMA",
            "NoiseModel",
            "Points3D",
        ),
        "pose": (
            "PnPConfig",
            "PoseEstimate",
            "estimate_pose_pnp",
            "fundamental_ransac",
            "rotation_angle_deg",
        ),
        "rectify": (
            "StereoRectifier",
            "rectification_of",
        ),
        "stereo": (
            "StereoConfig",
            "StereoLifter",
            "stereo_disparities",
        ),
        "triangles": (
            "Triangle",
            "TriangleCheck",
            "TriangleConfig",
            "check_triangles",
            "side_sigma",
        ),
    },
)

__all__ = [
    "KINECT_DEPTH_COEFF",
    "STEREO_DISPARITY_SIGMA",
    "TUM_CAMERAS",
    "Calibration",
    "DepthConfig",
    "NoiseModel",
    "PinholeCamera",
    "PnPConfig",
    "Points3D",
    "PoseEstimate",
    "Rectification",
    "StereoConfig",
    "StereoLifter",
    "StereoRectifier",
    "Triangle",
    "TriangleCheck",
    "TriangleConfig",
    "check_triangles",
    "depth_to_metres",
    "estimate_pose_pnp",
    "fundamental_ransac",
    "lift_depth",
    "lift_map_points",
    "load_calibration",
    "load_euroc",
    "load_euroc_stereo",
    "load_kitti",
    "load_orbslam",
    "rectification_of",
    "rotation_angle_deg",
    "side_sigma",
    "stereo_disparities",
    "tum_calibration",
]

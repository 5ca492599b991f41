"""The commands of the command line: the module that implements each and its one-line summary
(nothing imported here, so that `stablecues --help` answers at once)."""

from __future__ import annotations

# command name -> (module of this package that implements it, its one-line summary). Only the
# command being run has its parser built (its module's ``add_parser``): the others' options pull
# in numpy, the detector or the features to describe their choices, and `stablecues --help` must
# answer at once. Each module's parser takes its summary from here (:func:`summary`).
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("demo", "run the whole system on built-in synthetic data"),
    "vocab": ("vocab", "train, convert or describe a vocabulary"),
    "segment": ("segment", "semantic segmentation: train, eval, export, image"),
    "verify": ("verify", "verify that two images show the same place (triangles, PnP or fundamental matrix)"),
    "run": ("run", "detect loops over a dataset and write a run directory"),
    "eval": ("evaluate", "evaluate a run directory against loop ground truth"),
    "results": ("results", "one table across evaluated runs"),
    "report": ("report", "static HTML report of evaluated runs"),
    "synth": ("synth",
              "write a synthetic town drive with revisits (stereo, depth, labels, poses, loop truth)"),
    "mav": ("mav", "drone flight logs: plots, EKF poses per camera frame, loop ground truth"),
    "info": ("info", "list a ROS bag's topics (and which a run would read), or summarise a dataset folder"),
    "sweep": ("sweep", "run a grid of datasets x presets as tasks on a Dask cluster, into one table"),
    "map": ("mapcmd", "check a map file (what it holds, what is damaged) or repair it"),
    "gt": ("gt", "loop ground truth from camera poses (a dataset's own, TUM, EuRoC or KITTI files)"),
    "ros2": ("ros2", "the loop detector as a live ROS 2 node over DDS (no ROS install); play a bag to it"),
}


def summary(command: str) -> str:
    """The one-line summary of ``command`` (its ``help`` in ``stablecues --help``)."""
    return COMMANDS[command][1]

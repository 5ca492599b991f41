"""Options shared by several commands (the parsers stay in each command's module)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..detection import DetectorConfig
    from ..features import ExtractorConfig
    from ..posetruth import LoopRule
    from ..vocabulary import Vocabulary


def add_extractor_options(
    parser: argparse.ArgumentParser, what: str = "per image", n_features: int | None = None
) -> None:
    """``--features NAME`` and ``--n-features N``, read back by :func:`extractor_from_args`.

    Args:
        parser: the command's parser.
        what: what the number counts, for the help text.
        n_features: this command's default number of features (None: the extractor's).
    """
    from ..features import DEFAULT_EXTRACTOR, extractor_names

    parser.add_argument("--features", default=DEFAULT_EXTRACTOR, metavar="NAME",
                        help=f"feature extractor: {' | '.join(extractor_names())} (default "
                             f"{DEFAULT_EXTRACTOR}); a number N means --n-features N")
    parser.add_argument("--n-features", type=int, default=n_features, metavar="N",
                        help=f"features {what} (default: {n_features or 'the extractor default, 1000'})")


def extractor_from_args(args: argparse.Namespace) -> ExtractorConfig:
    """The extractor settings that ``--features`` and ``--n-features`` ask for.

    ``--features 200`` (a number, the options' old form) still means 200 ORB features.
    """
    from ..errors import ConfigError
    from ..features import DEFAULT_EXTRACTOR, extractor_config

    name, n = str(args.features), args.n_features
    if name.isdigit():
        if n is not None:
            raise ConfigError(f"--features {name} is a number of features; with --n-features, "
                              "give the extractor's name to --features")
        name, n = DEFAULT_EXTRACTOR, int(name)
    return extractor_config(name) if n is None else extractor_config(name, n_features=n)


def presets_epilog() -> str:
    """The detector presets, one line each (``name  description``), for a parser's epilog
    (use ``formatter_class=argparse.RawDescriptionHelpFormatter`` to keep the lines)."""
    from ..detection.presets import DEFAULT_PRESET, describe_preset, preset_names

    names = preset_names()
    width = max(len(n) for n in names)
    lines = [f"  {n:<{width}}  {describe_preset(n)}" for n in names]
    return f"presets (--preset NAME, default {DEFAULT_PRESET!r}):\n" + "\n".join(lines)


def add_preset_option(parser: argparse.ArgumentParser) -> None:
    """``--preset NAME``: one of the detector presets (list them with :func:`presets_epilog`)."""
    from ..detection.presets import DEFAULT_PRESET, preset_names

    parser.add_argument("--preset", default=DEFAULT_PRESET, choices=preset_names(), metavar="NAME",
                        help=f"detector preset, one of those listed below (default {DEFAULT_PRESET})")


def add_vocabulary_option(parser: argparse.ArgumentParser) -> None:
    """``--vocab FILE``, read back by :func:`vocabulary_from_args`."""
    from ..vocabulary import DEFAULT_VOCABULARY

    parser.add_argument("--vocab", type=Path, metavar="FILE",
                        help="vocabulary file: the own binary format (.scv, as `stablecues vocab train` "
                             "writes) or DBoW2/ORB-SLAM text (e.g. ORBvoc.txt); its descriptors must be "
                             f"the features' (default: the shipped {DEFAULT_VOCABULARY}); or 'incremental': "
                             "words learned from the map's own frames, no training set (the same as "
                             "--set vocabulary=incremental; kept beside a map file as MAP.words)")


def incremental_chosen(args: argparse.Namespace) -> bool:
    """Whether ``--vocab incremental`` was given (not a file of that name: a path is a file)."""
    return args.vocab is not None and str(args.vocab) == "incremental" and not Path(args.vocab).is_file()


def vocabulary_from_args(args: argparse.Namespace) -> Vocabulary | None:
    """The vocabulary ``--vocab`` names, or None for the shipped one or an incremental one
    (``--vocab incremental``: the detector makes it from its configuration, see
    :func:`config_with_vocabulary`).

    Raises:
        VocabularyError: a missing, truncated or corrupt file.
    """
    if args.vocab is None or incremental_chosen(args):
        return None
    from ..vocabulary import load_vocabulary

    return load_vocabulary(args.vocab)


def config_with_vocabulary(config: DetectorConfig, args: argparse.Namespace) -> DetectorConfig:
    """``config`` with ``vocabulary = "incremental"`` when ``--vocab incremental`` was given."""
    if not incremental_chosen(args):
        return config
    import dataclasses

    return dataclasses.replace(config, vocabulary="incremental")


def add_progress_option(parser: argparse.ArgumentParser) -> None:
    """``--no-progress``."""
    parser.add_argument("--no-progress", action="store_true",
                        help="do not draw the progress bar (for logs, CI and pipes; the summary is "
                             "still printed)")


#: what --format takes (the dataset readers of stablecues.datasets)
FORMAT_HELP = "auto | folder | tum | kitti | euroc | fabmap | vprbench | rosbag (default auto)"

#: the folder format's layout, for the epilog of the commands that read datasets
FOLDER_LAYOUT = """\
folder layout (--format folder; everything but the images optional):
  DIR/images/ (or frames/, color/, or DIR)     the images, in name order (digit runs as numbers)
  DIR/right/  DIR/depth/  DIR/labels/          the same names: right image, 16-bit depth, class ids
  DIR/times.txt  DIR/poses.txt                 one timestamp (s) / TUM pose (t x y z qx qy qz qw) a line
  DIR/calib.yaml                               ORB-SLAM settings (Camera.fx, ..., Camera.bf,
                                               DepthMapFactor); --calib FILE takes another
  DIR/loops.npy                                loop ground truth, N x N (beside an images/,
                                               frames/ or color/ folder also gt.npy or gt.png)
"""


#: the ROS-bag options and their defaults (an option off its default is "given")
_ROSBAG_DEFAULTS: dict[str, object] = {
    "topic": None, "right_topic": None, "mono": False, "stamps": "auto", "max_stereo_difference": 0.002,
}


def add_rosbag_options(parser: argparse.ArgumentParser) -> None:
    """--topic, --right-topic, --mono, --stamps, --max-stereo-difference (ROS bags only)."""
    parser.add_argument("--topic", help="ROS bag: the image topic (left camera) instead of the one found")
    parser.add_argument("--right-topic", help="ROS bag: the right camera's image topic")
    parser.add_argument("--mono", action="store_true", help="ROS bag: left images only, no stereo pair")
    parser.add_argument(
        "--stamps", choices=("auto", "header", "bag"), default=_ROSBAG_DEFAULTS["stamps"],
        help="ROS bag: header stamps, bag time, or header stamps unless one is zero (default)",
    )
    parser.add_argument(
        "--max-stereo-difference", type=float, default=_ROSBAG_DEFAULTS["max_stereo_difference"], metavar="S",
        help="ROS bag: largest gap between a left and its right image, seconds (default 0.002)",
    )


def rosbag_options(args: argparse.Namespace) -> dict[str, object]:
    """The keyword arguments of the ROS-bag reader from :func:`add_rosbag_options`' options."""
    return {"topic": args.topic, "right_topic": args.right_topic, "stereo": not args.mono,
            "stamps": args.stamps, "max_stereo_difference": args.max_stereo_difference}


def is_rosbag(args: argparse.Namespace) -> bool:
    """Whether ``args.dataset`` is read as a ROS bag (``--format rosbag``, or auto and a bag).

    Raises:
        ConfigError: a ROS-bag option given for a dataset that is not read as a bag.
    """
    from ..datasets.rosbag import is_bag
    from ..errors import ConfigError

    bag = bool(args.format == "rosbag" or (args.format == "auto" and is_bag(args.dataset)))
    given = [f"--{name.replace('_', '-')}" for name, default in _ROSBAG_DEFAULTS.items()
             if getattr(args, name) != default]
    if given and not bag:
        raise ConfigError(f"{args.dataset}: {', '.join(given)}: for ROS bags only, and this dataset is "
                          f"read as {args.format if args.format != 'auto' else 'a folder'}")
    return bag



def add_pose_truth_options(parser: argparse.ArgumentParser) -> None:
    """The loop rule of ground truth made from poses (:class:`stablecues.posetruth.LoopRule`)
    and how poses meet frames; read back by :func:`loop_rule_from_args`."""
    g = parser.add_argument_group("loop ground truth from poses")
    g.add_argument("--max-distance", type=float, metavar="M",
                   help="a loop: positions at most M apart (the trajectory's unit, metres); required")
    g.add_argument("--max-angle", default="30", metavar="DEG",
                   help="... and orientations at most DEG degrees apart (the relative rotation's angle; "
                        "default 30; 'any' for position only)")
    g.add_argument("--min-gap-s", type=float, metavar="S",
                   help="... and at least S seconds apart (default 20 when the frames have times)")
    g.add_argument("--min-gap-frames", type=int, default=0, metavar="N",
                   help="... and at least N frames apart (default 0)")
    g.add_argument("--max-dt", type=float, default=0.02, metavar="S",
                   help="a frame takes the trajectory's pose nearest in time within S seconds (default 0.02)")


def loop_rule_from_args(args: argparse.Namespace, option: str) -> LoopRule:
    """The loop rule of :func:`add_pose_truth_options`' options (``option`` names the option that
    asked for ground truth from poses, for the message when --max-distance is missing)."""
    from ..errors import ConfigError
    from ..posetruth import LoopRule

    if args.max_distance is None:
        raise ConfigError(f"{option} needs --max-distance M: how close two positions of a loop are "
                          "(e.g. 0.5 for a room, 10 for a street)")
    angle: float | None = None
    if str(args.max_angle).strip().lower() not in ("any", "none"):
        try:
            angle = float(args.max_angle)
        except ValueError:
            raise ConfigError(f"--max-angle {args.max_angle!r}: expected degrees or 'any'") from None
    return LoopRule(args.max_distance, angle, args.min_gap_s, args.min_gap_frames)

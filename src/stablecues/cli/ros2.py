"""``stablecues ros2``: the loop-closure node on a live ROS 2 graph (over DDS, no ROS install);
``stablecues ros2 play BAG`` replays a bag's camera topics; ``stablecues ros2 echo`` prints the
node's decisions."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from .commands import summary
from .options import add_preset_option, add_vocabulary_option, presets_epilog, vocabulary_from_args

DESCRIPTION = """\
Run the loop detector as a ROS 2 node: subscribe to a camera (sensor_msgs/Image or
CompressedImage, mono or a stereo pair matched by stamp, CameraInfo beside it as calibration,
optionally depth) and publish a decision per frame on PREFIX/loop_closure
(stablecues_msgs/msg/LoopClosure), PREFIX/loop_closure_json (std_msgs/msg/String JSON) and, with
--pose, PREFIX/loop_markers (visualization_msgs/msg/MarkerArray loop edges for RViz). It speaks
DDS with Cyclone DDS (the ros2 extra): ROS_DOMAIN_ID picks the domain, CYCLONEDDS_URI the
network configuration (--loopback: the shipped loopback-only one)."""


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "ros2",
        help=summary("ros2"),
        description=DESCRIPTION,
        epilog=presets_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _node_options(p)
    sub = p.add_subparsers(dest="ros2_action", metavar="{play,echo}")
    play = sub.add_parser(
        "play",
        help="publish a ROS 2 bag's image and CameraInfo topics at their recorded rate",
        description="Publish a ROS 2 bag's sensor_msgs/Image, CompressedImage and "
        "CameraInfo messages, their bytes as recorded, at the recorded rate.",
    )
    play.add_argument("bag", type=Path, help="ROS 2 bag folder (sqlite3 or MCAP)")
    play.add_argument("--rate", type=float, default=1.0, help="speed factor (default 1: as recorded)")
    play.add_argument(
        "--topic",
        action="append",
        default=[],
        metavar="TOPIC",
        help="a topic to replay (repeatable; default: every image and CameraInfo topic)",
    )
    play.add_argument(
        "--qos",
        choices=("sensor", "reliable"),
        default="sensor",
        help="QoS of the image topics (default sensor: best effort, keep last 5)",
    )
    play.add_argument("--start", type=int, default=0, help="first frame (message of the first image topic)")
    play.add_argument("--frames", type=int, help="frames to publish (default: all)")
    play.add_argument(
        "--wait-subscribers",
        type=int,
        default=0,
        metavar="N",
        help="wait until every topic has N subscribers before publishing",
    )
    play.add_argument(
        "--wait-timeout", type=float, default=10.0, metavar="S", help="... for at most S seconds"
    )
    play.add_argument(
        "--exact-types",
        action="store_true",
        help="announce the types' full descriptions (for a node run with --exact-types)",
    )
    play.add_argument(
        "--published",
        type=Path,
        metavar="FILE",
        help="write each image's topic, stamp and publication time (ns) to this JSON file",
    )
    _common(play)
    echo = sub.add_parser(
        "echo",
        help="print the node's decisions as JSON lines",
        description="Subscribe to the node's LoopClosure topic and print each decision as one line of JSON.",
    )
    echo.add_argument("--topic", default="/stablecues/loop_closure", help="LoopClosure topic")
    echo.add_argument("--count", type=int, help="exit after this many decisions")
    echo.add_argument("--timeout", type=float, metavar="S", help="exit after S seconds without a decision")
    echo.add_argument("--accepted", action="store_true", help="print accepted loops only")
    echo.add_argument(
        "--raw",
        type=Path,
        metavar="FILE",
        help="also write each payload as received (CDR, hex) to this file, one a line",
    )
    _common(echo)
    return p


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--loopback",
        action="store_true",
        help="use the shipped Cyclone DDS configuration: loopback interface only, no multicast",
    )
    p.add_argument("--domain", help="DDS domain id (default: ROS_DOMAIN_ID, else 0)")


def _node_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("topics")
    g.add_argument(
        "--image",
        default="/camera/image_raw",
        help="camera topic (CompressedImage when it ends in /compressed; default /camera/image_raw)",
    )
    g.add_argument("--right", help="right camera topic of a stereo pair")
    g.add_argument(
        "--camera-info",
        default="auto",
        help="CameraInfo topic of the camera (default: the one beside --image); 'none': none",
    )
    g.add_argument("--right-camera-info", default="auto", help="the right camera's (default: beside --right)")
    g.add_argument("--depth", help="depth image topic registered to --image (16UC1 mm or 32FC1 m)")
    g.add_argument("--pose", help="robot pose topic, for the RViz loop edges")
    g.add_argument(
        "--pose-type",
        choices=("pose", "odometry"),
        default="pose",
        help="geometry_msgs/PoseStamped (pose, default) or nav_msgs/Odometry",
    )
    g.add_argument("--prefix", default="/stablecues", help="namespace of the outputs (default /stablecues)")
    g.add_argument(
        "--rectified",
        action="store_true",
        default=None,
        help="the images are rectified (default: when the topic is an image_rect topic)",
    )
    g = p.add_argument_group("QoS and pacing")
    g.add_argument(
        "--qos",
        choices=("sensor", "reliable"),
        default="sensor",
        help="QoS of the camera topics (default sensor: best effort, keep last 5; outputs are reliable)",
    )
    g.add_argument(
        "--no-skip",
        action="store_true",
        help="decide every frame, queueing them (default: keep the newest when the detector is "
        "behind, counting the others as skipped)",
    )
    g.add_argument(
        "--max-stereo-difference",
        type=float,
        default=0.002,
        metavar="S",
        help="largest stamp gap of a stereo pair (default 0.002 s)",
    )
    g.add_argument(
        "--exact-types",
        action="store_true",
        help="announce the camera types' full XTypes descriptions (for DDS peers that send theirs; "
        "malformed payloads are then dropped by Cyclone DDS, unlogged)",
    )
    g = p.add_argument_group("detector")
    add_preset_option(g)  # type: ignore[arg-type]
    add_vocabulary_option(g)  # type: ignore[arg-type]
    g.add_argument(
        "--map",
        type=Path,
        help="map file (SQLite), reopened and continued when it exists (default: in memory)",
    )
    g.add_argument(
        "--new-session",
        action="store_true",
        help="store this run's frames as a new session of --map (another day, another robot run): "
        "a loop to an earlier session's place is taken before a view of this run",
    )
    g.add_argument("--calib", metavar="FILE", help="calibration file, used when no CameraInfo is read")
    g.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a detector setting (as `stablecues run --set`)",
    )
    g = p.add_argument_group("running")
    g.add_argument("--max-frames", type=int, help="exit after deciding this many frames")
    g.add_argument(
        "--exit-after-idle",
        type=float,
        metavar="S",
        help="exit after S seconds without a frame (once one came)",
    )
    g.add_argument(
        "--print", dest="print_decisions", action="store_true", help="print each decision as one line of JSON"
    )
    g.add_argument("--summary", type=Path, metavar="FILE", help="write the summary at exit as JSON")
    _common(p)


def _domain(args: argparse.Namespace) -> int:
    from ..ros2.dds import domain_id, use_loopback

    if args.loopback:
        use_loopback()
    return domain_id(args.domain)


def _on_signals(stop: threading.Event) -> None:
    def handler(signum: int, frame: Any) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)


def run(args: argparse.Namespace) -> int:
    if args.ros2_action == "play":
        return _play(args)
    if args.ros2_action == "echo":
        return _echo(args)
    return _node(args)


def _node(args: argparse.Namespace) -> int:
    from ..detection import LoopDetector, preset
    from ..errors import ConfigError
    from ..ros2.dds import cyclonedds
    from ..ros2.node import LoopClosureNode, NodeConfig
    from .options import config_with_vocabulary
    from .run import parse_overrides

    cyclonedds()  # a missing extra is said before the detector loads
    did = _domain(args)
    if args.map is not None and not args.map.parent.is_dir():
        raise ConfigError(f"--map {args.map}: its folder does not exist")
    if args.new_session and args.map is None:
        raise ConfigError("--new-session: needs --map (an in-memory map holds one session)")
    config = NodeConfig(
        image=args.image,
        right=args.right,
        camera_info=None if args.camera_info == "none" else args.camera_info,
        right_camera_info=None if args.right_camera_info == "none" else args.right_camera_info,
        depth=args.depth,
        pose=args.pose,
        pose_type=args.pose_type,
        prefix=args.prefix,
        input_qos=args.qos,
        skip=not args.no_skip,
        max_stereo_difference=args.max_stereo_difference,
        rectified=args.rectified,
        exact_types=args.exact_types,
        domain=did,
    )
    calibration = None
    if args.calib is not None:
        from ..geometry import load_calibration

        calibration = load_calibration(args.calib)
        if args.camera_info == "auto":
            config = NodeConfig(**{**config.__dict__, "camera_info": None, "right_camera_info": None})
    detector_config = config_with_vocabulary(preset(args.preset, parse_overrides(args.set)), args)
    detector = LoopDetector(
        detector_config, vocabulary=vocabulary_from_args(args), database=args.map, calibration=calibration
    )
    if args.new_session and len(detector.db):
        detector.db.new_session()
    stop = threading.Event()
    _on_signals(stop)
    try:
        node = LoopClosureNode(config, detector, calibration)

        def on_stop() -> None:
            stop.wait()
            node.stop()

        watcher = threading.Thread(target=on_stop, daemon=True)
        watcher.start()
        where = (f"map {args.map} ({len(detector.db)} frames, session {detector.db.session})" if args.map
                 else "an in-memory map")
        print(
            f"stablecues ros2: {args.preset} on {config.image}"
            + (f" + {config.right}" if config.right else "")
            + f", domain {did}, {where}; "
            f"decisions on {config.prefix.rstrip('/')}/loop_closure",
            file=sys.stderr,
            flush=True,
        )
        printer = (lambda d: print(json.dumps(d), flush=True)) if args.print_decisions else None
        result = node.run(max_frames=args.max_frames, idle_timeout=args.exit_after_idle, on_decision=printer)
    finally:
        detector.close(hint=False)
    print(f"stablecues ros2: {result.line()}", file=sys.stderr, flush=True)
    if args.summary is not None:
        args.summary.write_text(json.dumps(result.to_dict(), indent=1) + "\n")
    return 0


def _play(args: argparse.Namespace) -> int:
    from ..ros2.dds import cyclonedds
    from ..ros2.play import play

    cyclonedds()
    did = _domain(args)
    stop = threading.Event()
    _on_signals(stop)
    result = play(
        args.bag,
        topics=args.topic or None,
        rate=args.rate,
        domain=did,
        image_qos=args.qos,
        wait_for_subscribers=args.wait_subscribers,
        wait_timeout=args.wait_timeout,
        start=args.start,
        count=args.frames,
        stop=stop.is_set,
        description="exact" if args.exact_types else "opaque",
    )
    counts = ", ".join(f"{t} {n}" for t, n in sorted(result.messages.items()))
    print(f"stablecues ros2 play: published {counts} in {result.seconds:.1f} s", file=sys.stderr, flush=True)
    if args.published is not None:
        args.published.write_text(json.dumps([list(p) for p in result.published_ns]) + "\n")
    return 0


def _echo(args: argparse.Namespace) -> int:
    from ..ros2.dds import cyclonedds
    from ..ros2.play import listen

    cyclonedds()
    did = _domain(args)
    stop = threading.Event()
    _on_signals(stop)

    def show(d: dict[str, Any]) -> None:
        if d["accepted"] or not args.accepted:
            print(json.dumps(d), flush=True)

    raw_file = args.raw.open("w") if args.raw is not None else None

    def keep(payload: bytes) -> None:
        if raw_file is not None:
            raw_file.write(payload.hex() + "\n")
            raw_file.flush()

    try:
        n = listen(
            show,
            topic=args.topic,
            domain=did,
            count=args.count,
            timeout=args.timeout,
            stop=stop.is_set,
            raw=keep,
        )
    finally:
        if raw_file is not None:
            raw_file.close()
    logging.getLogger(__name__).info("%d decisions received", n)
    return 0

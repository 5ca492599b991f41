"""``stablecues verify``: geometric verification of two images (A = query, B = candidate)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from .commands import summary
from .options import add_extractor_options, extractor_from_args

if TYPE_CHECKING:
    from ..geometry import Calibration


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "verify",
        help=summary("verify"),
        description=(
            "Verify image A (the query) against image B (the candidate). With stereo or depth, "
            "keypoints are lifted to 3D and the paper's triangle check runs, then PnP gives the "
            "relative pose, which takes points from B's camera to A's camera. Without 3D, the "
            "fundamental-matrix check (DLoopDetector) decides."
        ),
    )
    p.add_argument("image_a", type=Path, help="query image (left image of a stereo pair)")
    p.add_argument("image_b", type=Path, help="candidate image")
    p.add_argument(
        "--calib",
        help="calibration: EuRoC sensor.yaml (left), KITTI calib.txt, ORB-SLAM settings yaml, or "
             "fr1/fr2/fr3; without it the images are monocular, the focal length guessed from A's size "
             "(1.2 x its larger side), and the fundamental-matrix check decides",
    )
    p.add_argument("--calib-right", type=Path, help="right camera's EuRoC sensor.yaml, when not found beside")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--right-a", type=Path, help="right image of A (stereo)")
    g.add_argument("--depth-a", type=Path, help="depth image of A (raw units, scale from the calibration)")
    p.add_argument("--right-b", type=Path, help="right image of B (stereo)")
    p.add_argument("--depth-b", type=Path, help="depth image of B")
    p.add_argument("--depth-scale", type=float, help="depth units per metre (overrides the calibration)")
    p.add_argument(
        "--method", choices=("triangles", "pnp", "fundamental"), help="verifier (default triangles)"
    )
    p.add_argument("--preset", default="default",
                   help="settings preset: default, paper, dloop, pnp, learned (for learned features: "
                        "mutual nearest neighbours, a loose ratio)")
    p.add_argument("--matcher", choices=("ratio", "mnn", "lighterglue"),
                   help="ratio: Lowe's ratio test (DBoW2); mnn: mutual nearest neighbours, brute force; "
                        "lighterglue: XFeat's learned matcher (with --features xfeat)")
    p.add_argument("--tolerance", choices=("noise", "relative"), help="triangle side tolerance")
    p.add_argument("--triangles", type=int, help="number of triangles T")
    p.add_argument("--acceptance", choices=("all", "majority", "at_least"), help="triangle acceptance rule")
    p.add_argument("--min-agree", type=int, help="agreeing triangles needed with --acceptance at_least")
    add_extractor_options(p, "per image", n_features=2000)
    p.add_argument(
        "--no-vocabulary", action="store_true", help="brute-force matching instead of the direct index"
    )
    p.add_argument("--plot", type=Path, help="write a match picture (PNG)")
    p.add_argument("--json", type=Path, help="write the result as JSON")
    return p


def check_image_size(path: Path | None, size: tuple[int, int] | None, source: str) -> None:
    """Raise unless the image file ``path`` is ``size`` (width, height), when both are known.

    Raises:
        ImageError: naming the file, the size the calibration says and the size found.
    """
    if path is None or size is None:
        return
    from ..errors import ImageError
    from ..imageio import header_size, read_image

    found = None
    if Path(path).is_file():
        with Path(path).open("rb") as fh:
            found = header_size(fh.read(65536))
    if found is None:
        image = read_image(path, "unchanged")
        found = (image.shape[1], image.shape[0])
    if tuple(found) != tuple(size):
        raise ImageError(
            f"{path}: expected a {size[0]}x{size[1]} image (the size {source or 'the calibration'} gives), "
            f"found {found[0]}x{found[1]}"
        )


def _calibration(args: argparse.Namespace) -> Calibration:
    """The calibration the options name, or a monocular one guessed from image A's size."""
    from ..errors import InputError
    from ..geometry import Calibration, load_calibration, load_euroc_stereo
    from ..geometry.twoview import guess_camera
    from ..imageio import read_image

    if args.calib is None:
        if args.calib_right is not None or args.right_a is not None or args.depth_a is not None:
            raise InputError("stereo and depth images need a calibration: give --calib")
        h, w = read_image(args.image_a, "grey").shape[:2]
        return Calibration(left=guess_camera(w, h), source=f"none (focal guessed from {args.image_a.name})")
    if args.calib_right:
        return load_euroc_stereo(args.calib, args.calib_right)
    return load_calibration(args.calib)


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from ..config import to_dict
    from ..detection.pair import ImagePairVerifier
    from ..errors import InputError
    from ..geometry import rotation_angle_deg
    from ..outputs import check_output, output_file, write_output
    from ..verification import preset

    for path, what in ((args.json, "verification record"), (args.plot, "plot")):
        if path:
            check_output(path, what, make_folder=True)
    if (args.right_a is None) != (args.right_b is None):
        raise InputError("give --right-a and --right-b together")
    if (args.depth_a is None) != (args.depth_b is None):
        raise InputError("give --depth-a and --depth-b together")
    if args.right_b is not None and args.depth_b is not None:
        raise InputError("give right images or depth images, not both")

    calib = _calibration(args)
    if args.depth_scale is not None:
        calib = dataclasses.replace(calib, depth_scale=args.depth_scale)
    right_size = calib.right.image_size if calib.right is not None else None
    for path, size in ((args.image_a, calib.left.image_size), (args.image_b, calib.left.image_size),
                       (args.right_a, right_size), (args.right_b, right_size),
                       (args.depth_a, calib.left.image_size), (args.depth_b, calib.left.image_size)):
        check_image_size(path, size, calib.source)
    overrides = {
        key: value
        for key, value in (
            ("method", args.method),
            ("matcher", args.matcher),
            ("tolerance", args.tolerance),
            ("n_triangles", args.triangles),
            ("acceptance", args.acceptance),
            ("min_agree", args.min_agree),
        )
        if value is not None
    }
    config = preset(args.preset, **overrides)
    features = extractor_from_args(args)
    pipeline = ImagePairVerifier(calib, config, features=features, use_vocabulary=not args.no_vocabulary)
    out = pipeline.verify(
        args.image_a,
        args.image_b,
        right_a=args.right_a,
        right_b=args.right_b,
        depth_a=args.depth_a,
        depth_b=args.depth_b,
    )
    res = out.verification

    decision = "ACCEPTED" if res.accepted else "REJECTED"
    fallback = " (fallback: no 3D points)" if res.fallback else ""
    why = "" if res.accepted else f": {res.status.value}"  # "accepted by ...: accepted" said nothing
    print(f"decision:   {decision} by {res.method.value}{fallback}{why} (matcher {res.matcher})")
    print(f"reason:     {res.reason}")
    print(f"matches:    {res.n_matches}   inliers: {res.n_inliers}")
    if res.triangles:
        print(f"triangles:  {res.n_triangles_agree} of {len(res.triangles)} agree")
    if res.rotation is not None and res.translation is not None:
        t = res.translation
        norm = float((t**2).sum()) ** 0.5
        print(
            f"pose B->A:  t = [{t[0]:+.3f} {t[1]:+.3f} {t[2]:+.3f}] m (|t| = {norm:.3f} m), "
            f"rotation {rotation_angle_deg(res.rotation):.2f} deg, reprojection rmse {res.rmse_px:.2f} px"
        )
    timing = ", ".join(f"{k} {v:.1f}" for k, v in res.timings.items())
    print(f"time (ms):  {timing}")

    if args.json:
        record = {
            "image_a": str(args.image_a),
            "image_b": str(args.image_b),
            "calibration": calib.source,
            "config": to_dict(config),
            "features": to_dict(features),
            "result": res.to_dict(),
        }
        write_output(args.json, json.dumps(record, indent=1), "verification record")
        print(f"json:       {args.json}")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from ..verification.plot import plot_verification

        h, w = out.query.image.shape[:2]
        fig, ax = plt.subplots(figsize=(min(18.0, 2 * w / 100 + 1.5), h / 100 + 0.8), dpi=110)
        plot_verification(
            ax,
            out.query.image,
            out.candidate.image,
            res,
        )
        with output_file(args.plot, "plot") as tmp:
            fig.savefig(tmp, bbox_inches="tight")
        plt.close(fig)
        print(f"plot:       {args.plot}")
    return 0

"""The command line of ``vlocnetpp extract BAG OUT`` (:mod:`.extract` does the work): flags, their parsing and checks
(``UserError`` naming the flag), and :func:`run`."""

from __future__ import annotations

import argparse
import math

import numpy as np

from vlocnetpp_core.bag.extract import extract
from vlocnetpp_core.bag.extract_plan import Selection
from vlocnetpp_core.bag.extract_scan import DEFAULT_DEPTH_TOLERANCE_S, DEFAULT_MAX_POSE_GAP_S, ExtractOptions
from vlocnetpp_core.bag.topics import DEFAULT_MAX_GAP_S, DEPTH_TOPIC, GROUND_TRUTH_TOPIC
from vlocnetpp_core.camera.extrinsics import CameraExtrinsics
from vlocnetpp_core.errors import UserError


def parse_extrinsics(text: str) -> tuple[np.ndarray, np.ndarray]:
    """``"X,Y,Z,QW,QX,QY,QZ"`` -> ``(t (3,), q (4,) (w, x, y, z), w >= 0)``: the pose of the camera (optical
    frame) in the robot frame, ``T_robot,camera`` (checked as the node's ``camera_extrinsics``)."""
    ext = CameraExtrinsics.from_text(text, "--camera-extrinsics")
    return ext.t, ext.q


def parse_ranges(text: str | None) -> tuple[tuple[float, float], ...]:
    """``"A:B[,C:D...]"`` (seconds after the first image; an empty A is 0, an empty B the end) -> ``((a, b), ...)``."""
    if not text:
        return ()
    out = []
    for part in text.split(","):
        a, sep, b = part.partition(":")
        try:
            lo, hi = float(a) if a.strip() else 0.0, float(b) if b.strip() else math.inf
        except ValueError:
            lo = hi = math.nan
        if not sep or not (lo < hi) or math.isnan(lo):
            raise UserError(f"--test-ranges: expected A:B[,C:D...] seconds with A < B, got {part!r}")
        out.append((lo, hi))
    return tuple(out)


def parse_min_motion(text: str | None) -> tuple[float, float | None]:
    """``"METRES[,DEGREES]"`` -> ``(metres, degrees or None)``."""
    if not text:
        return 0.0, None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) not in (1, 2) or not all(math.isfinite(x) for x in v) or v[0] < 0 or (len(v) == 2 and v[1] <= 0):
        raise UserError(f"--min-motion: expected METRES[,DEGREES] (metres >= 0, degrees > 0), got {text!r}")
    return v[0], (v[1] if len(v) == 2 else None)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bag", metavar="BAG", help="input ROS 2 bag: .mcap or .db3 file, or a rosbag2 folder")
    p.add_argument(
        "out", metavar="OUT", help="output dataset folder (DeepLoc layout: data-info / train --data read it)"
    )
    p.add_argument(
        "--image-topic",
        metavar="TOPIC",
        help="camera topic, Image or CompressedImage (default /camera/image_raw, "
        "else .../compressed, else the only one)",
    )
    p.add_argument(
        "--camera-info-topic",
        metavar="TOPIC",
        help="CameraInfo topic (default <image namespace>/camera_info, else /camera/camera_info)",
    )
    p.add_argument(
        "--intrinsics", metavar="FX,FY,CX,CY", help="intrinsics at the image size instead of a camera info topic"
    )
    p.add_argument(
        "--depth-topic",
        metavar="TOPIC",
        help=f"registered depth, Image 32FC1 metres or 16UC1 mm (default {DEPTH_TOPIC} when present)",
    )
    p.add_argument("--no-depth", action="store_true", help="write no depth even if the bag has the default depth topic")
    src = p.add_mutually_exclusive_group()
    src.add_argument(
        "--pose-topic",
        metavar="TOPIC",
        help=f"Odometry, PoseStamped or PoseWithCovarianceStamped topic (default {GROUND_TRUTH_TOPIC})",
    )
    src.add_argument(
        "--tf", nargs=2, metavar=("PARENT", "CHILD"), help="compose /tf and /tf_static from PARENT (e.g. map) to CHILD"
    )
    p.add_argument(
        "--camera-extrinsics",
        metavar="X,Y,Z,QW,QX,QY,QZ",
        help="pose of the camera optical frame in CHILD (or the pose topic's robot frame): "
        "T_child,camera (default identity)",
    )
    p.add_argument(
        "--max-pose-gap",
        type=float,
        default=DEFAULT_MAX_POSE_GAP_S,
        metavar="S",
        help=f"skip images between pose samples more than S seconds apart (default {DEFAULT_MAX_POSE_GAP_S:g})",
    )
    p.add_argument(
        "--depth-tolerance",
        type=float,
        default=DEFAULT_DEPTH_TOLERANCE_S,
        metavar="S",
        help=f"use the depth image nearest in stamp if within S seconds (default {DEFAULT_DEPTH_TOLERANCE_S:g})",
    )
    p.add_argument(
        "--max-gap-s",
        type=float,
        default=DEFAULT_MAX_GAP_S,
        metavar="S",
        help=f"a gap between usable images longer than S seconds starts a new sequence (default {DEFAULT_MAX_GAP_S:g})",
    )
    p.add_argument(
        "--stride", type=int, default=1, metavar="N", help="keep every Nth usable image of a sequence (default 1)"
    )
    p.add_argument(
        "--min-motion",
        metavar="M[,DEG]",
        help="keep an image only when it moved M metres (or DEG degrees) from the last kept one",
    )
    p.add_argument(
        "--test-ranges",
        metavar="A:B[,C:D...]",
        help="seconds after the first image that go to the test split (default: all train)",
    )
    p.add_argument(
        "--force", action="store_true", help="replace OUT if it exists (only once the new dataset is complete)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def options_from_args(args: argparse.Namespace) -> ExtractOptions:
    """:class:`ExtractOptions` from parsed flags, checked (``UserError`` on a bad value)."""
    for name in ("max_pose_gap", "depth_tolerance", "max_gap_s"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value >= 0):
            raise UserError(f"--{name.replace('_', '-')} must be a number of seconds >= 0, got {value}")
    if args.stride < 1:
        raise UserError(f"--stride must be >= 1, got {args.stride}")
    metres, degrees = parse_min_motion(args.min_motion)
    selection = Selection(parse_ranges(args.test_ranges), args.max_gap_s, args.stride, metres, degrees)
    return ExtractOptions(
        image_topic=args.image_topic,
        camera_info_topic=args.camera_info_topic,
        intrinsics=args.intrinsics,
        depth_topic=args.depth_topic,
        no_depth=args.no_depth,
        pose_topic=args.pose_topic,
        tf=tuple(args.tf) if args.tf else None,
        camera_extrinsics=parse_extrinsics(args.camera_extrinsics) if args.camera_extrinsics else None,
        max_pose_gap_s=args.max_pose_gap,
        depth_tolerance_s=args.depth_tolerance,
        selection=selection,
    )


def run(args: argparse.Namespace) -> int:
    if args.no_depth and args.depth_topic:
        raise UserError("--no-depth and --depth-topic contradict each other")
    summary = extract(args.bag, args.out, options_from_args(args), force=args.force, progress=not args.no_progress)
    print(summary.format())
    return 0

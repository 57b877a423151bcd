"""``vlocnetpp map``: build and inspect keyframe maps for the refinement (:mod:`vlocnetpp_core.mapping`).

* ``vlocnetpp map build OUT.npz --data DIR [--data DIR ...]``: the map of the datasets' ``--split`` (default
  ``train``: the images a model was trained on); or ``--scene NAME --seed S --loops N --frames-per-loop F``: the map
  of the train split ``vlocnetpp synth`` would render with those arguments, rendering only its keyframes (the same
  map, without the dataset). Refuses an existing OUT without ``--force``, writes it atomically.
* ``vlocnetpp map info MAP.npz``: keyframes, points and where they came from.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from vlocnetpp_core.data.formats import FORMATS
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.mapping.build import ANGLE_DEG, SPACING_M
from vlocnetpp_core.outputs import check_writable, refuse_existing
from vlocnetpp_core.synth.cli import parse_size


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    b = sub.add_parser(
        "build",
        help="build a map from datasets with poses (and depth, else triangulated)",
        description="Build a keyframe map (keyframes, SIFT features and their 3D points) of datasets with known poses.",
    )
    b.add_argument("out", metavar="OUT", help="map file to write (.npz)")
    what = b.add_mutually_exclusive_group(required=True)
    what.add_argument(
        "--data", action="append", metavar="DIR", help="dataset folder (DeepLoc layout or 7-Scenes); repeat for several"
    )
    what.add_argument(
        "--scene",
        metavar="NAME",
        help="synthetic scene (as 'vlocnetpp synth --scene'): render only the keyframes of its train visits",
    )
    b.add_argument("--format", choices=FORMATS, default=None, help="dataset format (default: detected from the layout)")
    b.add_argument(
        "--split",
        default="train",
        help="split of --data to build the map of (default: train, the model's training images)",
    )
    b.add_argument(
        "--seed", type=int, default=0, help="with --scene: the visits' seed, as 'vlocnetpp synth --seed' (default 0)"
    )
    b.add_argument(
        "--loops", type=int, default=4, help="with --scene: train visits, as 'vlocnetpp synth --loops' (default 4)"
    )
    b.add_argument(
        "--frames-per-loop", type=int, default=175, metavar="F", help="with --scene: as 'vlocnetpp synth' (default 175)"
    )
    b.add_argument(
        "--size",
        type=parse_size,
        default=(320, 180),
        metavar="WxH",
        help="with --scene: image size, as 'vlocnetpp synth' (default 320x180)",
    )
    b.add_argument(
        "--lane-wander", type=float, default=0.0, metavar="M", help="with --scene: as 'vlocnetpp synth' (default 0)"
    )
    b.add_argument(
        "--spacing",
        type=float,
        default=SPACING_M,
        metavar="M",
        help=f"a new keyframe every M metres along each sequence (default {SPACING_M:g}, the shipped map's)",
    )
    b.add_argument(
        "--angle",
        type=float,
        default=ANGLE_DEG,
        metavar="DEG",
        help=f"... or every DEG degrees of turn (default {ANGLE_DEG:g})",
    )
    b.add_argument(
        "--max-features", type=int, default=1500, metavar="N", help="SIFT keypoints per keyframe at most (default 1500)"
    )
    b.add_argument(
        "--workers",
        type=int,
        default=0,
        metavar="N",
        help="processes (default 0: one per core); the map is the same for any N",
    )
    b.add_argument("--force", action="store_true", help="replace OUT if it exists (only once the new map is complete)")
    b.add_argument("--no-progress", action="store_true", help="no progress bar")
    i = sub.add_parser("info", help="summarise a map file", description="Keyframes, points and sources of a map file.")
    i.add_argument("map", metavar="MAP", help="map file (.npz)")


def run(args: argparse.Namespace) -> int:
    return _build(args) if args.map_command == "build" else _info(args)


def _check_build_args(args: argparse.Namespace) -> Path:
    out = Path(args.out)
    if out.suffix != ".npz":
        raise UserError(f"{out}: a map file name ends in .npz")
    if out.is_dir():
        raise UserError(f"{out}: is a folder; give a file name ending in .npz")
    refuse_existing(out, args.force)
    check_writable(out.parent, out)
    if not (args.spacing > 0 and args.angle > 0):
        raise UserError(f"--spacing and --angle must be positive, got {args.spacing} and {args.angle}")
    if args.max_features < 20:
        raise UserError(f"--max-features must be >= 20, got {args.max_features}")
    if args.workers < 0:
        raise UserError(f"--workers must be >= 0 (0: one per core), got {args.workers}")
    return out


def _build(args: argparse.Namespace) -> int:
    out = _check_build_args(args)
    start = time.perf_counter()
    m = _build_map(args)
    try:
        m.save(out)
    except OSError as err:
        raise UserError(f"{out}: cannot write the map ({err.strerror or err})") from None
    print(
        f"wrote {out}: {len(m)} keyframes, {m.num_points} points ({m.num_points / len(m):.0f} a keyframe), "
        f"{out.stat().st_size / 1e6:.1f} MB, in {time.perf_counter() - start:.0f} s"
    )
    return 0


def _build_map(args: argparse.Namespace):
    """The :class:`~.keyframe_map.KeyframeMap` of ``--data`` or ``--scene``."""
    from vlocnetpp_core.mapping.build import build_map, build_scene_map
    from vlocnetpp_core.mapping.features import FeatureConfig

    features, progress = FeatureConfig(max_features=args.max_features), not args.no_progress
    workers = args.workers or os.cpu_count() or 1
    if args.data:
        from vlocnetpp_core.data import open_dataset

        indexes = [open_dataset(d, args.format, args.split) for d in args.data]
        return build_map(indexes, args.spacing, args.angle, features, progress, workers)
    from vlocnetpp_core.synth.writer import check_render_args

    if args.loops < 1:
        raise UserError(f"--loops must be >= 1 with --scene, got {args.loops}")
    size = check_render_args(
        args.scene, args.seed, args.loops, 0, args.frames_per_loop, args.size, None, args.lane_wander
    )
    return build_scene_map(
        args.scene,
        args.seed,
        args.loops,
        args.frames_per_loop,
        args.spacing,
        args.angle,
        size,
        args.lane_wander,
        features,
        progress,
        workers,
    )


def _info(args: argparse.Namespace) -> int:
    from vlocnetpp_core.mapping.keyframe_map import KeyframeMap

    m = KeyframeMap.load(args.map)
    lo, hi = m.t.min(axis=0), m.t.max(axis=0)
    print(f"{args.map}: {len(m)} keyframes, {m.num_points} points ({m.num_points / len(m):.0f} a keyframe)")
    print(
        f"  keyframe positions: x {lo[0]:.1f}..{hi[0]:.1f} m, "
        f"y {lo[1]:.1f}..{hi[1]:.1f} m, z {lo[2]:.1f}..{hi[2]:.1f} m"
    )
    print(f"  features: {m.features.to_dict()}")
    print(f"  source: {m.source}")
    return 0

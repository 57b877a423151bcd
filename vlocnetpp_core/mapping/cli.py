"""``vlocnetpp map``: build and inspect keyframe maps for the refinement (:mod:`vlocnetpp_core.mapping`).

* ``vlocnetpp map build OUT.npz --data DIR [--data DIR ...]``: the map of the datasets' ``--split`` (default
  ``train``: the images a model was trained on); refuses an existing OUT without ``--force``, writes it atomically.
* ``vlocnetpp map info MAP.npz``: keyframes, points and where they came from.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from vlocnetpp_core.data.formats import FORMATS
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.outputs import refuse_existing


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    b = sub.add_parser("build", help="build a map from datasets with poses (and depth, else triangulated)",
                       description="Build a keyframe map (keyframes, SIFT features and their 3D points) of datasets with known poses.")
    b.add_argument("out", metavar="OUT", help="map file to write (.npz)")
    b.add_argument("--data", action="append", required=True, metavar="DIR",
                   help="dataset folder (DeepLoc layout or 7-Scenes); repeat for several")
    b.add_argument("--format", choices=FORMATS, default=None, help="dataset format (default: detected from the layout)")
    b.add_argument("--split", default="train", help="split to build the map of (default: train, the model's training images)")
    b.add_argument("--spacing", type=float, default=5.0, metavar="M",
                   help="a new keyframe every M metres along each sequence (default 5)")
    b.add_argument("--angle", type=float, default=20.0, metavar="DEG", help="... or every DEG degrees of turn (default 20)")
    b.add_argument("--max-features", type=int, default=1500, metavar="N", help="SIFT keypoints per keyframe at most (default 1500)")
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
    parent = out.parent if str(out.parent) else Path(".")
    if parent.exists() and not (parent.is_dir() and os.access(parent, os.W_OK)):
        raise UserError(f"{parent}: cannot write the map there (not a writable folder)")
    if not (args.spacing > 0 and args.angle > 0):
        raise UserError(f"--spacing and --angle must be positive, got {args.spacing} and {args.angle}")
    if args.max_features < 20:
        raise UserError(f"--max-features must be >= 20, got {args.max_features}")
    return out


def _build(args: argparse.Namespace) -> int:
    out = _check_build_args(args)
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.mapping.build import build_map
    from vlocnetpp_core.mapping.features import FeatureConfig

    indexes = [open_dataset(d, args.format, args.split) for d in args.data]
    start = time.perf_counter()
    m = build_map(indexes, args.spacing, args.angle, FeatureConfig(max_features=args.max_features), progress=not args.no_progress)
    try:
        m.save(out)
    except OSError as err:
        raise UserError(f"{out}: cannot write the map ({err.strerror or err})") from None
    print(f"wrote {out}: {len(m)} keyframes, {m.num_points} points ({m.num_points / len(m):.0f} a keyframe), "
          f"{out.stat().st_size / 1e6:.1f} MB, in {time.perf_counter() - start:.0f} s")
    return 0


def _info(args: argparse.Namespace) -> int:
    from vlocnetpp_core.mapping.keyframe_map import KeyframeMap

    m = KeyframeMap.load(args.map)
    lo, hi = m.t.min(axis=0), m.t.max(axis=0)
    print(f"{args.map}: {len(m)} keyframes, {m.num_points} points ({m.num_points / len(m):.0f} a keyframe)")
    print(f"  keyframe positions: x {lo[0]:.1f}..{hi[0]:.1f} m, y {lo[1]:.1f}..{hi[1]:.1f} m, z {lo[2]:.1f}..{hi[2]:.1f} m")
    print(f"  features: {m.features.to_dict()}")
    print(f"  source: {m.source}")
    return 0

"""The command line of ``vlocnetpp replay BAG`` (:mod:`.replay` does the work): flags, their checks (``UserError``
naming the flag), the hand-over to the ROS package's ``replay-node`` program for ``--through-node``
(:func:`bridge_argv`), and :func:`run`."""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
from pathlib import Path

from vlocnetpp_core.bag.replay import replay
from vlocnetpp_core.bag.topics import DEFAULT_MAX_GAP_S, DEPTH_TOPIC, NETWORK_POSE_TOPIC
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.outputs import refuse_existing
from vlocnetpp_core.programs import program_command


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bag", metavar="BAG", help="input bag (.mcap file, or a rosbag2 folder) with camera images")
    p.add_argument(
        "--checkpoint", required=True, help="checkpoint (NAME.safetensors or NAME; the NAME.json sidecar next to it)"
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="OUT.mcap",
        help="output bag: the input topics plus /vlocnet/pose, /vlocnet/pose_with_covariance, "
        "/vlocnet/odometry, /vlocnet/segmentation (not for a pose-only model)",
    )
    p.add_argument(
        "--image-topic",
        default=None,
        help="camera topic (default /camera/image_raw, else /camera/image_raw/compressed)",
    )
    p.add_argument(
        "--through-node",
        action="store_true",
        help="run the real ROS node (console script 'localizer') and play the bag to it over DDS",
    )
    p.add_argument(
        "--rate",
        default=None,
        metavar="HZ|max",
        help="--through-node: publish at the bag's rate (default), at HZ frames/s, "
        "or 'max': the next image when the previous pose came back",
    )
    p.add_argument(
        "--max-gap-s",
        type=float,
        default=DEFAULT_MAX_GAP_S,
        help=f"reset the temporal state after a stamp gap longer than this (default {DEFAULT_MAX_GAP_S:g} s)",
    )
    p.add_argument(
        "--use-depth",
        action="store_true",
        help=f"give {DEPTH_TOPIC} to the localizer for warping instead of the predicted depth",
    )
    p.add_argument(
        "--map",
        default=None,
        metavar="MAP.npz|auto",
        help="refine the pose against this keyframe map (vlocnetpp map build), as the node's parameter map; 'auto': "
        f"NAME.map.npz beside the checkpoint (none, with a warning, when missing); adds {NETWORK_POSE_TOPIC} "
        "(the network's own pose). Default: no refinement",
    )
    p.add_argument(
        "--refine-every",
        type=int,
        default=1,
        metavar="K",
        help="with --map: refine every K-th frame, "
        "the odometry moves the refined pose on in between (default 1: every frame)",
    )
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--force", action="store_true", help="replace OUT.mcap if it exists")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def bridge_argv(args: argparse.Namespace) -> list[str]:
    """The ``replay`` flags again, for the ``replay-node`` program (which takes the same ones)."""
    argv = [
        str(args.bag),
        "--checkpoint",
        str(args.checkpoint),
        "--out",
        str(args.out),
        "--through-node",
        "--max-gap-s",
        repr(args.max_gap_s),
        "--device",
        args.device,
        "--refine-every",
        str(args.refine_every),
    ]
    for flag, value in (("--image-topic", args.image_topic), ("--rate", args.rate), ("--map", args.map)):
        if value is not None:
            argv += [flag, value]
    argv += [
        flag
        for flag, on in (("--use-depth", args.use_depth), ("--force", args.force), ("--no-progress", args.no_progress))
        if on
    ]
    return argv


def parse_rate(text: str | None) -> float | None:
    """``None`` -> None (the bag's rate), ``"max"`` -> ``math.inf``, ``"HZ"`` -> a positive float."""
    if text is None:
        return None
    if text.strip().lower() == "max":
        return math.inf
    try:
        hz = float(text)
    except ValueError:
        raise UserError(f"--rate must be a number of Hz or 'max', got {text!r}") from None
    if not (math.isfinite(hz) and hz > 0):
        raise UserError(f"--rate must be a positive number of Hz or 'max', got {text!r}")
    return hz


def map_argument(args: argparse.Namespace) -> Path | None:
    """The keyframe map of ``--map`` (:func:`vlocnetpp_core.inference.checkpoint.resolve_map_path`: ``auto`` without a
    map beside the checkpoint warns on stderr and gives None), ``--refine-every`` checked."""
    from vlocnetpp_core.inference.checkpoint import resolve_map_path

    if args.refine_every < 1:
        raise UserError(f"--refine-every must be >= 1, got {args.refine_every}")
    return resolve_map_path(args.checkpoint, args.map, "--map", lambda line: print(f"note: {line}", file=sys.stderr))


def run(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.max_gap_s) and args.max_gap_s > 0):
        raise UserError(f"--max-gap-s must be a positive number of seconds, got {args.max_gap_s}")
    rate = parse_rate(args.rate)
    if rate is not None and not args.through_node:
        raise UserError(
            "--rate only applies with --through-node (in process every frame is processed as fast as possible)"
        )
    if Path(args.out).resolve() == Path(args.bag).resolve():
        raise UserError(f"--out {args.out} is the input bag")
    refuse_existing(args.out, args.force)
    map_path = map_argument(args)
    args.map = None if map_path is None else str(map_path.resolve())  # resolved once: the node gets a path
    if args.through_node:
        # The DDS side is a ROS program of its own (vlocnetpp_core never imports ROS): same flags.
        return subprocess.call([*program_command("replay-node"), *bridge_argv(args)])
    else:
        from vlocnetpp_core.inference.localizer import Localizer

        localizer = Localizer.from_checkpoint(
            args.checkpoint,
            device=args.device,
            max_gap_s=args.max_gap_s,
            map_path=map_path,
            refine_every=args.refine_every,
        )
        summary = replay(
            args.bag, args.out, localizer, args.image_topic, args.use_depth, args.force, progress=not args.no_progress
        )
    print(summary.format())
    return 0

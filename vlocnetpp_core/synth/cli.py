"""``vlocnetpp synth OUT``: render the procedural campus as a DeepLoc-format dataset."""

from __future__ import annotations

import argparse


def parse_size(text: str) -> tuple[int, int]:
    """``'WIDTHxHEIGHT'`` -> ``(width, height)`` (an argparse ``type``)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 320x180, got {text!r}") from err
    return w, h


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from vlocnetpp_core.synth.writer import DEFAULT_FRAMES_PER_LOOP

    parser.add_argument("out", metavar="OUT", help="output folder (must not exist unless --force)")
    parser.add_argument(
        "--scene",
        default="campus",
        metavar="S",
        help="campus to build: fixes geometry and textures (default: campus, the one the shipped model knows)",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="S",
        help="varies the visits: driving patterns, lighting, moving objects (default: 0)",
    )
    parser.add_argument(
        "--loops",
        type=int,
        default=4,
        metavar="N",
        help="train loops (default: 4; with 4 or more every circuit/direction is covered)",
    )
    parser.add_argument("--test-loops", type=int, default=2, metavar="N", help="test loops (default: 2)")
    parser.add_argument(
        "--frames-per-loop",
        type=int,
        default=DEFAULT_FRAMES_PER_LOOP,
        metavar="N",
        help=f"frames per loop (default: {DEFAULT_FRAMES_PER_LOOP})",
    )
    parser.add_argument(
        "--size", type=parse_size, default=(320, 180), metavar="WxH", help="image size WIDTHxHEIGHT (default: 320x180)"
    )
    parser.add_argument(
        "--frame-interval",
        type=float,
        default=None,
        metavar="SECONDS",
        help="time between frames, e.g. 0.05 for 20 Hz video (default: "
        "spread each loop's frames over one lap, ~1 m apart)",
    )
    parser.add_argument(
        "--test-lane-offset",
        type=float,
        default=None,
        metavar="METRES",
        help="drive the test loops this far right of the circuit centreline instead of in a lane (the lanes are at "
        "+-1.5 m, the sidewalks at +-4.25 m), e.g. 3 or 0 for loops between the lanes training visits drove",
    )
    parser.add_argument(
        "--lane-wander",
        type=float,
        default=0.0,
        metavar="METRES",
        help="let every train loop drift slowly up to this far either side of its lane (e.g. 1.5: the train "
        "loops then cover the road between the lanes; default: 0, keep to the lane)",
    )
    parser.add_argument(
        "--lighting",
        default="",
        metavar="PRESET[,PRESET...]",
        help="lighting presets of the visits (noon, morning, evening, overcast, hazy): train loops cycle through "
        "them, test loops draw from them; a preset named twice comes twice as often (default: all five)",
    )
    parser.add_argument("--force", action="store_true", help="replace OUT if it exists")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from vlocnetpp_core.synth.writer import render_dataset

    # SIGTERM unwinds like Ctrl-C (vlocnetpp_core.cli runs every command so), so the partial output is removed
    s = render_dataset(
        args.out,
        scene=args.scene,
        seed=args.seed,
        train_loops=args.loops,
        test_loops=args.test_loops,
        frames_per_loop=args.frames_per_loop,
        size=args.size,
        force=args.force,
        progress=not args.no_progress,
        frame_interval=args.frame_interval,
        test_lane_offset=args.test_lane_offset,
        lane_wander=args.lane_wander,
        lighting_presets=tuple(args.lighting.split(",")) if args.lighting else None,
    )
    w, h = s["size"]
    print(
        f"wrote {s['out']}: {args.loops} train + {args.test_loops} test loops, {s['frames']} frames at {w}x{h} "
        f"(scene {s['scene']}, seed {s['seed']}) in {s['seconds']:.1f} s, rendering {s['render_fps']:.1f} frames/s"
    )
    return 0

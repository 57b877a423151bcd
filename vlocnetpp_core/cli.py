"""``vlocnetpp``: the command-line tool. One sub-command per module, imported only when used.

Each command module defines ``add_arguments(parser: argparse.ArgumentParser) -> None`` and
``run(args: argparse.Namespace) -> int``. The table below is the whole registry; its help
strings are what ``vlocnetpp --help`` lists, without importing torch.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.interrupts import sigterm_as_interrupt

# name -> (module, one-line help, aliases)
COMMANDS: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "demo": ("vlocnetpp_core.demo", "end-to-end demo: synth test loops -> bag -> node -> evaluate", ()),
    "synth": ("vlocnetpp_core.synth.cli", "render a procedural DeepLoc-format campus dataset", ()),
    "data-info": ("vlocnetpp_core.data.check", "summarise and sanity-check a dataset (run before training)", ()),
    "model-info": ("vlocnetpp_core.model.info", "parameter counts per stream of a model config", ()),
    "train": ("vlocnetpp_core.training.train", "train a stage (stl-loc, stl-vo, stl-seg, mtl)", ()),
    "evaluate": (
        "vlocnetpp_core.evaluation.evaluate",
        "evaluate a checkpoint on a dataset with the paper's metrics",
        (),
    ),
    "convert": (
        "vlocnetpp_core.bag.convert",
        "convert a DeepLoc / 7-Scenes dataset to a ROS 2 MCAP bag",
        ("convert-deeploc",),
    ),
    "extract": (
        "vlocnetpp_core.bag.extract_cli",
        "turn a robot's ROS 2 bag into a DeepLoc-layout dataset (images, poses, depth)",
        (),
    ),
    "replay": ("vlocnetpp_core.bag.replay_cli", "run the localizer over a bag and write an output bag", ()),
    "map": (
        "vlocnetpp_core.mapping.cli",
        "build a keyframe map of training images for refinement (map build, map info)",
        (),
    ),
    "evaluate-bag": ("vlocnetpp_core.bag.evaluate_bag", "score a bag holding ground truth and localizer outputs", ()),
    "bench": ("vlocnetpp_core.bench", "speed and memory benchmarks against the performance targets", ()),
    "calibrate-classes": (
        "vlocnetpp_core.inference.class_offsets",
        "fit a checkpoint's per-class segmentation offsets for mean IoU on labelled validation visits",
        (),
    ),
    "export-onnx": ("vlocnetpp_core.inference.onnx_export", "export the streaming step to ONNX", ()),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Top-level parser; the sub-command ``only`` (if given) gets its full arguments."""
    parser = argparse.ArgumentParser(
        prog="vlocnetpp",
        description="VLocNet++ toolkit: data, training, evaluation, bags, benchmarks. "
        "Run 'vlocnetpp COMMAND --help' for a command's options.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text, aliases) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text, aliases=list(aliases))
        if only is not None and (only == name or only in aliases):
            importlib.import_module(module).add_arguments(p)
            p.set_defaults(_module=module)
    return parser


def _command_in(argv: list[str]) -> str | None:
    for a in argv:
        if not a.startswith("-"):
            return a
    return None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(_command_in(argv))
    args = parser.parse_args(argv)
    if getattr(args, "_module", None) is None:
        parser.print_help()
        return 0 if args.command is None else 2
    module = importlib.import_module(args._module)
    try:
        with (
            sigterm_as_interrupt()
        ):  # SIGTERM stops every command as Ctrl-C does (a stopped recipe sends it to its jobs)
            return int(module.run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except UserError as err:
        print(f"vlocnetpp {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""``vlocnetpp train``: the paper's staged training, clip-unrolled, resumable, optionally distributed.

Stages (paper Sec. IV): ``stl-loc`` (global pose stream with the temporal Res5a fusion and the
geometric consistency loss), ``stl-vo`` (odometry streams), ``stl-seg`` (semantic stream with
warping, plus the depth head that warping needs; the warp uses the ground-truth relative pose
because the odometry stream is not trained in this stage), and ``mtl`` (everything, learned task
weighting of Eq. 6, initialised from the single-task checkpoints at the lower learning rate).
A pose-only config (``semantic_stream: false``, e.g. ``lite_pose``) trains ``stl-loc``, ``stl-vo``
and ``mtl`` (= ``loc`` + ``vo``) and refuses ``stl-seg``. Adam(0.9, 0.999, 1e-10), lr 1e-3 for single-task stages and
1e-4 for MTL, batch 32 by default.

Every step unrolls clips of ``--clip-len`` frames through ``model.forward_clip``, so the
previous-frame features the network fuses come from its own previous step (never from ground
truth). Run folder (``--out``): ``last.safetensors/.json`` and ``best.safetensors/.json``
checkpoints (inference sidecar with calibration; ``best`` has the lowest validation
:func:`~vlocnetpp_core.training.losses.selection_score`: the raw pose, odometry and segmentation errors
relative to the first validation, not the loss with its moving learned weights), ``train_state.*`` (optimiser, loss
weights, RNG, step) for ``--resume``, ``log.jsonl`` (every loss and the learning rate per step, and each
validation), all written atomically.

Distributed: ``torchrun --nproc-per-node N -m vlocnetpp_core.training.train --config ... --data ...``
(gloo on CPU, nccl on GPU). Each rank takes a disjoint share of the clips of every epoch (a
clip never straddles ranks); rank 0 alone validates and writes files.

This module is the command line, and the only code that sees the parsed ``argparse.Namespace``: it becomes a
:class:`~vlocnetpp_core.training.config.TrainConfig` (``--train-config FILE`` reads one from a JSON file, as a
recipe's stage processes do), which :class:`~vlocnetpp_core.training.trainer.Trainer` runs; ``train_data`` holds
the clips and their order, ``model/stages.py`` the rules of each stage (``STAGE_SPECS``), ``model/assembly.py``
those of ``--init``, and ``recipe`` (``--recipe``) runs a whole schedule.
"""

from __future__ import annotations

import argparse
import os
import sys

from vlocnetpp_core.data.formats import FORMATS
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.model.stages import PARTS, STAGE_SPECS, STAGES
from vlocnetpp_core.outputs import check_run_dir
from vlocnetpp_core.training.config import S_Q_INIT, TrainConfig


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--recipe",
        metavar="FILE",
        help="run a whole declarative schedule (datasets, stages, export; e.g. "
        "config/recipes/shipped.yaml) into --out, resumably; the other flags then come from the file "
        "(docs/training.md)",
    )
    p.add_argument(
        "--train-config",
        metavar="FILE",
        help="run the TrainConfig in this JSON file (every other flag, --out "
        "included, comes from it; what a recipe writes for each of its stage runs: OUT/NAME.K.json)",
    )
    p.add_argument("--config", help="model config: 'paper', 'lite' or a YAML file (required without --recipe)")
    p.add_argument("--data", help="dataset folder (DeepLoc layout or 7-Scenes scene) (required without --recipe)")
    p.add_argument("--format", choices=FORMATS, default=None, help="dataset format (default: detected)")
    p.add_argument(
        "--stage", choices=STAGES, help="training stage (paper's staged schedule) (required without --recipe)"
    )
    p.add_argument("--out", help="run folder for checkpoints and logs (required without --train-config)")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="optimiser steps to train (total, including resumed ones)")
    length.add_argument("--epochs", type=float, help="epochs over the training clips (default 30)")
    p.add_argument(
        "--init",
        action="append",
        default=[],
        metavar="CHECKPOINT",
        help="initialise from a checkpoint (a later one wins where they overlap); "
        "for mtl give each single-task checkpoint (each stream comes from its stage); "
        "for stl-loc an stl-seg checkpoint gives its encoder as the pre-trained backbone, "
        "an stl-vo checkpoint its trunk, kept frozen",
    )
    p.add_argument(
        "--init-backbone",
        metavar="FILE",
        help="standard ResNet-50 state dict (torchvision key names) for every backbone",
    )
    p.add_argument(
        "--freeze",
        type=_parts,
        default=(),
        metavar="PART[,PART...]",
        help=f"keep these parts of the network as they are, weights and BatchNorm statistics ({', '.join(PARTS)}); "
        "e.g. mtl that trains only the global stream with its Res4c semantic fusion: "
        "--freeze trunk,odometry,semantic,depth_head (default: "
        "none; a pose stage on the other's trunk freezes the trunk)",
    )
    again = p.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true", help="continue the run in --out exactly where it stopped")
    again.add_argument(
        "--restart",
        action="store_true",
        help="continue the run in --out from its weights and step with a fresh optimiser state (Adam's moments) "
        "and the learned loss weights at their initial values: a warm restart, e.g. with a new --lr/--lr-end cosine",
    )
    p.add_argument("--batch-size", type=int, default=32, help="clips per optimiser step, over all ranks (paper: 32)")
    p.add_argument(
        "--clip-len", type=int, default=3, help="frames per training clip, unrolled through the network (default 3)"
    )
    p.add_argument(
        "--frame-strides",
        type=_strides,
        default=(1,),
        metavar="S[,S...]",
        help="training clips at each of these frame strides (1: consecutive frames; 2: every other frame, "
        "i.e. twice the motion between the frames the network sees), pooled (default 1)",
    )
    p.add_argument(
        "--lr",
        type=float,
        help=f"learning rate (default: the stage's, as in the paper: {_per_stage('lr')}; with --resume: the run's, "
        "or this one from the resumed step on)",
    )
    p.add_argument(
        "--lr-end",
        type=float,
        default=None,
        metavar="R",
        help="anneal the rate along a half cosine from --lr to R at --steps (default: constant); resumed with the "
        "same --lr, --lr-end and --steps it continues the same curve",
    )
    p.add_argument(
        "--crop-scale",
        type=float,
        default=None,
        metavar="S",
        help="geometric augmentation: zoom by a random factor in [1, S], then crop the input size at a random place "
        f"(default: the stage's, {_per_stage('crop_scale')}; 1, none, for the stages with pose losses, whose targets "
        "a crop would falsify: a crop shifted by d pixels shows the view of a camera turned by about d/f radians)",
    )
    p.add_argument(
        "--s-q-init",
        type=float,
        default=S_Q_INIT,
        help="initial rotation loss weight s_q (paper: -3, i.e. rotation weighted e^3 = 20x at the start); "
        "0 lets a global stream trained from scratch leave the predict-the-mean plateau (docs/training.md)",
    )
    p.add_argument("--intrinsics", help="fx,fy,cx,cy of the dataset images (default: the reader's)")
    p.add_argument("--val-data", help="validation dataset folder (default: hold out the last training sequence)")
    p.add_argument("--val-split", default="train", help="split of --val-data to validate on (default train)")
    p.add_argument(
        "--val-every",
        type=int,
        default=500,
        help="validate (and write best/last) every N steps and at the last (default 500; 0: at the last only)",
    )
    p.add_argument(
        "--save-every-s",
        type=float,
        default=300.0,
        help="write last checkpoint + resumable state at most this often (s)",
    )
    p.add_argument("--workers", type=int, default=2, help="data loading worker processes (default 2)")
    p.add_argument(
        "--threads",
        type=int,
        default=os.cpu_count() or 1,
        help="CPU threads for the network (default: all %(default)s cores; 0: all but one)",
    )
    p.add_argument("--device", help="cpu or cuda (default: cuda if present)")
    p.add_argument(
        "--bf16",
        action="store_true",
        help="train with bfloat16 autocast: convolutions and matrix products in bfloat16, the pose heads, warping, "
        "losses and the weights in float32 (about 1.8x faster on CPUs with AMX or AVX-512 BF16, and on GPUs; "
        "slower on CPUs without); validation and the saved weights stay float32",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (data order, augmentation, init)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")


def _per_stage(key: str) -> str:
    """A default of every stage's :class:`StageSpec` for the help (``1e-3 stl-loc, ...``)."""
    return ", ".join(f"{getattr(spec, key):g} {name}" for name, spec in STAGE_SPECS.items())


def _strides(text: str) -> tuple[int, ...]:
    try:
        strides = tuple(sorted({int(s) for s in text.split(",")}))
    except ValueError:
        strides = ()
    if not strides or min(strides) < 1:
        raise argparse.ArgumentTypeError(f"expected frame strides >= 1 separated by commas (e.g. 1,2), got {text!r}")
    return strides


def _parts(text: str) -> tuple[str, ...]:
    parts = tuple(sorted({s.strip() for s in text.split(",") if s.strip()}))
    unknown = [p for p in parts if p not in PARTS]
    if not parts or unknown:
        raise argparse.ArgumentTypeError(
            f"expected parts of the network separated by commas ({', '.join(PARTS)}), got {text!r}"
        )
    return parts


def run(args: argparse.Namespace) -> int:
    if args.train_config:
        config = TrainConfig.read(args.train_config)
    else:
        if args.out is None:
            raise UserError("--out required (or --train-config FILE)")
        check_run_dir(args.out)  # a file there or a folder that cannot be written: one line, before anything is read
        if args.recipe:
            from vlocnetpp_core.training.recipe_run import run_recipe

            return run_recipe(args.recipe, args.out)
        config = train_config(args)
    check_run_dir(config.out)
    from vlocnetpp_core.training.trainer import Trainer

    Trainer(config).run()
    return 0


def train_config(args: argparse.Namespace) -> TrainConfig:
    """The :class:`TrainConfig` of the parsed flags (the command line's only conversion); ``UserError`` on a bad
    value."""
    missing = [f"--{k}" for k in ("config", "data", "stage") if getattr(args, k) is None]
    if missing:
        raise UserError(f"{', '.join(missing)} required (or --recipe FILE)")
    return TrainConfig(**{key: getattr(args, key) for key in TrainConfig.keys()})


def main() -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vlocnetpp_core.training.train", description=__doc__.splitlines()[0]
    )
    add_arguments(parser)
    try:
        return run(parser.parse_args())
    except UserError as err:
        print(f"vlocnetpp train: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""``vlocnetpp train``: the paper's staged training, clip-unrolled, resumable, optionally distributed.

Stages (paper Sec. IV): ``stl-loc`` (global pose stream with the temporal Res5a fusion and the
geometric consistency loss), ``stl-vo`` (odometry streams), ``stl-seg`` (semantic stream with
warping, plus the depth head that warping needs; the warp uses the ground-truth relative pose
because the odometry stream is not trained in this stage), and ``mtl`` (everything, learned task
weighting of Eq. 6, initialised from the single-task checkpoints at the lower learning rate).
Adam(0.9, 0.999, 1e-10), lr 1e-3 for single-task stages and 1e-4 for MTL, batch 32 by default.

Every step unrolls clips of ``--clip-len`` frames through ``model.forward_clip``, so the
previous-frame features the network fuses come from its own previous step (never from ground
truth). Run folder (``--out``): ``last.safetensors/.json`` and ``best.safetensors/.json``
checkpoints (inference sidecar with calibration; ``best`` has the lowest validation
:func:`~vlocnetpp_core.losses.selection_score`: the raw pose, odometry and segmentation errors
relative to the first validation, not the loss with its moving learned weights), ``train_state.*`` (optimiser, loss weights,
RNG, step) for ``--resume``, ``log.jsonl`` (every loss and the learning rate per step, and each
validation), all written atomically.

Distributed: ``torchrun --nproc-per-node N -m vlocnetpp_core.train --config ... --data ...``
(gloo on CPU, nccl on GPU). Each rank takes a disjoint share of the clips of every epoch (a
clip never straddles ranks); rank 0 alone validates and writes files.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.losses import S_Q_INIT, selection_score
from vlocnetpp_core.model.assembly import builds_semantic_fusion
from vlocnetpp_core.model.assembly import frozen_trunk as assembly_frozen_trunk
from vlocnetpp_core.model.stages import STAGE_TASKS, STAGES

DEFAULT_LR = {"stl-loc": 1e-3, "stl-vo": 1e-3, "stl-seg": 1e-3, "mtl": 1e-4}
DEFAULT_CROP_SCALE = {"stl-seg": 1.15}  # the pose stages: 1 (no geometric augmentation)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--recipe", metavar="FILE", help="run a whole declarative schedule (datasets, stages, export; e.g. "
                   "config/recipes/shipped.yaml) into --out, resumably; the other flags then come from the file (docs/training.md)")
    p.add_argument("--config", help="model config: 'paper', 'lite' or a YAML file (required without --recipe)")
    p.add_argument("--data", help="dataset folder (DeepLoc layout or 7-Scenes scene) (required without --recipe)")
    p.add_argument("--format", choices=("deeploc", "7scenes"), default=None, help="dataset format (default: detected)")
    p.add_argument("--stage", choices=STAGES, help="training stage (paper's staged schedule) (required without --recipe)")
    p.add_argument("--out", required=True, help="run folder for checkpoints and logs")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="optimiser steps to train (total, including resumed ones)")
    length.add_argument("--epochs", type=float, help="epochs over the training clips (default 30)")
    p.add_argument("--init", action="append", default=[], metavar="CHECKPOINT",
                   help="initialise from a checkpoint (a later one wins where they overlap); for mtl give each single-task checkpoint (each stream comes from its stage); "
                        "for stl-loc an stl-seg checkpoint gives its encoder as the pre-trained backbone, an stl-vo checkpoint its trunk, kept frozen")
    p.add_argument("--init-backbone", metavar="FILE", help="standard ResNet-50 state dict (torchvision key names) for every backbone")
    p.add_argument("--resume", action="store_true", help="continue the run in --out exactly where it stopped")
    p.add_argument("--batch-size", type=int, default=32, help="clips per optimiser step, over all ranks (paper: 32)")
    p.add_argument("--clip-len", type=int, default=3, help="frames per training clip, unrolled through the network (default 3)")
    p.add_argument("--frame-strides", type=_strides, default=(1,), metavar="S[,S...]",
                   help="training clips at each of these frame strides (1: consecutive frames; 2: every other frame, "
                        "i.e. twice the motion between the frames the network sees), pooled (default 1)")
    p.add_argument("--lr", type=float,
                   help="learning rate (default: 1e-3 single-task, 1e-4 mtl, as in the paper; with --resume: the run's, "
                        "or this one from the resumed step on)")
    p.add_argument("--crop-scale", type=float, default=None, metavar="S",
                   help="geometric augmentation: zoom by a random factor in [1, S], then crop the input size at a random place "
                        "(default: 1.15 for stl-seg; 1, none, for the stages with pose losses, whose targets a crop would falsify: "
                        "a crop shifted by d pixels shows the view of a camera turned by about d/f radians)")
    p.add_argument("--s-q-init", type=float, default=S_Q_INIT,
                   help="initial rotation loss weight s_q (paper: -3, i.e. rotation weighted e^3 = 20x at the start); "
                        "0 lets a global stream trained from scratch leave the predict-the-mean plateau (docs/training.md)")
    p.add_argument("--intrinsics", help="fx,fy,cx,cy of the dataset images (default: the reader's)")
    p.add_argument("--val-data", help="validation dataset folder (default: hold out the last training sequence)")
    p.add_argument("--val-split", default="train", help="split of --val-data to validate on (default train)")
    p.add_argument("--val-every", type=int, default=500, help="validate (and write best/last) every N steps (default 500)")
    p.add_argument("--save-every-s", type=float, default=300.0, help="write last checkpoint + resumable state at most this often (s)")
    p.add_argument("--workers", type=int, default=2, help="data loading worker processes (default 2)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="cpu or cuda (default: cuda if present)")
    p.add_argument("--seed", type=int, default=0, help="random seed (data order, augmentation, init)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")


# --------------------------------------------------------------------------- data


class EpochSampler(torch.utils.data.Sampler):
    """Yields ``(clip index, sample seed)`` in a per-epoch permutation, this rank's share only.

    The order and the augmentation seed of every sample are a pure function of
    ``(seed, epoch, position)``, so a run resumed at any step sees exactly the samples (and the
    augmentations) an uninterrupted run would, whatever the number of loader workers.
    """

    def __init__(self, n: int, batch_size: int, seed: int, rank: int = 0, world: int = 1):
        self.n, self.batch_size, self.seed, self.rank, self.world = n, batch_size, seed, rank, world
        self.per_rank = batch_size // world
        self.batches_per_epoch = max(1, n // batch_size)
        self.epoch = 0
        self.skip_batches = 0

    def set_position(self, epoch: int, skip_batches: int) -> None:
        self.epoch, self.skip_batches = epoch, skip_batches

    def __iter__(self):
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        perm = torch.randperm(self.n, generator=g).tolist()
        if len(perm) < self.batch_size:  # tiny datasets: repeat to fill one batch
            perm = (perm * math.ceil(self.batch_size / max(1, len(perm))))[: self.batch_size]
        for b in range(self.skip_batches, self.batches_per_epoch):
            batch = perm[b * self.batch_size:(b + 1) * self.batch_size]
            for k in range(self.rank * self.per_rank, (self.rank + 1) * self.per_rank):
                yield batch[k], _sample_seed(self.seed, self.epoch, b * self.batch_size + k)

    def __len__(self) -> int:
        return (self.batches_per_epoch - self.skip_batches) * self.per_rank


def _strides(text: str) -> tuple[int, ...]:
    try:
        strides = tuple(sorted({int(s) for s in text.split(",")}))
    except ValueError:
        strides = ()
    if not strides or min(strides) < 1:
        raise argparse.ArgumentTypeError(f"expected frame strides >= 1 separated by commas (e.g. 1,2), got {text!r}")
    return strides


def _sample_seed(*parts: int) -> int:
    return int.from_bytes(hashlib.blake2b(repr(parts).encode(), digest_size=8).digest(), "little") >> 2


def training_clips(index, clip_len: int, transform, strides: tuple[int, ...] = (1,), stage: str = "mtl") -> torch.utils.data.ConcatDataset:
    """The ``ClipDataset`` of ``index`` at each frame stride, pooled (item ``i`` as in ``ClipDataset``);
    depth and labels are decoded only for the stages that train on them (those with ``seg``).

    Stride ``s`` shows the network every ``s``-th frame: ``s`` times the motion between the frames
    it fuses, as from a faster robot or a slower camera. Odometry trained at one stride learns the
    training speed rather than the motion (docs/training.md).
    """
    from vlocnetpp_core.data import ClipDataset

    seg = "seg" in STAGE_TASKS[stage]
    return torch.utils.data.ConcatDataset([ClipDataset(index, clip_len, transform, stride=s, depth=seg, labels=seg) for s in strides])


class SeededClips(torch.utils.data.Dataset):
    """``ClipDataset`` indexed by ``(i, seed)``: the augmentation of a sample depends on its seed only."""

    def __init__(self, clips):
        self.clips = clips

    def __len__(self) -> int:
        return len(self.clips)

    def __getitem__(self, item):
        i, seed = item
        torch.manual_seed(seed)
        return self.clips[i]


def _split_validation(index):
    """Hold out the last sequence of a training split for validation (when it has at least 3)."""
    from dataclasses import replace

    if len(index.sequences) < 3:
        return index, None
    last = index.sequences[-1]
    train = replace(index, records=index.records[: last.start], sequences=index.sequences[:-1])
    val = replace(index, records=index.records[last.start:], sequences=[range(0, len(last))])
    return train, val


# --------------------------------------------------------------------------- model set-up


def _load_inits(model, criterion, paths: list[str], stage: str, log) -> list[dict]:
    """Initialise from checkpoints. For ``mtl`` each stream is taken from the checkpoint of its stage."""
    from vlocnetpp_core.checkpoint import read_checkpoint_tensors
    from vlocnetpp_core.model.assembly import init_rule, init_tensors
    from vlocnetpp_core.train_state import load_criterion_weights

    sources = []
    loaded: dict[str, torch.Tensor] = {}
    for path in paths:
        tensors, meta = read_checkpoint_tensors(path)
        src_stage = meta.get("training", {}).get("stage")
        sources.append({"path": str(path), "stage": src_stage})
        own = model.state_dict()
        keep = init_tensors(init_rule(stage, src_stage, len(paths)), src_stage, tensors, own)
        bad = [k for k, v in keep.items() if v.shape != own[k].shape]
        if bad:
            raise UserError(f"{path}: {len(bad)} tensors do not match this model config (e.g. {bad[0]}); was it trained with another --config?")
        model.load_state_dict({k: v.to(own[k].dtype) for k, v in keep.items()}, strict=False)
        loaded.update(keep)
        crit = load_criterion_weights(Path(path).parent)
        if crit:
            own_c = criterion.state_dict()
            criterion.load_state_dict({**own_c, **{k: v for k, v in crit.items() if k in own_c}})
        log(f"init: {len(keep)} tensors from {path} (stage {src_stage})")
    fusion = getattr(model, "semantic_fusion", None)
    if fusion is not None and not any(k.startswith("semantic_fusion.") for k in loaded):
        _identity_fusion_init(model)
        log("init: semantic fusion (Res4c) starts as an identity of the global stream's Res4c features")
    return sources


@torch.no_grad()
def _identity_fusion_init(model, margin: float = 8.0) -> None:
    """Start the Res4c semantic fusion added to trained streams as an identity of the global stream.

    The AWF is ``ReLU(pool(...) + b)`` and the global stream's Res4c features are signed, so the
    pooling passes them through shifted by a per-channel ``c >= 0`` that lifts ``margin`` standard
    deviations below their mean to zero (the statistics of the next block's BatchNorm, which reads
    them), and every BatchNorm that reads the shifted features takes ``c`` off again: their
    running means move by ``c`` (in training their batch means do). The shift rides the residual
    path up to the first block with a projection shortcut (Res5a), whose BatchNorm removes it. So
    the assembled network's outputs are unchanged wherever the features stay within ``margin``
    standard deviations. The semantic half of the pooling starts at zero: it still receives
    gradients (through the non-zero semantic features), and the per-channel semantic weights do
    from the second step on.
    """
    fusion, g, k = model.semantic_fusion, model.global_stream, model.config.res4_fusion_block
    readers = []
    for block in [*g.res4[k:], *g.res5]:
        readers.append(block.bn1)
        if block.shortcut is not None:
            break
    else:
        raise RuntimeError("no block with a projection shortcut after the Res4c fusion")
    bn = readers[0]
    c = torch.clamp(margin * torch.sqrt(bn.running_var + bn.eps) - bn.running_mean, min=0.0)
    w = fusion.pool.weight  # (C_a, C_a + C_b, 1, 1)
    ca = fusion.weight_a.numel()
    w.zero_()
    w[:, :ca, 0, 0] = torch.eye(ca, dtype=w.dtype)
    fusion.pool.bias.copy_(c)
    for reader in readers:
        reader.running_mean += c


# --------------------------------------------------------------------------- the loop


def run(args: argparse.Namespace) -> int:
    if args.recipe:
        from vlocnetpp_core.recipe import run_recipe

        return run_recipe(args.recipe, args.out)
    missing = [f"--{k}" for k in ("config", "data", "stage") if getattr(args, k) is None]
    if missing:
        raise UserError(f"{', '.join(missing)} required (or --recipe FILE)")
    from vlocnetpp_core.checkpoint import save_checkpoint
    from vlocnetpp_core.data import ClipDataset, make_transform, open_dataset
    from vlocnetpp_core.losses import VLocNetLoss
    from vlocnetpp_core.model import VLocNetPP, load_model_config, trainable_parameters
    from vlocnetpp_core.train_state import load_train_state, save_train_state

    if args.epochs is not None and args.epochs <= 0:
        raise UserError(f"--epochs must be > 0, got {args.epochs:g} (--steps 0 assembles mtl from its stages without training)")
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    distributed = world > 1
    device = torch.device(args.device)
    if distributed:
        if device.type == "cuda":
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
            torch.cuda.set_device(device)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.batch_size % world:
        raise UserError(f"--batch-size {args.batch_size} must be divisible by the number of processes ({world})")
    is_main = rank == 0
    out = Path(args.out)
    if is_main:
        out.mkdir(parents=True, exist_ok=True)
    log_path = out / "log.jsonl"

    def log(msg: str) -> None:
        if is_main:
            print(f"[train] {msg}", file=sys.stderr, flush=True)

    torch.manual_seed(args.seed)
    config = load_model_config(args.config)
    if config.semantic_fusion and not builds_semantic_fusion(args.stage, args.steps):
        # mtl training starts the Res4c AWF as an identity (_identity_fusion_init)
        config = dataclasses.replace(config, semantic_fusion=False)
        log(f"{args.stage}{' with no steps' if args.stage == 'mtl' else ''}: the network is built without the Res4c semantic fusion, which only mtl training learns")
    size = tuple(config.input_size)

    train_index = open_dataset(args.data, args.format, "train", args.intrinsics)
    if args.val_data:
        val_index = open_dataset(args.val_data, args.format, args.val_split, args.intrinsics)
    else:
        train_index, val_index = _split_validation(train_index)
    crop_scale = args.crop_scale if args.crop_scale is not None else DEFAULT_CROP_SCALE.get(args.stage, 1.0)
    if not (math.isfinite(crop_scale) and crop_scale >= 1.0):
        raise UserError(f"--crop-scale must be >= 1, got {crop_scale}")
    train_clips = training_clips(train_index, args.clip_len, make_transform(True, size, scale=(1.0, crop_scale)), args.frame_strides, args.stage)
    if len(train_clips) == 0:
        raise UserError(f"{args.data}: no training clips of {args.clip_len} frames")
    seg = "seg" in STAGE_TASKS[args.stage]
    val_clips = ClipDataset(val_index, args.clip_len, make_transform(False, size), depth=seg, labels=seg) if val_index is not None else None

    model = VLocNetPP(config)
    positions = np.array([r.t for r in train_index.records])
    model.set_position_prior(positions.mean(axis=0), np.maximum(positions.std(axis=0), 1.0))
    model.to(device)
    criterion = VLocNetLoss(args.stage, depth=config.warping, s_q_init=args.s_q_init).to(device)
    sources = _load_inits(model, criterion, args.init, args.stage, log) if args.init else []
    if args.init_backbone:
        from vlocnetpp_core.model import load_backbone_weights

        log(f"init-backbone: {load_backbone_weights(model, args.init_backbone)}")
    params = list(trainable_parameters(model, args.stage))
    frozen_trunk = assembly_frozen_trunk(args.stage, [src["stage"] for src in sources])
    if frozen_trunk:
        # One pose stream on top of the other's trunk (stl-vo on stl-loc, or stl-loc on stl-vo):
        # keep the shared trunk as the first stage learned it (weights and BatchNorm statistics),
        # so that mtl can combine the two streams consistently (mtl then trains it with everything
        # else: kept frozen too, 800 mtl steps were worse on every metric, README ablation).
        trunk = {id(p) for n, p in model.named_parameters() if n.startswith("trunk.")}
        params = [p for p in params if id(p) not in trunk]
    params += list(criterion.parameters())
    for p in model.parameters():
        p.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    lr = args.lr if args.lr is not None else DEFAULT_LR[args.stage]
    optimizer = torch.optim.Adam(params, lr=lr, betas=(0.9, 0.999), eps=1e-10)

    sampler = EpochSampler(len(train_clips), args.batch_size, args.seed, rank, world)
    steps_per_epoch = sampler.batches_per_epoch
    total = args.steps if args.steps is not None else int(math.ceil((30.0 if args.epochs is None else args.epochs) * steps_per_epoch))
    step, best, reference = 0, math.inf, None
    if args.resume:
        meta = load_train_state(out, optimizer=optimizer, criterion=criterion)
        saved_strides = tuple(meta.get("args", {}).get("frame_strides") or args.frame_strides)  # runs before the flag: unknown
        if saved_strides != args.frame_strides:  # the saved (epoch, offset) indexes that clip list
            raise UserError(f"{out}: the run trained with --frame-strides {','.join(map(str, saved_strides))}; "
                            f"resume it with the same (got {','.join(map(str, args.frame_strides))})")
        from vlocnetpp_core.checkpoint import read_checkpoint_tensors

        tensors, _ = read_checkpoint_tensors(out / "last.safetensors")
        if model.semantic_fusion is None:  # a run from before single-task stages were built without it
            tensors = {k: v for k, v in tensors.items() if not k.startswith("semantic_fusion.")}
        model.load_state_dict({k: v.to(device) for k, v in tensors.items()})
        step, reference = int(meta["step"]), meta.get("best_reference")
        saved_lr = optimizer.param_groups[0]["lr"]
        if args.lr is None:
            lr = saved_lr
        elif args.lr != saved_lr:  # a step-down for the last part of a run: --resume --lr 1e-4
            for group in optimizer.param_groups:
                group["lr"] = args.lr
            log(f"learning rate {saved_lr:g} -> {args.lr:g} from step {step}")
        if reference is None and val_clips is not None:
            best = math.inf  # a run from before the selection score ranked by validation loss: rank anew
        else:
            best = float(meta.get("best", math.inf))
        log(f"resumed at step {step}")
    net = torch.nn.parallel.DistributedDataParallel(model, find_unused_parameters=True) if distributed else model

    summary = {
        "stage": args.stage, "data": str(args.data), "train_frames": len(train_index), "train_sequences": len(train_index.sequences),
        "train_clips": len(train_clips), "frame_strides": list(args.frame_strides), "val_frames": len(val_index) if val_index is not None else 0, "clip_len": args.clip_len,
        "batch_size": args.batch_size, "lr": lr, "s_q_init": args.s_q_init, "crop_scale": crop_scale, "world_size": world, "init": sources, "seed": args.seed,
    }

    def checkpoint_meta(step_now: int, calibration: dict | None) -> dict:
        m = {"training": {**summary, "step": step_now}, "intrinsics": train_index.intrinsics.resized(*size).to_dict()}
        if calibration:
            m["calibration"] = calibration
        return m

    def write_files(step_now: int, calibration: dict | None, is_best: bool) -> None:
        save_checkpoint(out / "last", model, checkpoint_meta(step_now, calibration))
        if is_best:
            save_checkpoint(out / "best", model, checkpoint_meta(step_now, calibration))
        save_train_state(out, step=step_now, optimizer=optimizer, criterion=criterion, extra={"best": best, "best_reference": reference, "args": _jsonable_args(args)})

    progress = None
    if is_main and not args.no_progress:
        from tqdm import tqdm

        progress = tqdm(total=total, initial=step, desc=f"train {args.stage}", unit="step", dynamic_ncols=True)
    last_save = time.monotonic()
    calibration = None
    log(f"{args.stage}: {len(train_clips)} clips (frame strides {','.join(map(str, args.frame_strides))}), {steps_per_epoch} steps/epoch, {total} steps, lr {lr:g}, batch {args.batch_size}, device {device}")
    with open(log_path, "a") if is_main else open(os.devnull, "w") as logf:
        while step < total:
            epoch, offset = divmod(step, steps_per_epoch)
            sampler.set_position(epoch, offset)
            loader = torch.utils.data.DataLoader(
                SeededClips(train_clips), batch_size=sampler.per_rank, sampler=sampler, num_workers=args.workers,
                persistent_workers=False, drop_last=True,
            )
            for batch in loader:
                t0 = time.perf_counter()
                net.train()
                if frozen_trunk:
                    model.trunk.eval()
                batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
                outputs = _forward(net, batch, args.stage)
                loss, parts = criterion(outputs, batch)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                step += 1
                dt = time.perf_counter() - t0
                rec = {"step": step, "epoch": epoch, "lr": optimizer.param_groups[0]["lr"], "loss": float(loss.detach()),
                       **{k: float(v) for k, v in parts.items()}, "clips_per_s": args.batch_size / dt}
                logf.write(json.dumps(rec) + "\n")
                if progress is not None:
                    progress.update(1)
                    progress.set_postfix({k: f"{v:.3g}" for k, v in rec.items() if k in ("loss", *parts)} | {"clips/s": f"{rec['clips_per_s']:.1f}"})
                validate_now = step % args.val_every == 0 or step == total
                if validate_now:
                    metrics, calibration = (None, None)
                    if is_main and val_clips is not None:
                        metrics, calibration = validate(model, criterion, val_clips, args.stage, device)
                        logf.write(json.dumps({"step": step, "validation": metrics}) + "\n")
                        log(f"step {step}: validation {json.dumps(metrics)}")
                    if metrics:
                        reference = reference or metrics
                        score = selection_score(metrics, reference)
                    else:
                        score = float(loss.detach())
                    is_best = score < best
                    best = min(best, score)
                    if is_main:
                        write_files(step, calibration, is_best)
                    last_save = time.monotonic()
                elif is_main and time.monotonic() - last_save > args.save_every_s:
                    write_files(step, calibration, False)
                    last_save = time.monotonic()
                logf.flush()
                if step >= total:
                    break
    if is_main and total == 0:  # nothing to train: write the initialised network (e.g. mtl assembled from its stages)
        write_files(step, calibration, True)
    if progress is not None:
        progress.close()
    if distributed:
        dist.barrier()
        dist.destroy_process_group()
    log(f"done: {out / 'last.safetensors'} (best: {out / 'best.safetensors'})")
    return 0


def _forward(net, batch: dict, stage: str):
    """Unroll the clip. ``stl-seg`` warps with the ground-truth relative pose (its odometry stream is untrained)."""
    from vlocnetpp_core import geometry

    warp = None
    if stage == "stl-seg":
        warp = geometry.pose_to_matrix(batch["rel_t"], batch["rel_q"])
    return net(batch["image"], batch["K"], warp_rel_pose=warp, tasks=STAGE_TASKS[stage])  # forward = forward_clip


@torch.no_grad()
def validate(model, criterion, clips, stage: str, device) -> tuple[dict, dict]:
    """Mean validation losses (eval mode) and the covariance calibration of pose and odometry errors."""
    from vlocnetpp_core import geometry

    model.eval()
    loader = torch.utils.data.DataLoader(clips, batch_size=8, shuffle=False, num_workers=0)
    sums: dict[str, float] = {}
    n = 0
    pose_err, odo_err = [], []
    for batch in loader:
        batch = {k: v.to(device) for k, v in batch.items()}
        outputs = _forward(model, batch, stage)
        loss, parts = criterion(outputs, batch)
        for k, v in {"loss": loss, **parts}.items():
            sums[k] = sums.get(k, 0.0) + float(v)
        n += 1
        for i, o in enumerate(outputs):
            if o.xyz is not None:
                pose_err.append(_pose_residual(o.xyz, o.quat, batch["t"][:, i], batch["q"][:, i], geometry))
            if i > 0 and o.rel_xyz is not None:
                odo_err.append(_pose_residual(o.rel_xyz, o.rel_quat, batch["rel_t"][:, i], batch["rel_q"][:, i], geometry))
    model.train()
    metrics = {k: v / max(n, 1) for k, v in sums.items()}
    calib = {
        "pose_variance": _variance(pose_err),
        "odometry_variance": _variance(odo_err),
        "frames": int(sum(len(e) for e in pose_err)),
        "source": f"validation ({stage}, {len(clips)} clips)",
        "note": "per-axis variance of validation errors: x, y, z (m^2), rotation about x, y, z (rad^2); odometry per frame",
    }
    return metrics, calib


def _pose_residual(xyz, quat, t, q, geometry) -> np.ndarray:
    """``(B, 6)`` residual: translation error (m) and rotation-vector error (rad) of prediction vs truth."""
    dq = geometry.quat_normalize(geometry.quat_mul(geometry.quat_inverse(q.double()), quat.double()))
    angle = 2 * torch.atan2(dq[:, 1:].norm(dim=1), dq[:, 0].clamp_min(0))
    axis = dq[:, 1:] / dq[:, 1:].norm(dim=1, keepdim=True).clamp_min(1e-12)
    return torch.cat((xyz.double() - t.double(), axis * angle[:, None]), 1).cpu().numpy()


def _variance(chunks: list[np.ndarray]) -> list[float] | None:
    if not chunks:
        return None
    e = np.concatenate(chunks)
    return [float(v) for v in np.mean(e**2, axis=0)]


def _jsonable_args(args: argparse.Namespace) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in vars(args).items()
            if not k.startswith("_") and isinstance(v, (str, int, float, bool, list, tuple, type(None)))}


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m vlocnetpp_core.train", description=__doc__.splitlines()[0])
    add_arguments(parser)
    try:
        return run(parser.parse_args())
    except UserError as err:
        print(f"vlocnetpp train: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

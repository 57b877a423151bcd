"""The :class:`Trainer` of ``vlocnetpp train``: set-up, resume, optimiser steps, validation and saving (``--init``
sources: ``train_init``).

One run of a :class:`~vlocnetpp_core.training.config.TrainConfig` trains one stage, by the rules of its
:class:`~vlocnetpp_core.model.stages.StageSpec` (see ``train.py`` for the flags and the run folder). Every step
unrolls clips through ``model.forward_clip``, so the previous-frame features the network fuses come from its own
previous step. Distributed runs (``torchrun``) give each rank a disjoint share of every batch; rank 0 alone
validates and writes.
"""

from __future__ import annotations

import dataclasses
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
from vlocnetpp_core.model.assembly import builds_semantic_fusion, frozen_trunk
from vlocnetpp_core.model.stages import stage_spec, stage_tasks
from vlocnetpp_core.outputs import make_dirs
from vlocnetpp_core.threads import use_threads
from vlocnetpp_core.training.config import TrainConfig
from vlocnetpp_core.training.losses import selection_score
from vlocnetpp_core.training.lr_schedule import LearningRatePhase
from vlocnetpp_core.training.train_data import EpochSampler, SeededClips, split_validation, training_clips
from vlocnetpp_core.training.train_init import load_inits
from vlocnetpp_core.training.validation import float32_outputs, forward_stage, validate


class Trainer:
    """One training run: ``Trainer(config).run()``. ``config`` is the run's :class:`TrainConfig`, ``model_config``
    the network's ``ModelConfig``."""

    def __init__(self, config: TrainConfig):
        self.config = c = config
        self._setup_process()
        self._setup_data()
        self._setup_model()
        self.step, self.best, self.reference, self.calibration = 0, math.inf, None, None
        self.phase = LearningRatePhase(0, self.lr, c.lr_end, self.total)
        if c.resume or c.restart:
            self._resume(fresh=c.restart)
        self.net = (
            torch.nn.parallel.DistributedDataParallel(self.model, find_unused_parameters=True)
            if self.distributed
            else self.model
        )
        if self.is_main:  # once every input was read and checked: a refused run leaves no folder behind
            make_dirs(self.out, f"--out {self.out}")

    def log(self, msg: str) -> None:
        if self.is_main:
            print(f"[train] {msg}", file=sys.stderr, flush=True)

    # ------------------------------------------------------------------ set-up

    def _setup_process(self) -> None:
        """Ranks, device and threads (the run folder is made at the end of ``__init__``)."""
        c = self.config
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        self.distributed = self.world > 1
        self.is_main = self.rank == 0  # before the first log line
        self.device = torch.device(c.device or ("cuda" if torch.cuda.is_available() else "cpu"))
        if self.distributed:
            if self.device.type == "cuda":
                self.device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
                torch.cuda.set_device(self.device)
            dist.init_process_group("nccl" if self.device.type == "cuda" else "gloo")
        use_threads(c.threads)
        if (
            c.bf16
            and self.device.type == "cpu"
            and not (torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
        ):
            self.log(
                "--bf16: this CPU has neither AVX-512 BF16 nor AMX, so bfloat16 autocast runs slower here than float32"
            )
        if c.batch_size % self.world:
            raise UserError(f"--batch-size {c.batch_size} must be divisible by the number of processes ({self.world})")
        self.out = Path(c.out)
        torch.manual_seed(c.seed)

    def _setup_data(self) -> None:
        """The model config (its input size), training and validation clips, the sampler and the step count."""
        from vlocnetpp_core.data import ClipDataset, make_transform, open_dataset
        from vlocnetpp_core.model import load_model_config

        c = self.config
        config = load_model_config(c.config)
        if config.semantic_fusion and not builds_semantic_fusion(c.stage, c.steps):
            config = dataclasses.replace(config, semantic_fusion=False)  # mtl training starts it as an identity
            self.log(
                f"{c.stage}{' with no steps' if c.stage == 'mtl' else ''}: the network is built without the Res4c "
                "semantic fusion, which only mtl training learns"
            )
        self.model_config, self.size = config, tuple(config.input_size)
        self.tasks = stage_tasks(
            c.stage, config.tasks
        )  # mtl without the semantic stream: loc + vo (train.run refuses stl-seg)
        self.train_index = open_dataset(c.data, c.format, "train", c.intrinsics)
        if c.val_data:
            self.val_index = open_dataset(c.val_data, c.format, c.val_split, c.intrinsics)
        else:
            self.train_index, self.val_index = split_validation(self.train_index)
        self.crop_scale = c.crop
        transform = make_transform(True, self.size, scale=(1.0, self.crop_scale), flip=stage_spec(c.stage).mirrors)
        cache_size = (
            (round(self.size[0] * self.crop_scale), round(self.size[1] * self.crop_scale)) if c.steps != 0 else None
        )
        seg = "seg" in self.tasks  # depth and labels are decoded only for a run that trains segmentation
        self.train_clips = training_clips(
            self.train_index, c.clip_len, transform, c.frame_strides, seg, cache_size, self.log
        )
        if len(self.train_clips) == 0:
            raise UserError(f"{c.data}: no training clips of {c.clip_len} frames")
        self.val_clips = None
        if self.val_index is not None:
            # at every training stride: at one spacing a constant odometry step can score well (docs/training.md)
            self.val_clips = [
                ClipDataset(
                    self.val_index, c.clip_len, make_transform(False, self.size), stride=s, depth=seg, labels=seg
                )
                for s in sorted(c.frame_strides)
            ]
        self.sampler = EpochSampler(len(self.train_clips), c.batch_size, c.seed, self.rank, self.world)
        epochs = 30.0 if c.epochs is None else c.epochs
        self.total = c.steps if c.steps is not None else int(math.ceil(epochs * self.sampler.batches_per_epoch))

    def _setup_model(self) -> None:
        """The network (position prior, inits, backbone), the loss with its learned weights, the optimiser."""
        from vlocnetpp_core.model import VLocNetPP, train_only
        from vlocnetpp_core.training.losses import VLocNetLoss

        c = self.config
        self.model = model = VLocNetPP(self.model_config)
        records = self.train_index.records
        model.set_pose_prior(np.array([r.t for r in records]), np.array([r.q for r in records]), seed=c.seed)
        model.to(self.device)
        self.criterion = VLocNetLoss(self.tasks, depth=self.model_config.warping, s_q_init=c.s_q_init).to(self.device)
        self.sources = load_inits(model, self.criterion, list(c.init), c.stage, self.log) if c.init else []
        if c.init_backbone:
            from vlocnetpp_core.model import load_backbone_weights

            self.log(f"init-backbone: {load_backbone_weights(model, c.init_backbone)}")
        self.frozen = self._frozen_parts()
        params = train_only(model, c.stage, self.frozen)
        if not params:
            raise UserError(f"--freeze {','.join(self.frozen)}: nothing of what {c.stage} trains is left to train")
        params += list(self.criterion.parameters())
        self.lr = c.learning_rate
        self.optimizer = torch.optim.Adam(params, lr=self.lr, betas=(0.9, 0.999), eps=1e-10)

    def _frozen_parts(self) -> tuple[str, ...]:
        """``--freeze``, plus the trunk of one pose stream trained on top of the other's: kept as the first stage
        learned it (weights and BatchNorm statistics), so that mtl can combine the two streams consistently."""
        frozen = set(self.config.freeze)
        if frozen_trunk(self.config.stage, [src["stage"] for src in self.sources]):
            frozen.add("trunk")
        missing = [part for part in frozen if getattr(self.model, part) is None]
        if missing:
            raise UserError(
                f"--freeze {','.join(missing)}: this network (--config {self.config.config}) has no such part"
            )
        return tuple(sorted(frozen))

    def _resume(self, fresh: bool = False) -> None:
        """Weights, optimiser, loss weights, RNG, step and best score of the run in ``--out``; ``--lr`` steps the rate.
        ``fresh`` (``--restart``, a warm restart): the optimiser state (Adam's moments) and the learned loss weights
        start anew, as at the start of the run, and only the weights, RNG, step and best score come back."""
        from vlocnetpp_core.inference.checkpoint import read_checkpoint_tensors
        from vlocnetpp_core.training.train_state import load_train_state

        c, out = self.config, self.out
        meta = load_train_state(
            out, optimizer=None if fresh else self.optimizer, criterion=None if fresh else self.criterion
        )
        saved_strides = tuple(meta.get("config", meta.get("args", {})).get("frame_strides") or c.frame_strides)
        if saved_strides != c.frame_strides:  # the saved (epoch, offset) indexes that clip list
            raise UserError(
                f"{out}: the run trained with --frame-strides {','.join(map(str, saved_strides))}; "
                f"resume it with the same (got {','.join(map(str, c.frame_strides))})"
            )
        tensors, _ = read_checkpoint_tensors(out / "last.safetensors")
        self.model.load_state_dict({k: v.to(self.device) for k, v in tensors.items()})
        self.step, self.reference = int(meta["step"]), meta.get("best_reference")
        saved_lr = float(meta["optimizer"]["param_groups"][0]["lr"])
        self.lr = saved_lr if c.lr is None else c.lr  # --resume --lr 1e-4: a step-down for the last part of a run
        self.phase = LearningRatePhase(self.step, self.lr, c.lr_end, self.total).continues(meta.get("lr_phase"))
        if self.phase.start == self.step and self.phase.at(self.step) != saved_lr:
            self.log(f"learning rate {saved_lr:g} -> {self.phase.at(self.step):g} from step {self.step}")
        self.best = float(meta.get("best", math.inf))
        self.log(f"{'restarted (fresh optimiser state and loss weights)' if fresh else 'resumed'} at step {self.step}")

    # ------------------------------------------------------------------ the loop

    def run(self) -> None:
        """Train to ``total`` steps, validating and saving every ``--val-every`` steps (and at least every
        ``--save-every-s``)."""
        c = self.config
        progress = None
        if self.is_main and not c.no_progress:
            from tqdm import tqdm

            progress = tqdm(
                total=self.total, initial=self.step, desc=f"train {c.stage}", unit="step", dynamic_ncols=True
            )
        self.log(
            f"{c.stage}: {len(self.train_clips)} clips (frame strides {','.join(map(str, c.frame_strides))}), "
            f"{self.sampler.batches_per_epoch} steps/epoch, {self.total} steps, "
            f"lr {self.lr:g}, batch {c.batch_size}, device {self.device}"
        )
        self.last_save = time.monotonic()
        try:
            self._loop(progress)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: keep the steps since the last save
            if self.is_main and self.step > 0:
                self.save(False)
                self.log(
                    f"interrupted at step {self.step}: "
                    f"saved ({self.out / 'last.safetensors'}); --resume continues from there"
                )
            raise
        if (
            self.is_main and self.total == 0
        ):  # nothing to train: write the initialised network (e.g. mtl assembled from its stages)
            self.save(True)
        if progress is not None:
            progress.close()
        if self.distributed:
            dist.barrier()
            dist.destroy_process_group()
        self.log(f"done: {self.out / 'last.safetensors'} (best: {self.out / 'best.safetensors'})")

    def _loop(self, progress) -> None:
        """Steps from ``self.step`` to ``total``, appending each step's record to ``log.jsonl``."""
        c = self.config
        with open(self.out / "log.jsonl", "a") if self.is_main else open(os.devnull, "w") as logf:
            while self.step < self.total:
                epoch, offset = divmod(self.step, self.sampler.batches_per_epoch)
                self.sampler.set_position(epoch, offset)
                loader = torch.utils.data.DataLoader(
                    SeededClips(self.train_clips),
                    batch_size=self.sampler.per_rank,
                    sampler=self.sampler,
                    num_workers=c.workers,
                    persistent_workers=False,
                    drop_last=True,
                )
                for batch in loader:
                    rec = self.train_step(batch, epoch)
                    logf.write(json.dumps(rec) + "\n")
                    if progress is not None:
                        progress.update(1)
                        shown = {
                            k: f"{v:.3g}" for k, v in rec.items() if k not in ("step", "epoch", "lr", "clips_per_s")
                        }
                        progress.set_postfix(shown | {"clips/s": f"{rec['clips_per_s']:.1f}"})
                    self._validate_or_save(rec["loss"], logf)
                    logf.flush()
                    if self.step >= self.total:
                        break

    def train_step(self, batch: dict[str, torch.Tensor], epoch: int) -> dict:
        """One optimiser step on a batch of clips; returns the log record (every loss term, the rate, clips/s)."""
        t0 = time.perf_counter()
        self.net.train()
        for part in self.frozen:
            getattr(self.model, part).eval()
        batch = {k: v.to(self.device, non_blocking=True) for k, v in batch.items()}
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.config.bf16):
            outputs = forward_stage(self.net, batch, self.config.stage)
        loss, parts = self.criterion([float32_outputs(o) for o in outputs], batch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        for group in self.optimizer.param_groups:
            group["lr"] = self.phase.at(self.step)
        self.optimizer.step()
        self.step += 1
        return {
            "step": self.step,
            "epoch": epoch,
            "lr": self.optimizer.param_groups[0]["lr"],
            "loss": float(loss.detach()),
            **{k: float(v) for k, v in parts.items()},
            "clips_per_s": self.config.batch_size / (time.perf_counter() - t0),
        }

    def _validate_or_save(self, loss: float, logf) -> None:
        """At a validation step: validate (rank 0), rank by :func:`selection_score` and save; else save when due."""
        if (self.config.val_every and self.step % self.config.val_every == 0) or self.step == self.total:
            metrics = None
            if self.is_main and self.val_clips is not None:
                metrics, self.calibration = validate(
                    self.model, self.criterion, self.val_clips, self.config.stage, self.device
                )
                logf.write(json.dumps({"step": self.step, "validation": metrics}) + "\n")
                self.log(f"step {self.step}: validation {json.dumps(metrics)}")
            if metrics:
                self.reference = self.reference or metrics
                score = selection_score(metrics, self.reference)
            else:
                score = loss
            is_best = score < self.best
            self.best = min(self.best, score)
            if self.is_main:
                self.save(is_best)
            self.last_save = time.monotonic()
        elif self.is_main and time.monotonic() - self.last_save > self.config.save_every_s:
            self.save(False)
            self.last_save = time.monotonic()

    def save(self, is_best: bool) -> None:
        """``last`` (and ``best``) checkpoints with their sidecar, and the resumable state, atomically."""
        from vlocnetpp_core.inference.checkpoint import save_checkpoint
        from vlocnetpp_core.training.train_state import save_train_state

        meta = {
            "training": {**self.summary(), "step": self.step},
            "intrinsics": self.train_index.intrinsics.resized(*self.size).to_dict(),
        }
        if self.calibration:
            meta["calibration"] = self.calibration
        save_checkpoint(self.out / "last", self.model, meta)
        if is_best:
            save_checkpoint(self.out / "best", self.model, meta)
        save_train_state(
            self.out,
            step=self.step,
            optimizer=self.optimizer,
            criterion=self.criterion,
            extra={
                "best": self.best,
                "best_reference": self.reference,
                "lr_phase": self.phase.to_dict(),
                "config": self.config.to_dict(),
            },
        )

    def summary(self) -> dict:
        """The ``training`` entry of the checkpoint sidecars."""
        c = self.config
        return {
            "stage": c.stage,
            "data": str(c.data),
            "train_frames": len(self.train_index),
            "train_sequences": len(self.train_index.sequences),
            "train_clips": len(self.train_clips),
            "frame_strides": list(c.frame_strides),
            "val_frames": len(self.val_index) if self.val_index is not None else 0,
            "clip_len": c.clip_len,
            "batch_size": c.batch_size,
            "lr": self.lr,
            "lr_end": c.lr_end,
            "s_q_init": c.s_q_init,
            "crop_scale": self.crop_scale,
            "world_size": self.world,
            "init": self.sources,
            "frozen": list(self.frozen),
            "seed": c.seed,
        }


# --------------------------------------------------------------------------- forward and validation

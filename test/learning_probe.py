"""Learning checks that hold on any CPU: the raw loss terms of a FIXED batch, before and after training.

A training log's early and late means follow the path of the optimisation, which rounding (thread count, SIMD
width, library version) changes from one machine to the next. The loss of one fixed batch (every training clip
of the run, at test-time preprocessing) is a function of the weights alone; training must lower it by a factor
wide enough to hold on every path. The probe runs a copy of the network with batch-statistics BatchNorm (the
statistics of the probe batch, as in training, so that updated running statistics alone cannot lower it) and
dropout off, under ``no_grad`` and with torch's RNG state restored, so it changes neither the run nor its data
order.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Iterator

import torch

from vlocnetpp_core.cli import build_parser
from vlocnetpp_core.training.config import TrainConfig


@contextlib.contextmanager
def deterministic() -> Iterator[None]:
    """Torch's deterministic kernels (where torch has them) for the block; the previous setting after it."""
    before, warn = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before, warn_only=warn)


def probe_batch(trainer) -> dict[str, torch.Tensor]:
    """Every training clip of ``trainer``'s run (stride 1, no augmentation) as one batch."""
    from vlocnetpp_core.data import ClipDataset, make_transform

    seg = "seg" in trainer.tasks
    clips = ClipDataset(
        trainer.train_index, trainer.config.clip_len, make_transform(False, trainer.size), depth=seg, labels=seg
    )
    return torch.utils.data.default_collate([clips[i] for i in range(len(clips))])


@torch.no_grad()
def probe_losses(model, criterion, batch: dict[str, torch.Tensor], stage: str) -> dict[str, float]:
    """The raw loss terms (``parts``, not the learned weighting) of ``model`` on ``batch`` (module doc)."""
    from vlocnetpp_core.training.validation import forward_stage

    probe = copy.deepcopy(model).train()
    for m in probe.modules():
        if isinstance(m, torch.nn.Dropout):
            m.eval()
    with torch.random.fork_rng():
        _, parts = criterion(forward_stage(probe, batch, stage), batch)
    return {k: float(v) for k, v in parts.items()}


def train_probed(args: list[str]) -> tuple[dict[str, float], dict[str, float]]:
    """Run ``vlocnetpp train ARGS`` in-process; the probe losses of its network before and after the run."""
    from vlocnetpp_core.training.trainer import Trainer

    trainer = Trainer(train_config(args))
    batch = probe_batch(trainer)
    before = probe_losses(trainer.model, trainer.criterion, batch, trainer.config.stage)
    trainer.run()
    return before, probe_losses(trainer.model, trainer.criterion, batch, trainer.config.stage)


def ratios(before: dict[str, float], after: dict[str, float], keys) -> dict[str, float]:
    """``after / before`` of each key."""
    return {k: after[k] / before[k] for k in keys}


def train_config(argv: list[str]) -> TrainConfig:
    """The :class:`TrainConfig` of a ``vlocnetpp train`` command line (``argv`` starts with ``train``)."""
    from vlocnetpp_core.training.train import train_config as of_args

    return of_args(build_parser("train").parse_args(argv))

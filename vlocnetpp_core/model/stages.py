"""Which stream each weight belongs to, and the rules of each training stage: :data:`STAGE_SPECS`, one row per stage.

Streams: ``global`` (the shared trunk stem..Res3 and the global Res4, Res5, temporal Res5a AWF
and pose head), ``odometry`` (Siamese Res4, Res5, pose head), ``semantic`` (AdapNet encoder,
the Res4f / Res5c warp AWFs, decoder), ``depth`` (the depth head for warping) and ``fusion``
(the inter-task AWF that fuses semantic features into the global stream at Res4c).

Stages (paper Sec. IV): ``stl-loc`` trains ``global``; ``stl-vo`` trains ``odometry`` and the
shared trunk (its I_t stream up to Res3 *is* the trunk); ``stl-seg`` trains ``semantic`` and
``depth``; ``mtl`` trains everything. On a pose-only network (config ``semantic_stream: false``:
no ``semantic``, ``depth`` or ``fusion`` weights) ``mtl`` trains ``loc`` + ``vo`` and ``stl-seg``
is refused (:func:`stage_tasks`). The trainer, :mod:`~vlocnetpp_core.model.assembly` (``--init``), the
losses, ``evaluate`` and docs/training.md read the table; a new stage is one row. This module imports
no torch at run time, so that a recipe is checked before torch loads.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from vlocnetpp_core.model.config import TASKS

if TYPE_CHECKING:
    from torch import nn

STREAMS = ("global", "odometry", "semantic", "depth", "fusion")
TASK_NAMES = {"loc": "global pose", "vo": "odometry", "seg": "segmentation"}


@dataclass(frozen=True)
class StageSpec:
    """The rules of one training stage.

    ``tasks``: what it runs and trains (``VLocNetPP.step(tasks=...)``, ``VLocNetLoss``); ``streams``: the streams
    whose weights it trains (:func:`stream_of`); ``trains_trunk``: whether that includes the shared trunk;
    ``init_rules``: what an ``--init`` checkpoint of another stage gives it (source stage -> rule of
    :mod:`~vlocnetpp_core.model.assembly`; any other source: ``"whole"``), ``multi_init``: the rule for each of
    several ``--init``; ``init_freezes_trunk``: any ``--init`` keeps the trunk frozen (a ``"trunk"`` rule always
    does); ``lr``: the default learning rate (paper); ``crop_scale``: the default geometric augmentation (1: none,
    as a crop falsifies pose targets); ``mirrors``: half its training clips are mirrored left-right (exact for
    relative poses, a mirrored world for global ones: only a stage that trains odometry and no global pose);
    ``warps_with_ground_truth``: the semantic stream warps with the true relative pose (its odometry is untrained).
    """

    name: str
    tasks: tuple[str, ...]
    streams: frozenset[str]
    trains_trunk: bool
    lr: float
    init_rules: Mapping[str, str] = field(default_factory=dict)
    multi_init: str = "whole"
    init_freezes_trunk: bool = False
    crop_scale: float = 1.0
    mirrors: bool = False
    warps_with_ground_truth: bool = False


STAGE_SPECS: dict[str, StageSpec] = {
    spec.name: spec
    for spec in (
        StageSpec(
            "stl-loc",
            ("loc",),
            frozenset({"global"}),
            trains_trunk=True,
            lr=1e-3,
            init_rules={"stl-vo": "trunk", "stl-seg": "encoder"},
        ),
        StageSpec(
            "stl-vo",
            ("vo",),
            frozenset({"odometry"}),
            trains_trunk=True,
            lr=1e-3,
            init_rules={"stl-loc": "trunk"},
            init_freezes_trunk=True,
            mirrors=True,
        ),
        StageSpec(
            "stl-seg",
            ("seg",),
            frozenset({"semantic", "depth"}),
            trains_trunk=False,
            lr=1e-3,
            crop_scale=1.15,
            warps_with_ground_truth=True,
        ),
        StageSpec("mtl", ("loc", "vo", "seg"), frozenset(STREAMS), trains_trunk=True, lr=1e-4, multi_init="streams"),
    )
}
STAGES = tuple(STAGE_SPECS)
STAGE_TASKS: dict[str, tuple[str, ...]] = {name: spec.tasks for name, spec in STAGE_SPECS.items()}

_PREFIX_STREAM = {
    "trunk": "global",
    "global_stream": "global",
    "odometry": "odometry",
    "semantic": "semantic",
    "depth_head": "depth",
    "semantic_fusion": "fusion",
}


PARTS = tuple(_PREFIX_STREAM)  # the network's top-level modules, which ``vlocnetpp train --freeze`` names


def part_of(name: str) -> str:
    """Top-level module (one of :data:`PARTS`) of a parameter or buffer name (``"trunk.res3.0.conv1.weight"`` ->
    ``"trunk"``)."""
    part = name.removeprefix("module.").split(".", 1)[0]
    if part not in _PREFIX_STREAM:
        raise KeyError(f"{name!r} is not a VLocNetPP parameter name")
    return part


def stream_of(name: str) -> str:
    """Stream of a parameter or buffer name of :class:`VLocNetPP` (``"trunk.res3.0.conv1.weight"`` -> ``"global"``)."""
    return _PREFIX_STREAM[part_of(name)]


def stage_spec(stage: str) -> StageSpec:
    """The :data:`STAGE_SPECS` row of ``stage``; ``ValueError`` for an unknown stage."""
    if stage not in STAGE_SPECS:
        raise ValueError(f"unknown stage {stage!r}; expected one of {STAGES}")
    return STAGE_SPECS[stage]


def stage_tasks(stage: str, model_tasks: Iterable[str] = TASKS) -> tuple[str, ...]:
    """The tasks a run of ``stage`` trains on a network that has ``model_tasks`` (``ModelConfig.tasks``):
    :data:`STAGE_TASKS` of the stage, less those the network lacks (``mtl`` on a pose-only network:
    ``loc``, ``vo``). ``ValueError`` when none is left (``stl-seg`` without the semantic stream)."""
    have = set(model_tasks)
    tasks = tuple(t for t in stage_spec(stage).tasks if t in have)
    if not tasks:
        raise ValueError(
            f"stage {stage} trains the {' and '.join(TASK_NAMES[t] for t in STAGE_TASKS[stage])} stream, which this "
            f"model config does not have (semantic_stream: false, a pose-only network); it trains with "
            f"{', '.join(s for s in STAGES if set(STAGE_TASKS[s]) & have)}"
        )
    return tasks


def is_trained_in(name: str, stage: str) -> bool:
    """Whether ``stage`` trains the parameter ``name``: the trunk by its ``trains_trunk``, the rest by its
    ``streams``."""
    spec = stage_spec(stage)
    if part_of(name) == "trunk":
        return spec.trains_trunk
    return stream_of(name) in spec.streams


def trainable_parameters(model: nn.Module, stage: str, frozen: Iterable[str] = ()) -> Iterator[nn.Parameter]:
    """The parameters of ``model`` that ``stage`` trains (see the module docstring), less those of the ``frozen`` parts
    (:data:`PARTS`)."""
    stage_spec(stage)
    frozen = set(frozen)
    return (p for name, p in model.named_parameters() if is_trained_in(name, stage) and part_of(name) not in frozen)


def train_only(model: nn.Module, stage: str, frozen: Iterable[str] = ()) -> list[nn.Parameter]:
    """Let gradients reach only :func:`trainable_parameters` (``requires_grad``; every other weight of ``model``
    is kept out of autograd) and return them: what a ``stage`` step with the ``frozen`` parts optimises."""
    params = list(trainable_parameters(model, stage, frozen))
    model.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    return params


def params_per_stream(model: nn.Module) -> dict[str, int]:
    """Number of parameters (elements) per stream, every stream listed."""
    counts = dict.fromkeys(STREAMS, 0)
    for name, p in model.named_parameters():
        counts[stream_of(name)] += p.numel()
    return counts

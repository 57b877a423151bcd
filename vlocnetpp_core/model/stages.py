"""Which stream each weight belongs to, and which weights each training stage trains.

Streams: ``global`` (the shared trunk stem..Res3 and the global Res4, Res5, temporal Res5a AWF
and pose head), ``odometry`` (Siamese Res4, Res5, pose head), ``semantic`` (AdapNet encoder,
the Res4f / Res5c warp AWFs, decoder), ``depth`` (the depth head for warping) and ``fusion``
(the inter-task AWF that fuses semantic features into the global stream at Res4c).

Stages (paper Sec. IV): ``stl-loc`` trains ``global``; ``stl-vo`` trains ``odometry`` and the
shared trunk (its I_t stream up to Res3 *is* the trunk); ``stl-seg`` trains ``semantic`` and
``depth``; ``mtl`` trains everything. On a pose-only network (config ``semantic_stream: false``:
no ``semantic``, ``depth`` or ``fusion`` weights) ``mtl`` trains ``loc`` + ``vo`` and ``stl-seg``
is refused (:func:`stage_tasks`).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from torch import nn

from vlocnetpp_core.model.config import TASKS

STREAMS = ("global", "odometry", "semantic", "depth", "fusion")
STAGES = ("stl-loc", "stl-vo", "stl-seg", "mtl")
# Tasks (``VLocNetPP.step(tasks=...)`` and ``VLocNetLoss``) a stage runs.
STAGE_TASKS: dict[str, tuple[str, ...]] = {"stl-loc": ("loc",), "stl-vo": ("vo",), "stl-seg": ("seg",), "mtl": ("loc", "vo", "seg")}
TASK_NAMES = {"loc": "global pose", "vo": "odometry", "seg": "segmentation"}

_PREFIX_STREAM = {
    "trunk": "global",
    "global_stream": "global",
    "odometry": "odometry",
    "semantic": "semantic",
    "depth_head": "depth",
    "semantic_fusion": "fusion",
}
_STAGE_STREAMS = {
    "stl-loc": {"global"},
    "stl-vo": {"odometry"},
    "stl-seg": {"semantic", "depth"},
    "mtl": set(STREAMS),
}


PARTS = tuple(_PREFIX_STREAM)  # the network's top-level modules, which ``vlocnetpp train --freeze`` names


def part_of(name: str) -> str:
    """Top-level module (one of :data:`PARTS`) of a parameter or buffer name (``"trunk.res3.0.conv1.weight"`` -> ``"trunk"``)."""
    part = name.removeprefix("module.").split(".", 1)[0]
    if part not in _PREFIX_STREAM:
        raise KeyError(f"{name!r} is not a VLocNetPP parameter name")
    return part


def stream_of(name: str) -> str:
    """Stream of a parameter or buffer name of :class:`VLocNetPP` (``"trunk.res3.0.conv1.weight"`` -> ``"global"``)."""
    return _PREFIX_STREAM[part_of(name)]


def _check_stage(stage: str) -> None:
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; expected one of {STAGES}")


def stage_tasks(stage: str, model_tasks: Iterable[str] = TASKS) -> tuple[str, ...]:
    """The tasks a run of ``stage`` trains on a network that has ``model_tasks`` (``ModelConfig.tasks``):
    :data:`STAGE_TASKS` of the stage, less those the network lacks (``mtl`` on a pose-only network:
    ``loc``, ``vo``). ``ValueError`` when none is left (``stl-seg`` without the semantic stream)."""
    _check_stage(stage)
    have = set(model_tasks)
    tasks = tuple(t for t in STAGE_TASKS[stage] if t in have)
    if not tasks:
        raise ValueError(f"stage {stage} trains the {' and '.join(TASK_NAMES[t] for t in STAGE_TASKS[stage])} stream, which this "
                         f"model config does not have (semantic_stream: false, a pose-only network); it trains with "
                         f"{', '.join(s for s in STAGES if set(STAGE_TASKS[s]) & have)}")
    return tasks


def mirrors_clips(tasks: Iterable[str]) -> bool:
    """Whether a run's training clips are mirrored left-right half the time (``transforms.HorizontalFlip``): a run
    that trains odometry and no global pose (``stl-vo``). A mirrored clip's relative poses are exact, mirrored with
    its frames (yaw and roll change sign), so the stream sees every turn both ways and a constant turn gains
    nothing: one of two flattened-head runs without it stuck at a constant rotation, no mirrored run did
    (docs/results.md, 2026-12-16). Its absolute poses lie in a mirrored world that the global stream must not
    learn. ``stl-seg`` is left as measured, unmirrored."""
    tasks = set(tasks)
    return "vo" in tasks and "loc" not in tasks


def is_trained_in(name: str, stage: str) -> bool:
    """Whether ``stage`` trains the parameter ``name``."""
    _check_stage(stage)
    if stage == "stl-vo" and name.removeprefix("module.").startswith("trunk."):
        return True
    return stream_of(name) in _STAGE_STREAMS[stage]


def trainable_parameters(model: nn.Module, stage: str, frozen: Iterable[str] = ()) -> Iterator[nn.Parameter]:
    """The parameters of ``model`` that ``stage`` trains (see the module docstring), less those of the ``frozen`` parts (:data:`PARTS`)."""
    _check_stage(stage)
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

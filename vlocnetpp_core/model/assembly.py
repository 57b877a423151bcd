"""How a training stage is assembled from ``--init`` checkpoints: one table of rules that training
(which tensors to load, what stays frozen, whether the Res4c fusion is built) and ``evaluate``
(which tasks a checkpoint was trained for) both read.

A run's :class:`~vlocnetpp_core.model.stages.StageSpec` (``init_rules``, ``multi_init``) says which rule a
checkpoint of stage ``source`` follows:

* ``"whole"`` (the default): every tensor whose name exists in the run's network;
* ``"streams"`` (``mtl`` from several checkpoints): each stream from the checkpoint of the stage that
  trains it (:data:`STREAM_SOURCE`, the single-task stage whose ``streams`` hold it); an ``mtl`` checkpoint among them
  (an assembled or multitask network) gives every stream, and a later single-task one replaces its own (e.g. the shipped
  model with a retrained odometry stream:
  ``--init models/vlocnetpp_lite.safetensors --init runs/stl-vo/best.safetensors``);
* ``"trunk"`` (one pose stage on the other: ``stl-loc`` on ``stl-vo``, ``stl-vo`` on ``stl-loc``): only
  the shared trunk, kept frozen (weights and BatchNorm statistics) so ``mtl`` can combine the two
  pose streams; the other stream is not carried (its head may differ, e.g. the global stream's with
  or without position anchors);
* ``"encoder"`` (``stl-loc`` on ``stl-seg``): the semantic encoder as the global stream's
  backbone (our stand-in for ImageNet weights; :func:`semantic_encoder_as_global_stream`).

Only ``"whole"`` and ``"streams"`` pass the source stage's tasks on to the run. A pose-only network
(no semantic stream) follows the same rules: tensors of streams it lacks are not in its state dict
and are left out, and :func:`trained_tasks` counts only the tasks it has.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

from vlocnetpp_core.model.config import TASKS
from vlocnetpp_core.model.stages import STAGE_SPECS, stage_spec, stream_of

# each stream from the single-task stage that trains it (the fusion: none)
STREAM_SOURCE = {stream: spec.name for spec in STAGE_SPECS.values() if len(spec.tasks) == 1 for stream in spec.streams}
TASK_CARRYING_RULES = ("whole", "streams")


def init_rule(run: str, source: str | None, n_inits: int) -> str:
    """The rule for a checkpoint of stage ``source`` given to a run of stage ``run`` with ``n_inits`` checkpoints."""
    spec = stage_spec(run)
    if n_inits > 1 and spec.multi_init != "whole":
        return spec.multi_init
    return spec.init_rules.get(source or "", "whole")


def init_tensors(
    rule: str, source: str | None, tensors: dict[str, torch.Tensor], own: dict[str, torch.Tensor]
) -> dict[str, torch.Tensor]:
    """The tensors of a checkpoint (of stage ``source``) that ``rule`` loads into a network whose state dict is
    ``own``."""
    if rule == "encoder":
        return semantic_encoder_as_global_stream(tensors, own)
    if rule == "trunk":
        return {k: v for k, v in tensors.items() if k.startswith("trunk.")}
    if rule == "streams":
        return {
            k: v
            for k, v in tensors.items()
            if k in own and (source == "mtl" or STREAM_SOURCE.get(stream_of(k)) == source)
        }
    return {k: v for k, v in tensors.items() if k in own}


def frozen_trunk(run: str, sources: list[str | None]) -> bool:
    """Whether a run keeps the shared trunk frozen: one pose stream trained on top of the other's trunk
    (``stl-vo`` initialised from anything: ``init_freezes_trunk``; ``stl-loc`` on an ``stl-vo`` trunk: a ``"trunk"``
    rule)."""
    if stage_spec(run).init_freezes_trunk and sources:
        return True
    return any(init_rule(run, s, len(sources)) == "trunk" for s in sources)


def builds_semantic_fusion(stage: str, steps: int | None) -> bool:
    """Only a stage that trains the ``fusion`` stream (``mtl``) learns the Res4c AWF: every other run (and
    ``mtl --steps 0``, which assembles the stages) is built without it (a plain untrained AWF ends in a ReLU that clips
    the global stream)."""
    return "fusion" in stage_spec(stage).streams and steps != 0


def trained_tasks(training: dict, model_tasks: Iterable[str] = TASKS) -> set[str] | None:
    """The tasks (``loc``, ``vo``, ``seg``) whose streams a checkpoint's weights were trained for, from its
    sidecar's ``training`` entry: its stage's, plus those of ``--init`` checkpoints whose rule carries
    them, among the tasks its network has (``model_tasks``, ``ModelConfig.tasks``: no ``seg`` pose-only).
    One level deep: the sidecar records the stages of its inits, not theirs. A run of 0 steps
    trained nothing itself. ``set()`` for a freshly initialised checkpoint, None when no stage is recorded."""
    stage = training.get("stage")
    if stage == "init":
        return set()
    if stage not in STAGE_SPECS:
        return None
    tasks = set(STAGE_SPECS[stage].tasks) if training.get("step", 1) > 0 else set()
    inits = training.get("init") or []
    for source in inits:
        if (
            source.get("stage") in STAGE_SPECS
            and init_rule(stage, source.get("stage"), len(inits)) in TASK_CARRYING_RULES
        ):
            tasks |= set(STAGE_SPECS[source["stage"]].tasks)
    return tasks & set(model_tasks)


def semantic_encoder_as_global_stream(
    tensors: dict[str, torch.Tensor], own: dict[str, torch.Tensor]
) -> dict[str, torch.Tensor]:
    """An stl-seg encoder as the pre-trained backbone of stl-loc (our stand-in for ImageNet weights).

    ``semantic.{stem,res2,res3}.*`` -> ``trunk.*`` and ``semantic.{res4,res5}.*`` ->
    ``global_stream.{res4,res5}.*`` wherever the name and shape match (the multiscale blocks of
    the AdapNet encoder split their 3x3 convolutions, so those stay freshly initialised).
    """
    out = {}
    for key, value in tensors.items():
        if not key.startswith("semantic."):
            continue
        rest = key.removeprefix("semantic.")
        target = ("global_stream." if rest.startswith(("res4.", "res5.")) else "trunk.") + rest
        if target in own and own[target].shape == value.shape:
            out[target] = value
    return out

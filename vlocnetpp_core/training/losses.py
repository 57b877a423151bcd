"""VLocNet++ training losses (paper Eq. 1-3 and 6) with learned weights, on clip outputs.

Per clip of ``T`` frames (``outputs[t]`` are :class:`~vlocnetpp_core.model.StepOutput`):

* ``loc`` (Eq. 3): ``L_Euc + L_Rel`` as ``(L_x + L_x_rel) e^{-s_x} + s_x + (L_q + L_q_rel) e^{-s_q} + s_q`` with
  ``L_x = ||x_t - x^_t||``, ``L_q = ||q_t - q^_t||`` (the nearer of ``q^`` and ``-q^``) over every frame; ``L_Rel``
  (geometric consistency) compares the relative pose of the predicted global poses of frames t-1 and t,
  ``T^_{t-1}^{-1} T^_t`` (SE(3) form, docs/conventions.md, Relative pose), with the ground-truth ``rel_t, rel_q``
  over frames ``1..T-1``. **Departure from the paper**, which gives ``L_Rel`` weights of its own
  (``s_x_rel``, ``s_q_rel``): a learned weight tends to ``1 / L``, so the consistency errors, small on
  a camera that moves 0.5 m and a degree per frame, got weights 20x those of the global errors and
  training traded the global pose for smooth predictions until the stream predicted the mean of
  the campus (docs/results.md has the runs). Here the consistency errors, derived from the
  global predictions and in their units, share their weights.
  With position anchors (config ``global_pose_anchors``, a departure from the paper) ``loc`` adds
  the cross-entropy of the anchor scores against each frame's nearest anchor (weight 1, part
  ``anchor``): the classification that places the frame, before the offset refines it. Rotation
  anchors (config ``global_rotation_anchors``) add theirs likewise (part ``anchor_q``).
* ``vo`` (Eq. 3 of the odometry): the odometry outputs against ``rel_t, rel_q`` over frames
  ``1..T-1`` (frame 0 has no previous frame), weights ``s_x_vo, s_q_vo``.
* ``seg``: cross-entropy over pixels whose label is not 255, averaged over labelled pixels.
* ``depth``: L1 between log depths over pixels with ground-truth depth ``> 0`` (finite), on the
  depth head that warping uses; it belongs to the ``seg`` task (``stl-seg`` trains the head).

All ``s_x`` are initialised to 0 and all ``s_q`` to -3 (paper; ``s_q_init`` changes the latter). With several tasks
(``mtl``) the learned multitask weighting of Eq. 6 applies: ``L e^{-s} + s`` per task. For ``loc`` and
``vo`` the task weight of Eq. 6 is folded into their component weights (``e^{-s_loc} e^{-s_x}``
is one free weight): multiplying a loss that already holds learned weights by ``e^{-s_loc}``
makes the objective unbounded below as soon as the task loss turns negative, which happens
whenever an error drops below 1/e (``min_s a e^{-s} + s = 1 + log a``). ``seg`` and ``depth``
get their Eq. 6 weights ``s_seg``, ``s_depth`` (init 0). A term without support in the batch
(no labelled pixel, no valid depth, single-frame clips for the relative terms) is left out
entirely, so its learned weight does not drift.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from torch import nn
from torch.nn import functional as F

from vlocnetpp_core.classes import IGNORE_INDEX
from vlocnetpp_core.geometry import relative_pose
from vlocnetpp_core.model.stages import STAGE_TASKS
from vlocnetpp_core.model.step_types import StepOutput
from vlocnetpp_core.model.vlocnet import TASKS
from vlocnetpp_core.training.config import S_Q_INIT

S_X_INIT = 0.0


def pose_errors(
    xyz: torch.Tensor, quat: torch.Tensor, t: torch.Tensor, q: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean ``||t - xyz||_2`` and ``min(||q - quat||_2, ||q + quat||_2)`` over the batch: ``(..., 3)``, ``(..., 4)`` ->
    two scalars.

    ``q`` and ``-q`` are the same rotation. Canonical ``w >= 0`` quaternions jump to the other sign
    where ``w`` crosses 0 (a camera driving a loop passes such a heading every lap), so the plain
    difference would ask the network for a discontinuous output there.
    """
    q = q.to(quat.dtype)
    q_err = torch.minimum((q - quat).norm(dim=-1), (q + quat).norm(dim=-1))
    return (t.to(xyz.dtype) - xyz).norm(dim=-1).mean(), q_err.mean()


METRIC_TERMS = ("x", "q", "x_vo", "q_vo", "seg")
"""The errors that stand for the paper's metrics (global pose, odometry, segmentation): what
checkpoint selection compares. ``x_rel``/``q_rel`` (a consistency regulariser that a network
predicting one constant pose would minimise) and ``depth`` (an aid to warping) are left out."""


def selection_score(metrics: dict[str, float], reference: dict[str, float]) -> float:
    """Mean of ``metrics[k] / reference[k]`` over the :data:`METRIC_TERMS` both hold: lower is better.

    Validation losses with learned weights ``L e^{-s} + s`` cannot rank checkpoints: the ``s``
    keep moving, so the loss can fall while every error grows. The raw errors have units
    (metres, quaternion distance, cross-entropy), so each is taken relative to its value at a
    fixed reference (the run's first validation) and the tasks count alike.
    """
    terms = [k for k in METRIC_TERMS if k in metrics and k in reference]
    if not terms:
        raise ValueError(
            f"no metric term ({', '.join(METRIC_TERMS)}) in both {sorted(metrics)} and {sorted(reference)}"
        )
    return sum(metrics[k] / max(reference[k], 1e-12) for k in terms) / len(terms)


def weighted(loss: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Learned homoscedastic weighting ``loss * exp(-s) + s``."""
    return loss * torch.exp(-s) + s


def segmentation_loss(logits: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, int]:
    """Summed cross-entropy of ``logits (B, C, H, W)`` vs ``labels (B, H, W)`` (255 ignored), and the labelled pixel
    count."""
    labels = labels.long()
    if labels.shape[-2:] != logits.shape[-2:]:
        raise ValueError(f"labels {tuple(labels.shape)} do not match the logits {tuple(logits.shape)}")
    return F.cross_entropy(logits, labels, ignore_index=IGNORE_INDEX, reduction="sum"), int(
        (labels != IGNORE_INDEX).sum()
    )


def depth_loss(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, int]:
    """Summed ``|log pred - log target|`` over valid pixels (target ``> 0`` and finite), and their count;
    ``(B, 1, H, W)``."""
    if pred.shape != target.shape:
        raise ValueError(f"depth target {tuple(target.shape)} does not match the prediction {tuple(pred.shape)}")
    target = target.to(pred.dtype)
    valid = torch.isfinite(target) & (target > 0)
    safe = torch.where(valid, target, torch.ones_like(target))
    err = (torch.log(pred) - torch.log(safe)).abs()
    return torch.where(valid, err, torch.zeros_like(err)).sum(), int(valid.sum())


class VLocNetLoss(nn.Module):
    """The losses of the tasks (or the stage) given, from a clip's outputs and the batch dict.

    Args:
        tasks: a stage name (``"stl-loc"``, ``"stl-vo"``, ``"stl-seg"``, ``"mtl"``) or task names
            (``"loc"``, ``"vo"``, ``"seg"``).
        learned_weighting: learned Eq. 6 weights for ``seg`` and ``depth``; default: when more
            than one task is trained (``mtl``). Single-task ``seg`` sums ``L_seg + L_depth``.
        depth: whether the model has a depth head to supervise (config ``warping``).
        s_q_init: initial value of every rotation weight ``s_q`` (paper: -3; see ``train --s-q-init``).

    ``forward(outputs, batch)`` takes the ``T`` step outputs of a clip and the batch dict of
    ``ClipDataset`` (``t, q, rel_t, rel_q (B, T, 3|4)``, ``labels (B, T, H, W)``,
    ``depth (B, T, 1, H, W)``) and returns ``(total, parts)``; ``parts`` holds the raw errors
    (``x``, ``q``, ``x_rel``, ``q_rel``, ``anchor``, ``anchor_q``, ``x_vo``, ``q_vo``, ``seg``, ``depth``) and the task
    losses (``loc``, ``vo``), detached.
    """

    def __init__(
        self,
        tasks: str | Iterable[str] = TASKS,
        learned_weighting: bool | None = None,
        depth: bool = True,
        s_q_init: float = S_Q_INIT,
    ):
        super().__init__()
        if isinstance(tasks, str):
            if tasks not in STAGE_TASKS:
                raise ValueError(f"unknown stage {tasks!r}; expected one of {tuple(STAGE_TASKS)} or task names {TASKS}")
            tasks = STAGE_TASKS[tasks]
        self.tasks = tuple(t for t in TASKS if t in set(tasks))
        if not self.tasks or set(tasks) - set(TASKS):
            raise ValueError(f"tasks must be a non-empty subset of {TASKS}, got {tasks}")
        self.learned_weighting = len(self.tasks) > 1 if learned_weighting is None else learned_weighting
        self.depth = depth and "seg" in self.tasks

        def s(value: float) -> nn.Parameter:
            return nn.Parameter(torch.tensor(value))

        if "loc" in self.tasks:
            self.s_x, self.s_q = s(S_X_INIT), s(s_q_init)
        if "vo" in self.tasks:
            self.s_x_vo, self.s_q_vo = s(S_X_INIT), s(s_q_init)
        if "seg" in self.tasks and self.learned_weighting:
            self.s_seg = s(0.0)
            if self.depth:
                self.s_depth = s(0.0)

    def forward(
        self, outputs: Sequence[StepOutput], batch: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        terms: list[torch.Tensor] = []
        parts: dict[str, torch.Tensor] = {}
        T = len(outputs)
        if "loc" in self.tasks:
            xyz = torch.stack([_need(o.xyz, "xyz") for o in outputs], 1)
            quat = torch.stack([_need(o.quat, "quat") for o in outputs], 1)
            parts["x"], parts["q"] = pose_errors(xyz, quat, batch["t"][:, :T], batch["q"][:, :T])
            x_err, q_err = parts["x"], parts["q"]
            if T > 1:
                rel_xyz, rel_quat = relative_pose(xyz[:, :-1], quat[:, :-1], xyz[:, 1:], quat[:, 1:])
                parts["x_rel"], parts["q_rel"] = pose_errors(
                    rel_xyz, rel_quat, batch["rel_t"][:, 1:T], batch["rel_q"][:, 1:T]
                )
                x_err, q_err = x_err + parts["x_rel"], q_err + parts["q_rel"]
            loc = weighted(x_err, self.s_x) + weighted(q_err, self.s_q)
            if outputs[0].anchor_logits is not None:
                parts["anchor"] = anchor_loss(
                    [o.anchor_logits for o in outputs], outputs[0].anchor_xyz, batch["t"][:, :T]
                )
                loc = loc + parts["anchor"]
            if outputs[0].rotation_logits is not None:
                parts["anchor_q"] = rotation_anchor_loss(
                    [o.rotation_logits for o in outputs], outputs[0].anchor_quat, batch["q"][:, :T]
                )
                loc = loc + parts["anchor_q"]
            parts["loc"] = loc
            terms.append(loc)
        if "vo" in self.tasks and T > 1:
            rel_xyz = torch.stack([_need(o.rel_xyz, "rel_xyz") for o in outputs[1:]], 1)
            rel_quat = torch.stack([_need(o.rel_quat, "rel_quat") for o in outputs[1:]], 1)
            parts["x_vo"], parts["q_vo"] = pose_errors(
                rel_xyz, rel_quat, batch["rel_t"][:, 1:T], batch["rel_q"][:, 1:T]
            )
            parts["vo"] = weighted(parts["x_vo"], self.s_x_vo) + weighted(parts["q_vo"], self.s_q_vo)
            terms.append(parts["vo"])
        if "seg" in self.tasks:
            total, count = _sum_over_frames(
                segmentation_loss, [_need(o.seg_logits, "seg_logits") for o in outputs], batch["labels"]
            )
            if count:
                parts["seg"] = total / count
                terms.append(weighted(parts["seg"], self.s_seg) if self.learned_weighting else parts["seg"])
            if self.depth:
                total, count = _sum_over_frames(depth_loss, [_need(o.depth, "depth") for o in outputs], batch["depth"])
                if count:
                    parts["depth"] = total / count
                    terms.append(weighted(parts["depth"], self.s_depth) if self.learned_weighting else parts["depth"])
        if not terms:
            raise ValueError("no loss term has support in this batch (no labels, no depth and single-frame clips?)")
        return torch.stack(terms).sum(), {k: v.detach() for k, v in parts.items()}


def anchor_loss(logits: Sequence[torch.Tensor], anchor_xyz: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Mean cross-entropy of the anchor scores ``logits[i] (B, N)`` of frame ``i`` against each frame's
    nearest anchor (``anchor_xyz (N, 3)``, ground-truth positions ``t (B, T, 3)``, metres)."""
    logits_btn = torch.stack(list(logits), 1)
    nearest_bt = torch.cdist(t.to(anchor_xyz.dtype), anchor_xyz.expand(t.shape[0], -1, -1)).argmin(-1)
    return F.cross_entropy(logits_btn.flatten(0, 1), nearest_bt.flatten())


def rotation_anchor_loss(logits: Sequence[torch.Tensor], anchor_quat: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Mean cross-entropy of the rotation-anchor scores ``logits[i] (B, R)`` of frame ``i`` against each
    frame's nearest anchor rotation (``anchor_quat (R, 4)``, ground-truth quaternions ``q (B, T, 4)``;
    nearest: the largest ``|q . anchor|``)."""
    logits_btr = torch.stack(list(logits), 1)
    nearest_bt = torch.einsum("btc,rc->btr", q.to(anchor_quat.dtype), anchor_quat).abs().argmax(-1)
    return F.cross_entropy(logits_btr.flatten(0, 1), nearest_bt.flatten())


def _sum_over_frames(fn, predictions: list[torch.Tensor], targets: torch.Tensor) -> tuple[torch.Tensor, int]:
    total, count = predictions[0].new_zeros(()), 0
    for t, pred in enumerate(predictions):
        value, n = fn(pred, targets[:, t])
        total, count = total + value, count + n
    return total, count


def _need(value: torch.Tensor | None, name: str) -> torch.Tensor:
    if value is None:
        raise ValueError(
            f"the model output has no {name}: was the stream run (step tasks=...) and is its branch in the config?"
        )
    return value

"""What one streaming step of :class:`~vlocnetpp_core.model.vlocnet.VLocNetPP` returns (:class:`StepOutput`) and
carries to the next frame (:class:`StreamState`)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import torch


@dataclass
class StepOutput:
    """Outputs for one frame. Heads of tasks that were not run are ``None``.

    ``xyz (B, 3)`` metres and ``quat (B, 4)`` unit ``(w, x, y, z)``, ``w >= 0``: global pose
    ``T_wc``; ``rel_xyz``, ``rel_quat``: ``T_rel = T_{t-1}^{-1} T_t``; ``seg_logits (B, C, H, W)``;
    ``depth (B, 1, H, W)`` predicted metres; ``anchor_logits (B, N)``: the global pose head's scores
    of its position anchors ``anchor_xyz (N, 3)`` metres (config ``global_pose_anchors``; else None);
    ``rotation_logits (B, R)``: its scores of its rotation anchors ``anchor_quat (R, 4)`` (config
    ``global_rotation_anchors``; else None);
    ``taps``: named intermediate features.
    """

    xyz: torch.Tensor | None = None
    quat: torch.Tensor | None = None
    rel_xyz: torch.Tensor | None = None
    rel_quat: torch.Tensor | None = None
    seg_logits: torch.Tensor | None = None
    depth: torch.Tensor | None = None
    anchor_logits: torch.Tensor | None = None
    anchor_xyz: torch.Tensor | None = None
    rotation_logits: torch.Tensor | None = None
    anchor_quat: torch.Tensor | None = None
    taps: dict[str, torch.Tensor] = field(default_factory=dict)


@dataclass
class StreamState:
    """Previous-frame features the next step fuses (all before fusion; ``None``: not available).

    ``res5a`` global Res5a ``(B, C5, H/32, W/32)``; ``odo_res4`` odometry Res4 ``(B, C4, H/16, W/16)``;
    ``sem_res4f`` / ``sem_res5c`` semantic encoder ``(B, C4 | C5, H/16, W/16)``.
    """

    res5a: torch.Tensor | None = None
    odo_res4: torch.Tensor | None = None
    sem_res4f: torch.Tensor | None = None
    sem_res5c: torch.Tensor | None = None

    def detach(self) -> StreamState:
        """A copy cut from the autograd graph (for truncated back-propagation through time)."""
        return StreamState(
            **{f.name: None if getattr(self, f.name) is None else getattr(self, f.name).detach() for f in fields(self)}
        )

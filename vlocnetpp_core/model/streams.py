"""The streams of the VLocNet++ network, as modules: the shared trunk, the global pose stream, the
Siamese odometry stream and the AdapNet semantic stream (their wiring and the data flow of a step:
``vlocnet.py``)."""

from __future__ import annotations

import torch
from torch import nn

from vlocnetpp_core.model.backbone import Stem, make_stage
from vlocnetpp_core.model.config import ModelConfig
from vlocnetpp_core.model.fusion import AdaptiveWeightedFusion
from vlocnetpp_core.model.heads import PoseHead, SegmentationDecoder


class Trunk(nn.Module):
    """Stem, Res2, Res3 shared by the global stream and the odometry I_t stream:
    ``(B, 3, H, W) -> (B, C3, H/8, W/8)``."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c = cfg.stage_channels
        self.stem = Stem(cfg.stem_width)
        self.res2 = make_stage(cfg.stem_width, cfg.widths[0], c[0], cfg.depths[0], stride=1)
        self.res3 = make_stage(c[0], cfg.widths[1], c[1], cfg.depths[1], stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.res3(self.res2(self.stem(x)))


class GlobalPoseStream(nn.Module):
    """Res4, Res5 and the pose head of the global stream, with the temporal Res5a AWF."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c = cfg.stage_channels
        self.res4 = make_stage(c[1], cfg.widths[2], c[2], cfg.depths[2], stride=2)
        self.res5 = make_stage(c[2], cfg.widths[3], c[3], cfg.depths[3], stride=2)
        self.temporal_fusion = AdaptiveWeightedFusion(c[3], c[3]) if cfg.temporal_fusion else None
        flatten = cfg.global_res5_size if cfg.global_pose_pooling == "flatten" else None
        self.head = PoseHead(
            c[3], cfg.fc_width, cfg.dropout, flatten, cfg.global_pose_anchors, cfg.global_rotation_anchors
        )


class OdometryStream(nn.Module):
    """Siamese Res4 (one set of weights for both frames), Res5 on the concatenation, pose head."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c = cfg.stage_channels
        self.res4 = make_stage(c[1], cfg.widths[2], c[2], cfg.depths[2], stride=2)
        self.res5 = make_stage(2 * c[2], cfg.widths[3], c[3], cfg.depths[3], stride=2)
        flatten = cfg.odometry_res5_size if cfg.odometry_pose_pooling == "flatten" else None
        self.head = PoseHead(c[3], cfg.fc_width, cfg.dropout, flatten)

    def forward(self, prev_res4: torch.Tensor, res4: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(B, C4, h, w)`` twice -> ``rel_xyz (B, 3)``, ``rel_quat (B, 4)``, Res5 output."""
        res5 = self.res5(torch.cat((prev_res4, res4), 1))
        xyz, quat, _, _ = self.head(res5)
        return xyz, quat, res5


class SemanticStream(nn.Module):
    """AdapNet: ResNet encoder with multiscale blocks at output stride 16, warp AWFs, decoder."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c = cfg.stage_channels
        d4 = cfg.semantic_res4_dilation
        self.stem = Stem(cfg.stem_width)
        self.res2 = make_stage(cfg.stem_width, cfg.widths[0], c[0], cfg.depths[0], stride=1)
        self.res3 = make_stage(c[0], cfg.widths[1], c[1], cfg.depths[1], stride=2)
        self.res4 = make_stage(
            c[1], cfg.widths[2], c[2], cfg.depths[2], stride=2, multiscale=(None,) + (d4,) * (cfg.depths[2] - 1)
        )
        self.res5 = make_stage(
            c[2], cfg.widths[3], c[3], cfg.depths[3], stride=1, dilation=2, multiscale=cfg.res5_dilations()
        )
        self.warp_fusion_res4f = AdaptiveWeightedFusion(c[2], c[2]) if cfg.warping else None
        self.warp_fusion_res5c = AdaptiveWeightedFusion(c[3], c[3]) if cfg.warping else None
        self.decoder = SegmentationDecoder(c[3], c[1], cfg.num_classes)

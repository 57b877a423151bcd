"""Output heads: 6-DoF pose regression, AdapNet segmentation decoder, depth for warping."""

from __future__ import annotations

import contextlib
import math

import torch
from torch import nn
from torch.nn import functional as F

from vlocnetpp_core.geometry import quat_mul, quat_normalize
from vlocnetpp_core.model.backbone import PostNorm


class PoseHead(nn.Module):
    """``BN -> ELU -> GAP (or flatten) -> fc1 (ELU, dropout) -> fc2 xyz (3), fc3 quaternion (4)``.

    ``(B, C, h, w) -> (xyz (B, 3), quat (B, 4), anchor_logits (B, N) or None, rotation_logits (B, R) or None)``. With
    ``flatten_size=(h, w)`` the map is flattened into fc1 (``C * h * w`` inputs) instead of averaged,
    and only maps of that size are accepted (``ValueError`` otherwise). The quaternion is normalised
    to a unit ``(w, x, y, z)`` with ``w >= 0``. fc3 starts at the identity rotation.

    Translation, without anchors (``anchors=0``, the paper): ``xyz_offset + xyz_scale * fc2(h)``
    (buffers saved with the weights; 0 and 1 unless set, e.g. to the mean and spread of the training
    positions), so fc2 regresses numbers of order one whatever the size of the scene.
    With ``anchors=N``: a linear layer scores the ``N`` anchor positions ``anchor_xyz (N, 3)``
    (metres, world frame; a buffer set by :meth:`set_anchors`), fc2 regresses an offset in metres
    from each (``3 N`` outputs), and ``xyz = sum_k softmax(scores)_k (anchor_xyz_k + offset_k)``; the
    scores are returned for the classification loss (``None`` without anchors).

    Rotation, with ``rotation_anchors=R`` (else fc3 regresses the quaternion, the paper): a linear
    layer scores the ``R`` anchor rotations ``anchor_quat (R, 4)`` (a buffer set by
    :meth:`set_rotation_anchors`), fc3 regresses a residual rotation for each (``4 R`` outputs, the
    departure from the identity quaternion, in the camera frame), and the quaternion is the
    softmax-weighted sum of the turned anchors ``anchor_k * residual_k``, each first brought onto the
    hemisphere of the best-scored one, normalised.
    """

    def __init__(
        self,
        in_channels: int,
        fc_width: int,
        dropout: float,
        flatten_size: tuple[int, int] | None = None,
        anchors: int = 0,
        rotation_anchors: int = 0,
    ):
        super().__init__()
        self.norm = PostNorm(in_channels)
        self.flatten_size = flatten_size
        cells = 1 if flatten_size is None else flatten_size[0] * flatten_size[1]
        self.fc1 = nn.Linear(in_channels * cells, fc_width)
        self.dropout = nn.Dropout(dropout)
        self.fc_xyz = nn.Linear(fc_width, 3 * max(anchors, 1))
        self.fc_quat = nn.Linear(fc_width, 4 * max(rotation_anchors, 1))
        self.fc_anchor = nn.Linear(fc_width, anchors) if anchors else None
        self.fc_rotation_anchor = nn.Linear(fc_width, rotation_anchors) if rotation_anchors else None
        if rotation_anchors:
            self.register_buffer("anchor_quat", torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(rotation_anchors, 1))
        if anchors:
            self.register_buffer("anchor_xyz", torch.zeros(anchors, 3))
        else:
            self.register_buffer("xyz_offset", torch.zeros(3))
            self.register_buffer("xyz_scale", torch.ones(3))
        self.custom_init()

    def custom_init(self) -> None:
        for fc in (self.fc1, self.fc_xyz, self.fc_quat, self.fc_anchor, self.fc_rotation_anchor):
            if fc is not None:
                nn.init.normal_(fc.weight, std=0.01)
                nn.init.zeros_(fc.bias)
        if self.fc_rotation_anchor is None:  # with rotation anchors fc3 regresses departures from the identity
            with torch.no_grad():
                self.fc_quat.bias[0] = 1.0

    def set_anchors(self, xyz: torch.Tensor) -> None:
        """Set the anchor positions: ``xyz (N, 3)`` metres, world frame (``N`` as built)."""
        self._set_anchor_buffer("anchor_xyz", self.fc_anchor, xyz, "position")

    def set_rotation_anchors(self, quats: torch.Tensor) -> None:
        """Set the anchor rotations: ``quats (R, 4)`` unit ``(w, x, y, z)``, world frame (``R`` as built)."""
        self._set_anchor_buffer("anchor_quat", self.fc_rotation_anchor, quats, "rotation")

    def _set_anchor_buffer(self, name: str, scorer: nn.Linear | None, values: torch.Tensor, kind: str) -> None:
        """Copy ``values`` into the anchor buffer ``name`` (scored by ``scorer``); ``ValueError`` naming the count
        built."""
        if scorer is None or tuple(values.shape) != tuple(getattr(self, name).shape):
            have = 0 if scorer is None else scorer.out_features
            raise ValueError(f"this pose head has {have} {kind} anchors, got anchors of shape {tuple(values.shape)}")
        with torch.no_grad():
            getattr(self, name).copy_(values)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """In the weights' dtype (float32), also under autocast: bfloat16 resolves only half a metre at 100 m."""
        with without_autocast(x):
            return self._forward(x.to(self.fc1.weight.dtype))

    def _forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        if self.flatten_size is None:
            h = self.norm(x).mean(dim=(2, 3))
        elif tuple(x.shape[-2:]) != self.flatten_size:
            raise ValueError(
                f"this pose head flattens a {self.flatten_size[1]}x{self.flatten_size[0]} Res5 map (a pose_pooling "
                f"of flatten fixes the model config's input_size) but got {x.shape[-1]}x{x.shape[-2]}: feed images "
                "of the config's input_size"
            )
        else:
            h = self.norm(x).flatten(1)
        h = self.dropout(F.elu(self.fc1(h)))
        quat, rotation_logits_br = self._rotation(h)
        if self.fc_anchor is None:
            return self.xyz_offset + self.xyz_scale * self.fc_xyz(h), quat, None, rotation_logits_br
        logits_bn = self.fc_anchor(h)
        offsets_bn3 = self.fc_xyz(h).unflatten(1, (-1, 3))
        xyz = torch.einsum("bn,bnc->bc", logits_bn.softmax(dim=1), self.anchor_xyz + offsets_bn3)
        return xyz, quat, logits_bn, rotation_logits_br

    def _rotation(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """fc1 features ``(B, F)`` -> unit quaternion ``(B, 4)`` and the rotation-anchor scores ``(B, R)`` or None."""
        if self.fc_rotation_anchor is None:
            return quat_normalize(self.fc_quat(h)), None
        logits_br = self.fc_rotation_anchor(h)
        identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=h.dtype, device=h.device)
        residual_br4 = identity + self.fc_quat(h).unflatten(1, (-1, 4))
        turned_br4 = quat_mul(self.anchor_quat.expand_as(residual_br4), residual_br4)
        turned_br4 = turned_br4 / turned_br4.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        best_b14 = turned_br4.gather(1, logits_br.argmax(dim=1)[:, None, None].expand(-1, 1, 4))
        sign_br1 = torch.where((turned_br4 * best_b14).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(h.dtype)
        quat = torch.einsum("br,brc->bc", logits_br.softmax(dim=1), sign_br1 * turned_br4)
        return quat_normalize(quat), logits_br


def bilinear_kernel(channels: int, kernel_size: int) -> torch.Tensor:
    """``(channels, channels, k, k)`` transposed-convolution weight that upsamples each channel bilinearly."""
    factor = (kernel_size + 1) // 2
    center = factor - 1 if kernel_size % 2 == 1 else factor - 0.5
    r = torch.arange(kernel_size, dtype=torch.float32)
    k1 = 1 - (r - center).abs() / factor
    weight = torch.zeros(channels, channels, kernel_size, kernel_size)
    weight[range(channels), range(channels)] = k1[:, None] * k1[None, :]
    return weight


def without_autocast(x: torch.Tensor) -> contextlib.AbstractContextManager:
    """A block that autocast does not reach (on ``x``'s device), for what must compute in the weights' precision."""
    return (
        torch.autocast(x.device.type, enabled=False) if x.device.type in ("cpu", "cuda") else contextlib.nullcontext()
    )


def _in_weight_dtype(layer: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``layer(x)`` in the layer's dtype, also under autocast: on the CPU (torch 2.13) a bfloat16 ConvTranspose2d of
    kernel 16, stride 8 (``up8``) returns wrong input gradients (cosine 0.01 to float32's; kernel 4, stride 2 is right),
    and segmentation trained with ``--bf16`` diverged. At ``num_classes`` channels float32 costs next to nothing."""
    with without_autocast(x):
        return layer(x.to(layer.weight.dtype))


class SegmentationDecoder(nn.Module):
    """AdapNet decoder: class scores at stride 16, deconv x2, add a skip from Res3, deconv x8.

    ``deep (B, C_deep, H/16, W/16)`` (encoder end), ``skip (B, C_skip, H/8, W/8)`` ->
    logits ``(B, num_classes, H, W)``. Both deconvolutions start as bilinear upsampling.
    """

    def __init__(self, deep_channels: int, skip_channels: int, num_classes: int):
        super().__init__()
        self.deep_norm = PostNorm(deep_channels)
        self.score = nn.Conv2d(deep_channels, num_classes, 1)
        self.up2 = nn.ConvTranspose2d(num_classes, num_classes, 4, stride=2, padding=1, bias=False)
        self.skip_norm = PostNorm(skip_channels)
        self.skip = nn.Conv2d(skip_channels, num_classes, 1)
        self.up8 = nn.ConvTranspose2d(num_classes, num_classes, 16, stride=8, padding=4, bias=False)
        self.custom_init()

    def custom_init(self) -> None:
        with torch.no_grad():
            self.up2.weight.copy_(bilinear_kernel(self.up2.in_channels, 4))
            self.up8.weight.copy_(bilinear_kernel(self.up8.in_channels, 16))

    def forward(self, deep: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        y = _in_weight_dtype(self.up2, self.score(self.deep_norm(deep)))
        y = y + self.skip(self.skip_norm(skip))
        return _in_weight_dtype(self.up8, y)


class DepthHead(nn.Module):
    """Light depth head on the semantic encoder's Res3: ``(B, C, H/8, W/8) -> depth (B, 1, H, W)`` metres.

    ``BN -> ELU -> conv 3x3 -> ELU -> conv 1x1`` gives a score at stride 8, upsampled
    bilinearly to the input size; depth is ``exp`` of a log-depth squashed into
    ``[log(min), log(max)]`` with a sigmoid, so it is always positive and bounded (the score 0
    is the geometric mean of the range).
    """

    def __init__(self, in_channels: int, width: int, depth_range: tuple[float, float]):
        super().__init__()
        self.norm = PostNorm(in_channels)
        self.conv = nn.Conv2d(in_channels, width, 3, padding=1)
        self.out = nn.Conv2d(width, 1, 1)
        self.log_min = math.log(depth_range[0])
        self.log_max = math.log(depth_range[1])

    def forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """In the weights' dtype (float32), also under autocast, like the pose heads: a metric regression (the
        bfloat16 head's gradients were 28 % larger than float32's, cosine 0.975, against 0.999 in the encoder)."""
        with without_autocast(x):
            return self._forward(x.to(self.conv.weight.dtype), size)

    def _forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        score = self.out(F.elu(self.conv(self.norm(x))))
        score = F.interpolate(score, size=size, mode="bilinear", align_corners=False)
        return torch.exp(self.log_min + (self.log_max - self.log_min) * torch.sigmoid(score))

"""Full pre-activation ResNet parts with ELU (He et al. 2016, "Identity Mappings"), as VLocNet++ uses.

A pre-activation bottleneck computes ``x + conv3(act(bn3(conv2(act(bn2(conv1(act(bn1(x)))))))))``
where ``act`` is ELU; a projection shortcut (first block of a stage) takes ``act(bn1(x))``.
Block outputs are raw sums: whoever consumes the end of a stage applies :class:`PostNorm`.
Strides sit on the 3x3 convolution (the "ResNet v1.5" placement that torchvision uses), so a
standard ResNet-50 state dict maps onto these convolutions 1:1 (see ``init_backbone.py``).

The multiscale block of AdapNet replaces the 3x3 convolution by two parallel 3x3 convolutions
of half the channels each, one of them dilated, concatenated.
"""

from __future__ import annotations

import torch
from torch import nn


class PreActBottleneck(nn.Module):
    """Pre-activation bottleneck ``(B, in_channels, H, W) -> (B, out_channels, H/stride, W/stride)``.

    Args:
        dilation: dilation (and padding) of the 3x3 convolution.
        multiscale_dilation: if given, ``conv2`` has ``width // 2`` outputs and a parallel
            ``conv2_dilated`` with this dilation has the other half (AdapNet multiscale block).
    """

    def __init__(
        self,
        in_channels: int,
        width: int,
        out_channels: int,
        stride: int = 1,
        dilation: int = 1,
        multiscale_dilation: int | None = None,
    ):
        super().__init__()
        self.bn1 = nn.BatchNorm2d(in_channels)
        self.conv1 = nn.Conv2d(in_channels, width, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        branch = width if multiscale_dilation is None else width // 2
        self.conv2 = nn.Conv2d(width, branch, 3, stride=stride, padding=dilation, dilation=dilation, bias=False)
        self.conv2_dilated = None
        if multiscale_dilation is not None:
            d = multiscale_dilation
            self.conv2_dilated = nn.Conv2d(width, width - branch, 3, stride=stride, padding=d, dilation=d, bias=False)
        self.bn3 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, out_channels, 1, bias=False)
        self.shortcut = None
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Conv2d(in_channels, out_channels, 1, stride=stride, bias=False)
        self.act = nn.ELU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pre = self.act(self.bn1(x))
        identity = x if self.shortcut is None else self.shortcut(pre)
        y = self.act(self.bn2(self.conv1(pre)))
        if self.conv2_dilated is None:
            y = self.conv2(y)
        else:
            y = torch.cat((self.conv2(y), self.conv2_dilated(y)), 1)
        y = self.conv3(self.act(self.bn3(y)))
        return y + identity


def make_stage(
    in_channels: int,
    width: int,
    out_channels: int,
    depth: int,
    stride: int,
    dilation: int = 1,
    multiscale: tuple[int | None, ...] | None = None,
) -> nn.Sequential:
    """``depth`` bottlenecks; the first has ``stride`` and the projection shortcut.

    ``multiscale[i]`` is the parallel-branch dilation of block ``i`` (``None``: a plain block).
    """
    multiscale = multiscale or (None,) * depth
    blocks = [
        PreActBottleneck(
            in_channels if i == 0 else out_channels,
            width,
            out_channels,
            stride if i == 0 else 1,
            dilation,
            multiscale[i],
        )
        for i in range(depth)
    ]
    return nn.Sequential(*blocks)


class Stem(nn.Module):
    """``conv 7x7/2 -> BN -> ELU -> maxpool 3x3/2``: ``(B, 3, H, W) -> (B, width, H/4, W/4)``."""

    def __init__(self, width: int):
        super().__init__()
        self.conv = nn.Conv2d(3, width, 7, stride=2, padding=3, bias=False)
        self.bn = nn.BatchNorm2d(width)
        self.act = nn.ELU(inplace=True)
        self.pool = nn.MaxPool2d(3, stride=2, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pool(self.act(self.bn(self.conv(x))))


class PostNorm(nn.Sequential):
    """The final ``BN -> ELU`` of a pre-activation network, applied to a stage's raw output."""

    def __init__(self, channels: int):
        super().__init__(nn.BatchNorm2d(channels), nn.ELU(inplace=True))


def init_weights(module: nn.Module) -> None:
    """He init for convolutions, unit BN, small linear layers (in place, recursively)."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
        elif isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, std=0.01)
            nn.init.zeros_(m.bias)

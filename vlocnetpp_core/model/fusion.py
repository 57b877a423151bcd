"""Adaptive Weighted Fusion (AWF), paper Eq. 5."""

from __future__ import annotations

import torch
from torch import nn


class AdaptiveWeightedFusion(nn.Module):
    """``z = ReLU(Conv1x1((w_a * z_a) ++ (w_b * z_b)) + b)``.

    ``w_a (C_a)`` and ``w_b (C_b)`` are learned per-channel weights (init 1), ``++`` is channel
    concatenation and the 1x1 convolution (with bias) pools ``C_a + C_b`` channels into
    ``out_channels`` (default ``C_a``: the stream that receives the fusion keeps its width).

    Shapes: ``z_a (B, C_a, h, w)``, ``z_b (B, C_b, h, w)`` -> ``(B, out_channels, h, w)``.
    """

    def __init__(self, channels_a: int, channels_b: int, out_channels: int | None = None):
        super().__init__()
        self.weight_a = nn.Parameter(torch.ones(channels_a))
        self.weight_b = nn.Parameter(torch.ones(channels_b))
        self.pool = nn.Conv2d(channels_a + channels_b, out_channels or channels_a, 1, bias=True)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Unit channel weights; He (fan-in) init of the pooling so the output keeps the input's scale."""
        nn.init.ones_(self.weight_a)
        nn.init.ones_(self.weight_b)
        nn.init.kaiming_normal_(self.pool.weight, mode="fan_in", nonlinearity="relu")
        nn.init.zeros_(self.pool.bias)

    def forward(self, z_a: torch.Tensor, z_b: torch.Tensor) -> torch.Tensor:
        if z_a.shape[-2:] != z_b.shape[-2:]:
            raise ValueError(f"AWF inputs differ in spatial size: {tuple(z_a.shape)} vs {tuple(z_b.shape)}")
        weighted = torch.cat((z_a * self.weight_a[:, None, None], z_b * self.weight_b[:, None, None]), 1)
        return torch.relu(self.pool(weighted))

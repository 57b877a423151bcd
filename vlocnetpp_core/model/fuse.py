"""Inference-time folding of BatchNorm into the convolution before it.

In eval mode ``bn(conv(x)) = conv'(x)`` with ``w' = w * g / sqrt(v + eps)`` per output channel and
``b' = (b - m) * g / sqrt(v + eps) + beta``. Of the three BNs of a pre-activation bottleneck two
follow a convolution (``bn2`` after ``conv1``, ``bn3`` after ``conv2`` and ``conv2_dilated``,
whose outputs are concatenated) and fold; ``bn1`` acts on the block input, which the identity
shortcut also carries, and stays. The stem's BN folds too. Outputs match the unfolded network
to float rounding; training a folded network is not supported (the BNs are gone).
"""

from __future__ import annotations

import torch
from torch import nn

from vlocnetpp_core.model.backbone import PreActBottleneck, Stem


@torch.no_grad()
def fold_batchnorm(convs: list[nn.Conv2d], bn: nn.BatchNorm2d) -> None:
    """Fold ``bn`` into ``convs``, whose outputs concatenated along channels are ``bn``'s input (in place)."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    shift = bn.bias - bn.running_mean * scale
    start = 0
    for conv in convs:
        end = start + conv.out_channels
        s, b = scale[start:end], shift[start:end]
        if conv.bias is None:
            conv.bias = nn.Parameter(torch.zeros(conv.out_channels, dtype=conv.weight.dtype, device=conv.weight.device))
        conv.bias.copy_(conv.bias * s + b)
        conv.weight.mul_(s.reshape(-1, 1, 1, 1))
        start = end
    if start != bn.num_features:
        raise ValueError(f"the convolutions have {start} output channels, the BatchNorm {bn.num_features}")


def fuse_for_inference(model: nn.Module) -> nn.Module:
    """Fold every conv -> BN pair of the bottlenecks and stems of ``model`` (in place; eval mode). Returns ``model``."""
    if model.training:
        raise ValueError("fuse_for_inference needs a model in eval mode (BatchNorm running statistics)")
    for module in model.modules():
        if isinstance(module, PreActBottleneck) and isinstance(module.bn2, nn.BatchNorm2d):
            fold_batchnorm([module.conv1], module.bn2)
            fold_batchnorm([c for c in (module.conv2, module.conv2_dilated) if c is not None], module.bn3)
            module.bn2, module.bn3 = nn.Identity(), nn.Identity()
        elif isinstance(module, Stem) and isinstance(module.bn, nn.BatchNorm2d):
            fold_batchnorm([module.conv], module.bn)
            module.bn = nn.Identity()
    return model

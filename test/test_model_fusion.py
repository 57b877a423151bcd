"""Adaptive Weighted Fusion (Eq. 5) against a hand computation, and the backbone blocks."""

from __future__ import annotations

import pytest
import torch

from vlocnetpp_core.model import AdaptiveWeightedFusion
from vlocnetpp_core.model.backbone import PreActBottleneck
from vlocnetpp_core.model.heads import bilinear_kernel


def test_awf_matches_hand_computation():
    awf = AdaptiveWeightedFusion(2, 1, out_channels=2)
    with torch.no_grad():
        awf.weight_a.copy_(torch.tensor([2.0, -1.0]))
        awf.weight_b.copy_(torch.tensor([0.5]))
        # rows: output channels; columns: (w_a z_a)_0, (w_a z_a)_1, (w_b z_b)_0
        awf.pool.weight.copy_(torch.tensor([[1.0, 1.0, 1.0], [-1.0, 0.0, 2.0]]).view(2, 3, 1, 1))
        awf.pool.bias.copy_(torch.tensor([0.5, -1.0]))
    z_a = torch.tensor([[[[1.0, -2.0]], [[3.0, 0.0]]]])  # (1, 2, 1, 2)
    z_b = torch.tensor([[[[4.0, 10.0]]]])  # (1, 1, 1, 2)
    # pixel 0: weighted = (2, -3, 2) -> ch0 = 2 - 3 + 2 + 0.5 = 1.5, ch1 = -2 + 4 - 1 = 1
    # pixel 1: weighted = (-4, 0, 5) -> ch0 = -4 + 0 + 5 + 0.5 = 1.5, ch1 = 4 + 10 - 1 = 13
    expected = torch.tensor([[[[1.5, 1.5]], [[1.0, 13.0]]]])
    torch.testing.assert_close(awf(z_a, z_b), expected)
    with torch.no_grad():
        awf.pool.bias.copy_(torch.tensor([-10.0, -20.0]))
    assert (awf(z_a, z_b) == 0).all()  # the ReLU of Eq. 5


def test_awf_defaults_keep_the_receiving_width_and_check_sizes():
    awf = AdaptiveWeightedFusion(8, 16)
    assert awf(torch.randn(2, 8, 3, 5), torch.randn(2, 16, 3, 5)).shape == (2, 8, 3, 5)
    assert sum(p.numel() for p in awf.parameters()) == 8 + 16 + 24 * 8 + 8
    with pytest.raises(ValueError, match="spatial size"):
        awf(torch.randn(1, 8, 3, 5), torch.randn(1, 16, 4, 5))


def test_preactivation_bottleneck_is_identity_plus_residual():
    block = PreActBottleneck(8, 4, 8).eval()
    with torch.no_grad():
        block.conv3.weight.zero_()
    x = torch.randn(1, 8, 5, 7)
    torch.testing.assert_close(block(x), x)  # no activation on the identity path
    ms = PreActBottleneck(8, 4, 16, stride=2, multiscale_dilation=3)
    assert ms.conv2.out_channels + ms.conv2_dilated.out_channels == 4 and ms.conv2_dilated.dilation == (3, 3)
    assert ms(torch.randn(1, 8, 9, 9)).shape == (1, 16, 5, 5)


def test_bilinear_deconvolution_upsamples_a_ramp_exactly():
    up = torch.nn.ConvTranspose2d(1, 1, 4, stride=2, padding=1, bias=False)
    with torch.no_grad():
        up.weight.copy_(bilinear_kernel(1, 4))
    ramp = torch.arange(6.0).view(1, 1, 1, 6).expand(1, 1, 6, 6)
    out = up(ramp)
    expected = torch.nn.functional.interpolate(ramp, scale_factor=2, mode="bilinear", align_corners=False)
    torch.testing.assert_close(out[..., 1:-1, 1:-1], expected[..., 1:-1, 1:-1])  # borders differ by padding only

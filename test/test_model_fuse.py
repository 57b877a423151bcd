"""BatchNorm folding for inference: same outputs as the unfolded network, fewer BatchNorms."""

from __future__ import annotations

import copy

import pytest
import torch
from model_fixtures import intrinsics, lite, one_thread  # noqa: F401  (autouse: one thread)

from vlocnetpp_core.model import VLocNetPP
from vlocnetpp_core.model.fuse import fuse_for_inference


def test_folded_network_gives_the_same_stream_outputs():
    torch.manual_seed(0)
    cfg = lite(input_size=(96, 64))
    model = VLocNetPP(cfg).eval()
    with torch.no_grad():  # BatchNorms with non-trivial statistics, as after training
        for bn in (m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)):
            bn.running_mean.uniform_(-0.3, 0.3)
            bn.running_var.uniform_(0.5, 2.0)
            bn.weight.uniform_(0.5, 1.5)
            bn.bias.uniform_(-0.2, 0.2)
    folded = fuse_for_inference(copy.deepcopy(model))
    count = lambda m: sum(isinstance(x, torch.nn.BatchNorm2d) for x in m.modules())  # noqa: E731
    assert count(folded) < 0.6 * count(model)
    K = intrinsics(1, 96, 64)
    frames = torch.rand(3, 1, 3, 64, 96)
    with torch.inference_mode():
        state_a = state_b = None
        for x in frames:
            a, state_a = model.step(x, state_a, K)
            b, state_b = folded.step(x, state_b, K)
            for name in ("xyz", "quat", "rel_xyz", "rel_quat", "seg_logits", "depth"):
                ra, rb = getattr(a, name), getattr(b, name)
                if ra is None:
                    continue
                scale = ra.abs().max().clamp_min(1.0)
                assert (ra - rb).abs().max() / scale < 1e-4, name


def test_folding_needs_eval_mode():
    with pytest.raises(ValueError, match="eval mode"):
        fuse_for_inference(VLocNetPP(lite(input_size=(96, 64))).train())

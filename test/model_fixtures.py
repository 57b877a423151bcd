"""Helpers for the model and loss tests: small configs, intrinsics, consistent pose batches."""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator

import pytest
import torch

from vlocnetpp_core import geometry
from vlocnetpp_core.model import ModelConfig, load_model_config


@contextlib.contextmanager
def single_thread() -> Iterator[None]:
    """Run tiny-tensor loops on one thread: on a shared 2-core machine two spinning threads slow them down many
    times."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@pytest.fixture(autouse=True)
def one_thread() -> Iterator[None]:
    """Autouse fixture for a test module that imports it: every test on one thread (see :func:`single_thread`)."""
    with single_thread():
        yield


def lite(**overrides) -> ModelConfig:
    """The shipped ``lite`` config with fields replaced."""
    return dataclasses.replace(load_model_config("lite"), **overrides)


def intrinsics(batch: int, width: int, height: int, focal: float | None = None) -> torch.Tensor:
    """``(batch, 3, 3)`` pinhole intrinsics with the principal point at the image centre."""
    f = focal if focal is not None else 0.9 * width
    K = torch.tensor([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return K.expand(batch, 3, 3).clone()


def random_clip_batch(
    batch: int, frames: int, width: int, height: int, num_classes: int = 10, seed: int = 0
) -> dict[str, torch.Tensor]:
    """A ``ClipDataset``-style batch dict with random images and a consistent random trajectory."""
    g = torch.Generator().manual_seed(seed)
    t = torch.randn(batch, frames, 3, generator=g) * 3.0
    q = geometry.quat_normalize(torch.randn(batch, frames, 4, generator=g))
    rel_t, rel_q = geometry.relative_pose(t[:, :-1], q[:, :-1], t[:, 1:], q[:, 1:])
    identity_t = torch.zeros(batch, 1, 3)
    identity_q = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(batch, 1, 4)
    depth = torch.rand(batch, frames, 1, height, width, generator=g) * 20 + 1
    depth[..., : height // 4, :] = 0.0  # a band without depth (invalid)
    labels = torch.randint(0, num_classes, (batch, frames, height, width), generator=g)
    labels[..., -2:, :] = 255
    return {
        "image": torch.rand(batch, frames, 3, height, width, generator=g),
        "t": t,
        "q": q,
        "rel_t": torch.cat((identity_t, rel_t), 1),
        "rel_q": torch.cat((identity_q, rel_q), 1),
        "depth": depth,
        "labels": labels,
        "K": intrinsics(batch, width, height)[:, None].expand(batch, frames, 3, 3).clone(),
        "has_depth": torch.ones(batch, dtype=torch.bool),
        "has_labels": torch.ones(batch, dtype=torch.bool),
    }


def known_motion_lite(seed: int) -> torch.nn.Module:
    """An untrained lite network (seeded) whose odometry head says "0.3 m forward, no rotation" for every
    frame pair and whose depth head says about 5.5 m everywhere (the geometric mean of its range).

    A random odometry head can output any rotation (half a turn), and a random depth head can put every
    pixel at its 0.1 m bound (behind the camera after 0.3 m forward): either warps previous-frame
    features out of view, or to the border where out-of-view samples are zeroed, so a rounding of a
    few eps flips a sample and the streamed pose jumps. A small known motion at a known depth keeps the
    warp in view and smooth, so given depth and intrinsics reach the pose and two float32 runs agree."""
    from vlocnetpp_core.model import VLocNetPP

    torch.manual_seed(seed)
    model = VLocNetPP(load_model_config("lite"))
    head = model.odometry.head
    with torch.no_grad():
        for fc in (head.fc_xyz, head.fc_quat):
            fc.weight.mul_(1e-3)
        head.fc_xyz.bias.copy_(torch.tensor([0.0, 0.0, 0.3]))
        head.fc_quat.bias.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0]))  # the network-wide init zeroes it
        model.depth_head.out.weight.mul_(1e-3)
        model.depth_head.out.bias.zero_()
    return model

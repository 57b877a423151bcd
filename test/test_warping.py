"""Feature warping (paper Eq. 4): a rendered plane, identity motion, kornia as an oracle, the model's wiring."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from model_fixtures import (
    intrinsics,
    lite,
    one_thread,  # noqa: F401  (autouse: one thread per test)
)

from vlocnetpp_core import geometry
from vlocnetpp_core.geometry import pool_warp_grid, warp_features, warp_grid
from vlocnetpp_core.model import VLocNetPP

W, H = 128, 96


def rotation(axis: tuple[float, float, float], degrees: float) -> torch.Tensor:
    a = torch.tensor(axis, dtype=torch.float64)
    half = math.radians(degrees) / 2
    q = torch.cat((torch.tensor([math.cos(half)], dtype=torch.float64), a / a.norm() * math.sin(half)))
    return geometry.quat_to_matrix(q)


def texture(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Smooth RGB texture ``(3, ...)`` on the plane's coordinates (metres)."""
    return torch.stack(
        (
            0.5 + 0.25 * torch.sin(1.3 * x) + 0.2 * torch.cos(0.9 * y + 0.4 * x),
            0.5 + 0.3 * torch.cos(0.7 * x - 1.1 * y),
            0.5 + 0.2 * torch.sin(0.5 * x + 0.8 * y) * torch.cos(0.6 * y),
        )
    )


def render_plane(T_wc: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Image ``(1, 3, H, W)`` and depth ``(1, 1, H, W)`` of the slanted plane ``z = 6 + 0.15 x - 0.1 y`` (world
    frame)."""
    pix = geometry.pixel_grid(H, W, dtype=torch.float64)
    rays = geometry.backproject(pix, torch.ones(len(pix), dtype=torch.float64), K)  # camera frame, z = 1
    d = rays @ T_wc[:3, :3].T
    o = T_wc[:3, 3]
    a, b, z0 = 0.15, -0.1, 6.0
    lam = (z0 + a * o[0] + b * o[1] - o[2]) / (d[:, 2] - a * d[:, 0] - b * d[:, 1])
    p = o + lam[:, None] * d
    image = texture(p[:, 0], p[:, 1]).reshape(1, 3, H, W)
    return image.float(), lam.reshape(1, 1, H, W).float()  # rays have z = 1, so lambda is the depth


@pytest.fixture(scope="module")
def scene():
    K = intrinsics(1, W, H, focal=100.0)[0].double()
    T_rel = torch.eye(4, dtype=torch.float64)
    T_rel[:3, :3] = rotation((0.3, 1.0, 0.1), 4.0)
    T_rel[:3, 3] = torch.tensor([0.35, -0.12, 0.6], dtype=torch.float64)
    # camera t-1 is the world frame, so T_rel = T_{t-1}^{-1} T_t = T_t
    prev_image, _ = render_plane(torch.eye(4, dtype=torch.float64), K)
    image, depth = render_plane(T_rel, K)
    return prev_image, image, depth, T_rel.float()[None], K.float()[None]


def masked_error(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    return float(((a - b).abs() * mask).amax())


def interior(grid: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Valid pixels whose sample lies between source pixel centres (bilinear never touches the zero padding)."""
    h, w = grid.shape[1:3]
    u = ((grid[..., 0] + 1) * w - 1) / 2
    v = ((grid[..., 1] + 1) * h - 1) / 2
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    return valid * inside[:, None].to(valid.dtype)


def test_warping_the_previous_image_reproduces_the_current_one(scene):
    prev_image, image, depth, T_rel, K = scene
    grid, valid = warp_grid(depth, T_rel, K)
    warped = warp_features(prev_image, grid, valid)
    inner = interior(grid, valid)
    assert inner.mean() > 0.6  # most of the view overlaps
    assert masked_error(warped, image, inner) < 0.01
    assert (warped * (1 - valid)).abs().max() == 0  # out-of-view samples are zero
    # The motion matters: warping with the identity instead is far off.
    grid_id, valid_id = warp_grid(depth, torch.eye(4)[None], K)
    assert masked_error(warp_features(prev_image, grid_id, valid_id), image, inner) > 0.1


def test_pooled_grid_warps_downsampled_features(scene):
    prev_image, image, depth, T_rel, K = scene
    grid, valid = warp_grid(depth, T_rel, K)
    for factor in (4, 8):
        size = (H // factor, W // factor)
        g, v = pool_warp_grid(grid, valid, size)
        warped = warp_features(F.avg_pool2d(prev_image, factor), g, v)
        full = interior(g, (v > 0.999).float())
        assert full.sum() > 0.4 * size[0] * size[1]
        assert masked_error(warped, F.avg_pool2d(image, factor), full) < 0.03


def test_identity_motion_is_identity_at_every_scale():
    torch.manual_seed(0)
    depth = torch.rand(2, 1, H, W) * 30 + 0.5
    K = intrinsics(2, W, H)
    grid, valid = warp_grid(depth, torch.eye(4).expand(2, 4, 4), K)
    assert (valid == 1).all()
    for factor in (1, 8, 16):
        size = (H // factor, W // factor)
        features = torch.randn(2, 5, *size)
        g, v = pool_warp_grid(grid, valid, size)
        torch.testing.assert_close(warp_features(features, g, v), features, atol=2e-4, rtol=0)  # float32 round trip


def test_matches_kornia_warp_frame_depth_on_random_inputs():
    kornia_depth = pytest.importorskip("kornia.geometry.depth")
    g = torch.Generator().manual_seed(3)
    B = 3
    image_prev = torch.rand(B, 4, H, W, generator=g, dtype=torch.float64)
    depth = torch.rand(B, 1, H, W, generator=g, dtype=torch.float64) * 9 + 1
    t = torch.randn(B, 3, generator=g, dtype=torch.float64) * 0.3
    q = geometry.quat_normalize(
        torch.cat(
            (torch.ones(B, 1, dtype=torch.float64), 0.05 * torch.randn(B, 3, generator=g, dtype=torch.float64)), 1
        )
    )
    T_rel = geometry.pose_to_matrix(t, q)  # camera t in camera t-1: maps points of frame t into frame t-1
    K = intrinsics(B, W, H).double()
    K[:, 0, 0] += torch.rand(B, generator=g, dtype=torch.float64) * 30
    K[:, 1, 2] += 3.0
    grid, valid = warp_grid(depth, T_rel, K)
    ours = warp_features(image_prev, grid, valid)
    # kornia: the depth belongs to the destination (frame t), src_trans_dst maps frame-t points into
    # the source (frame t-1), i.e. T_rel itself; it samples with align_corners=True on the same pixel centres.
    theirs = kornia_depth.warp_frame_depth(image_prev, depth, T_rel, K)
    assert valid.mean() > 0.5
    torch.testing.assert_close(ours * valid, theirs * valid, atol=1e-9, rtol=0)


def test_model_warps_previous_features_with_the_given_depth_and_pose(scene):
    """The semantic stream's warped taps are the previous features warped by the one pooled input-resolution grid."""
    prev_image, image, depth, T_rel, K = scene
    torch.manual_seed(0)
    model = VLocNetPP(lite(input_size=(W, H))).eval()
    with torch.inference_mode():
        out0, state = model.step(prev_image, None, K)
        out1, _ = model.step(image, state, K, depth=depth, warp_rel_pose=T_rel)
        grid, valid = warp_grid(depth, T_rel, K)
        g, v = pool_warp_grid(grid, valid, state.sem_res4f.shape[-2:])
        torch.testing.assert_close(out1.taps["sem_res4f_warped"], warp_features(state.sem_res4f, g, v))
        torch.testing.assert_close(out1.taps["sem_res5c_warped"], warp_features(state.sem_res5c, g, v))
        # On a first frame the "previous" features are the frame's own (a static camera).
        torch.testing.assert_close(out0.taps["sem_res4f_warped"], out0.taps["sem_res4f"])
        # Without a given depth / pose the prediction of the depth head and the odometry stream are used.
        out2, _ = model.step(image, state, K)
        rel = geometry.pose_to_matrix(out2.rel_xyz, out2.rel_quat)
        grid, valid = warp_grid(out2.depth, rel, K)
        g, v = pool_warp_grid(grid, valid, state.sem_res4f.shape[-2:])
        torch.testing.assert_close(out2.taps["sem_res4f_warped"], warp_features(state.sem_res4f, g, v))

"""The streaming Localizer: cached state equals recomputation, odometry, twist, covariances, resets."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from model_fixtures import known_motion_lite
from scipy.spatial.transform import Rotation

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.errors import DataError, UserError
from vlocnetpp_core.inference.checkpoint import save_checkpoint
from vlocnetpp_core.inference.localizer import UNKNOWN_VARIANCE, Localizer
from vlocnetpp_core.inference.network_input import network_input
from vlocnetpp_core.inference.preprocess import FrameError

POSE_VAR = [0.04, 0.05, 0.06, 1e-3, 2e-3, 3e-3]
ODO_VAR = [1e-3, 2e-3, 3e-3, 1e-5, 2e-5, 3e-5]
H, W = 90, 150  # camera images: not the network's 224x128 and another aspect ratio


def _frames(n: int, seed: int = 0, size: tuple[int, int] = (H, W)) -> list[np.ndarray]:
    """Smooth random RGB images, each a small shift of a larger texture (a moving camera)."""
    rng = np.random.default_rng(seed)
    base = cv2.resize(
        rng.integers(0, 256, (size[0] // 6 + 4, size[1] // 6 + 4, 3), dtype=np.uint8), (size[1] + 40, size[0] + 40)
    )
    return [np.ascontiguousarray(base[2 * k : 2 * k + size[0], 3 * k : 3 * k + size[1]]) for k in range(n)]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """:func:`model_fixtures.known_motion_lite`: an untrained network whose warp stays in view."""
    calib = {"pose_variance": POSE_VAR, "odometry_variance": ODO_VAR}
    model = known_motion_lite(1)
    return save_checkpoint(tmp_path_factory.mktemp("loc") / "lite", model, {"calibration": calib})


@pytest.fixture()
def localizer(checkpoint: Path) -> Localizer:
    return Localizer.from_checkpoint(checkpoint, max_gap_s=1.0, num_threads=1)


def _clip(localizer: Localizer, frames, intrinsics=None, depths=None):
    """The model's clip forward over the same frames (every frame recomputed from its image)."""
    K = localizer.default_intrinsics if intrinsics is None else intrinsics
    inputs = [
        network_input(f, localizer.input_size, K, None if depths is None else depths[i]) for i, f in enumerate(frames)
    ]
    images = torch.stack([x for x, _, _ in inputs], 1)
    Ks = torch.stack([k for _, k, _ in inputs], 1)
    depth = None if depths is None else torch.stack([d for _, _, d in inputs], 1)
    with torch.inference_mode():
        return localizer.model.forward_clip(images, Ks, depth=depth)


def test_streaming_reuses_cached_features_and_equals_recomputing(localizer: Localizer):
    frames = _frames(3)
    trunk_calls = []
    localizer.model.trunk.register_forward_hook(lambda *a: trunk_calls.append(1))
    results = [localizer.step(f, "rgb8", 10.0 + 0.05 * k) for k, f in enumerate(frames)]
    assert len(trunk_calls) == 3  # one trunk pass per frame: the previous frame is never recomputed
    clip = _clip(localizer, frames)
    for k, (r, o) in enumerate(zip(results, clip, strict=True)):
        np.testing.assert_allclose(r.frame_t, o.xyz[0].double().numpy(), atol=1e-5)
        np.testing.assert_allclose(r.frame_q, geometry.quat_normalize(o.quat[0].double().numpy()), atol=1e-5)
        ids = o.seg_logits[0].argmax(0).to(torch.uint8).numpy()
        assert r.mask.shape == (H, W) and r.mask.dtype == np.uint8
        assert np.array_equal(r.mask, cv2.resize(ids, (W, H), interpolation=cv2.INTER_NEAREST_EXACT))
        if k > 0:
            np.testing.assert_allclose(r.rel_t, o.rel_xyz[0].double().numpy(), atol=1e-5)
            np.testing.assert_allclose(r.rel_q, geometry.quat_normalize(o.rel_quat[0].double().numpy()), atol=1e-5)
    # "recompute both frames from scratch": a fresh pair gives the second frame of the stream
    pair = _clip(localizer, frames[:2])
    np.testing.assert_allclose(results[1].frame_t, pair[1].xyz[0].double().numpy(), atol=1e-5)
    np.testing.assert_allclose(results[1].rel_t, pair[1].rel_xyz[0].double().numpy(), atol=1e-5)
    # and the cached state matters: frame 1 alone (as a first frame) gives another pose
    alone = _clip(localizer, frames[1:2])[0]
    assert not np.allclose(results[1].frame_t, alone.xyz[0].double().numpy(), atol=1e-6)


def test_odometry_accumulates_relative_poses_and_twist_is_motion_over_dt(localizer: Localizer):
    frames = _frames(5, seed=2)
    stamps = [3.0, 3.1, 3.25, 3.3, 3.5]
    results = [localizer.step(f, "rgb8", s) for f, s in zip(frames, stamps, strict=True)]
    first = results[0]
    assert first.reset_reason == "start" and first.dt == 0.0
    assert np.array_equal(first.rel_t, np.zeros(3)) and np.array_equal(first.rel_q, [1, 0, 0, 0])
    assert np.array_equal(first.linear, np.zeros(3)) and np.array_equal(first.angular, np.zeros(3))
    assert np.array_equal(np.diag(first.twist_covariance), np.full(6, UNKNOWN_VARIANCE))  # unknown motion
    T = np.eye(4)
    for k, r in enumerate(results):
        assert r.reset_reason is None or k == 0
        T_rel = geometry.pose_to_matrix(r.rel_t, r.rel_q)
        T = T @ T_rel
        np.testing.assert_allclose(geometry.pose_to_matrix(r.odom_t, r.odom_q), T, atol=1e-9)
        np.testing.assert_allclose(r.pose_covariance, np.diag(POSE_VAR))
        np.testing.assert_allclose(r.odom_covariance, np.diag(np.array(ODO_VAR) * (1 + k)))
        if k == 0:
            continue
        dt = stamps[k] - stamps[k - 1]
        assert r.dt == pytest.approx(dt)
        np.testing.assert_allclose(r.linear, T_rel[:3, :3].T @ T_rel[:3, 3] / dt, atol=1e-9)
        rotvec = Rotation.from_quat(geometry.quat_to_ros(r.rel_q)).as_rotvec()
        np.testing.assert_allclose(r.angular, rotvec / dt, atol=1e-9)
        np.testing.assert_allclose(r.twist_covariance, np.diag(np.array(ODO_VAR) / dt**2))
        assert np.abs(r.linear).sum() > 0  # an untrained net still predicts some motion


def test_state_resets_on_stamps_gaps_resolution_intrinsics_and_request(localizer: Localizer):
    f = _frames(10, seed=3)
    small = _frames(1, seed=3, size=(60, 100))[0]
    K_cam = Intrinsics(120.0, 120.0, 74.5, 44.5, W, H)
    steps = [
        (f[0], 1.0, None, "start"),
        (f[1], 1.1, None, None),
        (f[2], 1.05, None, "stamp_backwards"),
        (f[3], 1.05, None, "stamp_backwards"),  # a repeated stamp has no dt either
        (f[4], 2.5, None, "gap"),  # 1.45 s > max_gap_s
        (small, 2.6, None, "resolution_change"),
        (small, 2.7, None, None),
        (f[5], 2.8, None, "resolution_change"),
        (f[6], 2.9, K_cam, "intrinsics_change"),
        (f[7], 3.0, K_cam, None),
    ]
    prev = None
    for image, stamp, K, reason in steps:
        r = localizer.step(image, "rgb8", stamp, intrinsics=K)
        assert r.reset_reason == reason, (stamp, r.reset_reason)
        assert r.mask.shape == image.shape[:2]
        if reason is not None and prev is not None:  # odometry holds across a reset
            assert np.array_equal(r.odom_t, prev.odom_t) and np.array_equal(r.odom_q, prev.odom_q)
            assert np.array_equal(r.linear, np.zeros(3)) and r.dt == 0.0
        prev = r
    localizer.reset()
    r = localizer.step(f[8], "rgb8", 3.1, intrinsics=K_cam)
    assert r.reset_reason == "request" and np.array_equal(r.odom_t, prev.odom_t)
    # after a reset the global pose comes from the image alone: as from a fresh localizer
    fresh = Localizer(localizer.model, localizer.meta).step(f[8], "rgb8", 0.0, intrinsics=K_cam)
    np.testing.assert_allclose(r.t, fresh.t, atol=1e-6)
    localizer.reset(clear_odometry=True)
    r = localizer.step(f[9], "rgb8", 3.2)
    assert np.array_equal(r.odom_t, np.zeros(3)) and np.array_equal(r.odom_q, [1, 0, 0, 0])


def test_non_finite_outputs_reject_the_frame_and_reset_the_state(localizer: Localizer):
    f = _frames(4, seed=4)
    assert localizer.step(f[0], "rgb8", 0.0).reset_reason == "start"
    bias = localizer.model.global_stream.head.fc_xyz.bias
    saved = bias.detach().clone()
    with torch.no_grad():
        bias[1] = float("nan")
    with pytest.raises(FrameError) as err:
        localizer.step(f[1], "rgb8", 0.1)
    assert err.value.reason == "nan_output"
    with torch.no_grad():
        bias.copy_(saved)
    r = localizer.step(f[2], "rgb8", 0.2)
    assert r.reset_reason == "nan_output" and np.isfinite(r.t).all()
    assert localizer.step(f[3], "rgb8", 0.3).reset_reason is None


def test_every_encoding_gives_the_pose_of_the_rgb_image(localizer: Localizer):
    rgb = _frames(1, seed=5)[0]
    localizer.reset()
    ref = localizer.step(rgb, "rgb8", 0.0)
    for encoding, code in [("bgr8", cv2.COLOR_RGB2BGR), ("rgba8", cv2.COLOR_RGB2RGBA), ("bgra8", cv2.COLOR_RGB2BGRA)]:
        localizer.reset()
        r = localizer.step(cv2.cvtColor(rgb, code), encoding, 0.0)
        assert np.array_equal(r.t, ref.t) and np.array_equal(r.q, ref.q) and np.array_equal(r.mask, ref.mask), encoding
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    localizer.reset()
    mono = localizer.step(grey, "mono8", 0.0)
    localizer.reset()
    assert np.array_equal(mono.t, localizer.step(cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB), "rgb8", 0.0).t)
    with pytest.raises(FrameError) as err:
        localizer.step(rgb, "yuv422", 1.0)
    assert err.value.reason == "unsupported_encoding"


def test_given_depth_replaces_the_prediction_for_warping(localizer: Localizer):
    frames = _frames(2, seed=6)
    depths = [np.full((H, W), 6.0, np.float32) for _ in frames]
    depths[1][: H // 2] = 0.0  # invalid half
    with_depth = [
        localizer.step(f, "rgb8", 0.05 * k, depth=d) for k, (f, d) in enumerate(zip(frames, depths, strict=True))
    ]
    clip = _clip(localizer, frames, depths=depths)
    np.testing.assert_allclose(with_depth[1].frame_t, clip[1].xyz[0].double().numpy(), atol=1e-5)
    localizer.reset()
    predicted = [localizer.step(f, "rgb8", 1.0 + 0.05 * k) for k, f in enumerate(frames)]
    assert not np.allclose(with_depth[1].t, predicted[1].t, atol=1e-7)  # the warp (and so the fused pose) changed
    # a depth image of another size is refused before the state is touched
    with pytest.raises(FrameError) as err:
        localizer.step(frames[0], "rgb8", 1.1, depth=depths[0][:, :-1])
    assert err.value.reason == "depth_size"
    assert localizer.step(frames[0], "rgb8", 1.15).reset_reason is None


def test_intrinsics_describe_the_field_of_view_at_any_resolution(localizer: Localizer):
    frames = _frames(2, seed=7)
    K = Intrinsics(110.0, 100.0, 74.5, 44.5, W, H)
    K2 = K.resized(2 * W, 2 * H)  # the same camera calibrated at twice the resolution
    a = [localizer.step(f, "rgb8", 0.05 * k, intrinsics=K) for k, f in enumerate(frames)]
    localizer.reset()
    b = [localizer.step(f, "rgb8", 0.05 * k, intrinsics=K2) for k, f in enumerate(frames)]
    np.testing.assert_allclose(a[1].t, b[1].t, atol=1e-6)
    localizer.reset()
    c = [
        localizer.step(f, "rgb8", 0.05 * k, intrinsics=Intrinsics(300.0, 300.0, 74.5, 44.5, W, H))
        for k, f in enumerate(frames)
    ]
    assert not np.allclose(a[1].t, c[1].t, atol=1e-7)  # and they do reach the warp


def test_from_checkpoint_errors(tmp_path: Path, checkpoint: Path):
    with pytest.raises(DataError, match="no such checkpoint"):
        Localizer.from_checkpoint(tmp_path / "missing.safetensors")
    if not torch.cuda.is_available():
        with pytest.raises(UserError, match="CUDA is not available"):
            Localizer.from_checkpoint(checkpoint, device="cuda")


def test_one_meaning_of_threads_and_no_process_wide_setting_in_the_localizer(checkpoint):
    import os

    from vlocnetpp_core.threads import resolve_threads, use_threads

    assert resolve_threads(3) == 3
    assert resolve_threads(0) == max(1, (os.cpu_count() or 1) - 1)
    with pytest.raises(ValueError):
        resolve_threads(-1)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        Localizer.from_checkpoint(checkpoint, num_threads=1)
        assert torch.get_num_threads() == 2  # building a Localizer leaves the process's setting alone
        assert use_threads(1) == 1 and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)

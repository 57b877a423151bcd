"""Output shapes of every tap and head, for both configs and non-default input sizes; ablation switches."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from model_fixtures import (
    intrinsics,
    lite,
    one_thread,  # noqa: F401  (autouse: one thread per test)
)

from vlocnetpp_core.geometry import quat_mul
from vlocnetpp_core.model import STREAMS, ModelConfig, VLocNetPP, load_model_config, params_per_stream
from vlocnetpp_core.model.anchors import kmeans_anchors, rotation_anchors


def expected_taps(cfg: ModelConfig, batch: int, width: int, height: int) -> dict[str, tuple[int, ...]]:
    c1, c2, c3 = cfg.stage_channels[1:]

    def stride(s: int) -> tuple[int, int]:  # stride-2 layers and the pooling round up
        return math.ceil(height / s), math.ceil(width / s)

    s8, s16, p = (
        (height // 8, width // 8),
        (height // 16, width // 16),
        cfg.global_downsample,
    )  # the global stream pools Res3 by p
    shapes = {
        "res3": (c1, *s8),
        "res4c": (c2, *stride(16 * p)),
        "res4c_fused": (c2, *stride(16 * p)),
        "res4f": (c2, *stride(16 * p)),
        "res5a": (c3, *stride(32 * p)),
        "res5a_fused": (c3, *stride(32 * p)),
        "res5c": (c3, *stride(32 * p)),
        "odo_res4": (c2, *s16),
        "odo_res5": (c3, *stride(32)),
        "sem_res3": (c1, *s8),
        "sem_res4f": (c2, *s16),
        "sem_res4f_warped": (c2, *s16),
        "sem_res4f_fused": (c2, *s16),
        "sem_res5c": (c3, *s16),
        "sem_res5c_warped": (c3, *s16),
        "sem_res5c_fused": (c3, *s16),
    }
    return {k: (batch, *v) for k, v in shapes.items()}


def check_step_shapes(cfg: ModelConfig, width: int, height: int, batch: int = 2) -> None:
    torch.manual_seed(0)
    model = VLocNetPP(cfg).eval()
    K = intrinsics(batch, width, height)
    images = torch.rand(2, batch, 3, height, width)
    with torch.inference_mode():
        out, state = model.step(images[0], None, K)
        out, state = model.step(images[1], state, K)  # second frame: real warping and temporal fusion
    assert {k: tuple(v.shape) for k, v in out.taps.items()} == expected_taps(cfg, batch, width, height)
    for xyz, quat in ((out.xyz, out.quat), (out.rel_xyz, out.rel_quat)):
        assert xyz.shape == (batch, 3) and quat.shape == (batch, 4)
        torch.testing.assert_close(quat.norm(dim=1), torch.ones(batch))
        assert (quat[:, 0] >= 0).all()
    assert out.seg_logits.shape == (batch, cfg.num_classes, height, width)
    assert out.depth.shape == (batch, 1, height, width)
    lo, hi = cfg.depth_range
    assert (out.depth >= lo * 0.999).all() and (out.depth <= hi * 1.001).all()
    assert state.res5a.shape == out.taps["res5a"].shape and state.odo_res4.shape == out.taps["odo_res4"].shape
    assert state.sem_res4f.shape == out.taps["sem_res4f"].shape and state.sem_res5c.shape == out.taps["sem_res5c"].shape


@pytest.mark.parametrize("size", [(224, 128), (208, 112), (160, 48)])
@pytest.mark.parametrize("pooling", ["flatten", "average"])
def test_lite_shapes(size, pooling):
    check_step_shapes(lite(input_size=size, global_pose_pooling=pooling, odometry_pose_pooling=pooling), *size)


@pytest.mark.parametrize("size", [(96, 64), (80, 48)])
@pytest.mark.parametrize("global_downsample", [1, 2])
def test_paper_shapes_at_small_sizes(size, global_downsample):
    check_step_shapes(dataclasses.replace(load_model_config("paper"), global_downsample=global_downsample), *size)


def test_lite_is_a_few_million_parameters():
    total = sum(params_per_stream(VLocNetPP(load_model_config("lite"))).values())
    assert 1e6 < total < 1e7


def test_global_downsample_pools_res3_for_the_global_stream_only():
    """With ``global_downsample: 2`` the global stream reads the trunk's Res3 map 2x2-averaged and fuses the semantic
    Res5c map 2x2-averaged; the trunk and the odometry stream are those of the plain network with the same weights."""
    torch.manual_seed(0)
    cfg = lite(global_downsample=2, global_pose_pooling="average")
    halved, plain = VLocNetPP(cfg).eval(), VLocNetPP(lite(global_downsample=1, global_pose_pooling="average")).eval()
    plain.load_state_dict(halved.state_dict())
    image, K = torch.rand(1, 3, 128, 224), intrinsics(1, 224, 128)
    with torch.inference_mode():
        a, _ = halved.step(image, None, K)
        b, _ = plain.step(image, None, K)
        for key in ("res3", "odo_res5", "sem_res5c_fused"):
            torch.testing.assert_close(a.taps[key], b.taps[key], rtol=0, atol=0)
        pooled = a.taps["res3"].reshape(1, -1, 8, 2, 14, 2).mean(dim=(3, 5))
        for block in halved.global_stream.res4[: cfg.res4_fusion_block]:
            pooled = block(pooled)
        torch.testing.assert_close(a.taps["res4c"], pooled, rtol=1e-5, atol=1e-5)
        sem = a.taps["sem_res5c_fused"].reshape(1, -1, 4, 2, 7, 2).mean(dim=(3, 5))
        torch.testing.assert_close(
            a.taps["res4c_fused"], halved.semantic_fusion(a.taps["res4c"], sem), rtol=1e-5, atol=1e-5
        )


def test_flatten_head_reads_where_things_are():
    """The flattened head sees every Res5c cell (swapping two cells changes the pose; the average cannot tell)
    and refuses maps of another size than its config's input_size."""
    torch.manual_seed(0)
    cfg = lite(global_pose_pooling="flatten")
    head = VLocNetPP(cfg).global_stream.head.eval()
    h, w = cfg.global_res5_size
    assert head.fc1.in_features == cfg.stage_channels[3] * h * w
    x = torch.randn(1, cfg.stage_channels[3], h, w)
    swapped = x.clone()
    swapped[..., 0, 0], swapped[..., -1, -1] = x[..., -1, -1], x[..., 0, 0]
    with torch.inference_mode():
        assert not torch.allclose(head(x)[0], head(swapped)[0])
        with pytest.raises(ValueError, match="input_size"):
            head(torch.randn(1, cfg.stage_channels[3], h + 1, w))


def test_anchor_head_mixes_anchors_plus_offsets():
    """With position anchors the position is the softmax-weighted sum of anchor + offset: a score that dominates
    puts the camera on its anchor plus that anchor's offset, equal scores average; fc2 of the paper is gone."""
    torch.manual_seed(0)
    cfg = lite(global_pose_anchors=3, global_rotation_anchors=0)
    model = VLocNetPP(cfg).eval()
    head = model.global_stream.head
    assert head.fc_anchor.out_features == 3 and head.fc_xyz.out_features == 9
    positions = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 1.0], [0.0, -40.0, 2.0]]).repeat(4, axis=0)
    model.set_pose_prior(positions)
    anchors = head.anchor_xyz.clone()
    assert sorted(anchors[:, 2].tolist()) == [0.0, 1.0, 2.0]  # one anchor per cluster of positions
    offsets = torch.tensor([[1.0, 2.0, 3.0], [-1.0, 0.0, 0.5], [0.0, 0.0, -2.0]])
    x = torch.randn(1, cfg.stage_channels[3], *cfg.global_res5_size)
    with torch.no_grad():
        head.fc_anchor.weight.zero_()
        head.fc_xyz.weight.zero_()
        head.fc_xyz.bias.copy_(offsets.flatten())
        head.fc_anchor.bias.copy_(torch.tensor([0.0, 30.0, 0.0]))
        xyz, _, logits, _ = head(x)
        torch.testing.assert_close(xyz[0], anchors[1] + offsets[1])
        assert logits.shape == (1, 3)
        head.fc_anchor.bias.zero_()
        xyz, _, _, _ = head(x)
        torch.testing.assert_close(xyz[0], (anchors + offsets).mean(0))
    with pytest.raises(ValueError, match="3 position anchors"):
        head.set_anchors(torch.zeros(4, 3))
    out, _ = model.step(torch.rand(1, 3, 128, 224), tasks=("loc",))
    assert out.anchor_logits.shape == (1, 3) and out.anchor_xyz is head.anchor_xyz


def test_rotation_anchor_head_turns_the_best_anchors():
    """With rotation anchors the quaternion is the softmax-weighted mix of anchor * residual: a dominant score
    gives its anchor turned by its residual (zero residual: the anchor itself), whatever the sign of the anchor."""
    torch.manual_seed(0)
    cfg = lite(global_rotation_anchors=2)
    model = VLocNetPP(cfg).eval()
    head = model.global_stream.head
    assert head.fc_rotation_anchor.out_features == 2 and head.fc_quat.out_features == 8
    yaw = [np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)]) for a in (0.3, 2.0)]
    quats = np.stack([yaw[0]] * 5 + [-yaw[1]] * 5)  # the second cluster given with w < 0: the same rotation
    model.set_pose_prior(np.zeros((10, 3)), quats)
    anchors = head.anchor_quat.clone()
    assert {round(float(a), 4) for a in anchors[:, 3]} == {round(float(np.sin(0.15)), 4), round(float(np.sin(1.0)), 4)}
    x = torch.randn(1, cfg.stage_channels[3], *cfg.global_res5_size)
    turn = torch.tensor([np.cos(0.05), 0.0, 0.0, np.sin(0.05)], dtype=torch.float32)  # 0.1 rad about z
    with torch.no_grad():
        head.fc_rotation_anchor.weight.zero_()
        head.fc_quat.weight.zero_()
        head.fc_quat.bias.zero_()
        head.fc_rotation_anchor.bias.copy_(torch.tensor([0.0, 30.0]))
        _, quat, _, logits = head(x)
        torch.testing.assert_close(quat[0], anchors[1])
        head.fc_quat.bias[4:].copy_(turn - torch.tensor([1.0, 0.0, 0.0, 0.0]))
        _, quat, _, _ = head(x)
        torch.testing.assert_close(quat[0], quat_mul(anchors[1], turn))
    assert logits.shape == (1, 2)
    with pytest.raises(ValueError, match="2 rotation anchors"):
        head.set_rotation_anchors(torch.zeros(3, 4))
    with pytest.raises(ValueError, match="quaternions"):
        model.set_pose_prior(np.zeros((10, 3)))
    out, _ = model.step(torch.rand(1, 3, 128, 224), tasks=("loc",))
    assert out.rotation_logits.shape == (1, 2) and out.anchor_quat is head.anchor_quat


def test_rotation_anchors_are_unit_quaternions_of_the_clusters():
    rng = np.random.default_rng(0)
    angles = np.concatenate([rng.normal(a, 0.01, 40) for a in (0.0, 1.5, 3.1)])
    quats = np.stack([np.cos(angles / 2), np.zeros_like(angles), np.zeros_like(angles), np.sin(angles / 2)], 1)
    quats[::2] *= -1  # either sign of each rotation
    anchors = rotation_anchors(quats, 3, seed=0)
    np.testing.assert_allclose(np.linalg.norm(anchors, axis=1), 1.0, atol=1e-9)
    assert (anchors[:, 0] >= 0).all()
    np.testing.assert_allclose(np.sort(2 * np.arctan2(anchors[:, 3], anchors[:, 0])), [0.0, 1.5, 3.1], atol=0.02)


def test_kmeans_anchors_cover_the_positions():
    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 30.0, 0.0], [30.0, 30.0, 5.0]])
    positions = (centres[:, None] + rng.normal(0, 0.5, (4, 50, 3))).reshape(-1, 3)
    anchors = kmeans_anchors(positions, 4, seed=1)
    assert np.abs(np.sort(anchors, axis=0) - np.sort(centres, axis=0)).max() < 0.5
    np.testing.assert_array_equal(anchors, kmeans_anchors(positions, 4, seed=1))
    few = kmeans_anchors(positions[:2], 5)  # fewer distinct positions than anchors: each position, repeated
    assert few.shape == (5, 3) and {tuple(p) for p in few} == {tuple(p) for p in positions[:2]}
    with pytest.raises(ValueError, match="non-empty"):
        kmeans_anchors(np.zeros((0, 3)), 4)


@pytest.mark.parametrize(
    ("switch", "gone_modules", "gone_taps"),
    [
        ("temporal_fusion", ["global_stream.temporal_fusion"], ["res5a_fused"]),
        ("semantic_fusion", ["semantic_fusion"], ["res4c_fused"]),
        (
            "warping",
            ["semantic.warp_fusion_res4f", "semantic.warp_fusion_res5c", "depth_head"],
            ["sem_res4f_warped", "sem_res4f_fused", "sem_res5c_warped", "sem_res5c_fused"],
        ),
    ],
)
def test_ablation_switch_removes_the_branch(switch, gone_modules, gone_taps):
    full = VLocNetPP(lite(input_size=(96, 64)))
    cut = VLocNetPP(lite(input_size=(96, 64), **{switch: False}))
    full_names = {n for n, _ in full.named_parameters()}
    cut_names = {n for n, _ in cut.named_parameters()}
    removed = full_names - cut_names
    assert cut_names < full_names
    assert removed == {n for n in full_names if any(n.startswith(m + ".") for m in gone_modules)}
    W, H = 96, 64
    K = intrinsics(1, W, H)
    with torch.inference_mode():
        out, state = cut.eval().step(torch.rand(1, 3, H, W), None, K)
        out, state = cut.step(torch.rand(1, 3, H, W), state, K)
    assert not set(gone_taps) & set(out.taps)
    assert out.xyz is not None and out.rel_xyz is not None and out.seg_logits.shape == (1, 10, H, W)
    if switch == "warping":
        assert out.depth is None and state.sem_res4f is None
    if switch == "temporal_fusion":
        assert state.res5a is None


def test_all_switches_off_still_runs_every_task():
    model = VLocNetPP(lite(input_size=(96, 64), temporal_fusion=False, semantic_fusion=False, warping=False)).eval()
    assert set(params_per_stream(model)) == set(STREAMS)
    assert params_per_stream(model)["fusion"] == 0 and params_per_stream(model)["depth"] == 0
    with torch.inference_mode():
        out, _ = model.step(torch.rand(1, 3, 64, 96))  # no K needed without warping
    assert out.xyz.shape == (1, 3) and out.seg_logits.shape == (1, 10, 64, 96)


def test_bad_inputs_are_clear_errors():
    model = VLocNetPP(lite(input_size=(96, 64))).eval()
    with torch.inference_mode():
        with pytest.raises(ValueError, match="multiples of 16"):
            model.step(torch.rand(1, 3, 60, 96), None, intrinsics(1, 96, 60))
        with pytest.raises(ValueError, match="RGB"):
            model.step(torch.rand(1, 1, 64, 96), None, intrinsics(1, 96, 64))
        with pytest.raises(ValueError, match="K .* required"):
            model.step(torch.rand(1, 3, 64, 96))
        with pytest.raises(ValueError, match="tasks"):
            model.step(torch.rand(1, 3, 64, 96), None, intrinsics(1, 96, 64), tasks=("pose",))
        _, state = model.step(torch.rand(1, 3, 64, 96), None, intrinsics(1, 96, 64))
        with pytest.raises(ValueError, match="start again with state=None"):
            model.step(torch.rand(1, 3, 96, 128), state, intrinsics(1, 128, 96))


def test_config_input_size_is_only_a_default_with_average_pooling():
    check_step_shapes(
        lite(input_size=(64, 32), global_pose_pooling="average", odometry_pose_pooling="average"), 128, 64, batch=1
    )
    for flattened in ("global_pose_pooling", "odometry_pose_pooling"):  # either flattened head fixes the input size
        other = {"global_pose_pooling": "odometry_pose_pooling", "odometry_pose_pooling": "global_pose_pooling"}[
            flattened
        ]
        with pytest.raises(ValueError, match="input_size"), torch.inference_mode():
            VLocNetPP(lite(input_size=(64, 32), **{flattened: "flatten", other: "average"})).eval().step(
                torch.rand(1, 3, 64, 128), None, intrinsics(1, 128, 64)
            )

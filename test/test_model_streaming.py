"""Streaming state vs clip forward, the cached odometry Res4, gradients in MTL, and the stage helpers."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from model_fixtures import (
    lite,
    one_thread,  # noqa: F401  (autouse: one thread per test)
    random_clip_batch,
)

from vlocnetpp_core.geometry import pose_to_matrix
from vlocnetpp_core.model import (
    STAGES,
    STREAMS,
    StreamState,
    VLocNetPP,
    is_trained_in,
    params_per_stream,
    stream_of,
    trainable_parameters,
)
from vlocnetpp_core.training.losses import VLocNetLoss

W, H = 96, 64


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return VLocNetPP(lite(input_size=(W, H)))


def test_streaming_equals_clip_forward_in_eval_mode(model):
    batch = random_clip_batch(2, 4, W, H, seed=1)
    model.eval()
    with torch.no_grad():
        clip = model.forward_clip(batch["image"], batch["K"])
        state = None
        for t in range(4):
            out, state = model.step(batch["image"][:, t], state, K=batch["K"][:, t])
            for name in ("xyz", "quat", "rel_xyz", "rel_quat", "seg_logits", "depth"):
                diff = (getattr(out, name) - getattr(clip[t], name)).abs().max()
                assert diff < 1e-5, (t, name, float(diff))


def test_state_carries_the_previous_frame(model):
    """Frame t's outputs depend on frame t-1 through every fusion, and the cache equals recomputation."""
    batch = random_clip_batch(1, 3, W, H, seed=2)
    images, K = batch["image"], batch["K"][:, 0]
    # An untrained odometry stream predicts arbitrary motion (everything out of view): warp with a small known one.
    depth, small = (
        torch.full((1, 1, H, W), 5.0),
        pose_to_matrix(torch.tensor([[0.1, 0.0, 0.2]]), torch.tensor([[1.0, 0.0, 0.02, 0.0]])),
    )
    model.eval()
    with torch.no_grad():
        _, state_a = model.step(images[:, 0], None, K)
        _, state_b = model.step(images[:, 1], None, K)
        out_a, _ = model.step(images[:, 2], state_a, K, depth=depth, warp_rel_pose=small)
        out_b, _ = model.step(images[:, 2], state_b, K, depth=depth, warp_rel_pose=small)
        assert out_a.taps["sem_res5c_warped"].abs().amax(dim=1).gt(0).float().mean() > 0.5
        for name in ("xyz", "rel_xyz", "seg_logits"):
            assert (getattr(out_a, name) - getattr(out_b, name)).abs().max() > 1e-6, name
        # The cached odometry Res4 of frame t-1 is exactly what recomputing it from I_{t-1} gives.
        recomputed = model.odometry.res4(model.trunk((images[:, 0] - model.mean) / model.std))
        torch.testing.assert_close(state_a.odo_res4, recomputed, rtol=0, atol=0)
        rel_xyz, rel_quat, _ = model.odometry(recomputed, out_a.taps["odo_res4"])
        torch.testing.assert_close(out_a.rel_xyz, rel_xyz)
        torch.testing.assert_close(out_a.rel_quat, rel_quat)


def test_position_prior_shifts_the_global_translation():
    """The paper's head is centred on the mean training position and scaled by the spread (at least 1 m)."""
    model = VLocNetPP(lite(input_size=(W, H), global_pose_anchors=0, global_rotation_anchors=0)).eval()
    image = torch.rand(1, 3, H, W)
    positions = np.array([[100.0, -20.0, 3.5]]) + np.array([[-4.0, 0.0, 0.1], [4.0, 0.0, -0.1]])
    with torch.no_grad():
        before, _ = model.step(image, tasks=("loc",))
        model.set_pose_prior(positions)
        after, _ = model.step(image, tasks=("loc",))
    torch.testing.assert_close(model.global_stream.head.xyz_scale, torch.tensor([4.0, 1.0, 1.0]))
    torch.testing.assert_close(
        after.xyz, torch.tensor([[100.0, -20.0, 3.5]]) + torch.tensor([4.0, 1.0, 1.0]) * before.xyz
    )
    torch.testing.assert_close(after.quat, before.quat)


def test_tasks_run_only_their_streams(model):
    batch = random_clip_batch(1, 2, W, H, seed=3)
    model.eval()
    with torch.no_grad():
        loc = model.forward_clip(batch["image"], batch["K"], tasks=("loc",))[-1]
        assert loc.xyz is not None and loc.rel_xyz is None and loc.seg_logits is None
        assert "odo_res4" not in loc.taps and "sem_res3" not in loc.taps and "res4c_fused" not in loc.taps
        vo = model.forward_clip(batch["image"], batch["K"], tasks=("vo",))[-1]
        assert vo.rel_xyz is not None and vo.xyz is None and "res4c" not in vo.taps
        warp = pose_to_matrix(batch["rel_t"], batch["rel_q"])
        seg = model.forward_clip(batch["image"], batch["K"], warp_rel_pose=warp, tasks=("seg",))[-1]
        assert seg.seg_logits is not None and seg.depth is not None and "res3" not in seg.taps  # no odometry needed
        seg_pred = model.forward_clip(batch["image"], batch["K"], tasks=("seg",))[-1]
        assert "odo_res4" in seg_pred.taps  # warping uses the odometry's relative pose when none is given
    assert StreamState().detach() == StreamState()


def test_mtl_backward_reaches_every_parameter():
    torch.manual_seed(0)
    model = VLocNetPP(lite(input_size=(W, H))).train()
    criterion = VLocNetLoss("mtl")
    batch = random_clip_batch(2, 3, W, H, seed=4)
    outputs = model.forward_clip(batch["image"], batch["K"])
    loss, parts = criterion(outputs, batch)
    loss.backward()
    assert set(parts) >= {"x", "q", "x_rel", "q_rel", "x_vo", "q_vo", "seg", "depth", "loc", "vo"}
    dead = [n for n, p in model.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    assert dead == []
    dead_weights = [n for n, p in criterion.named_parameters() if p.grad is None or p.grad == 0]
    assert (
        dead_weights == [] and len(list(criterion.parameters())) == 6
    )  # s_x, s_q (shared with the consistency terms), s_x_vo, s_q_vo, s_seg, s_depth


def test_stage_helpers_partition_the_parameters(model):
    names = [n for n, _ in model.named_parameters()]
    assert {stream_of(n) for n in names} == set(STREAMS)
    assert stream_of("trunk.res3.0.conv1.weight") == "global" and stream_of("module.depth_head.out.bias") == "depth"
    assert (
        stream_of("semantic_fusion.weight_a") == "fusion"
        and stream_of("semantic.warp_fusion_res4f.weight_b") == "semantic"
    )
    assert stream_of("global_stream.temporal_fusion.pool.weight") == "global"
    with pytest.raises(KeyError):
        stream_of("decoder.weight")
    trained = {stage: {id(p) for p in trainable_parameters(model, stage)} for stage in STAGES}
    by_name = dict(model.named_parameters())
    assert trained["mtl"] == {id(p) for p in model.parameters()}
    assert {stream_of(n) for n in names if id(by_name[n]) in trained["stl-loc"]} == {"global"}
    assert {stream_of(n) for n in names if id(by_name[n]) in trained["stl-seg"]} == {"semantic", "depth"}
    vo = {n for n in names if is_trained_in(n, "stl-vo")}
    assert {n for n in vo if stream_of(n) == "global"} == {n for n in names if n.startswith("trunk.")}
    assert not any(n.startswith("global_stream.") for n in vo)
    assert sum(params_per_stream(model).values()) == sum(p.numel() for p in model.parameters())
    with pytest.raises(ValueError, match="unknown stage"):
        list(trainable_parameters(model, "stl-depth"))


def test_single_task_stage_trains_only_its_streams():
    """One optimiser step of stl-seg (as the trainer runs it) changes semantic and depth weights only."""
    torch.manual_seed(0)
    model = VLocNetPP(lite(input_size=(W, H))).train()
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    criterion = VLocNetLoss("stl-seg")
    for p in model.parameters():
        p.requires_grad_(False)
    params = list(trainable_parameters(model, "stl-seg"))
    for p in params:
        p.requires_grad_(True)
    optimizer = torch.optim.Adam(params + list(criterion.parameters()), lr=1e-3)
    batch = random_clip_batch(2, 2, W, H, seed=5)
    warp = pose_to_matrix(batch["rel_t"], batch["rel_q"])
    loss, _ = criterion(model.forward_clip(batch["image"], batch["K"], warp_rel_pose=warp, tasks=("seg",)), batch)
    loss.backward()
    optimizer.step()
    changed = {stream_of(n) for n, p in model.named_parameters() if not torch.equal(p, before[n])}
    assert changed == {"semantic", "depth"}


def test_bf16_autocast_keeps_the_pose_and_depth_heads_in_float32():
    """train --bf16: under bfloat16 autocast the trunk and streams run in bfloat16 but the pose (and depth) heads in
    float32, so a position 1000 m from the origin keeps centimetres (bfloat16 steps by 4 m there) and matches the
    float32 forward."""
    torch.manual_seed(0)
    net = VLocNetPP(lite(input_size=(W, H))).eval()
    rng = np.random.default_rng(0)
    net.set_pose_prior(
        np.array([1002.0, -1002.0, 2.0]) + rng.normal(0, 3, (200, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (200, 1))
    )
    batch = random_clip_batch(2, 2, W, H)
    with torch.no_grad():
        full = net(batch["image"], batch["K"])
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mixed = net(batch["image"], batch["K"])
    for low, ref in zip(mixed, full, strict=True):
        assert low.taps["res3"].dtype == torch.bfloat16  # autocast was on
        assert {o.dtype for o in (low.xyz, low.quat, low.rel_xyz, low.rel_quat, low.depth)} == {torch.float32}
        assert float((low.xyz - ref.xyz).abs().max()) < 0.25  # measured 0.015 m; a bfloat16 head: up to 2 m
        assert float((low.quat - ref.quat).abs().max()) < 0.1  # measured 0.02


def test_bf16_autocast_segmentation_decoder_passes_on_the_float32_gradients():
    """The decoder's deconvolutions run in float32 under autocast: in bfloat16 the CPU's ConvTranspose2d of kernel 16,
    stride 8 returned input gradients unrelated to float32's (cosine 0.01), and --bf16 segmentation diverged."""
    from vlocnetpp_core.model.heads import SegmentationDecoder

    torch.manual_seed(0)
    decoder = SegmentationDecoder(64, 32, 10).to(memory_format=torch.channels_last)
    deep, skip = torch.randn(2, 64, 8, 14), torch.randn(2, 32, 16, 28)
    upstream = torch.randn(2, 10, 128, 224)

    def input_grads(bf16: bool) -> list[torch.Tensor]:
        inputs = [deep.clone().requires_grad_(True), skip.clone().requires_grad_(True)]
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            logits = decoder(*inputs)
        (logits.float() * upstream).sum().backward()
        return [x.grad for x in inputs]

    for full, mixed in zip(input_grads(False), input_grads(True), strict=True):
        assert (
            torch.nn.functional.cosine_similarity(full.flatten(), mixed.float().flatten(), dim=0) > 0.98
        )  # measured 0.999+


def test_a_training_clip_runs_the_odometry_res5_on_real_pairs_only():
    # a first frame in training gives the identity without running Res5: its self-pair (zero motion) would
    # otherwise feed half the running statistics of Res5's and the head's BatchNorms with clips of 2, and
    # every evaluation then measured steps 1.6x too long (docs/results.md, 2026-12-15)
    torch.manual_seed(4)
    model = VLocNetPP(lite(input_size=(W, H)))
    batch = random_clip_batch(2, 2, W, H, seed=4)
    norms = [
        m
        for m in (*model.odometry.res5.modules(), *model.odometry.head.modules())
        if isinstance(m, torch.nn.BatchNorm2d)
    ]
    model.train()
    before = [int(m.num_batches_tracked) for m in norms]
    with torch.no_grad():
        first, second = model.forward_clip(batch["image"], batch["K"], tasks=("vo",))
    model.eval()
    assert norms and all(
        int(m.num_batches_tracked) == n + 1 for m, n in zip(norms, before, strict=True)
    )  # one update: the real pair
    torch.testing.assert_close(first.rel_xyz, torch.zeros(2, 3), rtol=0, atol=0)
    torch.testing.assert_close(first.rel_quat, torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2), rtol=0, atol=0)
    assert "odo_res5" in second.taps and "odo_res5" not in first.taps
    with torch.no_grad():  # eval mode (streaming, ONNX): a first frame is still paired with itself
        out, _ = model.step(batch["image"][:, 0], None, batch["K"][:, 0], tasks=("vo",))
    assert "odo_res5" in out.taps and bool((out.rel_xyz != 0).any())

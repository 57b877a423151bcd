"""ONNX export of the streaming step and the Localizer's onnx backend: same outputs as PyTorch over a
stream (first frame, cached state, given depth, resets), file lookup and staleness, CLI errors."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
import torch
from model_fixtures import one_thread  # noqa: F401  (autouse: every test on one thread)

from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.cli import main
from vlocnetpp_core.errors import DataError, UserError
from vlocnetpp_core.inference.checkpoint import init_checkpoint, load_checkpoint, read_checkpoint_meta, save_checkpoint
from vlocnetpp_core.inference.localizer import Localizer
from vlocnetpp_core.inference.network_input import network_input
from vlocnetpp_core.inference.onnx_backend import OnnxStep, onnx_step_for
from vlocnetpp_core.inference.onnx_export import export_checkpoint, read_metadata, state_names
from vlocnetpp_core.model import VLocNetPP, load_model_config

POSE_TOL = 1e-4  # metres / quaternion components
LOGIT_TOL = 1e-4  # relative to the largest |logit| of the frame (an untrained net's logits reach ~100)
HEADS = ("xyz", "quat", "rel_xyz", "rel_quat")


def _frames(n: int, height: int = 120, width: int = 200, seed: int = 0) -> list[np.ndarray]:
    """Smooth random RGB frames of a camera panning over a texture."""
    rng = np.random.default_rng(seed)
    base = cv2.resize(
        rng.integers(0, 256, (height // 6 + 4, width // 6 + 4, 3), dtype=np.uint8), (width + 5 * n, height + 2 * n)
    )
    return [np.ascontiguousarray(base[2 * k : 2 * k + height, 5 * k : 5 * k + width]) for k in range(n)]


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Path]:
    """An untrained lite checkpoint and its export next to it: ``(NAME.safetensors, NAME.onnx)``.

    Its odometry head predicts a fixed small motion (an untrained one predicts large random
    rotations, which move every warped sample out of view), so the warp and its depth matter.
    """
    folder = tmp_path_factory.mktemp("onnx")
    torch.manual_seed(3)
    model = VLocNetPP(load_model_config("lite"))
    head = model.odometry.head
    with torch.no_grad():
        head.fc_xyz.weight.zero_()
        head.fc_quat.weight.zero_()
        head.fc_xyz.bias.copy_(torch.tensor([0.3, 0.0, 0.8]))
        head.fc_quat.bias.copy_(torch.tensor([1.0, 0.0, 0.02, 0.0]))
    ckpt = save_checkpoint(folder / "lite", model, {"training": {"stage": "init", "note": "test: fixed odometry"}})
    return ckpt, export_checkpoint(ckpt, folder / "lite.onnx")


def _assert_same(ref, got, what: str) -> None:
    for head in HEADS:
        np.testing.assert_allclose(
            getattr(got, head).numpy(), getattr(ref, head).numpy(), atol=POSE_TOL, rtol=0, err_msg=f"{what} {head}"
        )
    scale = float(ref.seg_logits.abs().max())
    assert float((got.seg_logits - ref.seg_logits).abs().max()) < LOGIT_TOL * scale, f"{what} seg_logits"


def test_onnx_step_equals_pytorch_over_a_five_frame_stream(exported):
    ckpt, path = exported
    model, meta = load_checkpoint(ckpt)
    step = OnnxStep(path)
    assert step.state_names == state_names(model) == ["res5a", "odo_res4", "sem_res4f", "sem_res5c"]
    intrinsics = Intrinsics.from_dict(meta["intrinsics"])
    ref_state = got_state = None
    with torch.inference_mode():
        for k, rgb in enumerate(_frames(5)):
            x, K, _ = network_input(rgb, model.config.input_size, intrinsics)
            ref, ref_state = model.step(x, ref_state, K)
            got, got_state = step(x, got_state, K)
            _assert_same(ref, got, f"frame {k}")
            for name in step.state_names:  # the state handed to the next frame agrees too
                a, b = getattr(ref_state, name), getattr(got_state, name)
                assert a.shape == b.shape and float((a - b).abs().max()) < 1e-4 * max(1.0, float(a.abs().max())), name


def test_given_depth_and_first_frame_flag_match_pytorch(exported):
    """``use_depth`` replaces the predicted depth in the warp; ``state=None`` after a stream is a true first frame."""
    ckpt, path = exported
    model, _ = load_checkpoint(ckpt)
    step = OnnxStep(path)
    W, H = model.config.input_size
    frames = [network_input(f, (W, H), _intrinsics(W, H))[0] for f in _frames(3, seed=5)]
    K = torch.from_numpy(_intrinsics(W, H).matrix()).float()[None]
    depth = torch.linspace(2.0, 30.0, H)[None, None, :, None].expand(1, 1, H, W).contiguous()
    depth[..., : H // 3, :] = 0.0  # invalid
    with torch.inference_mode():
        _, ref_state = model.step(frames[0], None, K)
        _, got_state = step(frames[0], None, K)
        ref, _ = model.step(frames[1], ref_state, K, depth)
        got, _ = step(frames[1], got_state, K, depth)
        _assert_same(ref, got, "given depth")
        predicted, _ = step(frames[1], got_state, K)
        moved = float((predicted.seg_logits - got.seg_logits).abs().max())
        assert moved > 100 * LOGIT_TOL * float(got.seg_logits.abs().max())  # the given depth did reach the warp
        ref, _ = model.step(frames[2], None, K)
        got, _ = step(frames[2], None, K)
        _assert_same(ref, got, "first frame after a stream")


def _intrinsics(W: int, H: int) -> Intrinsics:
    return Intrinsics(0.6 * W, 0.6 * W, (W - 1) / 2, (H - 1) / 2, W, H)


def test_localizer_onnx_backend_agrees_with_torch_through_resets(exported):
    ckpt, path = exported
    torch_loc = Localizer.from_checkpoint(ckpt, num_threads=1)
    onnx_loc = Localizer.from_checkpoint(ckpt, num_threads=1, backend="onnx")
    assert onnx_loc.backend == "onnx" and Path(onnx_loc._step_fn.path) == path  # NAME.onnx next to the checkpoint
    stamps = [0.0, 0.05, 0.10, 5.0, 5.05]  # a gap: the state is reset before the fourth frame
    for k, (rgb, stamp) in enumerate(zip(_frames(5, seed=2), stamps, strict=True)):
        a, b = torch_loc.step(rgb, "rgb8", stamp), onnx_loc.step(rgb, "rgb8", stamp)
        assert a.reset_reason == b.reset_reason
        for field in ("t", "q", "rel_t", "rel_q", "odom_t", "odom_q"):
            np.testing.assert_allclose(
                getattr(b, field), getattr(a, field), atol=POSE_TOL, err_msg=f"frame {k} {field}"
            )
        assert b.mask.shape == a.mask.shape and (b.mask == a.mask).mean() > 0.999, f"frame {k} mask"


def test_stale_export_next_to_the_checkpoint_is_not_used(exported, tmp_path, monkeypatch):
    ckpt, path = exported
    other = init_checkpoint("lite", tmp_path / "other", seed=9)  # other weights
    (tmp_path / "other.onnx").write_bytes(path.read_bytes())  # ... with the first checkpoint's graph beside them
    monkeypatch.setenv("VLOCNETPP_CACHE", str(tmp_path / "cache"))
    model, meta = load_checkpoint(other)
    step = onnx_step_for(model, meta, next_to=tmp_path / "other.onnx")
    assert step.path == tmp_path / "cache" / "onnx" / f"{meta['weights_id']}.onnx"  # exported afresh into the cache
    assert step.weights_id == meta["weights_id"] != read_metadata(path)["weights_id"]
    assert onnx_step_for(model, meta, next_to=None).path == step.path  # reused on the next start


def test_export_cli_and_errors(exported, tmp_path, capsys):
    ckpt, _ = exported
    out = tmp_path / "m.onnx"
    assert main(["export-onnx", "--checkpoint", str(ckpt), "--out", str(out)]) == 0
    assert "streaming step at 224x128" in capsys.readouterr().out
    meta = read_metadata(out)
    assert (
        meta["weights_id"] == read_checkpoint_meta(ckpt)["weights_id"] and json.loads(meta["state_names"])[0] == "res5a"
    )
    names = [i.name for i in onnx.load(str(out), load_external_data=False).graph.input]
    assert names == [
        "image",
        "K",
        "depth",
        "use_depth",
        "first",
        "state_res5a",
        "state_odo_res4",
        "state_sem_res4f",
        "state_sem_res5c",
    ]
    assert main(["export-onnx", "--checkpoint", str(ckpt), "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert (
        main(["export-onnx", "--checkpoint", str(tmp_path / "missing.safetensors"), "--out", str(tmp_path / "x.onnx")])
        == 2
    )
    err = capsys.readouterr().err
    assert "missing.safetensors" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.onnx").exists() and not list(tmp_path.glob(".x.onnx.*"))
    (tmp_path / "bad.onnx").write_bytes(b"not a model")
    with pytest.raises(DataError, match="bad.onnx"):
        OnnxStep(tmp_path / "bad.onnx")
    with pytest.raises(UserError, match="backend"):
        Localizer.from_checkpoint(ckpt, backend="tensorrt")
    with pytest.raises(ValueError, match="224"):
        OnnxStep(out)(torch.zeros(1, 3, 64, 64), None, torch.eye(3)[None])


def test_node_runs_the_onnx_backend(exported, monkeypatch):
    """``backend: onnx`` in the node: its poses are the onnx Localizer's on the same frames; a bad value, or
    onnxruntime missing, stops it with a message."""
    import rclpy
    from node_fixtures import Harness, camera_frames, domain_id, image_msg, wait_until
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image

    from vlocnetpp_ros.node import LocalizerNode

    ckpt, _ = exported
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(140))
    params = {"checkpoint": str(ckpt), "num_threads": 1, "backend": "onnx"}
    try:
        with pytest.raises(UserError, match="backend must be"):
            LocalizerNode(
                context=ctx,
                parameter_overrides=[Parameter(k, value=v) for k, v in {**params, "backend": "trt"}.items()],
            )
        with monkeypatch.context() as m:  # onnxruntime is an optional package: without it the node names it and stops
            m.setitem(sys.modules, "onnxruntime", None)
            with pytest.raises(UserError, match="backend 'onnx' needs the Python package 'onnxruntime'"):
                LocalizerNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        node = LocalizerNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        tester = Harness(ctx, extra_nodes=(node,))
        try:
            assert node.localizer.backend == "onnx" and node.stats.info["backend"] == "onnx"
            tester.wait_for_subscriber("/camera/image_raw", Image)
            frames = camera_frames(3)
            for k, frame in enumerate(frames):
                tester.publish("/camera/image_raw", image_msg(frame, "rgb8", 0.05 * k))
                wait_until(lambda k=k: tester.count("pose") > k, 30.0, f"pose {k}")
            reference = Localizer.from_checkpoint(ckpt, num_threads=1, backend="onnx")
            for k, (frame, msg) in enumerate(zip(frames, tester.answers("pose"), strict=True)):
                p = msg.pose.position
                np.testing.assert_allclose([p.x, p.y, p.z], reference.step(frame, "rgb8", 0.05 * k).t, atol=1e-6)
        finally:
            tester.close()
            node.close()
            node.destroy_node()
    finally:
        ctx.try_shutdown()

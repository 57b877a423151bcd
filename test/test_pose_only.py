"""The pose-only configuration (``semantic_stream: false``, ``config/lite_pose.yaml``) end to end: the network,
the Localizer (torch and onnx), bag replay (in process and through the node) and evaluate-bag. Training on data without
labels or depth is in ``test_train_pose_only.py``, the node in ``test_node_outputs.py``."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import REPO
from data_fixtures import trajectory, write_deeploc_split
from model_fixtures import (
    intrinsics,
    lite,
    one_thread,  # noqa: F401  (autouse: one thread per test)
)

from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.replay import OUTPUT_TYPES, SEGMENTATION_TOPIC, checkpoint_output_types
from vlocnetpp_core.cli import main
from vlocnetpp_core.errors import DataError
from vlocnetpp_core.inference.checkpoint import init_checkpoint
from vlocnetpp_core.inference.localizer import Localizer
from vlocnetpp_core.model import ModelConfig, VLocNetPP, load_model_config, params_per_stream, stage_tasks
from vlocnetpp_core.model.assembly import trained_tasks

W, H = 64, 48
POSE_ONLY = {"semantic_stream": False, "warping": False, "semantic_fusion": False}


def pose_only(**overrides) -> ModelConfig:
    return dataclasses.replace(load_model_config("lite_pose"), input_size=(W, H), **overrides)


def test_lite_pose_is_lite_without_the_semantic_stream():
    cfg, ref = load_model_config("lite_pose").to_dict(), load_model_config("lite").to_dict()
    assert {k for k in cfg if cfg[k] != ref[k]} == {"name", *POSE_ONLY}
    assert cfg["semantic_stream"] is False and load_model_config("lite_pose").tasks == ("loc", "vo")
    full, cut = VLocNetPP(lite(input_size=(W, H))), VLocNetPP(pose_only())
    cut_names = {n: p.shape for n, p in cut.named_parameters()}
    assert not [n for n in cut_names if n.startswith(("semantic", "depth_head"))]
    # exactly the global and odometry weights of the full network, same shapes: its pose streams load into it
    assert cut_names == {
        n: p.shape for n, p in full.named_parameters() if n.startswith(("trunk.", "global_stream.", "odometry."))
    }
    counts = params_per_stream(cut)
    assert (
        counts["semantic"] == counts["depth"] == counts["fusion"] == 0
        and counts["global"] > 0
        and counts["odometry"] > 0
    )


def test_step_and_clip_give_poses_and_no_segmentation():
    torch.manual_seed(0)
    model = VLocNetPP(pose_only()).eval()
    images = torch.rand(2, 3, 3, H, W)  # (B, T, 3, H, W)
    with torch.inference_mode():
        out, state = model.step(images[:, 0])  # default tasks: loc and vo; no K needed without warping
        out, state = model.step(images[:, 1], state)
        clip = model.forward_clip(images, intrinsics(2, W, H))
        streamed, state = [], None
        for t in range(3):
            o, state = model.step(images[:, t], state)
            streamed.append(o)
    assert (
        out.xyz.shape == (2, 3)
        and out.quat.shape == (2, 4)
        and out.rel_xyz.shape == (2, 3)
        and out.rel_quat.shape == (2, 4)
    )
    assert out.seg_logits is None and out.depth is None
    assert not [k for k in out.taps if k.startswith("sem_")] and "res4c_fused" not in out.taps
    assert (
        state.sem_res4f is None and state.sem_res5c is None and state.res5a is not None and state.odo_res4 is not None
    )
    assert len(clip) == 3 and all(o.seg_logits is None and o.xyz is not None and o.rel_xyz is not None for o in clip)
    for a, b in zip(clip, streamed, strict=True):  # eval mode: streaming equals the clip forward
        torch.testing.assert_close(a.xyz, b.xyz)
        torch.testing.assert_close(a.rel_quat, b.rel_quat)


def test_seg_is_refused_and_inconsistent_switches_are_errors(tmp_path):
    model = VLocNetPP(pose_only()).eval()
    for tasks in (("seg",), ("loc", "seg")):
        with pytest.raises(ValueError, match=r"no semantic stream .*semantic_stream: false.*cannot run \['seg'\]"):
            model.step(torch.rand(1, 3, H, W), tasks=tasks)
    with pytest.raises(ValueError, match="semantic_stream is false .* warping and semantic_fusion are true"):
        ModelConfig(semantic_stream=False)
    with pytest.raises(ValueError, match="but semantic_fusion is true.*set semantic_fusion: false"):
        ModelConfig(semantic_stream=False, warping=False)
    path = tmp_path / "bad.yaml"
    path.write_text(
        yaml.safe_dump({**load_model_config("lite").to_dict(), "semantic_stream": False, "semantic_fusion": False})
    )
    with pytest.raises(DataError, match=r"bad\.yaml.*but warping is true"):
        load_model_config(path)
    assert stage_tasks("mtl", ("loc", "vo")) == ("loc", "vo") and stage_tasks("stl-vo", ("loc", "vo")) == ("vo",)
    with pytest.raises(ValueError, match="stage stl-seg .*semantic_stream: false.*trains with stl-loc, stl-vo, mtl"):
        stage_tasks("stl-seg", ("loc", "vo"))
    # what evaluate reads from a sidecar: an mtl run of a pose-only network trained loc and vo, nothing else
    assert trained_tasks({"stage": "mtl", "step": 5}, ("loc", "vo")) == {"loc", "vo"}
    assert trained_tasks(
        {"stage": "mtl", "step": 0, "init": [{"stage": "stl-loc"}, {"stage": "stl-seg"}]}, ("loc", "vo")
    ) == {"loc"}


def test_model_info_of_lite_pose(capsys):
    assert main(["model-info", "--config", "lite_pose", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["tasks"] == ["loc", "vo"] and info["switches"]["semantic_stream"] is False
    assert set(info["params_trained_per_stage"]) == {"stl-loc", "stl-vo", "mtl"}
    assert (
        info["params_trained_per_stage"]["mtl"]
        == info["params_total"]
        == info["params_per_stream"]["global"] + info["params_per_stream"]["odometry"]
    )
    assert main(["model-info", "--config", "lite_pose"]) == 0
    assert "pose only (no semantic stream)" in capsys.readouterr().out


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    return init_checkpoint(pose_only(), tmp_path_factory.mktemp("pose_only") / "model", seed=2)


def _frames(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (60, 80, 3), dtype=np.uint8) for _ in range(n)]


def test_localizer_on_a_pose_only_checkpoint(checkpoint, tmp_path, monkeypatch):
    loc = Localizer.from_checkpoint(checkpoint)
    assert not loc.has_segmentation
    results = [loc.step(f, "rgb8", 0.05 * k) for k, f in enumerate(_frames(3))]
    assert all(r.mask is None for r in results)
    assert all(np.isfinite(r.t).all() and np.isfinite(r.odom_t).all() for r in results) and results[
        -1
    ].dt == pytest.approx(0.05)
    # the ONNX backend: a graph without a seg_logits output (nor depth inputs), the same poses
    monkeypatch.setenv("VLOCNETPP_CACHE", str(tmp_path))
    onnx = Localizer.from_checkpoint(checkpoint, backend="onnx", num_threads=1)
    assert "seg_logits" not in onnx._step_fn.head_outputs and not onnx.has_segmentation
    for k, f in enumerate(_frames(3)):
        r = onnx.step(f, "rgb8", 0.05 * k)
        assert r.mask is None
        np.testing.assert_allclose(r.t, results[k].t, atol=1e-5)
        np.testing.assert_allclose(r.rel_t, results[k].rel_t, atol=1e-5)


@pytest.fixture(scope="module")
def replayed(checkpoint, tmp_path_factory) -> Path:
    """A folder with ``in.mcap`` (6 frames, no labels or depth) and ``out.mcap``, its in-process replay with the
    checkpoint."""
    root = tmp_path_factory.mktemp("pose_only_bag")
    ids = list(range(1, 7))
    t, q = trajectory(len(ids))
    write_deeploc_split(root / "ds", "test", ids, t, q, depth=None, labels=False)
    assert main(["convert", str(root / "ds"), str(root / "in.mcap"), "--no-progress"]) == 0
    assert (
        main(
            [
                "replay",
                str(root / "in.mcap"),
                "--checkpoint",
                str(checkpoint),
                "--out",
                str(root / "out.mcap"),
                "--no-progress",
            ]
        )
        == 0
    )
    return root


POSE_TOPICS = [topic for topic in OUTPUT_TYPES if topic != SEGMENTATION_TOPIC]


def _poses(path: Path) -> dict[tuple[str, int], np.ndarray]:
    """(topic, stamp) -> position and orientation of every /vlocnet/* pose message (no segmentation topic allowed)."""
    out = {}
    with BagReader(path) as reader:
        assert SEGMENTATION_TOPIC not in reader.topics
        for topic, _, msg in reader.messages(POSE_TOPICS):
            pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
            out[(topic, messages.stamp_ns(msg))] = np.concatenate(messages.pose_from_msg(pose))
    return out


def test_replay_and_evaluate_bag_write_and_score_no_segmentation(replayed, checkpoint, capsys):
    poses = _poses(replayed / "out.mcap")
    assert sorted({topic for topic, _ in poses}) == sorted(POSE_TOPICS) and len(poses) == 6 * len(POSE_TOPICS)
    # what the replay bridge (--through-node) waits for per frame
    assert list(checkpoint_output_types(checkpoint)) == POSE_TOPICS
    capsys.readouterr()
    assert main(["evaluate-bag", str(replayed / "out.mcap"), "--json", str(replayed / "m.json")]) == 0
    printed = capsys.readouterr().out
    report = json.loads((replayed / "m.json").read_text())
    assert "segmentation" not in report["overall"] and "mIoU" not in printed and "segmentation: none" in printed
    assert report["overall"]["pose"]["median_translation_m"] is not None


def test_replay_through_the_node_expects_no_segmentation(replayed, checkpoint, tmp_path):
    """The node of a pose-only model advertises no segmentation: the bridge must not wait for it (it would time out)."""
    out = tmp_path / "node.mcap"
    env = dict(os.environ, ROS_DOMAIN_ID=str(100 + (os.getpid() + 50) % 100), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "vlocnetpp_core.cli",
            "replay",
            str(replayed / "in.mcap"),
            "--checkpoint",
            str(checkpoint),
            "--out",
            str(out),
            "--through-node",
            "--rate",
            "max",
            "--no-progress",
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "6 frames localized" in proc.stdout and "skipped" not in proc.stdout
    ref, got = _poses(replayed / "out.mcap"), _poses(out)
    assert got.keys() == ref.keys()
    for key in ref:
        np.testing.assert_allclose(got[key], ref[key], atol=1e-5, rtol=0, err_msg=str(key))

"""From a robot's bag to a running localizer, end to end (docs/own-robot.md), at small sizes:

synthetic loops -> a bag as a robot records it (compressed images, camera info, the ground truth of the robot
base on /tf with a static camera transform, no labels) -> ``extract`` -> a short pose-only training -> the
real node over DDS (``replay --through-node``) -> ``evaluate-bag`` with the ground truth from /tf.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import REPO
from scipy.spatial.transform import Rotation

from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.topics import (
    GROUND_TRUTH_TOPIC,
    POSE_TOPIC,
    POSE_WITH_COVARIANCE_TOPIC,
    SEGMENTATION_TOPIC,
    SEMANTIC_TOPIC,
    TF_STATIC_TOPIC,
    TF_TOPIC,
)
from vlocnetpp_core.data import open_dataset
from vlocnetpp_core.model import load_model_config

# the camera (optical frame) 0.3 m ahead of a z-up base_link, 1.2 m up, looking along its x axis
_q = Rotation.from_matrix([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]).as_quat()
EXTRINSICS = ",".join(f"{v:.9f}" for v in (0.3, 0.0, 1.2, _q[3], _q[0], _q[1], _q[2]))
FRAMES = 16  # per loop, at 20 Hz: the test loop starts 2 x (0.75 s + 10 s gap) after the first image


def vlocnetpp(*args: str, timeout: float = 600.0) -> str:
    env = dict(os.environ, ROS_DOMAIN_ID=str(150 + os.getpid() % 50), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.run(
        [sys.executable, "-m", "vlocnetpp_core.cli", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, f"vlocnetpp {' '.join(args)}:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


@pytest.fixture(scope="module")
def robot_bag(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("own_robot")
    campus = root / "campus"
    vlocnetpp(
        "synth",
        str(campus),
        "--loops",
        "2",
        "--test-loops",
        "1",
        "--frames-per-loop",
        str(FRAMES),
        "--size",
        "128x72",
        "--seed",
        "5",
        "--no-progress",
    )
    bag = root / "robot.mcap"
    vlocnetpp(
        "convert",
        str(campus),
        str(bag),
        "--split",
        "all",
        "--compress",
        "png",
        "--robot-frame",
        "base_link",
        "--camera-extrinsics",
        EXTRINSICS,
        "--no-labels",
        "--no-progress",
    )
    return campus, bag


def test_a_robot_bag_becomes_a_dataset_a_model_and_a_scored_node_run(robot_bag, tmp_path):
    campus, bag = robot_bag
    with BagReader(bag) as reader:
        assert {TF_TOPIC, TF_STATIC_TOPIC} <= set(reader.topics) and not {GROUND_TRUTH_TOPIC, SEMANTIC_TOPIC} & set(
            reader.topics
        )

    # 1. extract: the camera poses of the source dataset come back from /tf + the extrinsics
    data = tmp_path / "dataset"
    vlocnetpp(
        "extract",
        str(bag),
        str(data),
        "--tf",
        "map",
        "base_link",
        "--camera-extrinsics",
        EXTRINSICS,
        "--test-ranges",
        "20:",
        "--no-progress",
    )
    for split, loops in (("train", 2), ("test", 1)):
        got, want = open_dataset(data, None, split), open_dataset(campus, None, split)
        assert len(got.sequences) == loops and len(got) == len(want) == loops * FRAMES
        np.testing.assert_allclose([r.t for r in got.records], [r.t for r in want.records], atol=1e-3)
        assert not got.has_labels

    # 2. a short pose-only training on it (lite_pose at 64x48)
    config = tmp_path / "tiny_pose.yaml"
    config.write_text(yaml.safe_dump({**load_model_config("lite_pose").to_dict(), "input_size": [64, 48]}))
    run = tmp_path / "stl-loc"
    vlocnetpp(
        "train",
        "--config",
        str(config),
        "--data",
        str(data),
        "--stage",
        "stl-loc",
        "--out",
        str(run),
        "--steps",
        "20",
        "--batch-size",
        "4",
        "--clip-len",
        "2",
        "--workers",
        "0",
        "--threads",
        "1",
        "--s-q-init",
        "0",
        "--no-progress",
    )
    checkpoint = run / "last.safetensors"

    # 3. the real node over DDS on the robot's bag: pose outputs, no segmentation topic
    out = tmp_path / "localized.mcap"
    summary = vlocnetpp(
        "replay",
        str(bag),
        "--checkpoint",
        str(checkpoint),
        "--out",
        str(out),
        "--through-node",
        "--rate",
        "max",
        "--no-progress",
    )
    assert f"{3 * FRAMES} frames localized" in summary
    with BagReader(out) as reader:
        assert {POSE_TOPIC, POSE_WITH_COVARIANCE_TOPIC} <= set(
            reader.topics
        ) and SEGMENTATION_TOPIC not in reader.topics

    # 4. evaluate-bag with the ground truth from /tf: every frame scored against the dataset's camera poses
    report_path, traj = tmp_path / "report.json", tmp_path / "traj"
    vlocnetpp(
        "evaluate-bag",
        str(out),
        "--tf",
        "map",
        "base_link",
        "--camera-extrinsics",
        EXTRINSICS,
        "--reference",
        str(data),
        "--json",
        str(report_path),
        "--trajectories",
        str(traj),
    )
    report = json.loads(report_path.read_text())
    assert sorted(report["per_sequence"]) == ["seq-00", "seq-01", "seq-02"]
    assert report["baseline"]["name"] == "retrieval" and report["baseline"]["reference_frames"] == 2 * FRAMES
    assert {"pose", "odometry"} <= set(report["overall"]) and "segmentation" not in report["overall"]
    truth = np.concatenate([np.loadtxt(traj / f"seq-0{k}" / "ground_truth.tum")[:, 1:4] for k in range(3)])
    sources = [open_dataset(campus, None, s) for s in ("train", "test")]
    np.testing.assert_allclose(truth, [r.t for idx in sources for r in idx.records], atol=1e-3)

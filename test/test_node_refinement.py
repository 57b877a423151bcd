"""Refinement against a keyframe map where users meet it: the node over real DDS (parameters ``map`` and
``refine_every``, ``vlocnet/network_pose``, ``/diagnostics``), ``replay --map`` (in process and through the
node) and ``evaluate-bag`` (the network, refined and structure-based rows).

The fixture renders one training visit of the synthetic campus (what the shipped model was trained on), builds
a small keyframe map of it and plays its first frames: the shipped network's pose is then within the map's search
radius, so the refinement has something to do.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import rclpy
import torch
from conftest import REPO
from node_fixtures import CAMERA, diagnostic_values, domain_id, image_msg, localizer_nodes, wait_until
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from vlocnetpp_core import geometry
from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader, BagWriter
from vlocnetpp_core.bag.topics import (
    CAMERA_INFO_TOPIC,
    GROUND_TRUTH_TOPIC,
    NETWORK_POSE_TOPIC,
    POSE_TOPIC,
    POSE_WITH_COVARIANCE_TOPIC,
)
from vlocnetpp_core.cli import main
from vlocnetpp_core.errors import DataError, UserError
from vlocnetpp_core.inference.checkpoint import resolve_map_path, shipped_checkpoint
from vlocnetpp_ros import conversions

DOMAIN = domain_id(40)
FRAMES = 6  # consecutive frames of the visit played to the node / written to the bag
POSE_ATOL = 1e-5  # node vs in-process network poses: float32 summed in another order (test_bag_replay.py)


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """The in-process network on one thread, as the node runs it (two threads on a shared 2-core machine crawl)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _linked_model(folder: Path) -> Path:
    """The shipped model as ``folder/lite.safetensors`` (+ ``.json``), linked, so that a map can lie beside it."""
    folder.mkdir(parents=True)
    shipped = shipped_checkpoint()
    for suffix in (".safetensors", ".json"):
        (folder / f"lite{suffix}").symlink_to(shipped.with_suffix(suffix))
    return folder / "lite.safetensors"


@pytest.fixture(scope="module")
def campus(tmp_path_factory) -> SimpleNamespace:
    """One visit (120 frames a lap, ~1.5 m apart), its map (a keyframe every 4 m) beside a link to the shipped model as
    ``lite.map.npz``, a second link with no map beside it, and a bag of the first :data:`FRAMES` frames."""
    from vlocnetpp_core.bag.convert import convert
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.mapping.build import build_map
    from vlocnetpp_core.synth import render_dataset

    root = tmp_path_factory.mktemp("refinement")
    render_dataset(root / "campus", seed=0, train_loops=1, test_loops=0, frames_per_loop=120, progress=False)
    index = open_dataset(root / "campus", None, "train")
    model = _linked_model(root / "with_map")
    map_path = build_map([index], spacing_m=4.0, angle_deg=20.0, progress=False).save(
        root / "with_map" / "lite.map.npz"
    )
    first = dataclasses.replace(index, records=index.records[:FRAMES], sequences=[range(FRAMES)])
    convert([first], root / "in.mcap", progress=False)
    return SimpleNamespace(
        root=root,
        index=index,
        model=model,
        map=map_path,
        bare=_linked_model(root / "without_map"),
        bag=root / "in.mcap",
    )


@pytest.fixture(scope="module")
def replayed(campus) -> Path:
    """The bag replayed in process with ``--map auto`` (the map beside the model)."""
    out = campus.root / "replayed.mcap"
    assert (
        main(
            [
                "replay",
                str(campus.bag),
                "--checkpoint",
                str(campus.model),
                "--map",
                "auto",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    return out


@pytest.fixture()
def make_node(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with localizer_nodes(shipped_checkpoint(), DOMAIN) as make:
        yield make


def _errors(msgs, frames) -> np.ndarray:
    """``(N, 2)`` metres, degrees of the poses of ``PoseStamped``-like ``msgs`` against the frames' true poses."""
    poses = [conversions.pose_from_msg(m.pose) for m in msgs]
    return np.array(
        [
            (geometry.translation_error(t, f.t), geometry.rotation_error_deg(q, f.q))
            for (t, q), f in zip(poses, frames, strict=True)
        ]
    )


def test_the_node_with_a_map_publishes_refined_poses_beside_the_network_pose(campus, make_node):
    node, tester = make_node(
        checkpoint=str(campus.model), map="auto", refine_every=2, camera_info_topic="/camera/camera_info"
    )
    assert node.localizer.refinement is not None and node.localizer.refinement.refine_every == 2
    frames = [campus.index.load(i) for i in range(FRAMES)]
    K = frames[0].intrinsics
    tester.publish(
        "/camera/camera_info",
        CameraInfo(header=Header(frame_id="camera"), width=K.width, height=K.height, k=K.matrix().reshape(-1).tolist()),
    )
    wait_until(lambda: node._intrinsics == K, 10.0, "camera info")
    for k, f in enumerate(frames):
        tester.publish(CAMERA, image_msg(f.image, "rgb8", 0.05 * k))
        wait_until(
            lambda k=k: all(tester.count(key) > k for key in ("pose", "pwc", "odom", "seg", "net")),
            60.0,
            f"answers to frame {k}",
        )
    pose, net, pwc = tester.answers("pose"), tester.answers("net"), tester.answers("pwc")
    assert [m.header for m in net] == [m.header for m in pose]  # same stamps, same map frame
    # every 2nd frame refined, the frames between propagated by the odometry
    assert node.stats.sources["refined"] >= FRAMES // 2 - 1 and node.stats.sources["propagated"] >= FRAMES // 2 - 1, (
        node.stats.sources
    )
    published, network = _errors(pose, frames), _errors(net, frames)
    # frames 0, 2, 4, ... refined (a few cm at most), the others the last refined pose moved on by the odometry
    assert np.median(published[::2, 0]) < 0.05 and np.median(published[::2, 0]) < np.median(network[::2, 0]) / 3, (
        published,
        network,
    )
    assert (
        sum(
            not np.array_equal(conversions.pose_from_msg(a.pose)[0], conversions.pose_from_msg(b.pose)[0])
            for a, b in zip(pose, net, strict=True)
        )
        >= FRAMES - 1
    )
    calibrated = np.diag(node.localizer.pose_variance)
    refined = [not np.allclose(np.reshape(m.pose.covariance, (6, 6)), calibrated) for m in pwc]
    assert sum(refined) >= FRAMES - 2  # the covariance of the refinement, not the network's calibration
    for m, p in zip(pwc, pose, strict=True):
        assert m.pose.pose == p.pose

    def reported() -> dict[str, str]:
        diags = tester.answers("diag")
        return diagnostic_values(diags[-1]) if diags else {}

    wait_until(lambda: reported().get("processed") == str(FRAMES), 10.0, "diagnostics with every frame")
    values = reported()
    assert float(values["refined"]) >= 0.5 and values["map"] == str(campus.map), values
    assert int(values["refine.refined"]) == node.stats.sources["refined"] and int(values["source.propagated"]) >= 1, (
        values
    )
    assert sum(int(v) for k, v in values.items() if k.startswith("source.")) == FRAMES


def test_with_base_frame_the_network_pose_is_the_bases_too(campus, make_node):
    from vlocnetpp_core.camera.extrinsics import CameraExtrinsics, base_pose
    from vlocnetpp_core.inference.localizer import Localizer

    values = [0.2, 0.0, 1.0, 0.5, -0.5, 0.5, -0.5]  # a camera looking along a z-up base's x axis
    node, tester = make_node(
        checkpoint=str(campus.model), map=str(campus.map), base_frame="base_link", camera_extrinsics=values
    )
    frame = campus.index.load(0)
    tester.publish(CAMERA, image_msg(frame.image, "rgb8", 1.0))
    wait_until(lambda: tester.count("net") == 1 and tester.count("pose") == 1, 60.0, "the answer")
    want = Localizer.from_checkpoint(campus.model, num_threads=1, map_path=campus.map).step(frame.image, "rgb8", 1.0)
    ext = CameraExtrinsics.from_values(values)
    for msg, (t, q), atol in (
        (tester.answers("net")[0], (want.network_t, want.network_q), POSE_ATOL),
        (tester.answers("pose")[0], (want.t, want.q), 1e-3),
    ):
        got_t, got_q = conversions.pose_from_msg(msg.pose)
        want_t, want_q = base_pose(t, q, ext)
        assert (
            geometry.translation_error(got_t, want_t) < atol and geometry.rotation_error_deg(got_q, want_q) < 100 * atol
        )


def test_map_auto_without_a_map_warns_and_runs_without_refinement(campus, make_node, capfd):
    node, tester = make_node(checkpoint=str(campus.bare), map="auto")
    assert node.localizer.refinement is None and node.network_pose_pub is None
    err = capfd.readouterr().err
    assert "running without refinement" in err and str(campus.bare.with_name("lite.map.npz")) in err, err
    tester.publish(CAMERA, image_msg(campus.index.load(0).image, "rgb8", 1.0))
    wait_until(lambda: tester.count("pose") == 1, 60.0, "an answer")
    values = node.stats.snapshot()
    assert values["map"] == "none" and "refined" not in values and not any(k.startswith("refine.") for k in values)
    assert tester.count("net") == 0


def test_a_missing_map_or_refine_every_0_stops_the_node_with_a_clear_error(campus, tmp_path):
    from vlocnetpp_ros.node import LocalizerNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN)
    try:
        missing = tmp_path / "nowhere.map.npz"
        cases = [
            ({"map": str(missing)}, f"{missing}: parameter map: no such keyframe map file"),
            ({"map": str(tmp_path)}, "parameter map: a folder"),
            ({"map": "auto", "refine_every": 0}, "parameter refine_every must be >= 1"),
            ({"refine_every": -3}, "parameter refine_every must be >= 1"),
        ]
        for params, message in cases:
            overrides = [Parameter(k, value=v) for k, v in {"checkpoint": str(campus.model), **params}.items()]
            with pytest.raises(UserError, match=message):
                LocalizerNode(context=ctx, parameter_overrides=overrides)
    finally:
        ctx.try_shutdown()
    # the one rule of "auto", "" and paths that the node, replay and the demo share
    lines: list[str] = []
    assert resolve_map_path(campus.model, "auto", "x", lines.append) == campus.map and not lines
    assert resolve_map_path(campus.bare, "auto", "x", lines.append) is None and len(lines) == 1
    assert (
        resolve_map_path(campus.model, "", "x", lines.append) is None and resolve_map_path(campus.model, None) is None
    )
    assert resolve_map_path(campus.bare, str(campus.map)) == campus.map
    with pytest.raises(DataError, match="--map: no such keyframe map file"):
        resolve_map_path(campus.model, missing, "--map")


def _bag_poses(path: Path, topic: str) -> dict[int, np.ndarray]:
    with BagReader(path) as reader:
        return {messages.stamp_ns(m): np.concatenate(messages.stamped_pose(m)) for _, _, m in reader.messages([topic])}


def test_replay_with_a_map_writes_the_network_pose_in_process_and_through_the_node(
    campus, replayed, tmp_path, monkeypatch, capfd
):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(DOMAIN))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    through_node = tmp_path / "node.mcap"
    assert (
        main(
            [
                "replay",
                str(campus.bag),
                "--checkpoint",
                str(campus.model),
                "--map",
                str(campus.map),
                "--refine-every",
                "1",
                "--out",
                str(through_node),
                "--through-node",
                "--rate",
                "max",
                "--no-progress",
            ]
        )
        == 0
    )
    assert f"{FRAMES} frames localized" in capfd.readouterr().out
    truth = _bag_poses(campus.bag, GROUND_TRUTH_TOPIC)
    network = {}
    for out in (replayed, through_node):
        with BagReader(out) as reader:
            assert reader.topics[NETWORK_POSE_TOPIC] == messages.POSE_STAMPED
        pose, network[out] = _bag_poses(out, POSE_TOPIC), _bag_poses(out, NETWORK_POSE_TOPIC)
        assert pose.keys() == network[out].keys() == _bag_poses(out, POSE_WITH_COVARIANCE_TOPIC).keys() == truth.keys()
        refined = [s for s in pose if not np.array_equal(pose[s], network[out][s])]
        assert len(refined) >= FRAMES - 1
        assert np.median([np.linalg.norm(pose[s][:3] - truth[s][:3]) for s in refined]) < 0.1
    for s in truth:  # the same network in both
        np.testing.assert_allclose(network[through_node][s], network[replayed][s], atol=POSE_ATOL, rtol=0)
    # no map: no network pose; "auto" without a map beside the model says so and goes on without
    plain = tmp_path / "plain.mcap"
    assert (
        main(
            [
                "replay",
                str(campus.bag),
                "--checkpoint",
                str(campus.bare),
                "--map",
                "auto",
                "--out",
                str(plain),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "running without refinement" in capfd.readouterr().err
    with BagReader(plain) as reader:
        assert NETWORK_POSE_TOPIC not in reader.topics and POSE_TOPIC in reader.topics
    for argv, message in (
        (["--map", str(tmp_path / "no.npz")], "no such keyframe map file"),
        (["--refine-every", "0"], "--refine-every must be >= 1"),
    ):
        assert (
            main(
                [
                    "replay",
                    str(campus.bag),
                    "--checkpoint",
                    str(campus.model),
                    "--out",
                    str(tmp_path / "x.mcap"),
                    "--no-progress",
                    *argv,
                ]
            )
            == 2
        )
        assert message in capfd.readouterr().err
    assert not (tmp_path / "x.mcap").exists()


def test_evaluate_bag_scores_network_refined_retrieval_and_structure_based_rows(campus, replayed, tmp_path, capsys):
    report_path = tmp_path / "m.json"
    reference = REPO / "models" / "vlocnetpp_lite.reference.npz"
    assert (
        main(
            [
                "evaluate-bag",
                str(replayed),
                "--map",
                str(campus.map),
                "--reference",
                str(reference),
                "--json",
                str(report_path),
            ]
        )
        == 0
    )
    table = capsys.readouterr().out.splitlines()
    rows = [line.split("  ")[0].strip() for line in table]
    start = rows.index("overall (network)")
    assert rows[start : start + 4] == ["overall (network)", "refined", "retrieval", "structure-based"], table
    report = json.loads(report_path.read_text())
    truth, network, pose = (_bag_poses(replayed, t) for t in (GROUND_TRUTH_TOPIC, NETWORK_POSE_TOPIC, POSE_TOPIC))

    def median_error(poses):
        return float(np.median([np.linalg.norm(poses[s][:3] - truth[s][:3]) for s in truth]))

    overall = report["overall"]
    assert overall["pose"]["median_translation_m"] == pytest.approx(
        median_error(network), abs=1e-9
    )  # from /vlocnet/network_pose
    assert overall["pose_refined"]["median_translation_m"] == pytest.approx(
        median_error(pose), abs=1e-9
    )  # from /vlocnet/pose
    assert overall["pose_refined"].keys() == overall["pose"].keys()
    assert report["per_sequence"]["seq-00"]["pose_refined"].keys() == overall["pose"].keys()
    assert overall["refined_share"] >= (FRAMES - 1) / FRAMES
    structure = report["structure_baseline"]
    assert structure["name"] == "structure-based" and structure["map_keyframes"] > 0
    assert structure["overall"]["pose"]["median_translation_m"] < 0.1 < overall["pose"]["median_translation_m"]
    assert report["baseline"]["name"] == "retrieval"
    # the map's own checks: "auto" means nothing without a checkpoint, and the baseline needs the camera's intrinsics
    assert main(["evaluate-bag", str(replayed), "--map", "auto"]) == 2
    assert "give the map file" in capsys.readouterr().err
    with BagReader(replayed) as reader, BagWriter(tmp_path / "no_info.mcap") as writer:
        for conn in reader.connections:
            if conn.topic != CAMERA_INFO_TOPIC and not writer.has_topic(conn.topic):
                writer.add_topic(conn.topic, conn.msgtype, conn.msgdef.data, conn.digest)
        for topic, ns, raw in reader.messages(raw=True):
            if topic != CAMERA_INFO_TOPIC:
                writer.write_raw(topic, ns, raw)
    assert main(["evaluate-bag", str(tmp_path / "no_info.mcap"), "--map", str(campus.map)]) == 2
    assert f"no {CAMERA_INFO_TOPIC}" in capsys.readouterr().err


def test_refinement_diagnostics_count_sources_and_outcomes_and_stay_bounded():
    from vlocnetpp_ros.diagnostics import MAX_KEYS, NodeStats

    stats = NodeStats(refinement=True)
    for source, status in (
        ("refined", "refined"),
        ("propagated", None),
        ("network", "no_features"),
        ("network", "disagrees"),
    ):
        stats.processed_frame(1.0, 0.01, None, source, status)
    values = stats.snapshot(now=1.0)
    assert values["refined"] == 0.5  # refined + propagated over processed
    assert {k: v for k, v in values.items() if k.startswith(("source.", "refine."))} == {
        "source.network": 2,
        "source.propagated": 1,
        "source.refined": 1,
        "refine.disagrees": 1,
        "refine.no_features": 1,
        "refine.refined": 1,
    }
    assert not any(
        k == "refined" or k.startswith(("source.", "refine.")) for k in NodeStats().snapshot(now=1.0)
    )  # no map, no keys
    for k in range(3 * MAX_KEYS):
        stats.processed_frame(1.0, 0.01, None, "network", f"status{k}")
    assert len(stats.refine_statuses) == MAX_KEYS + 1 and sum(stats.refine_statuses.values()) == 3 + 3 * MAX_KEYS

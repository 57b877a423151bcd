"""The localizer node in this process, over real DDS: bad inputs, encodings, depth, compressed images, flooding.

Each test runs the node and a tester node in their own rclpy context on a domain of its own.
The values the node publishes are compared with :class:`Localizer` run on the same frames.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import rclpy
import torch
import yaml
from conftest import REPO
from node_fixtures import (
    CAMERA,
    Harness,
    camera_frames,
    diagnostic_values,
    domain_id,
    image_msg,
    localizer_nodes,
    wait_until,
)
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.checkpoint import init_checkpoint
from vlocnetpp_core.inference.localizer import Localizer
from vlocnetpp_core.inference.preprocess import FrameError
from vlocnetpp_ros import conversions, storm
from vlocnetpp_ros.diagnostics import MAX_EVENTS, MAX_KEYS, MAX_LINE, NodeStats, ThrottledLog
from vlocnetpp_ros.node import PARAMETERS, LocalizerNode, default_checkpoint
from vlocnetpp_ros.parameters import PARAMS_FILE_VALUES

DOMAIN = domain_id(20)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    return init_checkpoint("lite", tmp_path_factory.mktemp("node") / "lite", seed=2)


@pytest.fixture()
def make_node(checkpoint: Path, monkeypatch):
    """``make_node(**params) -> (LocalizerNode, Harness)`` spinning in the background; torn down after the test."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with localizer_nodes(checkpoint, DOMAIN) as make:
        yield make


def _send_and_wait(tester: Harness, msg, condition, what: str) -> None:
    tester.publish(CAMERA, msg)
    wait_until(condition, 30.0, what)


def _pose(msg) -> np.ndarray:
    p = msg.pose.position
    return np.array([p.x, p.y, p.z])


def test_every_bad_frame_is_skipped_counted_and_good_frames_after_it_are_answered(make_node):
    node, tester = make_node()
    frames = camera_frames(4)
    stats = node.stats
    answered = [0]

    def good(image, stamp):
        answered[0] += 1
        n = answered[0]
        _send_and_wait(
            tester, image_msg(image, "rgb8", stamp), lambda: tester.count("seg") >= n, f"answer {n} (stamp {stamp})"
        )

    def bad(msg, reason):
        before = stats.rejected[reason]
        _send_and_wait(tester, msg, lambda: stats.rejected[reason] > before, f"rejection {reason}")

    good(frames[0], 1.00)
    ok = image_msg(frames[1], "rgb8", 1.02)
    odd = image_msg(frames[1], "rgb8", 1.02)
    odd.encoding = "yuv422"
    bad(odd, "unsupported_encoding")
    odd = image_msg(frames[1], "rgb8", 1.02)
    odd.width -= 1  # width * height no longer matches data
    odd.step -= 3
    bad(odd, "data_size_mismatch")
    odd = image_msg(frames[1], "rgb8", 1.02)
    odd.data = ok.data[: len(ok.data) // 2]
    bad(odd, "truncated_data")
    bad(Image(header=ok.header, height=0, width=0, encoding="rgb8", step=0), "empty_image")
    odd = image_msg(frames[1], "rgb8", 1.02)
    odd.step = 10
    bad(odd, "bad_step")
    good(frames[1], 1.05)
    assert not stats.resets  # skipped frames never touch the temporal state

    bias = node.localizer.model.global_stream.head.fc_xyz.bias
    saved = bias.detach().clone()
    with torch.no_grad():
        bias[0] = float("inf")
    bad(image_msg(frames[2], "rgb8", 1.10), "nan_output")
    with torch.no_grad():
        bias.copy_(saved)
    good(frames[3], 1.15)
    assert stats.resets["nan_output"] == 1
    good(frames[0], 1.12)  # stamp going backwards
    assert stats.resets["stamp_backwards"] == 1
    good(frames[1], 9.0)  # gap > max_gap_s
    assert stats.resets["gap"] == 1
    bigger = camera_frames(1, height=150, width=260)[0]
    good(bigger, 9.05)  # resolution change
    assert stats.resets["resolution_change"] == 1
    seg = tester.answers("seg")[-1]
    assert (seg.width, seg.height, seg.encoding) == (260, 150, "mono8")
    assert [stats.received, stats.processed, stats.dropped] == [answered[0] + 6, answered[0], 0]

    def reported() -> dict[str, str] | None:
        diags = tester.answers("diag")
        return diagnostic_values(diags[-1]) if diags else None

    wait_until(lambda: (reported() or {}).get("processed") == str(answered[0]), 10.0, "diagnostics with every frame")
    values = reported()
    for reason in (
        "unsupported_encoding",
        "data_size_mismatch",
        "truncated_data",
        "empty_image",
        "bad_step",
        "nan_output",
    ):
        assert values[f"rejected.{reason}"] == "1", reason
    for reason in ("nan_output", "stamp_backwards", "gap", "resolution_change"):
        assert values[f"reset.{reason}"] == "1", reason
    assert values["rejected"] == "6" and values["resets"] == "4" and values["dropped"] == "0"
    assert float(values["latency_ms_median"]) > 0 and float(values["processing_rate_hz"]) > 0


def test_encodings_and_row_padding_give_the_pose_of_the_plain_rgb8_image(make_node):
    node, tester = make_node()
    rgb = camera_frames(1, seed=4)[0]
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    padded = image_msg(rgb, "rgb8", 0.0)
    step = padded.step + 7
    rows = np.zeros((padded.height, step), np.uint8)
    rows[:, : padded.step] = rgb.reshape(padded.height, -1)
    padded.step, padded.data = step, rows.tobytes()
    messages = [
        image_msg(rgb, "rgb8", 0.0),
        padded,
        image_msg(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), "bgr8", 0.0),
        image_msg(cv2.cvtColor(rgb, cv2.COLOR_RGB2RGBA), "rgba8", 0.0),
        image_msg(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGRA), "bgra8", 0.0),
        image_msg(cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB), "rgb8", 0.0),
        image_msg(grey, "mono8", 0.0),
    ]
    for k, msg in enumerate(messages):
        msg.header.stamp = conversions.seconds_to_stamp(10.0 * (k + 1))  # gaps: every frame is a first frame
        _send_and_wait(tester, msg, lambda k=k: tester.count("pose") > k, f"answer {k}")
    poses = [_pose(m) for m in tester.answers("pose")]
    masks = [np.frombuffer(m.data, np.uint8) for m in tester.answers("seg")]
    for k in range(1, 5):
        assert np.array_equal(poses[k], poses[0]) and np.array_equal(masks[k], masks[0]), messages[k].encoding
    assert np.array_equal(poses[6], poses[5])  # mono8 == its grey as rgb8
    assert not np.array_equal(poses[5], poses[0])


def test_depth_images_are_matched_by_stamp_and_bad_ones_are_ignored(make_node, checkpoint: Path):
    node, tester = make_node(depth_topic="/camera/depth")
    reference = Localizer.from_checkpoint(checkpoint, num_threads=1)
    frames = camera_frames(5, seed=5)
    h, w = frames[0].shape[:2]
    metres = np.full((h, w), 4.0, np.float32)
    metres[: h // 3] = 0.0
    depths = [
        image_msg(metres, "32FC1", 0.0),
        image_msg((metres * 1000).astype(np.uint16), "16UC1", 0.1),
        image_msg(metres[:-2], "32FC1", 0.2),  # wrong size
        image_msg(frames[3], "rgb8", 0.3),  # wrong encoding
        None,  # no depth for this frame
    ]
    expected_depth = [metres, metres, None, None, None]
    ignored = [None, None, "depth_size", "depth_unsupported_encoding", "depth_missing"]
    for k, frame in enumerate(frames):
        stamp = 0.1 * k
        if depths[k] is not None:
            tester.publish("/camera/depth", depths[k])
            wait_until(lambda k=k: len(node._depths) > k, 10.0, "depth received")
        _send_and_wait(tester, image_msg(frame, "rgb8", stamp), lambda k=k: tester.count("odom") > k, f"answer {k}")
        if ignored[k]:
            assert node.stats.ignored[ignored[k]] == 1, ignored[k]
        expected = reference.step(frame, "rgb8", stamp, depth=expected_depth[k])
        got = tester.answers("odom")[-1]
        np.testing.assert_allclose(_pose(tester.answers("pose")[-1]), expected.t, atol=1e-6)
        o = got.pose.pose.position
        np.testing.assert_allclose([o.x, o.y, o.z], expected.odom_t, atol=1e-6)
    assert sum(node.stats.rejected.values()) == 0 and node.stats.processed == 5
    assert node.stats.ignored["depth_missing"] == 1  # frame 4 only: the refused depth of frame 3 is not counted twice


def test_compressed_images_and_camera_info(make_node, checkpoint: Path):
    node, tester = make_node(use_compressed=True, camera_info_topic="/camera/camera_info")
    reference = Localizer.from_checkpoint(checkpoint, num_threads=1)
    frames = camera_frames(3, seed=6)
    h, w = frames[0].shape[:2]
    K = Intrinsics(150.0, 140.0, (w - 1) / 2, (h - 1) / 2, w, h)
    info = CameraInfo(header=Header(frame_id="camera"), width=w, height=h, k=K.matrix().reshape(-1).tolist())
    tester.publish("/camera/camera_info", info)
    wait_until(lambda: node._intrinsics == K, 10.0, "camera info")
    bad_info = CameraInfo(header=Header(frame_id="camera"), width=w, height=h)  # k all zero
    tester.publish("/camera/camera_info", bad_info)
    wait_until(lambda: node.stats.ignored["camera_info_invalid"] == 1, 10.0, "invalid camera info ignored")
    assert node._intrinsics == K

    def compressed(rgb: np.ndarray, stamp: float) -> CompressedImage:
        ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        return CompressedImage(
            header=Header(stamp=conversions.seconds_to_stamp(stamp), frame_id="camera"),
            format="rgb8; png compressed bgr8",
            data=png.tobytes(),
        )

    topic = CAMERA + "/compressed"
    for k, frame in enumerate(frames[:2]):
        tester.publish(topic, compressed(frame, 0.05 * k))
        wait_until(lambda k=k: tester.count("pose") > k, 30.0, f"answer {k}")
        np.testing.assert_allclose(
            _pose(tester.answers("pose")[-1]), reference.step(frame, "rgb8", 0.05 * k, intrinsics=K).t, atol=1e-6
        )
    garbage = CompressedImage(
        header=Header(stamp=conversions.seconds_to_stamp(0.1)), format="jpeg", data=b"\xff\xd8 not a jpeg"
    )
    tester.publish(topic, garbage)
    wait_until(lambda: node.stats.rejected["decode_failed"] == 1, 10.0, "undecodable image rejected")
    tester.publish(topic, compressed(frames[2], 0.15))
    wait_until(lambda: tester.count("pose") == 3, 30.0, "answer after the bad one")
    np.testing.assert_allclose(
        _pose(tester.answers("pose")[-1]), reference.step(frames[2], "rgb8", 0.15, intrinsics=K).t, atol=1e-6
    )


def test_a_flood_drops_old_frames_and_answers_the_newest(make_node):
    node, tester = make_node(publish_segmentation=False)
    frames = camera_frames(4, height=240, width=320, seed=7)
    n = 40
    for k in range(n):
        tester.publish(CAMERA, image_msg(frames[k % 4], "rgb8", 0.02 * k))
    last = 0.02 * (n - 1)
    wait_until(lambda: any(abs(s - last) < 1e-6 for s in tester.stamps("pose")), 30.0, "the newest frame answered")
    stats = node.stats
    wait_until(
        lambda: stats.processed + stats.dropped == stats.received, 10.0, "every received frame processed or dropped"
    )
    assert stats.dropped > 0 and stats.processed < stats.received / 2
    assert tester.count("seg") == 0  # publish_segmentation false
    stamps = tester.stamps("pose")
    assert stamps == sorted(stamps) and len(stamps) == stats.processed


def test_a_best_effort_camera_started_after_the_node_is_received(make_node):
    node, harness = make_node()  # subscribed with BEST_AVAILABLE while no camera existed: resolved to reliable
    camera = harness.node.create_publisher(Image, CAMERA, qos_profile_sensor_data)
    frames = camera_frames(2, seed=8)
    first = image_msg(frames[0], "rgb8", 0.0)

    def first_answered() -> bool:
        camera.publish(first)  # best effort: repeat until the subscription is made again and matches
        return harness.count("pose") > 0

    wait_until(first_answered, 30.0, "an answer to the best-effort camera")
    wait_until(lambda: node.stats.processed + node.stats.dropped == node.stats.received, 10.0, "idle")
    camera.publish(image_msg(frames[1], "rgb8", 0.05))  # once, now that it is matched
    # (a late copy of the repeated first frame may still be answered before it: wait for the stamp itself)
    wait_until(lambda: 0.05 in harness.stamps(), 30.0, "the next frame answered")


def test_start_up_errors_are_user_errors(checkpoint: Path, tmp_path: Path, monkeypatch):
    corrupt = tmp_path / "corrupt.safetensors"
    corrupt.write_bytes(checkpoint.read_bytes()[:1000])
    (tmp_path / "corrupt.json").write_text(checkpoint.with_suffix(".json").read_text())
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN)
    try:
        cases = [
            ({"checkpoint": str(tmp_path / "missing.safetensors")}, "no such checkpoint"),
            ({"checkpoint": str(corrupt)}, "not a readable safetensors file"),
            ({"checkpoint": str(checkpoint), "max_gap_s": -1.0}, "max_gap_s must be > 0"),
            ({"checkpoint": str(checkpoint), "device": "tpu"}, "device must be"),
            ({"checkpoint": str(checkpoint), "num_threads": -2}, "num_threads must be >= 0"),
        ]
        for params, message in cases:
            with pytest.raises(UserError, match=message):
                LocalizerNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    finally:
        ctx.try_shutdown()
    # the default checkpoint is the model in the package share folder
    share = tmp_path / "prefix" / "share"
    (share / "ament_index" / "resource_index" / "packages").mkdir(parents=True)
    (share / "ament_index" / "resource_index" / "packages" / "vlocnetpp_ros").write_text("")
    model = share / "vlocnetpp_ros" / "models" / "vlocnetpp_lite.safetensors"
    model.parent.mkdir(parents=True)
    model.write_bytes(b"")
    monkeypatch.setenv(
        "AMENT_PREFIX_PATH", f"{tmp_path / 'prefix'}{os.pathsep}{os.environ.get('AMENT_PREFIX_PATH', '')}"
    )
    assert default_checkpoint() == model


def test_the_params_file_sets_every_declared_parameter_to_its_default():
    data = yaml.safe_load((REPO / "config" / "localizer.yaml").read_text())
    params = data["/**"]["ros__parameters"]
    # but map and backend: the launch YAML refines against the map beside the checkpoint, with ONNX Runtime; a node
    # started without it does not refine, and runs torch
    assert PARAMS_FILE_VALUES == {"map": "auto", "backend": "onnx"} and PARAMETERS["map"][0] == ""
    assert PARAMETERS["backend"][0] == "torch"
    assert params == {**{name: default for name, (default, _) in PARAMETERS.items()}, **PARAMS_FILE_VALUES}


def test_throttled_log_says_how_many_lines_it_held_back():
    lines: list[str] = []
    log = ThrottledLog(lines.append, period_s=5.0)
    assert log("a", "first", now=0.0) and not log("a", "again", now=1.0) and not log("a", "again", now=4.9)
    assert log("b", "other reason", now=2.0)  # throttled per key
    assert log("a", "later", now=5.1)
    assert lines == ["first", "other reason", "later (2 more like this in the last 5 s)"]


def test_counters_log_keys_and_windows_stay_bounded_whatever_the_reasons():
    lines: list[str] = []
    log = ThrottledLog(lines.append)
    for k in range(3 * MAX_KEYS):
        log(f"reason{k}", "x" * (10 * MAX_LINE), now=0.0)
    assert len(log._last) == MAX_KEYS + 1  # the rest share "other"
    assert len(lines) == MAX_KEYS + 1 and all(len(line) < MAX_LINE + 40 for line in lines)
    stats = NodeStats()
    for k in range(3 * MAX_KEYS):
        stats.reject(f"reason{k}")
        stats.ignore(f"reason{k}")
    assert len(stats.rejected) == len(stats.ignored) == MAX_KEYS + 1
    assert sum(stats.rejected.values()) == 3 * MAX_KEYS  # nothing lost, only pooled
    n = 3 * MAX_EVENTS  # 10 kHz for 3 s: more arrivals than the window keeps
    for k in range(n):
        stats.arrived(100.0 + k * 1e-4, False)
    assert len(stats._arrivals) == MAX_EVENTS
    # the kept arrivals cover the last second at 10 kHz and the rate is measured over them: N arrivals
    # span N - 1 intervals, so count / span overestimates by a factor N / (N - 1)
    rate = stats.snapshot(now=100.0 + (n - 1) * 1e-4)["input_rate_hz"]
    assert abs(rate - 1e4) <= 1e4 / (MAX_EVENTS - 1) * (1 + 1e-9)


def test_compressed_images_are_refused_from_their_header():
    rgb = camera_frames(1, seed=12)[0]
    header = Header(stamp=conversions.seconds_to_stamp(1.0))
    for ext, params in ((".png", []), (".jpg", []), (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])):
        ok, data = cv2.imencode(ext, rgb, params)
        conversions.check_image(CompressedImage(header=header, format=ext, data=data.tobytes()))  # accepted
        h, w = rgb.shape[:2]
        assert conversions.compressed_to_rgb(CompressedImage(header=header, format=ext, data=data.tobytes())).shape == (
            h,
            w,
            3,
        )
    cases = [
        (b"", "decode_failed"),
        (b"GIF89a" + bytes(100), "decode_failed"),
        (b"\xff\xd8\xff\xdb" + bytes(50), "decode_failed"),
        (storm._BOMB, "image_too_large"),
    ]
    for data, reason in cases:
        with pytest.raises(FrameError) as err:
            conversions.check_image(CompressedImage(header=header, format="png", data=data))
        assert err.value.reason == reason, data[:10]

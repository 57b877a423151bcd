"""The localizer started from the colcon install tree with the shipped YAML, as `ros2 run` starts it.

The node runs in its own process (default Fast DDS transports); this test process publishes the
camera and records the outputs, and compares them with :class:`Localizer` on the same frames.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rclpy
from model_fixtures import known_motion_lite
from node_fixtures import (
    Harness,
    InstalledNode,
    camera_frames,
    diagnostic_values,
    domain_id,
    float32_tolerance,
    float64_localizer,
    image_msg,
    params_file,
    wait_until,
)
from sensor_msgs.msg import Image

from vlocnetpp_core.inference.checkpoint import save_checkpoint
from vlocnetpp_core.inference.localizer import Localizer
from vlocnetpp_ros import conversions

DOMAIN = domain_id(60)
CAMERA = "/camera/image_raw"


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    # an untrained network whose warp stays in view, so the streamed poses of two float32 runs agree to rounding
    return save_checkpoint(tmp_path_factory.mktemp("install_node") / "lite", known_motion_lite(4))


@pytest.fixture(scope="module")
def rclpy_context():
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN)
    yield ctx
    ctx.try_shutdown()


@pytest.fixture(scope="module")
def running(colcon_install: Path, checkpoint: Path, tmp_path_factory, rclpy_context):
    """One node process (shared by the tests that only send frames) and the harness talking to it."""
    folder = tmp_path_factory.mktemp("running")
    node = InstalledNode(
        colcon_install,
        params_file(colcon_install, folder, checkpoint=str(checkpoint), num_threads=1),
        folder / "node.log",
        DOMAIN,
    )
    harness = Harness(rclpy_context)
    try:
        harness.wait_for_subscriber(CAMERA, Image, timeout=60.0)
    except AssertionError:
        node.stop()
        raise AssertionError(f"the node did not subscribe:\n{node.output()}") from None
    yield node, harness
    harness.close()
    node.stop()  # normally stopped already by the SIGTERM test


def _send(harness: Harness, msg, keys: tuple[str, ...] = ("pose", "odom", "seg"), timeout: float = 60.0) -> None:
    """Publish a frame and wait until its answers (by stamp) arrived on every topic of ``keys``."""
    stamp = conversions.stamp_to_seconds(msg.header.stamp)
    harness.publish(CAMERA, msg)
    wait_until(
        lambda: all(any(abs(s - stamp) < 1e-9 for s in harness.stamps(k)) for k in keys),
        timeout,
        f"answers to stamp {stamp}",
    )


def _by_stamp(harness: Harness, key: str, stamp: float):
    return next(m for m in harness.answers(key) if abs(conversions.stamp_to_seconds(m.header.stamp) - stamp) < 1e-9)


def test_outputs_have_the_input_stamps_and_frames_and_equal_localizer_step(running, checkpoint: Path):
    node, harness = running
    reference = Localizer.from_checkpoint(checkpoint, num_threads=1)
    exact = float64_localizer(checkpoint)  # the rounding to allow
    frames = camera_frames(4, height=240, width=320, seed=1)
    stamps = [100.0 + 0.05 * k for k in range(4)]
    for frame, stamp in zip(frames, stamps, strict=True):
        _send(harness, image_msg(frame, "rgb8", stamp, frame_id="camera_optical"))
        expected, exact_pose = reference.step(frame, "rgb8", stamp), exact.step(frame, "rgb8", stamp)
        pose, odom, seg = (_by_stamp(harness, k, stamp) for k in ("pose", "odom", "seg"))
        assert pose.header.frame_id == "map" and odom.header.frame_id == "odom"
        assert odom.child_frame_id == "camera_optical" and seg.header.frame_id == "camera_optical"
        assert pose.header.stamp == odom.header.stamp == seg.header.stamp == conversions.seconds_to_stamp(stamp)
        t, q = conversions.pose_from_msg(pose.pose)
        want = np.concatenate((expected.t, expected.q))
        tol = float32_tolerance(want, np.concatenate((exact_pose.t, exact_pose.q)))
        assert np.all(np.abs(np.concatenate((t, q)) - want) <= tol), (t, q, want, tol)
        ot, oq = conversions.pose_from_msg(odom.pose.pose)
        np.testing.assert_allclose(ot, expected.odom_t, atol=1e-5)
        np.testing.assert_allclose(oq, expected.odom_q, atol=1e-5)
        tw = odom.twist.twist
        np.testing.assert_allclose([tw.linear.x, tw.linear.y, tw.linear.z], expected.linear, atol=1e-4)
        np.testing.assert_allclose([tw.angular.x, tw.angular.y, tw.angular.z], expected.angular, atol=1e-4)
        np.testing.assert_allclose(np.asarray(odom.pose.covariance).reshape(6, 6), expected.odom_covariance)
        np.testing.assert_allclose(np.asarray(odom.twist.covariance).reshape(6, 6), expected.twist_covariance)
        assert np.any(np.asarray(odom.pose.covariance)) and np.any(np.asarray(odom.twist.covariance))
        assert (seg.width, seg.height, seg.encoding, seg.step) == (320, 240, "mono8", 320)
        mask = np.frombuffer(seg.data, np.uint8).reshape(240, 320)
        assert np.mean(mask == expected.mask) > 0.999


def test_full_size_deeploc_frames_from_another_process_are_all_answered(running):
    node, harness = running
    frames = camera_frames(2, height=720, width=1280, seed=2)
    for k in range(4):
        _send(harness, image_msg(frames[k % 2], "rgb8", 200.0 + 0.05 * k))
    assert len([s for s in harness.stamps("pose") if s >= 200.0]) == 4
    seg = _by_stamp(harness, "seg", 200.15)
    assert (seg.width, seg.height) == (1280, 720)


def test_a_flood_keeps_memory_flat_and_the_newest_frame_answered(running):
    node, harness = running
    frames = camera_frames(3, height=480, width=640, seed=3)
    for k in range(3):  # warm up at this size
        _send(harness, image_msg(frames[k], "rgb8", 300.0 + 0.05 * k), keys=("pose",))
    rss_before = node.rss_mb()
    n = 300  # 300 x 0.9 MB: queueing them would add ~270 MB
    for k in range(n):
        harness.publish(CAMERA, image_msg(frames[k % 3], "rgb8", 301.0 + 0.01 * k))
    last = 301.0 + 0.01 * (n - 1)
    wait_until(lambda: any(abs(s - last) < 1e-9 for s in harness.stamps("pose")), 60.0, "the newest frame answered")
    rss_after = node.rss_mb()
    assert rss_after - rss_before < 60.0, (rss_before, rss_after)
    answered = [s for s in harness.stamps("pose") if s >= 301.0]
    assert len(answered) < n / 2  # the rest were dropped, not queued

    def flood_reported() -> dict[str, str]:
        diags = harness.answers("diag")
        values = diagnostic_values(diags[-1]) if diags else {}
        return values if int(values.get("processed", 0)) >= len(harness.stamps("pose")) else {}

    wait_until(lambda: bool(flood_reported()), 10.0, "diagnostics after the flood")
    values = flood_reported()
    assert int(values["dropped"]) > 0
    assert int(values["received"]) == int(values["processed"]) + int(values["dropped"]) + int(values["rejected"])


def test_sigterm_stops_the_running_node_cleanly_within_two_seconds(running):
    node, harness = running
    harness.publish(CAMERA, image_msg(camera_frames(1)[0], "rgb8", 900.0))  # busy when the signal comes
    code, seconds = node.stop(signal.SIGTERM)
    out = node.output()
    assert code == 0 and "Traceback" not in out, out
    assert seconds < 2.0, (seconds, out)


_BEST_EFFORT_CAMERA = """
import sys, time, numpy as np, rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image
rclpy.init()
node = rclpy.create_node("best_effort_camera")
pub = node.create_publisher(Image, "/best_effort_camera/image_raw", qos_profile_sensor_data)
while pub.get_subscription_count() == 0:
    time.sleep(0.05)
time.sleep(0.5)
data = np.random.default_rng(0).integers(0, 256, (720, 1280, 3), dtype=np.uint8).tobytes()
for k in range(int(sys.argv[1])):
    msg = Image(height=720, width=1280, encoding="rgb8", step=3 * 1280, data=data)
    msg.header.stamp.sec, msg.header.frame_id = 500 + k, "camera"
    pub.publish(msg)
    time.sleep(float(sys.argv[2]))
"""


def test_best_effort_full_size_camera_with_the_shipped_profile_then_sigint(
    colcon_install: Path, checkpoint: Path, tmp_path: Path, rclpy_context
):
    """A best-effort 1280x720 camera and the node both using config/fastdds_large_data.xml: every frame
    is answered (default transports lose many). Then SIGINT stops the node cleanly."""
    profile = colcon_install / "vlocnetpp_ros" / "share" / "vlocnetpp_ros" / "config" / "fastdds_large_data.xml"
    assert profile.is_file()
    env = {"FASTRTPS_DEFAULT_PROFILES_FILE": str(profile)}
    params = params_file(
        colcon_install, tmp_path, checkpoint=str(checkpoint), num_threads=1, image_topic="/best_effort_camera/image_raw"
    )
    node = InstalledNode(colcon_install, params, tmp_path / "node.log", DOMAIN, env=env)
    harness = Harness(rclpy_context)
    try:
        wait_until(lambda: harness.node.count_publishers("/vlocnet/pose") > 0, 60.0, "the node's pose publisher")
        n = 3
        camera = subprocess.run(
            [sys.executable, "-c", _BEST_EFFORT_CAMERA, str(n), "0.4"],
            env={**node.env, **env},
            timeout=120,
            capture_output=True,
            text=True,
        )
        assert camera.returncode == 0, camera.stderr
        wait_until(
            lambda: len(harness.stamps("pose")) >= n, 30.0, f"{n} answers ({harness.stamps('pose')})\n{node.output()}"
        )
        assert harness.stamps("pose") == [500.0 + k for k in range(n)]
    finally:
        harness.close()
        code, seconds = node.stop(signal.SIGINT)
    out = node.output()
    assert code == 0 and "Traceback" not in out, out
    assert seconds < 2.0, (seconds, out)


def test_a_missing_checkpoint_fails_with_one_clear_line(colcon_install: Path, tmp_path: Path):
    missing = tmp_path / "nowhere" / "model.safetensors"
    node = InstalledNode(
        colcon_install, params_file(colcon_install, tmp_path, checkpoint=str(missing)), tmp_path / "node.log", DOMAIN
    )
    code = node.proc.wait(60)
    out = node.output()
    assert code == 1, out
    assert "Traceback" not in out
    errors = [line for line in out.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "cannot start" in errors[0] and str(missing) in errors[0], out

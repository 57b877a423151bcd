"""The node's outputs for the rest of a robot's stack, over real DDS: PoseWithCovarianceStamped, the pose of a
base frame placed by camera_extrinsics, no segmentation topic for a pose-only model, start-up errors.

The published values are compared with :class:`Localizer` run on the same frames in this process and
with 4x4 matrices built by scipy (independent of ``vlocnetpp_core.geometry``).
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rclpy
from conftest import REPO
from node_fixtures import CAMERA, camera_frames, domain_id, image_msg, localizer_nodes, wait_until
from rclpy.parameter import Parameter
from scipy.spatial.transform import Rotation

from vlocnetpp_core.camera import extrinsics
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.checkpoint import init_checkpoint
from vlocnetpp_core.inference.localizer import Localizer
from vlocnetpp_core.model import load_model_config
from vlocnetpp_ros import conversions
from vlocnetpp_ros.node import LocalizerNode

DOMAIN = domain_id(100)
# an optical camera looking along a z-up base_link's x axis, slightly pitched down, 0.3 m ahead, 0.1 m left, 1.2 m up
_q = (Rotation.from_euler("y", 0.1) * Rotation.from_matrix([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])).as_quat()
EXTRINSICS = [0.3, 0.1, 1.2, float(_q[3]), float(_q[0]), float(_q[1]), float(_q[2])]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    config = dataclasses.replace(load_model_config("lite"), input_size=(64, 48))
    return init_checkpoint(config, tmp_path_factory.mktemp("outputs") / "model", seed=4)


@pytest.fixture()
def make_node(checkpoint: Path, monkeypatch):
    """``make_node(**params) -> (LocalizerNode, Harness)`` once the node's pose outputs are advertised; torn down after
    the test."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with localizer_nodes(checkpoint, DOMAIN) as make:

        def make_advertised(**params):
            node, tester = make(**params)
            wait_until(
                lambda: all(
                    tester.node.count_publishers("/vlocnet/" + t) > 0 for t in ("pose_with_covariance", "odometry")
                ),
                20.0,
                "the outputs",
            )
            return node, tester

        yield make_advertised


def _matrix(t, q_wxyz) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]]).as_matrix()
    T[:3, 3] = t
    return T


def _msg_matrix(pose) -> np.ndarray:
    return _matrix(*conversions.pose_from_msg(pose))


def test_base_frame_pose_covariance_and_odometry(make_node, checkpoint: Path):
    node, tester = make_node(base_frame="base_link", camera_extrinsics=EXTRINSICS, publish_segmentation=False)
    reference = Localizer.from_checkpoint(checkpoint)
    ext = extrinsics.CameraExtrinsics.from_values(EXTRINSICS)
    E = _matrix(EXTRINSICS[:3], EXTRINSICS[3:])
    for k, frame in enumerate(camera_frames(3, seed=9)):
        msg = image_msg(frame, "rgb8", 0.05 * k, frame_id="camera_optical")
        tester.publish(CAMERA, msg)
        wait_until(
            lambda k=k: min(tester.count(key) for key in ("pose", "pwc", "odom")) > k, 30.0, f"answers to frame {k}"
        )
        camera = reference.step(frame, "rgb8", conversions.stamp_to_seconds(msg.header.stamp))
        pose, pwc, odom = tester.answers("pose")[-1], tester.answers("pwc")[-1], tester.answers("odom")[-1]
        assert pose.header == pwc.header == type(pose.header)(stamp=msg.header.stamp, frame_id="map")
        assert (odom.header.frame_id, odom.child_frame_id, odom.header.stamp) == ("odom", "base_link", msg.header.stamp)
        assert pwc.pose.pose == pose.pose
        cov = np.asarray(pwc.pose.covariance).reshape(6, 6)
        assert np.array_equal(cov, cov.T) and np.all(np.diag(cov) > 0)
        # the base's pose = the camera's (Localizer on the same frame) times the inverse extrinsics
        np.testing.assert_allclose(_msg_matrix(pose.pose), _matrix(camera.t, camera.q) @ np.linalg.inv(E), atol=1e-6)
        np.testing.assert_allclose(
            cov, extrinsics.base_pose_covariance(camera.pose_covariance, camera.q, ext), rtol=1e-9, atol=1e-12
        )
        assert not np.allclose(cov, camera.pose_covariance)  # rotated about the base's axes, lever arm
        # odometry of the base: identity at the start, the camera's conjugated by the extrinsics
        np.testing.assert_allclose(
            _msg_matrix(odom.pose.pose), E @ _matrix(camera.odom_t, camera.odom_q) @ np.linalg.inv(E), atol=1e-6
        )
        odom_cov = np.asarray(odom.pose.covariance).reshape(6, 6)
        assert np.array_equal(odom_cov, odom_cov.T) and np.all(np.diag(odom_cov) > 0)
        twist = odom.twist.twist
        linear, angular = extrinsics.base_twist(camera.linear, camera.angular, ext)
        np.testing.assert_allclose([twist.linear.x, twist.linear.y, twist.linear.z], linear, atol=1e-5)
        np.testing.assert_allclose([twist.angular.x, twist.angular.y, twist.angular.z], angular, atol=1e-5)
    np.testing.assert_allclose(_msg_matrix(tester.answers("odom")[0].pose.pose), np.eye(4), atol=1e-12)
    # publish_segmentation false: the topic is not even advertised
    assert tester.node.count_publishers("/vlocnet/segmentation") == 0 and tester.count("seg") == 0
    assert reference.has_segmentation


def test_without_base_frame_the_covariance_pose_is_the_camera_pose(make_node, checkpoint: Path):
    node, tester = make_node()
    reference = Localizer.from_checkpoint(checkpoint)
    frame = camera_frames(1, seed=10)[0]
    tester.publish(CAMERA, image_msg(frame, "rgb8", 1.0, frame_id="camera_optical"))
    wait_until(lambda: min(tester.count(key) for key in ("pose", "pwc", "odom", "seg")) > 0, 30.0, "the answers")
    camera = reference.step(frame, "rgb8", 1.0)
    pose, pwc, odom = tester.answers("pose")[0], tester.answers("pwc")[0], tester.answers("odom")[0]
    assert pwc.header == pose.header and pwc.pose.pose == pose.pose and odom.child_frame_id == "camera_optical"
    np.testing.assert_allclose(_msg_matrix(pose.pose), _matrix(camera.t, camera.q), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(pwc.pose.covariance).reshape(6, 6), camera.pose_covariance)


@pytest.fixture(scope="module")
def pose_only_checkpoint(tmp_path_factory) -> Path:
    """An untrained ``lite_pose`` model (no semantic stream) at 64x48."""
    config = dataclasses.replace(load_model_config("lite_pose"), input_size=(64, 48))
    return init_checkpoint(config, tmp_path_factory.mktemp("pose_only") / "model", seed=5)


def test_a_pose_only_model_publishes_poses_and_advertises_no_segmentation(make_node, pose_only_checkpoint: Path):
    node, tester = make_node(checkpoint=str(pose_only_checkpoint))  # publish_segmentation true (the default)
    assert not node.localizer.has_segmentation and node.seg_pub is None
    reference = Localizer.from_checkpoint(pose_only_checkpoint)
    for k, frame in enumerate(camera_frames(2, seed=11)):
        msg = image_msg(frame, "rgb8", 2.0 + 0.05 * k, frame_id="camera_optical")
        tester.publish(CAMERA, msg)
        wait_until(
            lambda k=k: min(tester.count(key) for key in ("pose", "pwc", "odom")) > k, 30.0, f"answers to frame {k}"
        )
        want = reference.step(frame, "rgb8", conversions.stamp_to_seconds(msg.header.stamp))
        assert want.mask is None
        pose, pwc, odom = tester.answers("pose")[-1], tester.answers("pwc")[-1], tester.answers("odom")[-1]
        assert pose.header.stamp == pwc.header.stamp == odom.header.stamp == msg.header.stamp
        np.testing.assert_allclose(_msg_matrix(pose.pose), _matrix(want.t, want.q), atol=1e-6)
        np.testing.assert_allclose(_msg_matrix(odom.pose.pose), _matrix(want.odom_t, want.odom_q), atol=1e-6)
    assert tester.node.count_publishers("/vlocnet/segmentation") == 0 and tester.count("seg") == 0


def test_bad_camera_extrinsics_stop_the_node_with_a_clear_error(checkpoint: Path, tmp_path: Path):
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN)
    base = {"checkpoint": str(checkpoint), "base_frame": "base_link"}
    try:
        cases = [
            ({"camera_extrinsics": [0.0, 0.0, 0.0, 1.0, 0.0, 0.0]}, "must be 7 numbers.*got 6 value"),
            ({"camera_extrinsics": [0.0, 0.0, 0.0, 1.5, 0.0, 0.0, 0.0]}, "norm 1.5, not 1 within 0.001"),
            ({"camera_extrinsics": "0 0 0 1 0 0 0"}, "must be 7 numbers"),
            ({"camera_extrinsics": EXTRINSICS, "base_frame": ""}, "base_frame is empty"),
        ]
        for params, message in cases:
            with pytest.raises(UserError, match=message):
                LocalizerNode(
                    context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in {**base, **params}.items()]
                )
        # integers are numbers too
        node = LocalizerNode(
            context=ctx,
            parameter_overrides=[
                Parameter(k, value=v)
                for k, v in {**base, "camera_extrinsics": [0, 0, 1, 1, 0, 0, 0], "num_threads": 1}.items()
            ],
        )
        assert node.extrinsics.values() == [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]
        node.close()
        node.destroy_node()
    finally:
        ctx.try_shutdown()
    # the node as a program: one error line, exit code 1
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "vlocnetpp_ros.node",
            "--ros-args",
            "-p",
            f"checkpoint:={checkpoint}",
            "-p",
            "base_frame:=base_link",
            "-p",
            "camera_extrinsics:=[0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0]",
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    output = proc.stdout + proc.stderr
    assert proc.returncode == 1, output
    assert "cannot start: parameter camera_extrinsics must be 7 numbers" in output and "norm 0.5" in output
    assert "Traceback" not in output

"""Helpers for the node tests: camera frames as messages, a tester node that collects the node's outputs,
and the node started from a colcon install tree as a process of its own."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import rclpy
import yaml
from conftest import install_env
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

from vlocnetpp_core.inference.localizer import Localizer
from vlocnetpp_ros import conversions

OUTPUTS = {
    "pose": ("vlocnet/pose", PoseStamped),
    "pwc": ("vlocnet/pose_with_covariance", PoseWithCovarianceStamped),
    "odom": ("vlocnet/odometry", Odometry),
    "seg": ("vlocnet/segmentation", Image),
    "net": ("vlocnet/network_pose", PoseStamped),
}  # the network's own pose: only a node with a map publishes it
CAMERA = "/camera/image_raw"


def domain_id(base: int) -> int:
    """A ROS domain for one test module of one pytest process (other sessions on the machine use other pids)."""
    return base + os.getpid() % 40


def camera_frames(n: int, height: int = 120, width: int = 200, seed: int = 0) -> list[np.ndarray]:
    """Smooth random RGB frames of a camera panning over a texture."""
    rng = np.random.default_rng(seed)
    base = cv2.resize(
        rng.integers(0, 256, (height // 8 + 4, width // 8 + 4, 3), dtype=np.uint8), (width + 4 * n, height + 2 * n)
    )
    return [np.ascontiguousarray(base[k : k + height, 3 * k : 3 * k + width]) for k in range(n)]


def image_msg(array: np.ndarray, encoding: str, stamp: float, frame_id: str = "camera") -> Image:
    return conversions.array_to_image(
        array, encoding, Header(stamp=conversions.seconds_to_stamp(stamp), frame_id=frame_id)
    )


class Harness:
    """A node that publishes camera messages and records the localizer's outputs (spun in a background thread)."""

    def __init__(self, context, extra_nodes: tuple[Node, ...] = ()):
        self.node = Node("tester", context=context)
        self.received: dict[str, list] = {k: [] for k in (*OUTPUTS, "diag")}
        self._lock = threading.Lock()
        for key, (topic, msg_type) in OUTPUTS.items():
            self.node.create_subscription(msg_type, topic, lambda m, key=key: self._add(key, m), 50)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: self._add("diag", m), 10)
        self.publishers: dict[str, object] = {}
        self.executor = SingleThreadedExecutor(context=context)
        for n in (self.node, *extra_nodes):
            self.executor.add_node(n)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._stop = threading.Event()
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and rclpy.ok(context=self.executor.context):
            self.executor.spin_once(timeout_sec=0.05)

    def _add(self, key: str, msg) -> None:
        with self._lock:
            self.received[key].append(msg)

    def count(self, key: str) -> int:
        with self._lock:
            return len(self.received[key])

    def publish(self, topic: str, msg) -> None:
        if topic not in self.publishers:
            self.publishers[topic] = self.node.create_publisher(type(msg), topic, 10)
        self.publishers[topic].publish(msg)

    def wait_for_subscriber(self, topic: str, msg_type, timeout: float = 20.0) -> None:
        if topic not in self.publishers:
            self.publishers[topic] = self.node.create_publisher(msg_type, topic, 10)
        wait_until(lambda: self.publishers[topic].get_subscription_count() > 0, timeout, f"no subscriber on {topic}")

    def answers(self, key: str = "pose") -> list:
        with self._lock:
            return list(self.received[key])

    def stamps(self, key: str = "pose") -> list[float]:
        return [conversions.stamp_to_seconds(m.header.stamp) for m in self.answers(key)]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


@contextmanager
def localizer_nodes(checkpoint: Path, domain: int) -> Iterator[Callable[..., tuple[Node, Harness]]]:
    """``make(**params) -> (LocalizerNode, Harness)``: a localizer node on ``checkpoint`` (one thread, ``params``
    overriding) and a tester, in their own context on ``domain``, spinning in the background and subscribed to
    the camera; everything made is torn down on exit."""
    from vlocnetpp_ros.node import LocalizerNode

    made = []

    def make(**params):
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        overrides = {"checkpoint": str(checkpoint), "num_threads": 1, **params}
        node = LocalizerNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
        tester = Harness(ctx, extra_nodes=(node,))
        made.append((ctx, node, tester))
        topic = CAMERA + "/compressed" if params.get("use_compressed") else CAMERA
        tester.wait_for_subscriber(topic, CompressedImage if params.get("use_compressed") else Image)
        return node, tester

    try:
        yield make
    finally:
        for ctx, node, tester in made:
            tester.close()
            node.close()
            node.destroy_node()
            ctx.try_shutdown()


def wait_until(condition: Callable[[], bool], timeout: float = 20.0, what: str = "condition") -> None:
    """Poll ``condition`` until true; fail the test after ``timeout`` s (a hang guard, not a speed check)."""
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def diagnostic_values(msg: DiagnosticArray) -> dict[str, str]:
    return {kv.key: kv.value for kv in msg.status[0].values}


def params_file(install: Path, folder: Path, **overrides) -> Path:
    """The installed config/localizer.yaml with some values replaced, written into ``folder``; ``backend`` torch unless
    given (the tests compare the node's outputs with an in-process torch Localizer's)."""
    shipped = install / "vlocnetpp_ros" / "share" / "vlocnetpp_ros" / "config" / "localizer.yaml"
    data = yaml.safe_load(shipped.read_text())
    data["/**"]["ros__parameters"].update({"backend": "torch", **overrides})
    path = folder / f"params_{len(list(folder.glob('params_*')))}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


class InstalledNode:
    """``lib/vlocnetpp_ros/localizer --ros-args --params-file FILE [ARGS]`` from the install tree, on ROS domain
    ``domain``."""

    def __init__(
        self,
        install: Path,
        params: Path,
        log: Path,
        domain: int,
        env: dict[str, str] | None = None,
        args: tuple[str, ...] = (),
    ):
        self.env = env = {**install_env(install), **(env or {})}
        env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
        exe = install / "vlocnetpp_ros" / "lib" / "vlocnetpp_ros" / "localizer"
        self.log = log
        self._out = open(log, "w")
        self.proc = subprocess.Popen(
            [str(exe), "--ros-args", "--params-file", str(params), *args],
            env=env,
            cwd="/",
            stdout=self._out,
            stderr=subprocess.STDOUT,
        )

    def output(self) -> str:
        if not self._out.closed:
            self._out.flush()
        return self.log.read_text()

    def rss_mb(self) -> float:
        """Resident memory (``VmRSS``) in MiB."""
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        raise AssertionError("no VmRSS")

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 10.0) -> tuple[int, float]:
        """Send ``sig``; ``(exit code, seconds until exit)``."""
        start = time.monotonic()
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        self._out.close()
        return code, time.monotonic() - start


def float64_localizer(checkpoint: Path) -> Localizer:
    """A one-thread ``Localizer`` of ``checkpoint`` with the network in float64: the exact values that
    :func:`float32_tolerance` measures float32 rounding against."""
    exact = Localizer.from_checkpoint(checkpoint, num_threads=1)
    exact.model.double()
    return exact


def float32_tolerance(want: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """Allowed difference between two float32 runs of the same network on the same pixels (node and
    ``Localizer``: a kernel may sum in another order, MKL and oneDNN picking by memory alignment), per
    component of the pose ``want`` ``(x, y, z, qw, qx, qy, qz)``: four times the largest distance of
    ``want``'s position (and of its quaternion) to ``exact``, the same network run in float64 (two
    summation orders each err by about that much, in any component), plus a few roundings of the
    values. An untrained network's activations reach hundreds, fc1 of the flattened global head sums
    4096 products and the anchor softmax turns a logit's rounding into metres' worth of weight, so
    that error is many float32 eps."""
    rounding = np.abs(np.asarray(want) - np.asarray(exact))
    rounding = np.repeat([rounding[:3].max(), rounding[3:].max()], [3, 4])
    return 4 * rounding + 8 * np.finfo(np.float32).eps * np.maximum(1.0, np.abs(want))

"""Helpers for the node tests: camera frames as messages, and a tester node that collects the node's outputs."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from vlocnetpp_ros import conversions

OUTPUTS = {"pose": ("vlocnet/pose", PoseStamped), "odom": ("vlocnet/odometry", Odometry), "seg": ("vlocnet/segmentation", Image)}


def domain_id(base: int) -> int:
    """A ROS domain for one test module of one pytest process (other sessions on the machine use other pids)."""
    return base + os.getpid() % 40


def camera_frames(n: int, height: int = 120, width: int = 200, seed: int = 0) -> list[np.ndarray]:
    """Smooth random RGB frames of a camera panning over a texture."""
    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.integers(0, 256, (height // 8 + 4, width // 8 + 4, 3), dtype=np.uint8), (width + 4 * n, height + 2 * n))
    return [np.ascontiguousarray(base[k : k + height, 3 * k : 3 * k + width]) for k in range(n)]


def image_msg(array: np.ndarray, encoding: str, stamp: float, frame_id: str = "camera") -> Image:
    return conversions.array_to_image(array, encoding, Header(stamp=conversions.seconds_to_stamp(stamp), frame_id=frame_id))


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


def wait_until(condition: Callable[[], bool], timeout: float = 20.0, what: str = "condition") -> None:
    """Poll ``condition`` until true; fail the test after ``timeout`` s (a hang guard, not a speed check)."""
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def diagnostic_values(msg: DiagnosticArray) -> dict[str, str]:
    return {kv.key: kv.value for kv in msg.status[0].values}

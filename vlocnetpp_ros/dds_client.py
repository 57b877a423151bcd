"""The rclpy side of the tools that drive a localizer node from another process (replay bridge, latency
bench, soak): a node in its own context, spun from the caller's thread."""

from __future__ import annotations

import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
RECORD = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE
)  # answers kept for scoring


class DdsClient:
    """``self.node`` (named ``name`` in ``namespace``) in a context and executor of its own; subclasses add
    publishers and subscriptions. ``close()`` shuts all three down."""

    def __init__(self, name: str, namespace: str):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, namespace=namespace, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, deadline: float, done=lambda: False) -> bool:
        """Process callbacks until ``done()`` or the monotonic ``deadline``; returns ``done()``."""
        while not done():
            left = deadline - time.monotonic()
            if left <= 0:
                return done()
            self.executor.spin_once(timeout_sec=min(left, 0.01))
        return True

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()

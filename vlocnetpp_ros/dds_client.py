"""The rclpy side of the tools that drive a localizer node from another process (replay bridge, latency
bench, soak): a node in its own context, spun from the caller's thread.

The first client of a process gives the process's Fast DDS participants the localizer's profile
(:mod:`vlocnetpp_ros.dds_profile`): the tools publish camera frames, and with Fast DDS's default 512 KiB
shared-memory segment a 640x480 frame reaches the node with up to ~0.5 s of jitter. Fast DDS reads a
profile file once per process, so a process whose first participant was made otherwise keeps that one."""

from __future__ import annotations

import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from vlocnetpp_ros import dds_profile

RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
RECORD = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE
)  # answers kept for scoring


class DdsClient:
    """``self.node`` (named ``name`` in ``namespace``) in a context and executor of its own; subclasses add
    publishers and subscriptions. ``close()`` shuts all three down."""

    def __init__(self, name: str, namespace: str):
        self.context = rclpy.Context()
        profile = dds_profile.apply()
        try:
            rclpy.init(context=self.context)
            self.node = rclpy.create_node(name, namespace=namespace, context=self.context)
        finally:
            profile.restore()  # the participant exists: Fast DDS has read the profile
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

"""A hand-made rosbag2 (sqlite3 storage) for the `vlocnetpp extract` tests (``test_extract*.py``): images, camera
info, 16UC1 depth and Odometry on a known constant-velocity, constant-rate trajectory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from vlocnetpp_core import geometry
from vlocnetpp_core.bag import messages
from vlocnetpp_core.camera.intrinsics import Intrinsics

W, H = 16, 12
V = np.array([0.8, -0.3, 0.1])  # m/s
AXIS = np.array([0.2, 0.3, 0.9]) / np.linalg.norm([0.2, 0.3, 0.9])
OMEGA = np.deg2rad(40.0)  # rad/s about AXIS: SLERP and linear interpolation are exact on this trajectory


def truth(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T_odom,base`` at times ``s`` (seconds): constant velocity, constant rate about a fixed axis."""
    s = np.asarray(s, dtype=np.float64)
    half = OMEGA * s / 2
    q = np.concatenate((np.cos(half)[:, None], np.sin(half)[:, None] * AXIS), 1)
    return np.array([1.0, 2.0, 0.5]) + s[:, None] * V, geometry.quat_normalize(q)


def write_sqlite_bag(path: Path, image_s: np.ndarray, pose_s: np.ndarray, encoding: str = "mono8") -> None:
    """A rosbag2 folder (sqlite3 storage): mono8 images (value 10 k) and camera info at ``image_s``, Odometry on /odom
    at ``pose_s``, and 16UC1 depth (1000 + 100 k mm) 5 ms after the even images and 30 ms after the odd ones."""
    ts = messages.TYPESTORE
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3)
    writer.open()
    conns = {
        t: writer.add_connection(t, ty, typestore=ts)
        for t, ty in (
            ("/camera/image_raw", messages.IMAGE),
            ("/camera/camera_info", messages.CAMERA_INFO),
            ("/odom", messages.ODOMETRY),
            ("/camera/depth/image_raw", messages.IMAGE),
        )
    }
    K = Intrinsics(20.0, 20.0, 7.5, 5.5, W, H)
    t, q = truth(pose_s)
    items = [
        (
            messages.seconds_to_ns(s),
            "/odom",
            messages.odometry(
                messages.seconds_to_ns(s),
                "odom",
                "base_link",
                t[k],
                q[k],
                np.zeros(3),
                np.zeros(3),
                np.eye(6),
                np.eye(6),
            ),
        )
        for k, s in enumerate(pose_s)
    ]
    for k, s in enumerate(image_s):
        ns = messages.seconds_to_ns(s)
        img = messages.image(ns, "camera", np.full((H, W), 10 * k % 256, np.uint8), "mono8")
        img.encoding = encoding
        items += [(ns, "/camera/image_raw", img), (ns, "/camera/camera_info", messages.camera_info(ns, "camera", K))]
        dns = messages.seconds_to_ns(s + (0.005 if k % 2 == 0 else 0.03))
        items.append(
            (
                dns,
                "/camera/depth/image_raw",
                messages.image(dns, "camera", np.full((H, W), 1000 + 100 * k, np.uint16), "16UC1"),
            )
        )
    for ns, topic, msg in sorted(items, key=lambda x: x[0]):
        writer.write(conns[topic], ns, messages.serialize(msg))
    writer.close()

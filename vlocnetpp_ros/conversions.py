"""ROS 2 messages <-> numpy for the localizer node (rclpy types; no inference here).

Decoding goes through :mod:`vlocnetpp_core.inference.preprocess`, the code path of the offline tools, so
a bag replayed offline and a live camera give the same arrays. Quaternions are ``(w, x, y, z)``
in core and ``(x, y, z, w)`` in the messages; they are converted only here. Stamps are float
seconds in core; output messages reuse the input ``builtin_interfaces/Time`` unchanged.
The ``rosbags`` twin of the builders is ``vlocnetpp_core/bag/messages.py``.
"""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.inference.localizer import LocalizerResult
from vlocnetpp_core.inference.preprocess import (
    DEPTH_ENCODINGS,
    IMAGE_ENCODINGS,
    FrameError,
    check_compressed,
    check_raw,
    decode_compressed,
    decode_raw,
    depth_to_metres,
)

_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "32FC1": 1, "16UC1": 1}


def stamp_to_seconds(stamp: Time) -> float:
    """``builtin_interfaces/Time`` -> float seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


def seconds_to_stamp(seconds: float) -> Time:
    """Float seconds -> ``builtin_interfaces/Time`` (rounded to the nanosecond)."""
    sec, nanosec = divmod(int(round(seconds * 1e9)), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


# --------------------------------------------------------------------------- images in


def check_image(msg: Image | CompressedImage) -> None:
    """Refuse a camera message from its header and data length alone (no pixel is read; O(1) for ``Image``,
    a few bytes per JPEG segment for ``CompressedImage``): the :class:`FrameError` decoding would raise."""
    if isinstance(msg, CompressedImage):
        check_compressed(msg.data)
    else:
        check_raw(len(msg.data), msg.width, msg.height, msg.step, msg.encoding, allowed=IMAGE_ENCODINGS)


def check_depth(msg: Image) -> None:
    """:func:`check_image` for a depth image (reasons prefixed ``depth_``)."""
    try:
        check_raw(len(msg.data), msg.width, msg.height, msg.step, msg.encoding, allowed=DEPTH_ENCODINGS)
    except FrameError as err:
        raise FrameError(f"depth_{err.reason}", f"depth: {err}") from None


def image_to_array(msg: Image) -> np.ndarray:
    """Pixels of a colour ``sensor_msgs/Image`` in its own encoding (``msg.encoding``), row padding removed.

    Raises :class:`FrameError` for an unsupported encoding, a zero size, a bad ``step`` or a
    ``data`` length that does not match ``step * height``.
    """
    return decode_raw(
        msg.data, msg.width, msg.height, msg.step, msg.encoding, bool(msg.is_bigendian), allowed=IMAGE_ENCODINGS
    )


def compressed_to_rgb(msg: CompressedImage) -> np.ndarray:
    """``(H, W, 3) uint8`` RGB of a PNG / JPEG ``sensor_msgs/CompressedImage``."""
    return decode_compressed(msg.data)


def depth_to_array(msg: Image) -> np.ndarray:
    """``(H, W) float32`` metres (0 = invalid) of a ``32FC1`` (metres) or ``16UC1`` (millimetres) image."""
    try:
        raw = decode_raw(
            msg.data, msg.width, msg.height, msg.step, msg.encoding, bool(msg.is_bigendian), allowed=DEPTH_ENCODINGS
        )
    except FrameError as err:
        raise FrameError(f"depth_{err.reason}", f"depth: {err}") from None
    return depth_to_metres(raw, msg.encoding)


def camera_info_to_intrinsics(msg: CameraInfo) -> Intrinsics:
    """:class:`Intrinsics` from ``k`` of a ``sensor_msgs/CameraInfo`` (distortion is ignored: rectified images
    expected)."""
    k = np.asarray(msg.k, dtype=np.float64)
    if k.size != 9 or not np.isfinite(k).all() or k[0] <= 0 or k[4] <= 0 or msg.width <= 0 or msg.height <= 0:
        raise FrameError(
            "camera_info_invalid",
            f"CameraInfo {msg.width}x{msg.height} with k={k.tolist()}: need positive fx, fy and size",
        )
    return Intrinsics.from_matrix(k, msg.width, msg.height)


# --------------------------------------------------------------------------- messages out


def array_to_image(array: np.ndarray, encoding: str, header: Header) -> Image:
    """``sensor_msgs/Image`` of an array in ``encoding`` (little-endian, no row padding)."""
    if encoding not in _CHANNELS:
        raise ValueError(f"unsupported encoding {encoding!r}; expected one of {', '.join(_CHANNELS)}")
    a = np.ascontiguousarray(array)
    h, w = a.shape[:2]
    return Image(
        header=header,
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * _CHANNELS[encoding] * a.dtype.itemsize,
        data=a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes(),
    )


def mask_to_image(mask: np.ndarray, header: Header) -> Image:
    """``mono8`` image of class ids ``(H, W) uint8``."""
    return array_to_image(mask.astype(np.uint8, copy=False), "mono8", header)


def pose_msg(t: np.ndarray, q: np.ndarray) -> Pose:
    """``geometry_msgs/Pose`` of ``t (3,)`` metres and core ``q (4,) (w, x, y, z)``."""
    p = Pose()
    p.position.x, p.position.y, p.position.z = (float(v) for v in t)
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (
        float(v) for v in geometry.quat_to_ros(np.asarray(q))
    )
    return p


def pose_from_msg(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """``(t (3,), q (4,) (w, x, y, z), w >= 0)`` of a ``geometry_msgs/Pose``."""
    o = pose.orientation
    q = geometry.quat_normalize(geometry.quat_from_ros(np.array([o.x, o.y, o.z, o.w], dtype=np.float64)))
    return np.array([pose.position.x, pose.position.y, pose.position.z]), q


def pose_stamped(result: LocalizerResult, header: Header) -> PoseStamped:
    """Global pose ``T_map,cam`` of a result (``T_map,base`` once :func:`vlocnetpp_core.camera.extrinsics.to_base_frame`
    moved it)."""
    return PoseStamped(header=header, pose=pose_msg(result.t, result.q))


def pose_with_covariance(result: LocalizerResult, header: Header) -> PoseWithCovarianceStamped:
    """The global pose of :func:`pose_stamped` with ``result.pose_covariance`` (6x6, ROS order x, y, z, rot x, y, z;
    row-major)."""
    msg = PoseWithCovarianceStamped(header=header)
    msg.pose.pose = pose_msg(result.t, result.q)
    msg.pose.covariance = np.asarray(result.pose_covariance, dtype=np.float64).reshape(36)
    return msg


def odometry(result: LocalizerResult, header: Header, child_frame_id: str) -> Odometry:
    """``nav_msgs/Odometry``: accumulated pose in ``header.frame_id``, twist in the child frame (camera or base),
    covariances."""
    msg = Odometry(header=header, child_frame_id=child_frame_id)
    msg.pose.pose = pose_msg(result.odom_t, result.odom_q)
    msg.pose.covariance = np.asarray(result.odom_covariance, dtype=np.float64).reshape(36)
    tw = msg.twist.twist
    tw.linear.x, tw.linear.y, tw.linear.z = (float(v) for v in result.linear)
    tw.angular.x, tw.angular.y, tw.angular.z = (float(v) for v in result.angular)
    msg.twist.covariance = np.asarray(result.twist_covariance, dtype=np.float64).reshape(36)
    return msg

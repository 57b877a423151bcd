"""ROS 2 Jazzy messages as ``rosbags`` objects: built from numpy, read back to numpy. No rclpy here.

The types come from ``rosbags.typesys`` (``Stores.ROS2_JAZZY``), so the definitions written into
a bag are the real Jazzy ones. Conventions (docs/conventions.md, Stamps; Poses and frames): stamps are float seconds in
core and ``builtin_interfaces/Time`` (or integer nanoseconds, the bag's log time) here; quaternions
are ``(w, x, y, z)`` in core and ``(x, y, z, w)`` in the messages, converted only in this module.
The rclpy twin of these builders is the node package's ``conversions`` module (a different type system).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from rosbags.typesys import Stores, get_typestore

from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.geometry import quat_from_ros, quat_to_ros
from vlocnetpp_core.inference import preprocess

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_T = TYPESTORE.types

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

# Encodings :func:`image` writes: channels and numpy dtype (reading accepts every encoding of
# ``vlocnetpp_core.inference.preprocess``, the decoder the node uses too).
WRITE_ENCODINGS: dict[str, tuple[int, np.dtype]] = {
    "rgb8": (3, np.dtype(np.uint8)),
    "bgr8": (3, np.dtype(np.uint8)),
    "mono8": (1, np.dtype(np.uint8)),
    "16UC1": (1, np.dtype(np.uint16)),
    "32FC1": (1, np.dtype(np.float32)),
}


def seconds_to_ns(stamp: float) -> int:
    """Float seconds -> integer nanoseconds (rounded, so ``ns_to_seconds`` gives the same float back)."""
    return int(round(float(stamp) * 1e9))


def ns_to_seconds(ns: int) -> float:
    return ns / 1e9


def stamp_ns(msg: Any) -> int:
    """The ``header.stamp`` of a message in integer nanoseconds."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def header(ns: int, frame_id: str) -> Any:
    """``std_msgs/Header`` at ``ns`` nanoseconds."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return _T["std_msgs/msg/Header"](
        stamp=_T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


# --------------------------------------------------------------------------- images


def image(ns: int, frame_id: str, array: np.ndarray, encoding: str) -> Any:
    """``sensor_msgs/Image`` of ``array`` ((H, W) or (H, W, C), little-endian, no row padding)."""
    if encoding not in WRITE_ENCODINGS:
        raise ValueError(f"cannot write encoding {encoding!r}; expected one of {', '.join(WRITE_ENCODINGS)}")
    channels, dtype = WRITE_ENCODINGS[encoding]
    a = np.ascontiguousarray(array, dtype=dtype.newbyteorder("<"))
    fits = a.shape[2:] in ((), (1,)) if channels == 1 else a.shape[2:] == (channels,)
    if a.ndim not in (2, 3) or not fits:
        raise ValueError(f"array of shape {a.shape} does not fit encoding {encoding} ({channels} channels)")
    h, w = a.shape[:2]
    return _T[IMAGE](
        header=header(ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * channels * dtype.itemsize,
        data=a.reshape(-1).view(np.uint8),
    )


def image_to_array(msg: Any) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image``: ``(H, W)`` for one channel, else ``(H, W, C)``, in the
    message's own channel order and dtype (a copy; row padding and big-endian data handled by
    :func:`vlocnetpp_core.inference.preprocess.decode_raw`, which raises ``FrameError``)."""
    return preprocess.decode_raw(msg.data, msg.width, msg.height, msg.step, msg.encoding, bool(msg.is_bigendian))


def image_to_rgb(msg: Any) -> np.ndarray:
    """``(H, W, 3) uint8`` RGB of an 8-bit colour or grey ``sensor_msgs/Image``."""
    return preprocess.to_rgb(image_to_array(msg), msg.encoding)


def compressed_image(ns: int, frame_id: str, rgb: np.ndarray, fmt: str = "png", jpeg_quality: int = 95) -> Any:
    """``sensor_msgs/CompressedImage`` of an RGB ``(H, W, 3) uint8`` image as PNG (lossless) or JPEG.

    ``format`` follows image_transport's ``compressed`` plugin: ``"rgb8; png compressed bgr8"``
    (the file holds ordinary colour, which every PNG/JPEG decoder returns correctly).
    """
    if fmt not in ("png", "jpeg"):
        raise ValueError(f"compression must be 'png' or 'jpeg', got {fmt!r}")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise ValueError(f"cv2 could not encode a {rgb.shape} image as {fmt}")
    return _T[COMPRESSED_IMAGE](
        header=header(ns, frame_id), format=f"rgb8; {fmt} compressed bgr8", data=buf.reshape(-1)
    )


def compressed_to_rgb(msg: Any) -> np.ndarray:
    """``(H, W, 3) uint8`` RGB of a PNG or JPEG ``sensor_msgs/CompressedImage``."""
    return preprocess.decode_compressed(msg.data)


def any_image_to_rgb(msg: Any) -> np.ndarray:
    """RGB of a ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``."""
    return compressed_to_rgb(msg) if msg.__msgtype__ == COMPRESSED_IMAGE else image_to_rgb(msg)


# --------------------------------------------------------------------------- camera info


def camera_info(ns: int, frame_id: str, K: Intrinsics) -> Any:
    """``sensor_msgs/CameraInfo`` of a distortion-free pinhole (``plumb_bob`` with zero coefficients)."""
    k = K.matrix()
    p = np.zeros((3, 4))
    p[:, :3] = k
    return _T[CAMERA_INFO](
        header=header(ns, frame_id),
        height=K.height,
        width=K.width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=k.reshape(-1),
        r=np.eye(3).reshape(-1),
        p=p.reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=_T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def intrinsics_from_camera_info(msg: Any) -> Intrinsics:
    """:class:`Intrinsics` from the ``k`` matrix of a ``sensor_msgs/CameraInfo``."""
    return Intrinsics.from_matrix(np.asarray(msg.k, dtype=np.float64), int(msg.width), int(msg.height))


# --------------------------------------------------------------------------- poses


def _pose(t: np.ndarray, q_wxyz: np.ndarray) -> Any:
    t = np.asarray(t, dtype=np.float64)
    x, y, z, w = (float(v) for v in quat_to_ros(np.asarray(q_wxyz, dtype=np.float64)))
    return _T["geometry_msgs/msg/Pose"](
        position=_T["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=_T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def pose_stamped(ns: int, frame_id: str, t: np.ndarray, q_wxyz: np.ndarray) -> Any:
    """``geometry_msgs/PoseStamped`` of ``T_wc`` (``t`` metres, ``q`` core order ``(w, x, y, z)``)."""
    return _T[POSE_STAMPED](header=header(ns, frame_id), pose=_pose(t, q_wxyz))


def pose_with_covariance_stamped(
    ns: int, frame_id: str, t: np.ndarray, q_wxyz: np.ndarray, covariance: np.ndarray
) -> Any:
    """``geometry_msgs/PoseWithCovarianceStamped``: :func:`pose_stamped` plus a 6x6 covariance (ROS order,
    row-major)."""
    return _T[POSE_WITH_COVARIANCE_STAMPED](
        header=header(ns, frame_id),
        pose=_T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose(t, q_wxyz), covariance=np.asarray(covariance, np.float64).reshape(36)
        ),
    )


def pose_from_msg(pose: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(t (3,), q (4,) (w, x, y, z), w >= 0)`` of a ``geometry_msgs/Pose``."""
    p, o = pose.position, pose.orientation
    q = quat_from_ros(np.array([o.x, o.y, o.z, o.w], dtype=np.float64))
    q /= np.linalg.norm(q)
    return np.array([p.x, p.y, p.z], dtype=np.float64), (-q if q[0] < 0 else q)


def stamped_pose(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pose_from_msg` of a ``PoseStamped``, ``PoseWithCovarianceStamped`` or ``Odometry`` message."""
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    return pose_from_msg(pose)


def transform_stamped(ns: int, parent: str, child: str, t: np.ndarray, q_wxyz: np.ndarray) -> Any:
    """``geometry_msgs/TransformStamped`` of ``T_parent,child`` (``t`` metres, ``q`` core order ``(w, x, y, z)``)."""
    t = np.asarray(t, dtype=np.float64)
    x, y, z, w = (float(v) for v in quat_to_ros(np.asarray(q_wxyz, dtype=np.float64)))
    return _T["geometry_msgs/msg/TransformStamped"](
        header=header(ns, parent),
        child_frame_id=child,
        transform=_T["geometry_msgs/msg/Transform"](
            translation=_T["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
            rotation=_T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        ),
    )


def tf_message(transforms: list[Any]) -> Any:
    """``tf2_msgs/TFMessage`` (what ``/tf`` and ``/tf_static`` carry) of ``transform_stamped`` messages."""
    return _T[TF_MESSAGE](transforms=list(transforms))


def transform_from_msg(transform: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(t (3,), q (4,) (w, x, y, z), w >= 0)`` of a ``geometry_msgs/Transform``."""
    v, o = transform.translation, transform.rotation
    q = quat_from_ros(np.array([o.x, o.y, o.z, o.w], dtype=np.float64))
    q /= np.linalg.norm(q)
    return np.array([v.x, v.y, v.z], dtype=np.float64), (-q if q[0] < 0 else q)


def odometry(
    ns: int,
    frame_id: str,
    child_frame_id: str,
    t: np.ndarray,
    q_wxyz: np.ndarray,
    linear: np.ndarray,
    angular: np.ndarray,
    pose_covariance: np.ndarray,
    twist_covariance: np.ndarray,
) -> Any:
    """``nav_msgs/Odometry``: pose ``T_odom,camera``, twist in the child (camera) frame, 6x6 covariances."""
    lin, ang = np.asarray(linear, dtype=np.float64), np.asarray(angular, dtype=np.float64)
    vec = _T["geometry_msgs/msg/Vector3"]
    return _T[ODOMETRY](
        header=header(ns, frame_id),
        child_frame_id=child_frame_id,
        pose=_T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose(t, q_wxyz), covariance=np.asarray(pose_covariance, np.float64).reshape(36)
        ),
        twist=_T["geometry_msgs/msg/TwistWithCovariance"](
            twist=_T["geometry_msgs/msg/Twist"](
                linear=vec(x=float(lin[0]), y=float(lin[1]), z=float(lin[2])),
                angular=vec(x=float(ang[0]), y=float(ang[1]), z=float(ang[2])),
            ),
            covariance=np.asarray(twist_covariance, np.float64).reshape(36),
        ),
    )


# --------------------------------------------------------------------------- (de)serialisation


def serialize(msg: Any) -> bytes:
    """CDR bytes of a message (what a ROS 2 bag stores)."""
    return TYPESTORE.serialize_cdr(msg, msg.__msgtype__)


def deserialize(data: bytes | memoryview, msgtype: str) -> Any:
    """A message of type ``msgtype`` (e.g. ``"sensor_msgs/msg/Image"``) from CDR bytes."""
    return TYPESTORE.deserialize_cdr(data, msgtype)

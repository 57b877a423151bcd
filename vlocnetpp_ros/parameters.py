"""The localizer node's parameters: names, defaults and descriptions (``config/localizer.yaml`` sets every one),
and their checks at start-up (:class:`~vlocnetpp_core.errors.UserError`, one line naming the parameter)."""

from __future__ import annotations

from pathlib import Path

from vlocnetpp_core.bag import topics
from vlocnetpp_core.camera.extrinsics import IDENTITY_VALUES, CameraExtrinsics
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.checkpoint import MAP_AUTO, SHIPPED_MODEL, resolve_map_path, shipped_checkpoint
from vlocnetpp_core.inference.localizer import BACKENDS

PACKAGE = "vlocnetpp_ros"

# name -> (default, description); every one is in config/localizer.yaml.
PARAMETERS: dict[str, tuple[object, str]] = {
    "checkpoint": (
        "",
        f"checkpoint NAME.safetensors (NAME.json next to it); empty: the shipped share/{PACKAGE}/{SHIPPED_MODEL}",
    ),
    "image_topic": (topics.IMAGE_TOPIC, "sensor_msgs/Image topic (with use_compressed: <image_topic>/compressed)"),
    "depth_topic": (
        "",
        "aligned depth Image (32FC1 metres or 16UC1 mm, "
        "same stamp and size as the colour image); empty: predicted depth",
    ),
    "camera_info_topic": ("", "sensor_msgs/CameraInfo topic of the camera; empty: the checkpoint's default intrinsics"),
    "use_compressed": (False, "subscribe to sensor_msgs/CompressedImage (PNG/JPEG) on <image_topic>/compressed"),
    "map_frame": (topics.MAP_FRAME, "frame_id of the published global pose"),
    "odom_frame": (topics.ODOM_FRAME, "frame_id of the published odometry"),
    "base_frame": (
        "",
        "frame whose pose is published (vlocnet/pose, pose_with_covariance, odometry child_frame_id), placed by "
        "camera_extrinsics (no TF lookup); empty: the camera's pose, odometry child = the image's frame_id",
    ),
    "camera_extrinsics": (
        list(IDENTITY_VALUES),
        "the camera's pose in base_frame, T_base_camera: x y z (m) qw qx qy qz (unit quaternion); "
        "camera = the images' optical frame (x right, y down, z forward); must be identity when base_frame is empty",
    ),
    "max_gap_s": (
        topics.DEFAULT_MAX_GAP_S,
        "reset the temporal state when consecutive processed frames are further apart than this (seconds)",
    ),
    "publish_segmentation": (True, "publish the class-id mask on vlocnet/segmentation"),
    "device": ("cpu", "torch device: cpu or cuda (cuda:N)"),
    "num_threads": (0, "CPU inference threads (torch or ONNX Runtime); 0: all cores but one, at least 1"),
    "backend": (
        "torch",
        "inference backend: torch, or onnx (ONNX Runtime; NAME.onnx next to the checkpoint or a cached export)",
    ),
    "map": (
        "",
        f"keyframe map (vlocnetpp map build) to refine the global pose against; empty: no refinement; {MAP_AUTO}: "
        "NAME.map.npz beside the checkpoint NAME.safetensors (none, with a warning, when it is missing); else a path",
    ),
    "refine_every": (
        1,
        "with a map: refine every k-th frame, the refined pose moved on by the odometry in between (1: every frame)",
    ),
    "fuse_odometry": (
        True,
        "fuse the network's global poses with its own odometry over the frames (a causal filter, docs/node.md); "
        "false: every frame's global pose alone (for an estimator that fuses vlocnet/pose with vlocnet/odometry)",
    ),
}
# What config/localizer.yaml sets apart from the defaults above: the package's launch YAML refines against the
# shipped map beside the shipped model (a node started without it does not refine), with ONNX Runtime (faster on a
# CPU: the rate with refinement, docs/performance.md; a node started without it runs torch, which needs no export).
PARAMS_FILE_VALUES: dict[str, object] = {"map": MAP_AUTO, "backend": "onnx"}


def default_checkpoint() -> Path:
    """The shipped model (see :func:`vlocnetpp_core.inference.checkpoint.shipped_checkpoint`), as a node error when
    missing."""
    try:
        return shipped_checkpoint()
    except FileNotFoundError as err:
        raise UserError(
            f"no 'checkpoint' parameter given and {err}; set one with --ros-args -p checkpoint:=/path/NAME.safetensors"
        ) from None


def check_parameters(p: dict) -> None:
    """The checks of the values that need no file."""
    if not p["max_gap_s"] > 0:
        raise UserError(f"parameter max_gap_s must be > 0 seconds, got {p['max_gap_s']}")
    if p["num_threads"] < 0:
        raise UserError(f"parameter num_threads must be >= 0 (0: all cores but one), got {p['num_threads']}")
    dev = str(p["device"])
    if not (dev == "cpu" or dev == "cuda" or (dev.startswith("cuda:") and dev[5:].isdigit())):
        raise UserError(f"parameter device must be 'cpu', 'cuda' or 'cuda:N', got {dev!r}")
    if p["backend"] not in BACKENDS:
        raise UserError(f"parameter backend must be one of {', '.join(BACKENDS)}, got {p['backend']!r}")
    if not p["image_topic"]:
        raise UserError("parameter image_topic is empty")
    if p["refine_every"] < 1:
        raise UserError(
            f"parameter refine_every must be >= 1 (1: refine every frame, k: every k-th frame), got {p['refine_every']}"
        )


def extrinsics_of(p: dict) -> CameraExtrinsics | None:
    """``camera_extrinsics`` checked (:class:`UserError`); None when the published pose is the camera's: without
    ``base_frame``, or with identity extrinsics (then the base frame is only a name)."""
    ext = CameraExtrinsics.from_values(p["camera_extrinsics"])
    if p["base_frame"]:
        return None if ext.is_identity else ext
    if not ext.is_identity:
        raise UserError(
            f"parameter camera_extrinsics is {ext.values()} but base_frame is empty: set base_frame to the frame "
            "the extrinsics place the camera in, or leave camera_extrinsics at identity [0, 0, 0, 1, 0, 0, 0]"
        )
    return None


def map_of(p: dict, checkpoint: Path, warn) -> Path | None:
    """The keyframe map of parameter ``map`` (:func:`vlocnetpp_core.inference.checkpoint.resolve_map_path`; ``warn``
    gets the line for a missing ``auto`` map), or None: no refinement. A missing map file named by path is a
    ``DataError``."""
    return resolve_map_path(checkpoint, p["map"], "parameter map", warn)

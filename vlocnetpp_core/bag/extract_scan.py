"""The first pass of ``vlocnetpp extract``: which topics to read, and what they hold before anything is written.

:func:`resolve_sources` picks the topics from the flags and the defaults of
:mod:`vlocnetpp_core.bag.topics` (checking that each exists with the right type),
:func:`scan_bag` reads the header stamps of every camera and depth image, the camera infos and the
pose samples in one pass, and :func:`image_size`, :func:`check_depth`, :func:`camera_intrinsics`
and :func:`camera_poses` turn that into the image size, the intrinsics and the camera pose ``T_wc``
at every image stamp, or a ``UserError`` that names the topic (see :mod:`vlocnetpp_core.bag.extract`).
"""

from __future__ import annotations

import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.extract_plan import Selection
from vlocnetpp_core.bag.pose_source import POSE_TYPES, PoseChain, PoseTopicCollector, TfCollector
from vlocnetpp_core.bag.topics import CAMERA_INFO_TOPIC, DEPTH_TOPIC, GROUND_TRUTH_TOPIC, TF_STATIC_TOPIC, TF_TOPIC
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference import preprocess

DEFAULT_MAX_POSE_GAP_S = 0.5
DEFAULT_DEPTH_TOLERANCE_S = 0.02
IMAGE_TYPES = (messages.IMAGE, messages.COMPRESSED_IMAGE)


@dataclass
class ExtractOptions:
    """The ``extract`` flags. ``camera_extrinsics``: ``T_CHILD,camera`` as ``(t (3,), q (4,) w,x,y,z)`` or None."""

    image_topic: str | None = None
    camera_info_topic: str | None = None
    intrinsics: str | None = None
    depth_topic: str | None = None
    no_depth: bool = False
    pose_topic: str | None = None
    tf: tuple[str, str] | None = None
    camera_extrinsics: tuple[np.ndarray, np.ndarray] | None = None
    max_pose_gap_s: float = DEFAULT_MAX_POSE_GAP_S
    depth_tolerance_s: float = DEFAULT_DEPTH_TOLERANCE_S
    selection: Selection = field(default_factory=Selection)


@dataclass
class Sources:
    """The topics read: ``image``, ``camera_info`` (None with ``--intrinsics``), ``depth`` (None: no depth) and
    the pose source, ``pose_topic`` or ``tf`` ``(PARENT, CHILD)``."""

    image: str
    camera_info: str | None
    depth: str | None
    pose_topic: str | None
    tf: tuple[str, str] | None

    @property
    def pose_name(self) -> str:
        return self.pose_topic if self.tf is None else f"/tf {self.tf[0]} -> {self.tf[1]}"


@dataclass
class Scan:
    """What the first pass found: header stamps (ns, log order) of images and depth, their first messages,
    the distinct camera infos ``(k, width, height, has distortion)``, and the pose collector."""

    pose: PoseTopicCollector | TfCollector
    image_stamps: list[int] = field(default_factory=list)
    depth_stamps: list[int] = field(default_factory=list)
    first_image: Any = None
    first_depth: Any = None
    infos: dict[tuple, int] = field(default_factory=dict)


# --------------------------------------------------------------------------- topics


def _require(topics: dict[str, str], topic: str, types: tuple[str, ...], option: str) -> str:
    """``topic`` when the bag has it with one of ``types``; else a ``UserError`` naming it."""
    if topic not in topics:
        near = [t for t, ty in topics.items() if ty in types] or sorted(topics)
        raise UserError(f"{option} {topic}: the bag has no such topic (candidates: {', '.join(near[:20]) or 'none'})")
    if topics[topic] not in types:
        raise UserError(f"{option} {topic}: the topic is {topics[topic]}, expected {' or '.join(types)}")
    return topic


def _default_camera_info(topics: dict[str, str], image: str) -> str:
    """``<image namespace>/camera_info``, else ``/camera/camera_info``, else the bag's only CameraInfo topic."""
    base = image.removesuffix("/compressed").rsplit("/", 1)[0]
    infos = [t for t, ty in topics.items() if ty == messages.CAMERA_INFO]
    for t in (f"{base}/camera_info", CAMERA_INFO_TOPIC):
        if topics.get(t) == messages.CAMERA_INFO:
            return t
    if len(infos) == 1:
        return infos[0]
    raise UserError(
        f"no camera info for {image}: pass --camera-info-topic (CameraInfo topics: {', '.join(infos) or 'none'}) "
        "or --intrinsics fx,fy,cx,cy"
    )


def resolve_sources(topics: dict[str, str], opts: ExtractOptions, path: Path) -> Sources:
    """The topics to read, from the flags and the bag's defaults (``vlocnetpp_core.bag.topics``)."""
    from vlocnetpp_core.bag.replay import choose_image_topic

    if opts.image_topic is not None:
        image = _require(topics, opts.image_topic, IMAGE_TYPES, "--image-topic")
    else:
        image = choose_image_topic(topics, None, path)
    if opts.camera_info_topic is not None:
        info = _require(topics, opts.camera_info_topic, (messages.CAMERA_INFO,), "--camera-info-topic")
    else:
        info = None if opts.intrinsics else _default_camera_info(topics, image)
    depth = None
    if opts.depth_topic is not None:
        depth = _require(topics, opts.depth_topic, (messages.IMAGE,), "--depth-topic")
    elif not opts.no_depth and topics.get(DEPTH_TOPIC) == messages.IMAGE:
        depth = DEPTH_TOPIC
    if depth == image:
        raise UserError(f"--depth-topic {depth} is the camera topic")
    pose_topic = opts.pose_topic
    if opts.tf is not None:
        for t in (TF_TOPIC, TF_STATIC_TOPIC):
            if t in topics:
                _require(topics, t, (messages.TF_MESSAGE,), "--tf:")
        if TF_TOPIC not in topics and TF_STATIC_TOPIC not in topics:
            raise UserError(f"--tf {opts.tf[0]} {opts.tf[1]}: the bag has no {TF_TOPIC} or {TF_STATIC_TOPIC} topic")
    elif pose_topic is not None:
        _require(topics, pose_topic, POSE_TYPES, "--pose-topic")
    elif topics.get(GROUND_TRUTH_TOPIC) in POSE_TYPES:
        pose_topic = GROUND_TRUTH_TOPIC
    else:
        poses = [t for t, ty in topics.items() if ty in POSE_TYPES]
        raise UserError(
            f"no pose source: pass --pose-topic TOPIC (pose topics in the bag: {', '.join(poses) or 'none'}) "
            f"or --tf PARENT CHILD ({TF_TOPIC} {'present' if TF_TOPIC in topics else 'absent'})"
        )
    return Sources(image, info, depth, pose_topic, opts.tf)


# --------------------------------------------------------------------------- pass 1: scan


def scan_bag(reader: BagReader, src: Sources, progress: bool) -> Scan:
    """Stamps of images and depth, camera infos and pose samples, in one pass over the small topics and images."""
    from tqdm import tqdm

    scan = Scan(pose=TfCollector() if src.tf is not None else PoseTopicCollector(src.pose_topic or ""))
    wanted = [t for t in (src.image, src.camera_info, src.depth, src.pose_topic) if t]
    wanted += [TF_TOPIC, TF_STATIC_TOPIC] if src.tf is not None else []
    total = sum(reader.count(t) for t in set(wanted))
    with tqdm(total=total, unit="msg", desc="extract: scan", disable=not progress, file=sys.stderr) as bar:
        for topic, _, msg in reader.messages(wanted):
            if topic == src.image:
                scan.image_stamps.append(messages.stamp_ns(msg))
                scan.first_image = msg if scan.first_image is None else scan.first_image
            elif topic == src.depth:
                scan.depth_stamps.append(messages.stamp_ns(msg))
                scan.first_depth = msg if scan.first_depth is None else scan.first_depth
            elif topic == src.camera_info:
                key = (
                    tuple(float(v) for v in msg.k),
                    int(msg.width),
                    int(msg.height),
                    bool(np.any(np.asarray(msg.d) != 0)),
                )
                scan.infos.setdefault(key, len(scan.infos))
            elif src.tf is not None:
                scan.pose.add(msg, static=topic == TF_STATIC_TOPIC)
            else:
                scan.pose.add(msg)
            bar.update(1)
    return scan


def image_size(msg: Any, topic: str) -> tuple[int, int]:
    """``(width, height)`` of the first camera message; a ``UserError`` naming ``topic`` for an unsupported encoding."""
    try:
        if msg.__msgtype__ == messages.COMPRESSED_IMAGE:
            return preprocess.check_compressed(msg.data)
        if msg.encoding not in preprocess.IMAGE_ENCODINGS:
            raise UserError(
                f"{topic}: unsupported image encoding {msg.encoding!r} "
                f"(supported: {', '.join(preprocess.IMAGE_ENCODINGS)}, or a PNG/JPEG CompressedImage)"
            )
        return int(msg.width), int(msg.height)
    except preprocess.FrameError as err:
        raise UserError(f"{topic}: {err} (format {getattr(msg, 'format', '')!r})") from err


def check_depth(msg: Any, topic: str, size: tuple[int, int]) -> None:
    """The first depth image: a supported encoding and the camera image's size (registered depth)."""
    if msg.encoding not in preprocess.DEPTH_ENCODINGS:
        raise UserError(
            f"{topic}: unsupported depth encoding {msg.encoding!r} (supported: 32FC1 metres, 16UC1 millimetres)"
        )
    if (int(msg.width), int(msg.height)) != size:
        raise UserError(
            f"{topic}: depth images are {msg.width}x{msg.height}, the camera images {size[0]}x{size[1]}; "
            "the depth must be registered to the colour camera (e.g. aligned_depth_to_color), or pass --no-depth"
        )


def camera_intrinsics(
    scan: Scan, src: Sources, opts: ExtractOptions, size: tuple[int, int], notes: list[str]
) -> Intrinsics:
    """``--intrinsics`` at the image size, else the (first) camera info, which must be of the image size."""
    if opts.intrinsics is not None:
        try:
            return Intrinsics.parse(opts.intrinsics, *size)
        except ValueError as err:
            raise UserError(f"--intrinsics: {err}") from err
    if not scan.infos:
        raise UserError(f"{src.camera_info}: the topic has no messages (or pass --intrinsics fx,fy,cx,cy)")
    k, width, height, distorted = next(iter(scan.infos))
    if (width, height) != size:
        raise UserError(
            f"{src.camera_info}: camera info is for {width}x{height} images but {src.image} has {size[0]}x{size[1]}"
        )
    if k[0] <= 0 or k[4] <= 0:
        raise UserError(
            f"{src.camera_info}: the camera is not calibrated (K = {list(k)}); pass --intrinsics fx,fy,cx,cy"
        )
    if len(scan.infos) > 1:
        notes.append(
            f"{src.camera_info} changes during the bag ({len(scan.infos)} different messages); the first one is used"
        )
    if distorted:
        notes.append(
            f"{src.camera_info} has distortion coefficients: the images are written as they are (not rectified); "
            "extract a rectified topic (image_rect) for exact geometry"
        )
    return Intrinsics.from_matrix(np.asarray(k), width, height)


def camera_poses(
    chain: PoseChain, stamps: np.ndarray, src: Sources, opts: ExtractOptions
) -> tuple[np.ndarray, np.ndarray, list]:
    """``T_wc`` ``(t (N, 3), q (N, 4))`` at the image stamps and the pose reasons; a ``UserError`` when no image has
    one."""
    t, q, reasons = chain.camera_at(stamps, opts.max_pose_gap_s, opts.camera_extrinsics)
    if all(r is not None for r in reasons):
        span = chain.dynamic_span_ns()
        poses = "" if span is None else f", poses {span[0] / 1e9:.3f}..{span[1] / 1e9:.3f} s"
        why = Counter(reasons).most_common(1)[0][0]
        raise UserError(
            f"no image of {src.image} has a pose from {src.pose_name} "
            f"(images {stamps.min() / 1e9:.3f}..{stamps.max() / 1e9:.3f} s"
            f"{poses}; {why})"
        )
    return t, q, reasons

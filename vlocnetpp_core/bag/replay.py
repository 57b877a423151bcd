"""``vlocnetpp replay``: run the localizer over every image of a bag and write an output bag.

The output bag holds every input topic unchanged plus, per processed image (stamp of the image):

===================== ========================= ==============================================
``/vlocnet/pose``         ``geometry_msgs/PoseStamped`` global pose ``T_map,cam`` in ``map``
``/vlocnet/pose_with_covariance`` ``geometry_msgs/PoseWithCovarianceStamped`` the same pose with its 6x6 covariance
``/vlocnet/odometry``     ``nav_msgs/Odometry``         accumulated odometry in ``odom``, child = the image frame
``/vlocnet/segmentation`` ``sensor_msgs/Image``         ``mono8`` class ids at the image resolution
``/vlocnet/network_pose`` ``geometry_msgs/PoseStamped`` with ``--map`` only: the network's own pose
===================== ========================= ==============================================

A pose-only model (no semantic stream, e.g. config ``lite_pose``) gives no segmentation: the output
bag then has no ``/vlocnet/segmentation`` topic (:func:`output_types`, :func:`checkpoint_output_types`).
With ``--map`` (a keyframe map, or ``auto``: ``NAME.map.npz`` beside the checkpoint) the localizer refines
its pose against the map every ``--refine-every``-th frame, as the node's parameters ``map`` and
``refine_every`` do: ``/vlocnet/pose`` and ``/vlocnet/pose_with_covariance`` then hold the published
(refined, propagated or network) pose, ``/vlocnet/network_pose`` the network's own.

In process (default) the images are read in log-time order and given to
:class:`~vlocnetpp_core.inference.localizer.Localizer` (the node's code path) with the intrinsics of the
latest ``/camera/camera_info``; the localizer resets its temporal state itself on stamp gaps
longer than ``--max-gap-s`` (the converter leaves 10 s between sequences). Messages that share a
log time are handled together, so a frame's camera info or depth is used whatever order the bag
stores them in. With ``--through-node`` the real ROS node runs as a subprocess and the bag is
played to it over DDS by the ROS package's ``replay-node`` program (:mod:`vlocnetpp_core.programs`;
this module never imports ROS); both paths give the same poses for the same frames.

Frames the localizer rejects (unsupported encoding, truncated data, ...) are skipped and counted.
The output is written like the converter's: one ``.mcap`` file, renamed into place when complete.
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader, BagWriter
from vlocnetpp_core.bag.topics import (
    CAMERA_INFO_TOPIC,
    COMPRESSED_TOPIC,
    DEPTH_TOPIC,
    IMAGE_TOPIC,
    MAP_FRAME,
    NETWORK_POSE_TOPIC,
    ODOM_FRAME,
    ODOMETRY_TOPIC,
    POSE_TOPIC,
    POSE_WITH_COVARIANCE_TOPIC,
    SEGMENTATION_TOPIC,
    SEMANTIC_TOPIC,
)
from vlocnetpp_core.errors import DataError
from vlocnetpp_core.interrupts import sigterm_as_interrupt

OUTPUT_TYPES = {
    POSE_TOPIC: messages.POSE_STAMPED,
    POSE_WITH_COVARIANCE_TOPIC: messages.POSE_WITH_COVARIANCE_STAMPED,
    ODOMETRY_TOPIC: messages.ODOMETRY,
    SEGMENTATION_TOPIC: messages.IMAGE,
}
REFINEMENT_TYPES = {NETWORK_POSE_TOPIC: messages.POSE_STAMPED}  # with a map: the network's own pose
ALL_OUTPUT_TYPES = {
    **OUTPUT_TYPES,
    **REFINEMENT_TYPES,
}  # every /vlocnet/* output: what a replay replaces in its input bag


def output_types(segmentation: bool = True, network_pose: bool = False) -> dict[str, str]:
    """The ``/vlocnet/*`` topics (and types) written per frame: :data:`OUTPUT_TYPES`, without
    ``/vlocnet/segmentation`` for a model that has no semantic stream (``segmentation`` False), and
    with ``/vlocnet/network_pose`` when the localizer refines against a map (``network_pose``)."""
    out = {t: ty for t, ty in OUTPUT_TYPES.items() if segmentation or t != SEGMENTATION_TOPIC}
    return {**out, **REFINEMENT_TYPES} if network_pose else out


def checkpoint_output_types(checkpoint: str | Path, network_pose: bool = False) -> dict[str, str]:
    """:func:`output_types` of the model of a checkpoint, from its sidecar (the weights are not read);
    raises ``DataError`` naming the file when the sidecar is missing or malformed."""
    from vlocnetpp_core.inference.checkpoint import checkpoint_paths, read_checkpoint_meta
    from vlocnetpp_core.model import ModelConfig

    meta = read_checkpoint_meta(checkpoint)
    config = ModelConfig.from_dict(meta["model_config"], source=f"{checkpoint_paths(checkpoint)[1]} (model_config)")
    return output_types("seg" in config.tasks, network_pose)


@dataclass
class ReplaySummary:
    """What a replay did: images ``processed``, ``skipped`` per reason, ``resets`` per reason and ``sources`` of the
    published pose with a map (in process only), ``wall_s`` spent replaying and ``startup_s`` spent starting the
    node (through the node only)."""

    path: Path
    processed: int = 0
    skipped: Counter = field(default_factory=Counter)
    resets: Counter = field(default_factory=Counter)
    sources: Counter = field(default_factory=Counter)
    wall_s: float = 0.0
    startup_s: float = 0.0

    def format(self) -> str:
        text = (
            f"wrote {self.path}: {self.processed} frames localized in {self.wall_s:.1f} s "
            f"({self.processed / max(self.wall_s, 1e-9):.1f} frames/s)"
        )
        if self.startup_s:
            text += f", after {self.startup_s:.1f} s of node start-up"
        if self.resets:
            text += "\n  temporal state resets: " + ", ".join(f"{k} {v}" for k, v in sorted(self.resets.items()))
        if self.sources:
            text += "\n  published pose: " + ", ".join(f"{k} {v}" for k, v in sorted(self.sources.items()))
        if self.skipped:
            text += "\n  skipped frames: " + ", ".join(f"{k} {v}" for k, v in sorted(self.skipped.items()))
        return text


def choose_image_topic(topics: dict[str, str], wanted: str | None, path: Path) -> str:
    """``wanted``, else ``/camera/image_raw``, else ``/camera/image_raw/compressed``, else the only image topic."""
    images = [
        t for t, ty in topics.items() if ty in (messages.IMAGE, messages.COMPRESSED_IMAGE) and t not in ALL_OUTPUT_TYPES
    ]
    if wanted is not None:
        if topics.get(wanted) not in (messages.IMAGE, messages.COMPRESSED_IMAGE):
            raise DataError(
                path,
                f"--image-topic {wanted}: no Image or CompressedImage topic "
                f"of that name (image topics: {', '.join(images) or 'none'})",
            )
        return wanted
    for t in (IMAGE_TOPIC, COMPRESSED_TOPIC):
        if t in topics:
            return t
    candidates = [t for t in images if t not in (DEPTH_TOPIC, SEMANTIC_TOPIC)]
    if len(candidates) != 1:
        raise DataError(
            path, f"cannot tell the camera topic; pass --image-topic (image topics: {', '.join(images) or 'none'})"
        )
    return candidates[0]


def groups_by_log_time(stream: Iterable[tuple[str, int, Any]]) -> Iterator[list[tuple[str, int, Any]]]:
    """Consecutive messages with the same log time, as lists."""
    group: list = []
    for item in stream:
        if group and item[1] != group[0][1]:
            yield group
            group = []
        group.append(item)
    if group:
        yield group


def output_messages(result, image_msg: Any, network_pose: bool = False) -> list[tuple[str, Any]]:
    """The ``/vlocnet/*`` messages of a :class:`~vlocnetpp_core.inference.localizer.LocalizerResult` with the stamp and
    frame of ``image_msg`` (no segmentation when ``result.mask`` is None: a pose-only model; the network's own pose on
    ``/vlocnet/network_pose`` with ``network_pose``: a localizer refining against a map)."""
    ns, camera = messages.stamp_ns(image_msg), image_msg.header.frame_id
    out = [
        (POSE_TOPIC, messages.pose_stamped(ns, MAP_FRAME, result.t, result.q)),
        (
            POSE_WITH_COVARIANCE_TOPIC,
            messages.pose_with_covariance_stamped(ns, MAP_FRAME, result.t, result.q, result.pose_covariance),
        ),
        (
            ODOMETRY_TOPIC,
            messages.odometry(
                ns,
                ODOM_FRAME,
                camera,
                result.odom_t,
                result.odom_q,
                result.linear,
                result.angular,
                result.odom_covariance,
                result.twist_covariance,
            ),
        ),
    ]
    if result.mask is not None:
        out.append((SEGMENTATION_TOPIC, messages.image(ns, camera, result.mask, "mono8")))
    if network_pose:
        out.append((NETWORK_POSE_TOPIC, messages.pose_stamped(ns, MAP_FRAME, result.network_t, result.network_q)))
    return out


def copy_topics(reader: BagReader, writer: BagWriter, outputs: dict[str, str] | None = None) -> None:
    """Declare every input topic (except old ``/vlocnet/*`` outputs, which the replay replaces) and the
    ``outputs`` (:func:`output_types`; default all of :data:`OUTPUT_TYPES`) on ``writer``."""
    for conn in reader.connections:
        if conn.topic not in ALL_OUTPUT_TYPES and not writer.has_topic(conn.topic):
            writer.add_topic(conn.topic, conn.msgtype, conn.msgdef.data, conn.digest)
    for topic, msgtype in (OUTPUT_TYPES if outputs is None else outputs).items():
        writer.add_topic(topic, msgtype)


def replay(
    bag: str | Path,
    out: str | Path,
    localizer,
    image_topic: str | None = None,
    use_depth: bool = False,
    force: bool = False,
    progress: bool = True,
) -> ReplaySummary:
    """Run ``localizer`` over every image of ``bag`` in log-time order and write ``out`` (see module doc)."""
    from tqdm import tqdm

    from vlocnetpp_core.inference.preprocess import FrameError, depth_to_metres

    summary = ReplaySummary(Path(out))
    start = time.perf_counter()
    with BagReader(bag) as reader:
        topics = reader.topics
        topic = choose_image_topic(topics, image_topic, reader.path)
        if use_depth and DEPTH_TOPIC not in topics:
            raise DataError(reader.path, f"--use-depth: the bag has no {DEPTH_TOPIC} topic")
        decoded = {topic, CAMERA_INFO_TOPIC} | ({DEPTH_TOPIC} if use_depth else set())
        intrinsics = None
        depth_by_stamp: dict[int, Any] = {}
        bar = tqdm(total=reader.count(topic), unit="frame", desc="replay", disable=not progress, file=sys.stderr)
        with sigterm_as_interrupt(), BagWriter(out, force=force) as writer, bar:
            network_pose = localizer.refinement is not None
            copy_topics(reader, writer, output_types(localizer.has_segmentation, network_pose))
            for group in groups_by_log_time(reader.messages(raw=True)):
                images = []
                for t, ns, raw in group:
                    if t in ALL_OUTPUT_TYPES:
                        continue
                    writer.write_raw(t, ns, raw)
                    if t not in decoded:
                        continue
                    msg = messages.deserialize(raw, topics[t])
                    if t == CAMERA_INFO_TOPIC:
                        intrinsics = messages.intrinsics_from_camera_info(msg)
                    elif t == DEPTH_TOPIC:
                        depth_by_stamp[messages.stamp_ns(msg)] = msg
                        while len(depth_by_stamp) > 16:
                            del depth_by_stamp[min(depth_by_stamp)]
                    else:
                        images.append((ns, msg))
                for ns, msg in images:
                    try:
                        rgb = messages.any_image_to_rgb(msg)
                        depth_msg = depth_by_stamp.pop(messages.stamp_ns(msg), None) if use_depth else None
                        depth = (
                            None
                            if depth_msg is None
                            else depth_to_metres(messages.image_to_array(depth_msg), depth_msg.encoding)
                        )
                        result = localizer.step(
                            rgb, "rgb8", messages.stamp_ns(msg) / 1e9, depth=depth, intrinsics=intrinsics
                        )
                    except FrameError as err:
                        summary.skipped[err.reason] += 1
                        bar.update(1)
                        continue
                    if result.reset_reason is not None:
                        summary.resets[result.reset_reason] += 1
                    if network_pose:
                        summary.sources[result.source] += 1
                    for out_topic, out_msg in output_messages(result, msg, network_pose):
                        writer.write(out_topic, ns, out_msg)
                    summary.processed += 1
                    bar.update(1)
    summary.wall_s = time.perf_counter() - start
    return summary

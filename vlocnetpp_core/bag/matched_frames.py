"""Pass 1 of ``vlocnetpp evaluate-bag``: the frames of a bag that have a ground-truth pose and a ``/vlocnet/pose``
with the same stamp, their poses and odometry, split into sequences at gaps (:mod:`.evaluate_bag`'s docstring)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.pose_source import TfCollector
from vlocnetpp_core.bag.topics import (
    DEFAULT_MAX_GAP_S,
    GROUND_TRUTH_TOPIC,
    NETWORK_POSE_TOPIC,
    ODOMETRY_TOPIC,
    POSE_TOPIC,
    TF_STATIC_TOPIC,
    TF_TOPIC,
)
from vlocnetpp_core.errors import DataError
from vlocnetpp_core.geometry import matrix_to_quat, pose_to_matrix


@dataclass
class MatchedFrames:
    """The frames of a bag with ground truth and a global pose: ``stamps (N,)`` ns, poses ``(N, 3)`` /
    ``(N, 4)`` ``(w, x, y, z)``, odometry poses (rows NaN where missing) and ``sequences`` (ranges). ``pred``:
    the network's pose (``/vlocnet/network_pose`` when the bag has it, else ``/vlocnet/pose``); ``refined``: the
    published ``/vlocnet/pose`` of a bag with ``/vlocnet/network_pose``, else None."""

    stamps: np.ndarray
    true_t: np.ndarray
    true_q: np.ndarray
    pred_t: np.ndarray
    pred_q: np.ndarray
    odom_t: np.ndarray
    odom_q: np.ndarray
    sequences: list[range]
    refined_t: np.ndarray | None = None
    refined_q: np.ndarray | None = None


@dataclass(frozen=True)
class GroundTruth:
    """Where the true camera poses are: a pose ``topic``, or the TF chain ``tf = (PARENT, CHILD)`` composed with
    ``extrinsics = (t, q)`` ``T_CHILD,camera`` and interpolated to the frames' stamps (``max_pose_gap_s``)."""

    topic: str = GROUND_TRUTH_TOPIC
    tf: tuple[str, str] | None = None
    extrinsics: tuple[np.ndarray, np.ndarray] | None = None
    max_pose_gap_s: float = 0.5

    @property
    def topics(self) -> list[str]:
        return [TF_TOPIC, TF_STATIC_TOPIC] if self.tf is not None else [self.topic]


def split_on_gaps(stamps_ns: np.ndarray, max_gap_s: float) -> list[range]:
    """Contiguous ranges of sorted stamps; a new range starts after a gap longer than ``max_gap_s``."""
    if len(stamps_ns) == 0:
        return []
    cuts = np.nonzero(np.diff(stamps_ns) > max_gap_s * 1e9)[0] + 1
    bounds = [0, *cuts.tolist(), len(stamps_ns)]
    return [range(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def read_matched_frames(
    reader: BagReader, ground_truth: GroundTruth = GroundTruth(), max_gap_s: float = DEFAULT_MAX_GAP_S
) -> MatchedFrames:
    """Pass 1: the poses of every frame with ground truth and ``/vlocnet/pose`` (see module doc)."""
    for topic in (ground_truth.topics[0], POSE_TOPIC):
        if topic not in reader.topics:
            raise DataError(reader.path, f"no {topic} topic (topics: {', '.join(sorted(reader.topics)) or 'none'})")
    from_tf = ground_truth.tf is not None
    refined = NETWORK_POSE_TOPIC in reader.topics
    pose_topics = (
        [POSE_TOPIC, ODOMETRY_TOPIC]
        + ([NETWORK_POSE_TOPIC] if refined else [])
        + ([] if from_tf else [ground_truth.topic])
    )
    poses: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {t: {} for t in pose_topics}
    tf = TfCollector()
    for topic, _, msg in reader.messages({*pose_topics, *ground_truth.topics}):
        if topic in poses:
            poses[topic][messages.stamp_ns(msg)] = messages.stamped_pose(msg)
        else:
            tf.add(msg, static=topic == TF_STATIC_TOPIC)
    published, odom = poses[POSE_TOPIC], poses[ODOMETRY_TOPIC]
    pred = poses[NETWORK_POSE_TOPIC] if refined else published
    gt = _tf_poses_at(tf, ground_truth, sorted(pred)) if from_tf else poses[ground_truth.topic]
    stamps = np.array(sorted(gt.keys() & pred.keys() & published.keys()), dtype=np.int64)
    if len(stamps) == 0:
        raise DataError(
            reader.path,
            f"no {POSE_TOPIC} message has the stamp of a ground-truth pose "
            f"({'TF ' + ' -> '.join(ground_truth.tf) if from_tf else ground_truth.topic})",
        )
    nan_pose = (np.full(3, np.nan), np.full(4, np.nan))

    def column(source, part, width):
        return np.array([source.get(s, nan_pose)[part] for s in stamps.tolist()], dtype=np.float64).reshape(-1, width)

    return MatchedFrames(
        stamps,
        column(gt, 0, 3),
        column(gt, 1, 4),
        column(pred, 0, 3),
        column(pred, 1, 4),
        column(odom, 0, 3),
        column(odom, 1, 4),
        split_on_gaps(stamps, max_gap_s),
        column(published, 0, 3) if refined else None,
        column(published, 1, 4) if refined else None,
    )


def _tf_poses_at(
    tf: TfCollector, ground_truth: GroundTruth, stamps: list[int]
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The camera's true pose at each of ``stamps`` (ns) where the TF chain has one (see :class:`GroundTruth`)."""
    if not stamps:
        return {}
    t, q, reasons = tf.chain(*ground_truth.tf).camera_at(
        np.array(stamps, dtype=np.int64), ground_truth.max_pose_gap_s, ground_truth.extrinsics
    )
    return {s: (t[k], q[k]) for k, s in enumerate(stamps) if reasons[k] is None}


def relative_odometry(odom_t: np.ndarray, odom_q: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``T_{k-1}^{-1} T_k`` of consecutive odometry poses (row 0 identity), or None when any pose is missing."""
    if len(odom_t) == 0 or np.isnan(odom_t).any() or np.isnan(odom_q).any():
        return None
    T = pose_to_matrix(odom_t, odom_q)
    rel = np.broadcast_to(np.eye(4), T.shape).copy()
    rel[1:] = np.linalg.inv(T[:-1]) @ T[1:]
    return rel[:, :3, 3].copy(), matrix_to_quat(rel[:, :3, :3])

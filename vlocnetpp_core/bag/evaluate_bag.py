"""``vlocnetpp evaluate-bag``: the metrics of ``vlocnetpp evaluate`` from a bag that holds ground truth and localizer
outputs.

Frames are matched by ``header.stamp``: a frame is scored when the bag has a ground-truth pose
(``/ground_truth/pose``, or ``--ground-truth-topic``: ``PoseStamped``, ``PoseWithCovarianceStamped``
or ``Odometry``) and a ``/vlocnet/pose`` with the same stamp. A robot's bag has its ground truth
as TF instead: ``--tf PARENT CHILD`` (with ``--camera-extrinsics`` when CHILD is the robot, not the
camera) takes it from ``/tf`` and ``/tf_static`` as ``extract`` does, interpolated to the stamps of
``/vlocnet/pose`` (a frame further than ``--max-pose-gap`` from a TF sample is not scored). The matched frames are split
into sequences where consecutive stamps are more than ``--max-gap-s`` apart (default 1 s, the node's
``max_gap_s`` after which it resets its temporal state; the converter leaves 10 s between
sequences) and named
``seq-00``, ``seq-01``, ... in time order. Per sequence:

* global pose: ``/vlocnet/pose`` against the ground truth; when the bag has ``/vlocnet/network_pose`` (a localizer
  refining against a keyframe map) that is the network's pose (``pose``, the row ``overall (network)``) and
  ``/vlocnet/pose``, the published one (refined, propagated or the network's), is scored as ``pose_refined`` (the
  row ``refined``; same keys as ``pose``), on the frames that have both;
* odometry: the relative poses ``T_{k-1}^{-1} T_k`` between consecutive ``/vlocnet/odometry``
  poses (the localizer's accumulated odometry), chained from the true first pose as ``evaluate`` does;
* segmentation: ``/vlocnet/segmentation`` (``mono8`` class ids) against ``/camera/semantic`` when both
  exist, at the image resolution (as the node publishes masks and ``evaluate`` scores them). A bag
  without ``/vlocnet/segmentation`` (the replay of a pose-only model) gets no segmentation entries
  or columns, as ``evaluate`` of that model.

Baselines on the bag's camera images: ``--reference`` the retrieval row (the nearest reference image's pose),
``--map MAP.npz`` the structure-based row (retrieval + SIFT + PnP against the keyframe map, no network:
:meth:`vlocnetpp_core.mapping.refiner.Refiner.locate`, as ``evaluate --map``; intrinsics from ``/camera/camera_info``).

:func:`vlocnetpp_core.evaluation.metrics.evaluate_sequences` computes the report, so the numbers equal
``vlocnetpp evaluate`` on the same frames (timing is not in a bag: it is reported as ``-``).
The bag is read twice (poses, then label maps), streaming: label maps are never all in memory.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.image_baselines import describe_frames
from vlocnetpp_core.bag.pose_source import TfCollector
from vlocnetpp_core.bag.topics import (
    DEFAULT_MAX_GAP_S,
    GROUND_TRUTH_TOPIC,
    IMAGE_TOPICS,
    NETWORK_POSE_TOPIC,
    ODOMETRY_TOPIC,
    POSE_TOPIC,
    SEGMENTATION_TOPIC,
    SEMANTIC_TOPIC,
    TF_STATIC_TOPIC,
    TF_TOPIC,
)
from vlocnetpp_core.classes import CLASS_NAMES
from vlocnetpp_core.errors import DataError, UserError
from vlocnetpp_core.evaluation.metrics import DEFAULT_THRESHOLDS, SequenceResult, confusion_matrix, evaluate_sequences
from vlocnetpp_core.evaluation.report import (
    add_baseline,
    add_report_arguments,
    check_report_args,
    format_report,
    without_segmentation,
    write_outputs,
)
from vlocnetpp_core.geometry import matrix_to_quat, pose_to_matrix

_PENDING_LIMIT = 64  # label maps / masks waiting for their partner stamp (a partner never seen is dropped)


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


@dataclass
class SegmentationScores:
    """Pass 2 per sequence: ``confusion`` (or None without labels) and the ``samples`` kept for plots."""

    confusion: list[np.ndarray | None]
    samples: list[list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]]]


def score_segmentation(
    reader: BagReader, where: dict[int, tuple[int, int]], sample_stamps: set[int], num_classes: int = len(CLASS_NAMES)
) -> SegmentationScores:
    """Pass 2: ``/vlocnet/segmentation`` against ``/camera/semantic`` for the frames in ``where`` (stamp ->
    (sequence, position)); camera images are decoded only for ``sample_stamps``."""
    n_seq = 1 + max((k for k, _ in where.values()), default=-1)
    scores = SegmentationScores([None] * n_seq, [[] for _ in range(n_seq)])
    have_labels = SEMANTIC_TOPIC in reader.topics
    image_topic = next((t for t in IMAGE_TOPICS if t in reader.topics), None) if sample_stamps else None
    if SEGMENTATION_TOPIC not in reader.topics or not (have_labels or image_topic):
        return scores
    topics = [SEGMENTATION_TOPIC] + ([SEMANTIC_TOPIC] if have_labels else []) + ([image_topic] if image_topic else [])
    pending: dict[
        int, dict[str, np.ndarray]
    ] = {}  # stamp -> the parts that arrived (topics may be logged at different times)
    for topic, _, msg in reader.messages(topics):
        ns = messages.stamp_ns(msg)
        if ns not in where or (topic == image_topic and ns not in sample_stamps):
            continue
        parts = pending.setdefault(ns, {})
        parts[topic] = messages.any_image_to_rgb(msg) if topic == image_topic else messages.image_to_array(msg)
        needed = (
            [SEGMENTATION_TOPIC]
            + ([SEMANTIC_TOPIC] if have_labels else [])
            + ([image_topic] if image_topic and ns in sample_stamps else [])
        )
        if not all(t in parts for t in needed):
            if len(pending) > _PENDING_LIMIT:
                del pending[min(pending)]
            continue
        del pending[ns]
        k, position = where[ns]
        mask, labels, image = parts[SEGMENTATION_TOPIC], parts.get(SEMANTIC_TOPIC), parts.get(image_topic)
        for other, what in ((labels, SEMANTIC_TOPIC), (None if image is None else image[..., 0], image_topic)):
            if other is not None and other.shape != mask.shape:
                raise DataError(
                    reader.path,
                    f"at stamp {ns / 1e9:.9f} s the {SEGMENTATION_TOPIC} mask is {mask.shape[1]}x{mask.shape[0]} "
                    f"but {what} is {other.shape[1]}x{other.shape[0]} "
                    "(the localizer publishes masks at the image size)",
                )
        if labels is not None:
            conf = confusion_matrix(labels, mask, num_classes)
            scores.confusion[k] = conf if scores.confusion[k] is None else scores.confusion[k] + conf
        if image is not None:
            scores.samples[k].append((position, image, mask, labels))
    return scores


@dataclass
class BagResults:
    """What :func:`collect_bag` read: per sequence the ``results`` (the network's pose as the prediction), the published
    poses of a refining localizer (``refined``: ``(t (N_k, 3), q (N_k, 4))``, None without ``/vlocnet/network_pose``),
    the retrieval ``descriptors`` and the structure-based baseline's poses (``structure``), each None when not asked
    for; ``segmentation``: whether the bag has ``/vlocnet/segmentation``."""

    results: list[SequenceResult]
    refined: list[tuple[np.ndarray, np.ndarray]] | None = None
    descriptors: list[np.ndarray] | None = None
    structure: list[tuple[np.ndarray, np.ndarray]] | None = None
    segmentation: bool = True


def collect_bag(
    path: str | Path,
    ground_truth: GroundTruth = GroundTruth(),
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    samples: int = 0,
    num_classes: int = len(CLASS_NAMES),
    describe: bool = False,
    refiner=None,
) -> BagResults:
    """One :class:`SequenceResult` per sequence of the bag at ``path`` (see the module doc); ``samples`` frames per
    sequence are kept for the segmentation strip plot. With ``describe`` also the retrieval descriptors of each
    sequence's camera images, with ``refiner`` the structure-based baseline's poses (:func:`describe_frames`)."""
    from vlocnetpp_core.evaluation.report import sample_positions, sequence_name

    with BagReader(path) as reader:
        frames = read_matched_frames(reader, ground_truth, max_gap_s)
        where = {s: (k, p) for k, rng in enumerate(frames.sequences) for p, s in enumerate(frames.stamps[rng].tolist())}
        sample_stamps = {
            int(frames.stamps[rng[p]]) for rng in frames.sequences for p in sample_positions(len(rng), samples)
        }
        seg = score_segmentation(reader, where, sample_stamps, num_classes)
        descriptors, structure = (
            describe_frames(reader, where, refiner) if describe or refiner is not None else (None, None)
        )
        segmentation = SEGMENTATION_TOPIC in reader.topics
    out = BagResults(
        [], None if frames.refined_t is None else [], descriptors if describe else None, structure, segmentation
    )
    for k, rng in enumerate(frames.sequences):
        rel = relative_odometry(frames.odom_t[rng], frames.odom_q[rng])
        out.results.append(
            SequenceResult(
                name=sequence_name(k),
                stamps=frames.stamps[rng] / 1e9,
                true_t=frames.true_t[rng],
                true_q=frames.true_q[rng],
                pred_t=frames.pred_t[rng],
                pred_q=frames.pred_q[rng],
                rel_t=None if rel is None else rel[0],
                rel_q=None if rel is None else rel[1],
                confusion=seg.confusion[k],
                ms=None,
                samples=tuple(s[1:] for s in sorted(seg.samples[k], key=lambda s: s[0])),
            )
        )
        if out.refined is not None:
            out.refined.append((frames.refined_t[rng], frames.refined_q[rng]))
    return out


def collect_results(
    path: str | Path,
    ground_truth: GroundTruth = GroundTruth(),
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    samples: int = 0,
    num_classes: int = len(CLASS_NAMES),
    describe: bool = False,
) -> tuple[list[SequenceResult], list[np.ndarray] | None]:
    """``(results, descriptors)`` of :func:`collect_bag`."""
    bag = collect_bag(path, ground_truth, max_gap_s, samples, num_classes, describe)
    return bag.results, bag.descriptors


def add_refined_pose(
    report: dict,
    results: list[SequenceResult],
    poses: list[tuple[np.ndarray, np.ndarray]],
    thresholds=DEFAULT_THRESHOLDS,
) -> dict:
    """Score the published poses of a refining localizer (``/vlocnet/pose`` beside ``/vlocnet/network_pose``) on the
    frames of ``results`` as ``pose_refined`` (overall and per sequence; the keys of ``pose``), and store
    ``overall.refined_share``: the share of frames whose published pose is not the network's (refined or propagated)."""
    from vlocnetpp_core.mapping.evaluation import add_pose_refined

    add_pose_refined(report, results, poses, thresholds)
    changed = [
        np.any(t != r.pred_t, axis=1) | np.any(q != r.pred_q, axis=1) for r, (t, q) in zip(results, poses, strict=True)
    ]
    report["overall"]["refined_share"] = float(np.mean(np.concatenate(changed)))
    return report


def refined_share_line(report: dict) -> str | None:
    """One line under the table on how many published poses were not the network's, or None (no refinement)."""
    share = report["overall"].get("refined_share")
    if share is None:
        return None
    return (
        f"refined: {100 * share:.1f} % of the frames' {POSE_TOPIC} is not the network's {NETWORK_POSE_TOPIC} "
        "(refined against the map, or propagated by the odometry)"
    )


def bag_report(
    path: str | Path,
    ground_truth: GroundTruth = GroundTruth(),
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    samples: int = 0,
    thresholds=DEFAULT_THRESHOLDS,
    lengths: list[float] | None = None,
    reference=None,
    refiner=None,
) -> tuple[dict, list[SequenceResult]]:
    """``(report, results)`` of the bag at ``path`` (see the module doc): the network's pose, the refined one when the
    bag has ``/vlocnet/network_pose``, the retrieval baseline against ``reference`` (a
    :class:`~vlocnetpp_core.evaluation.retrieval.ReferenceSet`) and the structure-based one against ``refiner``'s map,
    on the same frames."""
    from vlocnetpp_core.mapping.evaluation import add_structure_baseline

    bag = collect_bag(path, ground_truth, max_gap_s, samples, describe=reference is not None, refiner=refiner)
    report = evaluate_sequences(bag.results, thresholds, lengths, CLASS_NAMES)
    if not bag.segmentation:
        without_segmentation(report, f"none: the bag has no {SEGMENTATION_TOPIC} (a model without a semantic stream)")
    if reference is not None:
        add_baseline(report, bag.results, bag.descriptors, reference, thresholds)
    if bag.refined is not None:
        add_refined_pose(report, bag.results, bag.refined, thresholds)
    if refiner is not None:
        add_structure_baseline(report, bag.results, bag.structure, refiner.map.source, len(refiner.map), thresholds)
    report["meta"] = {"bag": str(path)}
    return report, bag.results


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "bag", metavar="BAG", help="bag with ground truth and /vlocnet/* outputs (e.g. written by 'vlocnetpp replay')"
    )
    gt = p.add_mutually_exclusive_group()
    gt.add_argument(
        "--ground-truth-topic",
        default=GROUND_TRUTH_TOPIC,
        help="ground-truth camera poses: PoseStamped, "
        f"PoseWithCovarianceStamped or Odometry (default {GROUND_TRUTH_TOPIC})",
    )
    gt.add_argument(
        "--tf",
        nargs=2,
        metavar=("PARENT", "CHILD"),
        default=None,
        help="ground truth from /tf and /tf_static instead: the pose of CHILD in PARENT (e.g. map base_link), "
        "interpolated to the frames' stamps",
    )
    p.add_argument(
        "--camera-extrinsics",
        metavar="X,Y,Z,QW,QX,QY,QZ",
        default=None,
        help="with --tf: the camera's pose in CHILD (metres, "
        "unit quaternion), when CHILD is the robot and not the camera",
    )
    p.add_argument(
        "--max-pose-gap",
        type=float,
        default=0.5,
        metavar="S",
        help="with --tf: a frame more than S seconds from a TF sample is not scored (default 0.5)",
    )
    p.add_argument(
        "--max-gap-s",
        type=float,
        default=DEFAULT_MAX_GAP_S,
        help=f"a stamp gap longer than this starts a new sequence (default {DEFAULT_MAX_GAP_S:g} s)",
    )
    add_report_arguments(
        p,
        "retrieval baseline reference: the training dataset folder of the model (its train split) or a .npz "
        "from ReferenceSet.save, e.g. models/vlocnetpp_lite.reference.npz (default: no baseline)",
    )
    p.add_argument(
        "--map",
        default=None,
        metavar="MAP.npz",
        help="keyframe map (vlocnetpp map build, "
        "e.g. models/vlocnetpp_lite.map.npz): adds the structure-based baseline "
        "(retrieval + SIFT + PnP against the map, no network) on the bag's images; needs /camera/camera_info",
    )


def ground_truth_of(args: argparse.Namespace) -> GroundTruth:
    """The :class:`GroundTruth` of the command line (``--camera-extrinsics`` checked as the node's)."""
    if args.tf is None and args.camera_extrinsics is not None:
        raise UserError("--camera-extrinsics applies with --tf PARENT CHILD (a ground-truth topic holds camera poses)")
    from vlocnetpp_core.bag.extract import parse_extrinsics

    extrinsics = parse_extrinsics(args.camera_extrinsics) if args.camera_extrinsics is not None else None
    return GroundTruth(args.ground_truth_topic, tuple(args.tf) if args.tf else None, extrinsics, args.max_pose_gap)


def run(args: argparse.Namespace) -> int:
    from vlocnetpp_core.evaluation.retrieval import open_reference
    from vlocnetpp_core.inference.checkpoint import MAP_AUTO

    if not (math.isfinite(args.max_gap_s) and args.max_gap_s > 0):
        raise UserError(f"--max-gap-s must be a positive number of seconds, got {args.max_gap_s}")
    if args.map == MAP_AUTO:
        raise UserError(
            f"--map {MAP_AUTO}: evaluate-bag has no checkpoint to find NAME.map.npz beside; give the map file"
        )
    thresholds, lengths = check_report_args(args)
    reference = open_reference(args.reference) if args.reference else None
    refiner = None
    if args.map is not None:
        from vlocnetpp_core.mapping.refiner import Refiner

        refiner = Refiner.from_file(args.map)
    report, results = bag_report(
        args.bag,
        ground_truth_of(args),
        args.max_gap_s,
        args.samples if args.plots else 0,
        thresholds,
        lengths,
        reference,
        refiner,
    )
    print(format_report(report, {r.name: len(r.stamps) for r in results}))
    if refined_share_line(report):
        print(refined_share_line(report))
    if any(r.rel_t is None for r in results):
        print(
            f"note: {ODOMETRY_TOPIC} missing for some frames: no odometry metrics for those sequences", file=sys.stderr
        )
    write_outputs(report, results, CLASS_NAMES, args.json, args.trajectories, args.plots)
    return 0

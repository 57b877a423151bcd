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

from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.image_baselines import describe_frames
from vlocnetpp_core.bag.matched_frames import GroundTruth, read_matched_frames, relative_odometry
from vlocnetpp_core.bag.segmentation_scores import score_segmentation
from vlocnetpp_core.bag.topics import (
    DEFAULT_MAX_GAP_S,
    GROUND_TRUTH_TOPIC,
    NETWORK_POSE_TOPIC,
    ODOMETRY_TOPIC,
    POSE_TOPIC,
    SEGMENTATION_TOPIC,
)
from vlocnetpp_core.classes import CLASS_NAMES
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.evaluation.metrics import DEFAULT_THRESHOLDS, SequenceResult, evaluate_sequences
from vlocnetpp_core.evaluation.report import (
    add_baseline,
    add_report_arguments,
    check_report_args,
    format_report,
    without_segmentation,
    write_outputs,
)


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
    from vlocnetpp_core.bag.extract_cli import parse_extrinsics

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

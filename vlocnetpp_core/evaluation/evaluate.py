"""``vlocnetpp evaluate``: run a checkpoint over a dataset split frame by frame and score it.

Every sequence is streamed through :class:`vlocnetpp_core.inference.localizer.Localizer`, the code path of
the ROS node: raw RGB frames in, one ``step`` per frame, the temporal state reset at each sequence
start. Per frame the global pose, the predicted relative pose, the class-id mask and the wall time
of ``step`` are recorded; :func:`vlocnetpp_core.evaluation.metrics.evaluate_sequences` turns them into the
report (pose, KITTI-style odometry, segmentation, timing; see ``metrics``), which is printed as a
table and optionally written as JSON, TUM trajectories and plots (``vlocnetpp_core.evaluation.report``).

Beside the network, the nearest-neighbour retrieval baseline (``vlocnetpp_core.evaluation.retrieval``) is
scored on the same frames: the pose of the most similar image of ``--reference`` (default: the
training split of ``--data``), as a row under the table and as ``baseline`` in the JSON.

Segmentation is scored at the dataset image resolution: the localizer brings its class-id mask
back to the size of the image it was given (nearest neighbour), as the node publishes it. A pose-only
checkpoint (no semantic stream) has no mask: its report has no ``segmentation`` entries and the table
no segmentation columns (:func:`vlocnetpp_core.evaluation.report.without_segmentation`).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from vlocnetpp_core.classes import CLASS_NAMES
from vlocnetpp_core.data.formats import FORMATS
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.evaluation.metrics import SequenceRecorder, SequenceResult, evaluate_sequences
from vlocnetpp_core.evaluation.report import (
    add_baseline,
    add_frame_poses,
    add_report_arguments,
    check_report_args,
    format_report,
    sample_positions,
    sequence_name,
    without_segmentation,
    write_outputs,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--checkpoint", required=True, help="checkpoint (NAME.safetensors or NAME; the NAME.json sidecar next to it)"
    )
    p.add_argument("--data", required=True, help="dataset folder (DeepLoc layout or 7-Scenes)")
    p.add_argument("--format", choices=FORMATS, default=None, help="dataset format (default: detected from the layout)")
    p.add_argument("--split", default="test", help="split to evaluate (default: test)")
    p.add_argument(
        "--intrinsics",
        default=None,
        metavar="FX,FY,CX,CY",
        help="camera intrinsics at the dataset image size (default: the reader's)",
    )
    add_report_arguments(
        p,
        "retrieval baseline reference: a dataset folder (its training images) or a .npz from ReferenceSet.save "
        "(default: the train split of --data when another split is evaluated)",
    )
    p.add_argument(
        "--map",
        default=None,
        metavar="MAP",
        help="keyframe map (vlocnetpp map build) to refine the network's pose against; "
        "adds the refined row (overall.pose_refined in the JSON) and the structure-based baseline (no network)",
    )
    p.add_argument(
        "--refine-every",
        type=int,
        default=1,
        metavar="K",
        help="with --map: refine every K-th frame, propagate "
        "the refined pose with the odometry in between (default 1: every frame)",
    )
    p.add_argument(
        "--use-depth",
        action="store_true",
        help="give the dataset depth to the localizer (as the node's "
        "aligned depth input) instead of the predicted depth",
    )
    p.add_argument(
        "--max-frames", type=int, default=None, metavar="N", help="evaluate at most the first N frames of each sequence"
    )
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _check_mask(frame, mask: np.ndarray) -> None:
    if mask.shape != frame.image.shape[:2]:
        raise UserError(
            f"the localizer returned a {mask.shape[1]}x{mask.shape[0]} mask for the "
            f"{frame.image.shape[1]}x{frame.image.shape[0]} image {frame.frame_id}"
        )


@dataclass
class LocalizerRun:
    """What :func:`run_localizer` measured: per-sequence ``results`` (the network's global pose, fused with its
    odometry when the localizer does, as the prediction),
    frames ``rejected`` per reason, the retrieval ``descriptors (N_k, D)`` of each result's frames (or None), the
    published poses of a refining localizer (``tracks``, or None) and the structure-based baseline's poses per
    result (``structure``: ``(t (N_k, 3), q (N_k, 4))``, or None), and the network's pose of each frame alone when the
    localizer fuses it with the odometry (``frame_poses``, shaped like ``structure``, or None)."""

    results: list[SequenceResult]
    rejected: dict[str, int]
    descriptors: list[np.ndarray] | None = None
    tracks: list | None = None
    structure: list[tuple[np.ndarray, np.ndarray]] | None = None
    frame_poses: list[tuple[np.ndarray, np.ndarray]] | None = None


def run_localizer(
    localizer,
    index,
    max_frames: int | None = None,
    samples: int = 3,
    use_depth: bool = False,
    progress: bool = True,
    describe: bool = False,
    structure=None,
) -> LocalizerRun:
    """Stream every sequence of ``index`` (a ``DatasetIndex``) through ``localizer`` (a ``Localizer``).

    The temporal state is reset at each sequence start. Frames the localizer rejects
    (``FrameError``, e.g. non-finite outputs) are left out, as the node drops them. With ``describe`` the
    retrieval descriptors of the frames are kept (:func:`vlocnetpp_core.evaluation.retrieval.describe`); with
    ``structure`` (a :class:`~vlocnetpp_core.mapping.refiner.Refiner`) the structure-based baseline runs on the same
    frames. ``ms`` is the localizer's own wall time of ``step`` (decoding the dataset files is not included).
    """
    from tqdm import tqdm

    from vlocnetpp_core.evaluation.retrieval import describe as describe_image
    from vlocnetpp_core.inference.preprocess import FrameError
    from vlocnetpp_core.mapping.evaluation import RefinedTrack

    ranges = [r if max_frames is None else r[:max_frames] for r in index.sequences]
    bar = tqdm(
        total=sum(len(r) for r in ranges), unit="frame", desc="evaluate", disable=not progress, dynamic_ncols=True
    )
    run = LocalizerRun(
        [],
        {},
        [] if describe else None,
        [] if localizer.refinement is not None else None,
        [] if structure is not None else None,
        [] if localizer.fusion is not None else None,
    )
    try:
        for rng in ranges:
            if len(rng) == 0:
                continue
            name = sequence_name(index.records[rng[0]].sequence)
            bar.set_postfix_str(name)
            recorder = SequenceRecorder(name, localizer.num_classes)
            keep = {rng[p] for p in sample_positions(len(rng), samples)}
            localizer.reset("start")
            described, track, located, single = [], RefinedTrack(), [], []
            for i in rng:
                frame = index.load(i, depth=use_depth)
                bar.update(1)
                try:
                    out = localizer.step(
                        frame.image,
                        "rgb8",
                        frame.stamp,
                        depth=frame.depth if use_depth else None,
                        intrinsics=frame.intrinsics,
                    )
                except FrameError as err:
                    run.rejected[err.reason] = run.rejected.get(err.reason, 0) + 1
                    continue
                if describe or structure is not None:
                    described.append(describe_image(frame.image))
                if structure is not None:
                    located.append(structure.locate_image(frame.image, frame.intrinsics, described[-1])[:2])
                track.add(out)
                if run.frame_poses is not None:
                    single.append((out.frame_t, out.frame_q))
                recorder.add(
                    frame.stamp,
                    frame.t,
                    frame.q,
                    out.network_t,
                    out.network_q,
                    out.rel_t,
                    out.rel_q,
                    out.seconds * 1000.0,
                )
                if out.mask is None:  # a pose-only model
                    continue
                _check_mask(frame, out.mask)
                if frame.labels is not None:
                    recorder.add_labels(frame.labels, out.mask)
                if i in keep:
                    recorder.add_sample(frame.image, out.mask, frame.labels)
            if len(recorder):
                run.results.append(recorder.result())
                if describe:
                    run.descriptors.append(np.stack(described))
                if run.tracks is not None:
                    run.tracks.append(track)
                if structure is not None:
                    run.structure.append(_stacked(located))
                if run.frame_poses is not None:
                    run.frame_poses.append(_stacked(single))
    finally:
        bar.close()
    return run


def _stacked(poses: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame ``(t (3,), q (4,))`` pairs as ``(t (N, 3), q (N, 4))``."""
    t, q = zip(*poses, strict=True)
    return np.array(t), np.array(q)


def run(args: argparse.Namespace) -> int:
    if args.max_frames is not None and args.max_frames < 1:
        raise UserError(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.refine_every < 1:
        raise UserError(f"--refine-every must be >= 1, got {args.refine_every}")
    thresholds, lengths = check_report_args(args)

    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.inference.localizer import Localizer
    from vlocnetpp_core.mapping.evaluation import add_refined, add_structure_baseline
    from vlocnetpp_core.model.stages import TASK_NAMES

    index = open_dataset(args.data, args.format, args.split, args.intrinsics)
    if len(index) == 0:
        raise UserError(f"{args.data}: split {args.split!r} has no frames")
    reference = _reference(args, index.format)
    localizer = Localizer.from_checkpoint(
        args.checkpoint, device=args.device, map_path=args.map, refine_every=args.refine_every
    )
    structure = None
    if args.map is not None:
        from vlocnetpp_core.mapping.refiner import Refiner

        structure = Refiner(localizer.refinement.refiner.map)
    run = run_localizer(
        localizer,
        index,
        args.max_frames,
        args.samples,
        args.use_depth,
        progress=not args.no_progress,
        describe=reference is not None,
        structure=structure,
    )
    results, rejected = run.results, run.rejected
    if not results:
        raise UserError(f"{args.checkpoint}: the localizer rejected every frame ({rejected})")
    class_names = (
        localizer.class_names
        if len(localizer.class_names) == localizer.num_classes
        else CLASS_NAMES[: localizer.num_classes]
    )

    report = evaluate_sequences(results, thresholds, lengths, class_names)
    if not localizer.has_segmentation:
        without_segmentation(report, "none: the model has no semantic stream (a pose-only config)")
    if run.frame_poses is not None:
        add_frame_poses(report, results, run.frame_poses, thresholds)
    if reference is not None:
        add_baseline(report, results, run.descriptors, reference, thresholds)
    if structure is not None:
        add_refined(report, results, run.tracks, thresholds)
        add_structure_baseline(report, results, run.structure, structure.map.source, len(structure.map), thresholds)
    tasks = localizer.model.config.tasks
    untrained = untrained_tasks(localizer.meta, tasks)
    report["meta"] = {
        "checkpoint": str(args.checkpoint),
        "data": str(args.data),
        "split": args.split,
        "tasks": list(tasks),
        "untrained_tasks": untrained,
    }
    print(format_report(report, {r.name: len(r.stamps) for r in results}))
    if reference is None:
        print(
            "note: no retrieval baseline: --data has no other split "
            f"than {args.split!r} to look frames up in; give --reference"
        )
    if untrained:
        print(
            f"note: {args.checkpoint} was not trained for {', '.join(TASK_NAMES[t] for t in untrained)} (stage "
            f"{localizer.meta['training'].get('stage')} and its --init checkpoints): "
            "those columns are an untrained network's"
        )
    if rejected:
        print(
            "frames rejected by the localizer (left out): " + ", ".join(f"{k} {v}" for k, v in sorted(rejected.items()))
        )
    write_outputs(report, results, class_names, args.json, args.trajectories, args.plots, run.frame_poses)
    return 0


def _reference(args: argparse.Namespace, format: str):
    """The retrieval reference: ``--reference``, else the train split of ``--data`` when another split is
    evaluated and a train split exists; None otherwise."""
    from vlocnetpp_core.data.dataset import available_splits
    from vlocnetpp_core.evaluation.retrieval import open_reference

    if args.reference:
        return open_reference(args.reference, progress=not args.no_progress)
    if args.split != "train" and "train" in available_splits(args.data, format):
        return open_reference(args.data, format, "train", progress=not args.no_progress)
    return None


def untrained_tasks(meta: dict, model_tasks: tuple[str, ...] | None = None) -> list[str] | None:
    """Tasks of the network (``model_tasks``, ``ModelConfig.tasks``: ``loc``, ``vo``, and ``seg`` unless
    pose-only; default all three) the checkpoint with sidecar ``meta`` was not trained for; None when its
    sidecar does not say how it was trained."""
    from vlocnetpp_core.model.assembly import trained_tasks
    from vlocnetpp_core.model.config import TASKS

    model_tasks = TASKS if model_tasks is None else model_tasks
    trained = trained_tasks(meta.get("training") or {}, model_tasks)
    return None if trained is None else [t for t in model_tasks if t not in trained]

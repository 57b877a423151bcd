"""``vlocnetpp evaluate``: run a checkpoint over a dataset split frame by frame and score it.

Every sequence is streamed through :class:`vlocnetpp_core.localizer.Localizer`, the code path of
the ROS node: raw RGB frames in, one ``step`` per frame, the temporal state reset at each sequence
start. Per frame the global pose, the predicted relative pose, the class-id mask and the wall time
of ``step`` are recorded; :func:`vlocnetpp_core.metrics.evaluate_sequences` turns them into the
report (pose, KITTI-style odometry, segmentation, timing; see ``metrics``), which is printed as a
table and optionally written as JSON, TUM trajectories and plots.

Segmentation is scored at the dataset image resolution: the localizer brings its class-id mask
back to the size of the image it was given (nearest neighbour), as the node publishes it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from vlocnetpp_core.classes import CLASS_NAMES
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.metrics import DEFAULT_THRESHOLDS, SequenceRecorder, SequenceResult, accuracy_key, evaluate_sequences


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", required=True, help="checkpoint (NAME.safetensors or NAME; the NAME.json sidecar next to it)")
    p.add_argument("--data", required=True, help="dataset folder (DeepLoc layout or 7-Scenes)")
    p.add_argument("--format", choices=("deeploc", "7scenes"), default=None, help="dataset format (default: detected from the layout)")
    p.add_argument("--split", default="test", help="split to evaluate (default: test)")
    p.add_argument("--intrinsics", default=None, metavar="FX,FY,CX,CY", help="camera intrinsics at the dataset image size (default: the reader's)")
    p.add_argument("--json", default=None, metavar="OUT", help="write the metrics as JSON to OUT")
    p.add_argument("--trajectories", default=None, metavar="DIR", help="write TUM trajectories per sequence (global_pose.tum, odometry.tum, ground_truth.tum)")
    p.add_argument("--plots", default=None, metavar="DIR", help="write PNG plots (trajectories, errors, confusion matrix, segmentation strip)")
    p.add_argument("--threshold-m", type=float, default=0.5, help="translation threshold of the second pose accuracy (default 0.5 m; 5 cm / 5 deg is always reported)")
    p.add_argument("--threshold-deg", type=float, default=5.0, help="rotation threshold of the second pose accuracy (default 5 deg)")
    p.add_argument("--odometry-lengths", default=None, metavar="L1,L2,...",
                   help="KITTI-style segment lengths in metres (default: 10%%..80%% of the shortest sequence's path)")
    p.add_argument("--use-depth", action="store_true", help="give the dataset depth to the localizer (as the node's aligned depth input) instead of the predicted depth")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="evaluate at most the first N frames of each sequence")
    p.add_argument("--samples", type=int, default=3, metavar="K", help="frames per sequence in the segmentation strip plot (default 3)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def positive_flag(value: float, flag: str) -> float:
    if not (math.isfinite(value) and value > 0):
        raise UserError(f"{flag} must be a positive number, got {value}")
    return value


def parse_lengths(text: str | None) -> list[float] | None:
    """``"1,2.5,4"`` -> ``[1.0, 2.5, 4.0]`` (positive metres); None stays None."""
    if text is None:
        return None
    try:
        lengths = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UserError(f"--odometry-lengths must be comma-separated metres, got {text!r}") from None
    if not lengths:
        raise UserError("--odometry-lengths is empty")
    for v in lengths:
        positive_flag(v, "--odometry-lengths")
    return lengths


def sequence_name(sequence_id: int) -> str:
    """Folder / JSON name of a sequence: ``seq-XX``."""
    return f"seq-{sequence_id:02d}"


def sample_positions(n: int, k: int) -> set[int]:
    return set(np.linspace(0, n - 1, k).round().astype(int).tolist()) if n > 0 and k > 0 else set()


def _check_mask(frame, mask: np.ndarray) -> None:
    if mask.shape != frame.image.shape[:2]:
        raise UserError(f"the localizer returned a {mask.shape[1]}x{mask.shape[0]} mask for the "
                        f"{frame.image.shape[1]}x{frame.image.shape[0]} image {frame.frame_id}")


def run_localizer(localizer, index, max_frames: int | None = None, samples: int = 3, use_depth: bool = False,
                  progress: bool = True) -> tuple[list[SequenceResult], dict[str, int]]:
    """Stream every sequence of ``index`` (a ``DatasetIndex``) through ``localizer`` (a ``Localizer``).

    The temporal state is reset at each sequence start. Frames the localizer rejects
    (``FrameError``, e.g. non-finite outputs) are left out, as the node drops them; the count per
    reason is returned with the per-sequence results. ``ms`` is the localizer's own wall time of
    ``step`` (decoding the dataset files is not included).
    """
    from tqdm import tqdm

    from vlocnetpp_core.preprocess import FrameError

    ranges = [r if max_frames is None else r[:max_frames] for r in index.sequences]
    bar = tqdm(total=sum(len(r) for r in ranges), unit="frame", desc="evaluate", disable=not progress, dynamic_ncols=True)
    results: list[SequenceResult] = []
    rejected: dict[str, int] = {}
    try:
        for rng in ranges:
            if len(rng) == 0:
                continue
            name = sequence_name(index.records[rng[0]].sequence)
            bar.set_postfix_str(name)
            recorder = SequenceRecorder(name, localizer.num_classes)
            keep = {rng[p] for p in sample_positions(len(rng), samples)}
            localizer.reset("start")
            for i in rng:
                frame = index.load(i)
                bar.update(1)
                try:
                    out = localizer.step(frame.image, "rgb8", frame.stamp, depth=frame.depth if use_depth else None, intrinsics=frame.intrinsics)
                except FrameError as err:
                    rejected[err.reason] = rejected.get(err.reason, 0) + 1
                    continue
                _check_mask(frame, out.mask)
                recorder.add(frame.stamp, frame.t, frame.q, out.t, out.q, out.rel_t, out.rel_q, out.seconds * 1000.0)
                if frame.labels is not None:
                    recorder.add_labels(frame.labels, out.mask)
                if i in keep:
                    recorder.add_sample(frame.image, out.mask, frame.labels)
            if len(recorder):
                results.append(recorder.result())
    finally:
        bar.close()
    return results, rejected


# --------------------------------------------------------------------------- output


def _pct(v: float | None, digits: int = 1) -> str:
    return "-" if v is None else f"{100.0 * v:.{digits}f}"


def _num(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def format_report(report: dict, frames: dict[str, int] | None = None) -> str:
    """A readable table: per sequence and overall median errors, pose accuracies, odometry errors, mIoU, ms/frame."""
    overall = report["overall"]
    acc_keys = [k for k in overall["pose"] if k.startswith("accuracy_")]
    headers = ["sequence", "frames", "median t [m]", "median R [deg]"]
    headers += [k.removeprefix("accuracy_").replace("_", "/") + " [%]" for k in acc_keys]
    headers += ["VO t [%]", "VO R [deg/m]", "mIoU [%]", "pix acc [%]", "ms/frame"]
    frames = frames or {}

    def row(name: str, part: dict, n: int | None) -> list[str]:
        pose, odo, seg, tim = part["pose"], part["odometry"], part["segmentation"], part["timing"]
        return [
            name,
            "-" if n is None else str(n),
            _num(pose["median_translation_m"], ".3f"),
            _num(pose["median_rotation_deg"], ".2f"),
            *[_pct(pose[k]) for k in acc_keys],
            _num(odo["translation_error_percent"], ".2f"),
            _num(odo["rotation_error_deg_per_m"], ".3f"),
            _pct(seg["miou"]),
            _pct(seg["pixel_accuracy"]),
            _num(tim["mean_ms"], ".1f"),
        ]

    rows = [row(name, part, frames.get(name)) for name, part in report["per_sequence"].items()]
    total = sum(frames.values()) if frames else None
    rows.append(row("overall", overall, total))
    widths = [max(len(h), *(len(r[c]) for r in rows)) for c, h in enumerate(headers)]
    fmt = "  ".join(f"{{:<{w}}}" if c == 0 else f"{{:>{w}}}" for c, w in enumerate(widths))
    lines = [fmt.format(*headers), "  ".join("-" * w for w in widths)]
    lines += [fmt.format(*r) for r in rows[:-1]] + ["  ".join("-" * w for w in widths), fmt.format(*rows[-1])]
    lengths = overall["odometry"]["lengths_m"]
    lines.append(f"odometry segment lengths [m]: {', '.join(f'{v:g}' for v in lengths) if lengths else '- (sequences too short)'}")
    iou = {k: v for k, v in overall["segmentation"]["iou"].items() if v is not None}
    if iou:
        lines.append("IoU [%] (overall): " + ", ".join(f"{k} {100 * v:.1f}" for k, v in iou.items()))
    tim = overall["timing"]
    if tim["median_ms"] is not None:
        lines.append(f"time per frame: mean {tim['mean_ms']:.1f} ms, median {tim['median_ms']:.1f} ms")
    return "\n".join(lines)


def write_json(path: str | Path, data: dict) -> None:
    """Write ``data`` as indented JSON, atomically (temporary file renamed into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
    os.replace(tmp, path)


def write_trajectories(folder: str | Path, results: Iterable[SequenceResult]) -> list[Path]:
    """``<folder>/<seq>/{ground_truth,global_pose,odometry}.tum`` (odometry only when predicted)."""
    from vlocnetpp_core.trajectory import write_tum

    written = []
    for r in results:
        sub = Path(folder) / r.name
        for name, traj in (("ground_truth", r.ground_truth()), ("global_pose", r.global_pose()), ("odometry", r.odometry())):
            if traj is not None:
                write_tum(sub / f"{name}.tum", traj)
                written.append(sub / f"{name}.tum")
    return written


def _check_outputs(args: argparse.Namespace) -> None:
    """Fail before the (long) run when an output path cannot be written."""
    if args.json and Path(args.json).is_dir():
        raise UserError(f"--json {args.json}: is a folder; give a file name")
    for flag, folder in (("--trajectories", args.trajectories), ("--plots", args.plots)):
        if folder and Path(folder).exists() and not Path(folder).is_dir():
            raise UserError(f"{flag} {folder}: exists and is not a folder")


def run(args: argparse.Namespace) -> int:
    threshold = (positive_flag(args.threshold_m, "--threshold-m"), positive_flag(args.threshold_deg, "--threshold-deg"))
    thresholds = list(DEFAULT_THRESHOLDS[:1]) + ([threshold] if accuracy_key(*threshold) != accuracy_key(*DEFAULT_THRESHOLDS[0]) else [])
    lengths = parse_lengths(args.odometry_lengths)
    if args.max_frames is not None and args.max_frames < 1:
        raise UserError(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.samples < 0:
        raise UserError(f"--samples must be >= 0, got {args.samples}")
    _check_outputs(args)

    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.localizer import Localizer
    from vlocnetpp_core.model.stages import TASK_NAMES

    index = open_dataset(args.data, args.format, args.split, args.intrinsics)
    if len(index) == 0:
        raise UserError(f"{args.data}: split {args.split!r} has no frames")
    localizer = Localizer.from_checkpoint(args.checkpoint, device=args.device)
    results, rejected = run_localizer(localizer, index, args.max_frames, args.samples, args.use_depth, progress=not args.no_progress)
    if not results:
        raise UserError(f"{args.checkpoint}: the localizer rejected every frame ({rejected})")
    class_names = localizer.class_names if len(localizer.class_names) == localizer.num_classes else CLASS_NAMES[: localizer.num_classes]

    report = evaluate_sequences(results, thresholds, lengths, class_names)
    untrained = untrained_tasks(localizer.meta)
    report["meta"] = {"checkpoint": str(args.checkpoint), "data": str(args.data), "split": args.split, "untrained_tasks": untrained}
    print(format_report(report, {r.name: len(r.stamps) for r in results}))
    if untrained:
        print(f"note: {args.checkpoint} was not trained for {', '.join(TASK_NAMES[t] for t in untrained)} (stage "
              f"{localizer.meta['training'].get('stage')} and its --init checkpoints): those columns are an untrained network's")
    if rejected:
        print("frames rejected by the localizer (left out): " + ", ".join(f"{k} {v}" for k, v in sorted(rejected.items())))
    write_outputs(report, results, class_names, args.json, args.trajectories, args.plots)
    return 0


def untrained_tasks(meta: dict) -> list[str] | None:
    """Tasks (``loc``, ``vo``, ``seg``) the checkpoint with sidecar ``meta`` was not trained for; None when its
    sidecar does not say how it was trained."""
    from vlocnetpp_core.model.stages import TASK_NAMES
    from vlocnetpp_core.train import trained_tasks

    trained = trained_tasks(meta.get("training") or {})
    return None if trained is None else [t for t in TASK_NAMES if t not in trained]


def write_outputs(report: dict, results: list[SequenceResult], class_names: Sequence[str], json_path: str | Path | None = None,
                  trajectories: str | Path | None = None, plots: str | Path | None = None) -> None:
    """Write the report as JSON, the TUM trajectories and the plots, where asked, and say where they went."""
    if json_path:
        write_json(json_path, report)
        print(f"metrics: {json_path}")
    if trajectories:
        write_trajectories(trajectories, results)
        print(f"trajectories (TUM): {trajectories}")
    if plots:
        from vlocnetpp_core.plots import write_plots

        write_plots(plots, results, class_names)
        print(f"plots: {plots}")

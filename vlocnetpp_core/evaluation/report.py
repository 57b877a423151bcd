"""The evaluation report shared by ``evaluate``, ``evaluate-bag`` and ``demo``: flags, table, baseline, files.

A report is the dict of :func:`vlocnetpp_core.evaluation.metrics.evaluate_sequences` (``overall`` and
``per_sequence``, each with ``pose``, ``odometry``, ``segmentation``, ``timing``) plus ``meta``
and, when a retrieval reference was given, ``baseline``: the same pose metrics for the
nearest-neighbour retrieval baseline (:mod:`vlocnetpp_core.evaluation.retrieval`) on the same frames, and
whether the network beats it (``network_beats_baseline``: translation and rotation medians), and
``frame_network``: the network's global pose of each frame alone when the localizer fused it with its odometry. A
report of a model without segmentation (pose-only) has no ``segmentation`` entries but a
``segmentation_note`` saying why (:func:`without_segmentation`); its table has no segmentation columns.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.evaluation.metrics import DEFAULT_THRESHOLDS, SequenceResult, accuracy_key, evaluate_sequences

BASELINE_NAME = "retrieval"
BASELINE_METHOD = (
    "pose of the nearest reference image (gradient thumbnails, cosine similarity; vlocnetpp_core.evaluation.retrieval)"
)


# --------------------------------------------------------------------------- flags


def add_report_arguments(p: argparse.ArgumentParser, reference_help: str) -> None:
    """The output, threshold and baseline flags common to ``evaluate`` and ``evaluate-bag``."""
    p.add_argument("--json", default=None, metavar="OUT", help="write the metrics as JSON to OUT")
    p.add_argument(
        "--trajectories",
        default=None,
        metavar="DIR",
        help="write TUM trajectories per sequence (global_pose.tum, odometry.tum, ground_truth.tum)",
    )
    p.add_argument(
        "--plots",
        default=None,
        metavar="DIR",
        help="write PNG plots (trajectories, errors, confusion matrix, segmentation strip)",
    )
    p.add_argument(
        "--threshold-m",
        type=float,
        default=0.5,
        help="translation threshold of a further pose accuracy (default 0.5 m; "
        "5 cm / 5 deg and 0.5 m / 5 deg are always reported)",
    )
    p.add_argument(
        "--threshold-deg",
        type=float,
        default=5.0,
        help="rotation threshold of that further pose accuracy (default 5 deg)",
    )
    p.add_argument(
        "--odometry-lengths",
        default=None,
        metavar="L1,L2,...",
        help="KITTI-style segment lengths in metres (default: 10%%..80%% of the shortest sequence's path)",
    )
    p.add_argument(
        "--samples",
        type=int,
        default=3,
        metavar="K",
        help="frames per sequence in the segmentation strip plot (default 3)",
    )
    p.add_argument("--reference", default=None, metavar="DIR|FILE.npz", help=reference_help)


def positive_flag(value: float, flag: str) -> float:
    if not (math.isfinite(value) and value > 0):
        raise UserError(f"{flag} must be a positive number, got {value}")
    return value


def thresholds_from_args(args: argparse.Namespace) -> list[tuple[float, float]]:
    """5 cm / 5 deg, 0.5 m / 5 deg and ``--threshold-m/--threshold-deg`` (each once)."""
    threshold = (positive_flag(args.threshold_m, "--threshold-m"), positive_flag(args.threshold_deg, "--threshold-deg"))
    keys = {accuracy_key(*t) for t in DEFAULT_THRESHOLDS}
    return list(DEFAULT_THRESHOLDS) + ([threshold] if accuracy_key(*threshold) not in keys else [])


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


def check_report_args(args: argparse.Namespace) -> tuple[list[tuple[float, float]], list[float] | None]:
    """The pose thresholds and odometry lengths of the flags; fails before a (long) run when a flag is
    invalid or an output path cannot be written."""
    thresholds, lengths = thresholds_from_args(args), parse_lengths(args.odometry_lengths)
    if args.samples < 0:
        raise UserError(f"--samples must be >= 0, got {args.samples}")
    if args.json and Path(args.json).is_dir():
        raise UserError(f"--json {args.json}: is a folder; give a file name")
    for flag, folder in (("--trajectories", args.trajectories), ("--plots", args.plots)):
        if folder and Path(folder).exists() and not Path(folder).is_dir():
            raise UserError(f"{flag} {folder}: exists and is not a folder")
    if args.reference and not Path(args.reference).exists():
        raise UserError(f"--reference {args.reference}: not found (a dataset folder or a reference .npz)")
    return thresholds, lengths


# --------------------------------------------------------------------------- sequences


def sequence_name(sequence_id: int) -> str:
    """Folder / JSON name of a sequence: ``seq-XX``."""
    return f"seq-{sequence_id:02d}"


def sample_positions(n: int, k: int) -> set[int]:
    """``k`` positions spread evenly over ``n`` frames (first and last included)."""
    return set(np.linspace(0, n - 1, k).round().astype(int).tolist()) if n > 0 and k > 0 else set()


def without_segmentation(report: dict, note: str) -> dict:
    """Remove the ``segmentation`` entries of a report (overall and per sequence) of a model that has none,
    and say why in ``report["segmentation_note"]`` (printed under the table)."""
    for part in (report["overall"], *report["per_sequence"].values()):
        part.pop("segmentation", None)
    report["segmentation_note"] = note
    return report


# --------------------------------------------------------------------------- baseline


def add_baseline(
    report: dict,
    results: Sequence[SequenceResult],
    descriptors: Sequence[np.ndarray],
    reference,
    thresholds: Sequence[tuple[float, float]] = DEFAULT_THRESHOLDS,
) -> dict:
    """Score the retrieval baseline (``reference``: a :class:`~vlocnetpp_core.evaluation.retrieval.ReferenceSet`) on the
    frames of ``results`` (``descriptors[k] (N_k, D)``) and store it as ``report["baseline"]``."""
    from vlocnetpp_core.evaluation.retrieval import retrieval_results

    # pose metrics only (no odometry: the segment lengths are a placeholder)
    scored = evaluate_sequences(retrieval_results(reference, results, descriptors), thresholds, [1.0])
    net, base = report["overall"]["pose"], scored["overall"]["pose"]
    report["baseline"] = {
        "name": BASELINE_NAME,
        "method": BASELINE_METHOD,
        "reference": reference.source,
        "reference_frames": len(reference),
        "overall": {"pose": base},
        "per_sequence": {name: {"pose": part["pose"]} for name, part in scored["per_sequence"].items()},
        "network_beats_baseline": {
            "translation": _less(net["median_translation_m"], base["median_translation_m"]),
            "rotation": _less(net["median_rotation_deg"], base["median_rotation_deg"]),
        },
    }
    return report


FRAME_NAME = "network, each frame alone"


def add_frame_poses(
    report: dict,
    results: Sequence[SequenceResult],
    poses: Sequence[tuple[np.ndarray, np.ndarray]],
    thresholds: Sequence[tuple[float, float]] = DEFAULT_THRESHOLDS,
) -> dict:
    """Score the network's global pose of each frame alone (``poses[k] = (t (N_k, 3), q (N_k, 4))``, before the
    odometry fusion of :mod:`vlocnetpp_core.inference.pose_fusion`) on the frames of ``results`` as
    ``report["frame_network"]``, shaped like the ``baseline``."""
    from vlocnetpp_core.mapping.evaluation import scored_poses

    report["frame_network"] = {"name": FRAME_NAME, **scored_poses(results, poses, thresholds)}
    return report


def _less(a: float | None, b: float | None) -> bool | None:
    return None if a is None or b is None else bool(a < b)


def baseline_verdict(report: dict) -> str | None:
    """One line comparing the network's median pose errors with the baseline's, or None without a baseline."""
    base = report.get("baseline")
    if not base:
        return None
    net, ref = report["overall"]["pose"], base["overall"]["pose"]
    beats = base["network_beats_baseline"]
    if beats["translation"] and beats["rotation"]:
        verdict = "the network beats retrieval"
    elif beats["translation"] or beats["rotation"]:
        verdict = f"the network beats retrieval in {'translation' if beats['translation'] else 'rotation'} only"
    else:
        verdict = "the network does NOT beat retrieval"
    return (
        f"{verdict}: median {_num(net['median_translation_m'], '.3f')} m "
        f"/ {_num(net['median_rotation_deg'], '.2f')} deg against "
        f"{_num(ref['median_translation_m'], '.3f')} m / {_num(ref['median_rotation_deg'], '.2f')} deg "
        f"(nearest of {base['reference_frames']} reference images of {base['reference']})"
    )


# --------------------------------------------------------------------------- table


def _pct(v: float | None, digits: int = 1) -> str:
    return "-" if v is None else f"{100.0 * v:.{digits}f}"


def _num(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def format_report(report: dict, frames: dict[str, int] | None = None) -> str:
    """A readable table: per sequence and overall median errors, pose accuracies, odometry errors, mIoU, ms/frame
    (no segmentation columns when the report has no ``segmentation``, e.g. a pose-only model's); the retrieval
    baseline's overall row under it when the report has one."""
    overall = report["overall"]
    has_seg = "segmentation" in overall
    acc_keys = [k for k in overall["pose"] if k.startswith("accuracy_")]
    headers = ["sequence", "frames", "median t [m]", "median R [deg]"]
    headers += [k.removeprefix("accuracy_").replace("_", "/") + " [%]" for k in acc_keys]
    headers += ["VO t [%]", "VO R [deg/m]", "VO scale", *(["mIoU [%]", "pix acc [%]"] if has_seg else []), "ms/frame"]
    frames = frames or {}
    empty = {
        "odometry": {"translation_error_percent": None, "rotation_error_deg_per_m": None, "step_scale": None},
        "segmentation": {"miou": None, "pixel_accuracy": None},
        "timing": {"mean_ms": None},
    }

    def row(name: str, part: dict, n: int | None) -> list[str]:
        part = {**empty, **part}
        pose, odo, seg, tim = part["pose"], part["odometry"], part["segmentation"], part["timing"]
        return [
            name,
            "-" if n is None else str(n),
            _num(pose["median_translation_m"], ".3f"),
            _num(pose["median_rotation_deg"], ".2f"),
            *[_pct(pose.get(k)) for k in acc_keys],
            _num(odo["translation_error_percent"], ".2f"),
            _num(odo["rotation_error_deg_per_m"], ".3f"),
            _num(odo.get("step_scale"), ".3f"),
            *([_pct(seg["miou"]), _pct(seg["pixel_accuracy"])] if has_seg else []),
            _num(tim["mean_ms"], ".1f"),
        ]

    rows = [row(name, part, frames.get(name)) for name, part in report["per_sequence"].items()]
    total = sum(frames.values()) if frames else None
    rows.append(row("overall (network)" if "pose_refined" in overall else "overall", overall, total))
    if "pose_refined" in overall:
        rows.append(row("refined", {"pose": overall["pose_refined"]}, total))
    for key in ("frame_network", "baseline", "structure_baseline"):
        if report.get(key):
            rows.append(row(report[key]["name"], report[key]["overall"], total))
    widths = [max(len(h), *(len(r[c]) for r in rows)) for c, h in enumerate(headers)]
    fmt = "  ".join(f"{{:<{w}}}" if c == 0 else f"{{:>{w}}}" for c, w in enumerate(widths))
    rule = "  ".join("-" * w for w in widths)
    n_seq = len(report["per_sequence"])
    lines = [
        fmt.format(*headers),
        rule,
        *[fmt.format(*r) for r in rows[:n_seq]],
        rule,
        *[fmt.format(*r) for r in rows[n_seq:]],
    ]
    verdict = baseline_verdict(report)
    if verdict:
        lines.append(verdict)
    if "pose_refined" in overall:
        from vlocnetpp_core.mapping.evaluation import refinement_lines

        lines += refinement_lines(report)
    lengths = overall["odometry"]["lengths_m"]
    lines.append(
        "odometry segment lengths [m]: "
        f"{', '.join(f'{v:g}' for v in lengths) if lengths else '- (sequences too short)'}"
    )
    iou = {k: v for k, v in overall["segmentation"]["iou"].items() if v is not None} if has_seg else {}
    if iou:
        lines.append("IoU [%] (overall): " + ", ".join(f"{k} {100 * v:.1f}" for k, v in iou.items()))
    if report.get("segmentation_note"):
        lines.append(f"segmentation: {report['segmentation_note']}")
    tim = overall["timing"]
    if tim["median_ms"] is not None:
        lines.append(f"time per frame: mean {tim['mean_ms']:.1f} ms, median {tim['median_ms']:.1f} ms")
    return "\n".join(lines)


# --------------------------------------------------------------------------- files


def write_json(path: str | Path, data: dict) -> None:
    """Write ``data`` as indented JSON, atomically (temporary file renamed into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
    os.replace(tmp, path)


def write_trajectories(
    folder: str | Path,
    results: Sequence[SequenceResult],
    frame_poses: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> list[Path]:
    """``<folder>/<seq>/{ground_truth,global_pose,odometry}.tum`` (odometry only when predicted), and
    ``frame_pose.tum``, the network's pose of each frame alone, with ``frame_poses[k] = (t (N_k, 3), q (N_k, 4))``."""
    from vlocnetpp_core.evaluation.trajectory import Trajectory, write_tum

    written = []
    for k, r in enumerate(results):
        sub = Path(folder) / r.name
        frame = None if frame_poses is None else Trajectory(r.stamps, *frame_poses[k])
        for name, traj in (
            ("ground_truth", r.ground_truth()),
            ("global_pose", r.global_pose()),
            ("odometry", r.odometry()),
            ("frame_pose", frame),
        ):
            if traj is not None:
                write_tum(sub / f"{name}.tum", traj)
                written.append(sub / f"{name}.tum")
    return written


def write_outputs(
    report: dict,
    results: list[SequenceResult],
    class_names: Sequence[str],
    json_path: str | Path | None = None,
    trajectories: str | Path | None = None,
    plots: str | Path | None = None,
    frame_poses: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> None:
    """Write the report as JSON, the TUM trajectories (with ``frame_poses``: the network's pose of each frame alone
    too) and the plots, where asked, and say where they went."""
    if json_path:
        write_json(json_path, report)
        print(f"metrics: {json_path}")
    if trajectories:
        write_trajectories(trajectories, results, frame_poses)
        print(f"trajectories (TUM): {trajectories}")
    if plots:
        from vlocnetpp_core.evaluation.plots import write_plots

        write_plots(plots, results, class_names)
        print(f"plots: {plots}")

"""``vlocnetpp data-info DIR``: summarise a dataset and check that poses, depth and intrinsics agree.

The warp-consistency check: for consecutive frames (t-1, t) of a sequence that both have depth,
warp frame t-1 into frame t with the depth of frame t, the ground-truth relative pose and the
intrinsics (``geometry.warp_grid`` + ``grid_sample`` on grey images at most ``WARP_WIDTH`` px
wide) and compare the mean absolute photometric error over valid pixels with the error without
warping on the same pixels. The median of that ratio over up to ``--pairs`` evenly spread pairs
is ``warp_consistency``: well below 1 when poses, depth and intrinsics agree; a wrong quaternion
order, wrong intrinsics or depth in the wrong unit push it towards or above 1.
"""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np
import torch

from vlocnetpp_core import geometry
from vlocnetpp_core.classes import CLASS_NAMES, IGNORE_INDEX
from vlocnetpp_core.data import imageio
from vlocnetpp_core.data.dataset import FORMATS, available_splits, detect_format, open_dataset
from vlocnetpp_core.data.sample import DatasetIndex, Frame
from vlocnetpp_core.data.transforms import resize_frame
from vlocnetpp_core.errors import DataError, UserError

WARP_WIDTH = 320
WARN_RATIO = 0.8
SPLITS = ("train", "test")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", metavar="DIR", help="dataset folder (holding DeepLoc/, or a 7-Scenes scene folder)")
    parser.add_argument(
        "--format", choices=FORMATS, default=None, help="dataset format (default: detect from the layout)"
    )
    parser.add_argument(
        "--split", choices=(*SPLITS, "all"), default="all", help="split to check (default: all present)"
    )
    parser.add_argument(
        "--intrinsics", metavar="fx,fy,cx,cy", default=None, help="camera intrinsics at the dataset's image size"
    )
    parser.add_argument(
        "--quaternion-order",
        choices=("wxyz", "xyzw"),
        default="wxyz",
        help="DeepLoc poses.txt quaternion column order (default wxyz)",
    )
    parser.add_argument("--pairs", type=int, default=50, help="frame pairs sampled for the warp check (default 50)")
    parser.add_argument(
        "--label-frames", type=int, default=200, help="label images sampled for the class histogram (default 200)"
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a report")


def evenly_spread(items: list, n: int) -> list:
    """Up to ``n`` items at evenly spaced positions (first and last included)."""
    if len(items) <= n:
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, n).round().astype(int)]


def _grey(frame: Frame) -> torch.Tensor:
    g = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    return torch.from_numpy(g)[None, None]


def pair_warp_ratio(prev: Frame, cur: Frame, min_valid: float = 0.05) -> float | None:
    """Photometric error of ``prev`` warped into ``cur`` over the error without warping (valid pixels);
    None when too few pixels are valid or the two images are (nearly) identical."""
    h, w = cur.image.shape[:2]
    if w > WARP_WIDTH:
        size = (WARP_WIDTH, max(1, round(h * WARP_WIDTH / w)))
        prev, cur = resize_frame(prev, *size), resize_frame(cur, *size)
    t_rel, q_rel = geometry.relative_pose(prev.t, prev.q, cur.t, cur.q)
    T = torch.from_numpy(geometry.pose_to_matrix(t_rel, q_rel)).float()[None]
    K = torch.from_numpy(cur.intrinsics.matrix()).float()[None]
    depth = torch.from_numpy(cur.depth)[None, None]
    grid, valid = geometry.warp_grid(depth, T, K)
    a, b = _grey(prev), _grey(cur)
    warped = torch.nn.functional.grid_sample(a, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    m = valid > 0.5
    if m.float().mean() < min_valid:
        return None
    e_warp = (warped - b).abs()[m].mean().item()
    e_id = (a - b).abs()[m].mean().item()
    return None if e_id < 1e-4 else e_warp / e_id


def warp_consistency(index: DatasetIndex, max_pairs: int = 50) -> tuple[float | None, int]:
    """``(median ratio, pairs used)`` over up to ``max_pairs`` consecutive depth pairs (None, 0 without depth)."""
    pairs = [
        (i - 1, i)
        for rng in index.sequences
        for i in rng[1:]
        if index.records[i].depth is not None and index.records[i - 1].depth is not None
    ]
    ratios = []
    for i, j in evenly_spread(pairs, max_pairs):
        r = pair_warp_ratio(index.load(i), index.load(j))
        if r is not None:
            ratios.append(r)
    return (float(np.median(ratios)) if ratios else None), len(ratios)


def class_histogram(index: DatasetIndex, max_frames: int = 200) -> tuple[dict[str, float], int]:
    """Pixel share per class name (plus ``"ignore"``) over up to ``max_frames`` evenly spread label images."""
    paths = evenly_spread([r.labels for r in index.records if r.labels is not None], max_frames)
    counts = np.zeros(256, dtype=np.int64)
    for p in paths:
        counts += np.bincount(imageio.read_labels(p).ravel(), minlength=256)
    total = max(int(counts.sum()), 1)
    hist = {name: counts[k] / total for k, name in enumerate(CLASS_NAMES)}
    hist["ignore"] = counts[IGNORE_INDEX] / total
    return {k: round(float(v), 6) for k, v in hist.items()}, len(paths)


def split_summary(index: DatasetIndex, max_pairs: int, max_label_frames: int) -> dict:
    """The per-split part of the ``data-info`` report."""
    t = np.array([r.t for r in index.records])
    steps = np.concatenate(
        [np.linalg.norm(np.diff(t[rng.start : rng.stop], axis=0), axis=1) for rng in index.sequences]
    )
    first = index.load(0)
    out = {
        "frames": len(index),
        "sequences": len(index.sequences),
        "sequence_lengths": [len(s) for s in index.sequences],
        "image_size": [int(first.image.shape[1]), int(first.image.shape[0])],
        "has_depth": index.has_depth,
        "depth_frames": sum(r.depth is not None for r in index.records),
        "has_labels": index.has_labels,
        "label_frames": sum(r.labels is not None for r in index.records),
        "trajectory_length_m": round(float(steps.sum()), 3),
        "median_step_m": round(float(np.median(steps)), 4) if steps.size else 0.0,
        "max_step_m": round(float(steps.max()), 4) if steps.size else 0.0,
        "notes": list(index.notes),
    }
    if index.has_labels:
        out["class_histogram"], out["class_histogram_frames"] = class_histogram(index, max_label_frames)
    ratio, n = warp_consistency(index, max_pairs)
    out["warp_consistency"], out["warp_pairs"] = (None if ratio is None else round(ratio, 4)), n
    return out


def dataset_info(
    path,
    format: str | None = None,
    splits=SPLITS,
    intrinsics=None,
    max_pairs: int = 50,
    max_label_frames: int = 200,
    **options,
) -> dict:
    """The ``data-info --json`` object for the dataset at ``path``; splits not present are skipped."""
    fmt = format or detect_format(path)
    if fmt != "deeploc":
        options.pop("quaternion_order", None)
    present = available_splits(path, fmt)
    chosen = [s for s in splits if s in present]
    if not chosen:
        raise DataError(path, f"no {' or '.join(splits)} split found (present: {', '.join(present) or 'none'})")
    indices = {s: open_dataset(path, fmt, s, intrinsics, **options) for s in chosen}
    first = next(iter(indices.values()))
    report = {
        "format": first.format,
        "root": str(first.root),
        "intrinsics": first.intrinsics.to_dict(),
        "intrinsics_source": first.intrinsics_source,
        "splits": {s: split_summary(ix, max_pairs, max_label_frames) for s, ix in indices.items()},
    }
    ratios = [
        (v["warp_consistency"], v["warp_pairs"]) for v in report["splits"].values() if v["warp_consistency"] is not None
    ]
    n = sum(k for _, k in ratios)
    report["warp_consistency"] = round(sum(r * k for r, k in ratios) / n, 4) if n else None
    report["warp_pairs"] = n
    return report


def format_report(report: dict) -> str:
    """Human-readable ``data-info`` report, with warnings in plain language."""
    K = report["intrinsics"]
    lines = [
        f"{report['format']} dataset at {report['root']}",
        f"intrinsics: fx={K['fx']:.1f} fy={K['fy']:.1f} cx={K['cx']:.1f} cy={K['cy']:.1f} at {K['width']}x{K['height']}"
        f" ({report['intrinsics_source']})",
    ]
    warnings = []
    for split, s in report["splits"].items():
        lines.append(
            f"{split}: {s['frames']} frames in {s['sequences']} sequences "
            f"(lengths {', '.join(map(str, s['sequence_lengths']))}),"
            f" images {s['image_size'][0]}x{s['image_size'][1]}"
        )
        lines.append(f"  depth on {s['depth_frames']} frames, labels on {s['label_frames']} frames")
        lines.append(
            f"  trajectory {s['trajectory_length_m']:.1f} m, "
            f"step median {s['median_step_m']:.3f} m, max {s['max_step_m']:.3f} m"
        )
        if "class_histogram" in s:
            shares = ", ".join(f"{k} {100 * v:.1f}%" for k, v in s["class_histogram"].items() if v > 0)
            lines.append(f"  classes ({s['class_histogram_frames']} label images): {shares}")
        for note in s["notes"]:
            lines.append(f"  note: {note}")
        r = s["warp_consistency"]
        if r is None:
            lines.append("  warp consistency: not measured (needs consecutive frames with depth)")
        else:
            lines.append(
                f"  warp consistency: {r:.3f} over {s['warp_pairs']} frame pairs "
                "(below 1 = poses, depth, intrinsics agree)"
            )
            if r > WARN_RATIO:
                warnings.append(
                    f"warning: {split}: warping with the ground-truth poses and depth barely helps (ratio {r:.2f}). "
                    "Poses, depth and intrinsics probably disagree: check the quaternion order (--quaternion-order), "
                    "the intrinsics (--intrinsics) and the depth unit."
                )
    return "\n".join(lines + warnings)


def run(args: argparse.Namespace) -> int:
    splits = SPLITS if args.split == "all" else (args.split,)
    options = {"quaternion_order": args.quaternion_order} if args.quaternion_order != "wxyz" else {}
    if args.pairs < 0 or args.label_frames < 0:
        raise UserError("--pairs and --label-frames must be >= 0")
    report = dataset_info(args.dir, args.format, splits, args.intrinsics, args.pairs, args.label_frames, **options)
    print(json.dumps(report, indent=2) if args.json else format_report(report))
    return 0

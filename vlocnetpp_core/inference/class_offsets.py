"""Per-class offsets of the segmentation's scores, fitted for mean IoU on labelled frames the network did not train on.

The semantic stream is trained for cross-entropy, whose argmax favours the large classes (road, sidewalk, grass) at
the small ones' cost (poles and fences, moving objects): mean IoU weighs every class alike. A constant offset per
class added to the scores before the argmax (``ids = argmax_c(scores_c + offset_c)``, the decision rule only: no
weight changes, the poses are the same bit for bit) moves the boundary between them. :func:`fit_class_offsets` finds
the offsets by coordinate ascent on the pooled confusion of the given frames; ``vlocnetpp calibrate-classes`` (and a
recipe's export, key ``class_offsets``) writes them into the checkpoint's ``calibration.class_logit_offsets``, which
:class:`~vlocnetpp_core.inference.localizer.Localizer` applies. Fit them on validation visits, never on test ones.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from vlocnetpp_core.classes import IGNORE_INDEX
from vlocnetpp_core.errors import UserError

OFFSET_STEPS = (1.0, 0.5, 0.25)  # the coordinate ascent's trial moves, largest first
ROUNDS = 3  # passes over the classes per step size


def collect_scores(
    model: torch.nn.Module, meta: dict, index, frame_stride: int = 2, pixel_stride: int = 2, progress: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Stream every sequence of ``index`` (a labelled ``DatasetIndex``) through ``model.step`` as the localizer does
    (temporal state reset at each sequence start) and keep every ``frame_stride``-th frame's scores.

    Returns ``scores (N, C, h, w)`` float16 and ``labels (N, h, w)`` int64 at the network resolution subsampled by
    ``pixel_stride`` (labels brought there by nearest neighbour; :data:`IGNORE_INDEX` where unlabelled).
    """
    from tqdm import tqdm

    from vlocnetpp_core.camera.intrinsics import Intrinsics
    from vlocnetpp_core.inference.network_input import network_input

    size = tuple(model.config.input_size)  # (W, H)
    default = Intrinsics.from_dict(meta["intrinsics"]).resized(*size)
    scores, labels = [], []
    model.eval()
    with torch.inference_mode(), tqdm(total=len(index), unit="frame", desc="scores", disable=not progress) as bar:
        for rng in index.sequences:
            state = None
            for k, i in enumerate(rng):
                frame = index.load(i)
                bar.update(1)
                intrinsics = default if frame.intrinsics is None else frame.intrinsics.resized(*size)
                x, K, _ = network_input(frame.image, size, intrinsics)
                out, state = model.step(x, state, K)
                if k % frame_stride or frame.labels is None:
                    continue
                y = cv2.resize(frame.labels, size, interpolation=cv2.INTER_NEAREST_EXACT)
                scores.append(out.seg_logits[0, :, ::pixel_stride, ::pixel_stride].to(torch.float16))
                labels.append(torch.from_numpy(y[::pixel_stride, ::pixel_stride].astype(np.int64)))
    if not scores:
        raise UserError("no labelled frames to fit the class offsets on")
    return torch.stack(scores), torch.stack(labels)


def fit_class_offsets(scores: torch.Tensor, labels: torch.Tensor) -> tuple[np.ndarray, float, float]:
    """Offsets ``(C,)`` (mean zero) that raise the mean IoU of ``argmax(scores + offsets)`` over ``labels``.

    ``scores (N, C, h, w)``, ``labels (N, h, w)`` as :func:`collect_scores` returns them. Coordinate ascent: each
    class's offset is moved by each of :data:`OFFSET_STEPS` in turn, kept where the pooled mean IoU rises. Returns
    the offsets, the mean IoU without them and with them.
    """
    from vlocnetpp_core.evaluation.metrics import confusion_matrix, segmentation_metrics

    num_classes = scores.shape[1]
    keep = labels != IGNORE_INDEX
    y = labels[keep].numpy()
    logits = scores.float().permute(0, 2, 3, 1)[keep]  # (P, C): the labelled pixels

    names = [str(c) for c in range(num_classes)]

    def miou(offsets: np.ndarray) -> float:
        pred = (logits + torch.from_numpy(offsets)).argmax(1).numpy()
        return segmentation_metrics(confusion_matrix(y, pred, num_classes), names)["miou"]

    offsets = np.zeros(num_classes, np.float32)
    before = best = miou(offsets)
    for step in OFFSET_STEPS:
        for _ in range(ROUNDS):
            for c in range(num_classes):
                for move in (step, -step):
                    trial = offsets.copy()
                    trial[c] += move
                    value = miou(trial)
                    if value > best + 1e-6:
                        offsets, best = trial, value
                        break
    return offsets - offsets.mean(), before, best


def offsets_of(meta: dict) -> torch.Tensor | None:
    """The checkpoint's ``calibration.class_logit_offsets`` (checked by ``read_checkpoint_meta``: one finite number
    per class) as a ``(C,)`` float32 tensor, or None without them."""
    values = (meta.get("calibration") or {}).get("class_logit_offsets")
    return None if values is None else torch.tensor(values, dtype=torch.float32)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint", help="NAME.safetensors (its NAME.json gets the offsets)")
    p.add_argument("--data", required=True, help="labelled validation visits (a dataset folder)")
    p.add_argument("--split", default="test", help="the split of --data to fit on (default test)")
    p.add_argument("--format", default=None, help="dataset format (default: detected)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    mious = calibrate(args.checkpoint, args.data, args.split, args.format, progress=not args.no_progress)
    print(f"{args.checkpoint}: mean IoU on {args.data} ({args.split}) {mious[0]:.4f} -> {mious[1]:.4f}")
    return 0


def calibrate(
    checkpoint: str | Path, data: str | Path, split: str = "test", format: str | None = None, progress: bool = True
) -> tuple[float, float]:
    """Fit the offsets of ``checkpoint`` on ``data``'s ``split`` and write them into its sidecar's calibration (the
    weights stay as they are). Returns the mean IoU on those frames without and with them."""
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.inference.checkpoint import load_checkpoint, update_calibration

    model, meta = load_checkpoint(checkpoint)
    if not model.config.semantic_stream:
        raise UserError(f"{checkpoint}: this model has no semantic stream (a pose-only config): nothing to calibrate")
    index = open_dataset(data, format, split)
    scores, labels = collect_scores(model, meta, index, progress=progress)
    offsets, before, after = fit_class_offsets(scores, labels)
    update_calibration(
        checkpoint,
        {
            "class_logit_offsets": [round(float(v), 4) for v in offsets],
            "class_logit_offsets_source": f"mean IoU on {Path(data).name} ({split}): {before:.4f} -> {after:.4f}",
        },
    )
    return before, after

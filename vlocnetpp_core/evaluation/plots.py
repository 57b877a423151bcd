"""PNG plots of an evaluation: trajectories, errors over time, confusion matrix, segmentation strip.

Figures are drawn with matplotlib's object API on the Agg canvas (no pyplot, no global backend
state, no display needed). Every file is written next to its destination and renamed into place.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from vlocnetpp_core.classes import CLASS_NAMES, colorize
from vlocnetpp_core.evaluation.metrics import SequenceResult, pose_errors
from vlocnetpp_core.evaluation.trajectory import Trajectory

AXIS_NAMES = ("x", "y", "z")


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    FigureCanvasAgg(fig)
    fig.savefig(tmp, dpi=100)
    os.replace(tmp, path)
    return path


def top_down_axes(points: np.ndarray) -> tuple[int, int]:
    """The two world axes (indices, ascending) along which ``points (N, 3)`` spread most.

    Neither dataset fixes which world axis is up, so the axis with the smallest extent of the
    ground truth is taken as the vertical one and the view looks down along it.
    """
    extent = np.ptp(np.asarray(points).reshape(-1, 3), axis=0)
    a, b = sorted(np.argsort(extent)[1:].tolist())
    return a, b


def plot_trajectories(
    path: str | Path,
    ground_truth: Trajectory,
    global_pose: Trajectory,
    odometry: Trajectory | None = None,
    title: str = "",
) -> Path:
    """Top-down view (see :func:`top_down_axes`) of the true, global-pose and odometry positions."""
    a, b = top_down_axes(ground_truth.t)
    fig = Figure(figsize=(6, 6))
    ax = fig.add_subplot()
    ax.plot(ground_truth.t[:, a], ground_truth.t[:, b], "-", color="black", lw=2, label="ground truth")
    ax.plot(global_pose.t[:, a], global_pose.t[:, b], ".", color="tab:blue", ms=3, label="global pose")
    if odometry is not None:
        ax.plot(odometry.t[:, a], odometry.t[:, b], "-", color="tab:orange", lw=1, label="odometry")
    ax.plot(ground_truth.t[:1, a], ground_truth.t[:1, b], "o", color="black", ms=6, label="start")
    ax.set_xlabel(f"{AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title(title or "trajectories (top-down)")
    fig.tight_layout()
    return _save(fig, path)


def plot_errors(path: str | Path, result: SequenceResult, title: str = "") -> Path:
    """Translation (m) and rotation (deg) error per frame over time, global pose and odometry."""
    stamps = result.stamps - (result.stamps[0] if len(result.stamps) else 0.0)
    trans, rot = pose_errors(result.pred_t, result.pred_q, result.true_t, result.true_q)
    fig = Figure(figsize=(8, 5))
    ax_t, ax_r = fig.subplots(2, 1, sharex=True)
    ax_t.plot(stamps, trans, color="tab:blue", lw=1, label="global pose")
    ax_r.plot(stamps, rot, color="tab:blue", lw=1, label="global pose")
    odom = result.odometry()
    if odom is not None:
        o_trans, o_rot = pose_errors(odom.t, odom.q, result.true_t, result.true_q)
        ax_t.plot(stamps, o_trans, color="tab:orange", lw=1, label="odometry (drift)")
        ax_r.plot(stamps, o_rot, color="tab:orange", lw=1, label="odometry (drift)")
    ax_t.set_ylabel("translation error [m]")
    ax_r.set_ylabel("rotation error [deg]")
    ax_r.set_xlabel("time since sequence start [s]")
    for ax in (ax_t, ax_r):
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", fontsize="small")
    ax_t.set_title(title or "error over time")
    fig.tight_layout()
    return _save(fig, path)


def plot_confusion(
    path: str | Path, confusion: np.ndarray, class_names: Sequence[str] = CLASS_NAMES, title: str = ""
) -> Path:
    """Row-normalised confusion matrix (rows true, columns predicted) with the share in each cell."""
    conf = np.asarray(confusion, np.float64)
    rows = conf.sum(1, keepdims=True)
    norm = np.divide(conf, rows, out=np.zeros_like(conf), where=rows > 0)
    n = len(class_names)
    fig = Figure(figsize=(1.0 + 0.7 * n, 0.8 + 0.6 * n))
    ax = fig.add_subplot()
    im = ax.imshow(norm, vmin=0.0, vmax=1.0, cmap="Blues")
    for i in range(n):
        for j in range(n):
            if conf[i, j] > 0:
                ax.text(
                    j,
                    i,
                    f"{norm[i, j]:.2f}",
                    ha="center",
                    va="center",
                    fontsize=7,
                    color="white" if norm[i, j] > 0.5 else "black",
                )
    ax.set_xticks(range(n), class_names, rotation=45, ha="right", fontsize=8)
    ax.set_yticks(range(n), class_names, fontsize=8)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(title or "confusion matrix (rows normalised)")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    fig.tight_layout()
    return _save(fig, path)


def plot_segmentation_strip(
    path: str | Path, samples: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None]], title: str = ""
) -> Path:
    """One row per sample: input image, predicted and true class ids in ``classes.CLASS_COLORS``."""
    if not samples:
        raise ValueError("no samples to plot")
    h, w = samples[0][0].shape[:2]
    fig = Figure(figsize=(3 * 3.2, len(samples) * 3.2 * h / w + 0.4))
    axes = np.asarray(fig.subplots(len(samples), 3, squeeze=False))
    for row, (image, pred, true) in zip(axes, samples, strict=True):
        row[0].imshow(image, interpolation="nearest")
        row[1].imshow(colorize(pred), interpolation="nearest")
        if true is not None:
            row[2].imshow(colorize(true), interpolation="nearest")
        for ax in row:
            ax.set_axis_off()
    for ax, name in zip(axes[0], ("input", "predicted", "ground truth"), strict=True):
        ax.set_title(name, fontsize=9)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def write_plots(
    folder: str | Path, results: Sequence[SequenceResult], class_names: Sequence[str] = CLASS_NAMES
) -> list[Path]:
    """All plots of an evaluation: per sequence ``<seq>/trajectory.png``, ``errors.png``,
    ``confusion.png`` and ``segmentation.png`` (when it has labels / samples), and the overall
    ``confusion.png``. Returns the paths written."""
    folder = Path(folder)
    written: list[Path] = []
    total = None
    for r in results:
        sub = folder / r.name
        if len(r.stamps):
            written.append(
                plot_trajectories(
                    sub / "trajectory.png", r.ground_truth(), r.global_pose(), r.odometry(), f"{r.name}: top-down"
                )
            )
            written.append(plot_errors(sub / "errors.png", r, f"{r.name}: error over time"))
        if r.confusion is not None:
            written.append(
                plot_confusion(
                    sub / "confusion.png", r.confusion, class_names, f"{r.name}: confusion (rows normalised)"
                )
            )
            total = r.confusion if total is None else total + r.confusion
        if r.samples:
            written.append(plot_segmentation_strip(sub / "segmentation.png", r.samples, f"{r.name}: segmentation"))
    if total is not None:
        written.append(
            plot_confusion(folder / "confusion.png", total, class_names, "all sequences: confusion (rows normalised)")
        )
    return written

"""The paper's metrics (docs/conventions.md, Metrics) computed from arrays; numpy only, no torch.

* Global pose: median translation (m) / rotation (deg) error, and the share of frames under
  ``x m`` and ``y deg`` for each threshold (``accuracy_5cm_5deg``, ``accuracy_0.5m_5deg``).
* Odometry (KITTI-style, as in the paper's Tables III and VI): the trajectory is chained from the
  predicted relative poses starting at the ground-truth first pose. For every start frame and every
  length ``L`` in ``lengths_m``, the segment ends at the first frame whose ground-truth path
  distance from the start exceeds ``L``; its error ``E = (P_s^-1 P_e)^-1 (Q_s^-1 Q_e)`` (``P``
  predicted, ``Q`` true) gives ``|t_E| / L`` and ``angle(R_E) / L``. The KITTI devkit uses 100..800 m
  on km-long drives and a start every 10 frames; our sequences are far shorter, so by default the
  lengths are 10%, 20%, ..., 80% of the *shortest* sequence's ground-truth path length (one set for
  every sequence, so per-sequence numbers are comparable and pool into the overall number), and
  every frame starts segments. Errors are averaged over all segments (pooled over sequences for
  "overall"), reported as ``translation_error_percent`` and ``rotation_error_deg_per_m``; beside
  them ``step_scale``, the median over frame pairs of the predicted step length over the true one
  (a monocular odometry's scale bias, the usual share of its drift: 1.2 = 20 % too far).
* Segmentation: per-class IoU, mIoU and pixel accuracy from a confusion matrix (rows true, columns
  predicted, label 255 ignored). A class absent from both ground truth and prediction has IoU
  ``None`` and is left out of the mean.
* Trajectory metrics as ``evo`` computes them: :func:`ate` (absolute translation error; no alignment
  by default, like ``evo_ape``; Umeyama SE(3) or Sim(3) alignment on request) and :func:`rpe`.

Shares (accuracies, IoU, pixel accuracy) are fractions in ``[0, 1]``; ``None`` marks "no data".
:func:`evaluate_sequences` turns per-sequence results (:class:`SequenceResult`, filled frame by frame
with :class:`SequenceRecorder`) into the report of ``vlocnetpp evaluate`` / ``evaluate-bag``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vlocnetpp_core.classes import CLASS_NAMES, IGNORE_INDEX
from vlocnetpp_core.evaluation.trajectory import Trajectory, accumulate_odometry, align_trajectory
from vlocnetpp_core.geometry import pose_to_matrix

DEFAULT_THRESHOLDS: tuple[tuple[float, float], ...] = ((0.05, 5.0), (0.5, 5.0))
DEFAULT_LENGTH_FRACTIONS: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)


# --------------------------------------------------------------------------- global pose


def pose_errors(
    t_pred: np.ndarray, q_pred: np.ndarray, t_true: np.ndarray, q_true: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation error (m, Euclidean) and rotation error (deg, ``2 acos |<q1, q2>|``), each ``(N,)``."""
    dt = np.linalg.norm(np.asarray(t_pred, np.float64) - np.asarray(t_true, np.float64), axis=-1)
    q1 = np.asarray(q_pred, np.float64)
    q2 = np.asarray(q_true, np.float64)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    q2 = q2 / np.linalg.norm(q2, axis=-1, keepdims=True)
    dot = np.clip(np.abs((q1 * q2).sum(-1)), 0.0, 1.0)
    return dt, np.degrees(2.0 * np.arccos(dot))


def accuracy_key(threshold_m: float, threshold_deg: float) -> str:
    """JSON key of a threshold: below 0.1 m in centimetres (``accuracy_5cm_5deg``), else metres
    (``accuracy_0.5m_5deg``)."""
    dist = f"{threshold_m * 100:g}cm" if threshold_m < 0.1 else f"{threshold_m:g}m"
    return f"accuracy_{dist}_{threshold_deg:g}deg"


def pose_metrics(
    trans_err: np.ndarray, rot_err: np.ndarray, thresholds: Sequence[tuple[float, float]] = DEFAULT_THRESHOLDS
) -> dict:
    """``median_translation_m``, ``median_rotation_deg`` and one ``accuracy_*`` share per ``(metres, degrees)``
    threshold."""
    trans_err = np.asarray(trans_err, np.float64)
    rot_err = np.asarray(rot_err, np.float64)
    empty = len(trans_err) == 0
    out: dict = {
        "median_translation_m": None if empty else float(np.median(trans_err)),
        "median_rotation_deg": None if empty else float(np.median(rot_err)),
    }
    for m, deg in thresholds:
        out[accuracy_key(m, deg)] = None if empty else float(np.mean((trans_err <= m) & (rot_err <= deg)))
    return out


# --------------------------------------------------------------------------- odometry (KITTI-style)


def default_odometry_lengths(
    path_lengths_m: Sequence[float], fractions: Sequence[float] = DEFAULT_LENGTH_FRACTIONS
) -> list[float]:
    """Segment lengths: ``fractions`` of the shortest positive path length, to 3 significant digits."""
    positive = [p for p in path_lengths_m if p > 0]
    if not positive:
        return []
    shortest = min(positive)
    return [float(f"{f * shortest:.3g}") for f in fractions]


def kitti_segment_errors(
    T_true: np.ndarray, T_pred: np.ndarray, lengths_m: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """Per-segment errors of the KITTI odometry devkit, every frame a start (see module docstring).

    ``T_true``, ``T_pred``: ``(N, 4, 4)`` poses. Returns translation error per metre (ratio) and
    rotation error in deg/m, each ``(S,)`` over all segments of all lengths that fit.
    """
    if any(length <= 0 for length in lengths_m):
        raise ValueError(f"segment lengths must be positive, got {list(lengths_m)}")
    steps = np.linalg.norm(np.diff(T_true[:, :3, 3], axis=0), axis=1)
    dist = np.concatenate(([0.0], np.cumsum(steps)))
    t_err, r_err = [], []
    for length in lengths_m:
        for first in range(len(dist)):
            last = int(np.searchsorted(dist, dist[first] + length, side="right"))
            if last >= len(dist):
                break
            d_true = np.linalg.inv(T_true[first]) @ T_true[last]
            d_pred = np.linalg.inv(T_pred[first]) @ T_pred[last]
            E = np.linalg.inv(d_pred) @ d_true
            cos = np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
            t_err.append(np.linalg.norm(E[:3, 3]) / length)
            r_err.append(np.degrees(np.arccos(cos)) / length)
    return np.array(t_err), np.array(r_err)


MIN_STEP_M = 0.01
"""Frame pairs whose camera moved less than this (metres) have no step ratio: a standing camera's ratio is noise."""


def step_ratios(true_t: np.ndarray, rel_t: np.ndarray, min_step_m: float = MIN_STEP_M) -> np.ndarray:
    """``(M,)`` predicted over true step length of every frame pair whose camera moved at least ``min_step_m``:
    ``|rel_t[k]| / |true_t[k] - true_t[k-1]|`` (``true_t (N, 3)`` world positions, ``rel_t (N, 3)`` the predicted
    ``T_{k-1}^{-1} T_k`` translations, row 0 ignored)."""
    true_step = np.linalg.norm(np.diff(true_t, axis=0), axis=1)
    moved = true_step >= min_step_m
    return np.linalg.norm(rel_t[1:], axis=1)[moved] / true_step[moved]


def odometry_metrics(
    t_err: np.ndarray, r_err: np.ndarray, lengths_m: Sequence[float], ratios: np.ndarray | None = None
) -> dict:
    """``translation_error_percent``, ``rotation_error_deg_per_m`` (means over segments), ``lengths_m`` and
    ``step_scale`` (median of :func:`step_ratios`; None without pairs)."""
    empty = len(t_err) == 0
    return {
        "translation_error_percent": None if empty else float(np.mean(t_err) * 100.0),
        "rotation_error_deg_per_m": None if empty else float(np.mean(r_err)),
        "lengths_m": [float(v) for v in lengths_m],
        "step_scale": None if ratios is None or len(ratios) == 0 else float(np.median(ratios)),
    }


# --------------------------------------------------------------------------- segmentation


def confusion_matrix(
    labels_true: np.ndarray, labels_pred: np.ndarray, num_classes: int, ignore_index: int = IGNORE_INDEX
) -> np.ndarray:
    """``(C, C)`` int64 counts, rows true class, columns predicted; pixels labelled ``ignore_index`` are skipped.

    Raises ``ValueError`` for different shapes or ids outside ``0..C-1`` (other than ``ignore_index``).
    """
    y = np.asarray(labels_true).reshape(-1).astype(np.int64)
    p = np.asarray(labels_pred).reshape(-1).astype(np.int64)
    if np.shape(labels_true) != np.shape(labels_pred):
        raise ValueError(f"label maps differ in shape: {np.shape(labels_true)} vs {np.shape(labels_pred)}")
    keep = y != ignore_index
    y, p = y[keep], p[keep]
    for name, v in (("true", y), ("predicted", p)):
        if v.size and (v.min() < 0 or v.max() >= num_classes):
            raise ValueError(
                f"{name} labels outside 0..{num_classes - 1}: "
                f"{sorted(set(v[(v < 0) | (v >= num_classes)].tolist()))[:5]}"
            )
    return np.bincount(y * num_classes + p, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def segmentation_metrics(confusion: np.ndarray | None, class_names: Sequence[str] = CLASS_NAMES) -> dict:
    """``miou``, ``iou`` (dict by class name, ``None`` for classes in neither truth nor prediction) and
    ``pixel_accuracy``."""
    if confusion is None or confusion.sum() == 0:
        return {"miou": None, "iou": {n: None for n in class_names}, "pixel_accuracy": None}
    conf = np.asarray(confusion, np.float64)
    tp = np.diag(conf)
    union = conf.sum(0) + conf.sum(1) - tp
    iou = {n: (float(tp[i] / union[i]) if union[i] > 0 else None) for i, n in enumerate(class_names)}
    present = [v for v in iou.values() if v is not None]
    return {"miou": float(np.mean(present)), "iou": iou, "pixel_accuracy": float(tp.sum() / conf.sum())}


# --------------------------------------------------------------------------- timing


def timing_metrics(ms: np.ndarray | None) -> dict:
    """``mean_ms`` and ``median_ms`` per frame."""
    if ms is None or len(ms) == 0:
        return {"mean_ms": None, "median_ms": None}
    return {"mean_ms": float(np.mean(ms)), "median_ms": float(np.median(ms))}


# --------------------------------------------------------------------------- trajectory metrics (evo-compatible)


def ate(ref: Trajectory, est: Trajectory, align: bool = False, with_scale: bool = False) -> np.ndarray:
    """Absolute translation error ``(N,)`` in metres of ``est`` against ``ref`` (matched frame by frame).

    Without ``align`` (the default, like ``evo_ape``) the poses are compared as they are; with it
    ``est`` is first moved by the Umeyama SE(3) (Sim(3) with ``with_scale``) fit of its positions.
    """
    if align:
        est = align_trajectory(est, ref, with_scale)
    return np.linalg.norm(est.t - ref.t, axis=1)


def rpe(ref: Trajectory, est: Trajectory, delta: int = 1, all_pairs: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose error over frame pairs ``(i, i + delta)``: translation (m) and rotation (deg), each ``(P,)``.

    ``E_i = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` (TUM RGB-D / ``evo_rpe``). Pairs are consecutive
    (``0-d, d-2d, ...``) as ``evo``'s default, or every ``i`` with ``all_pairs``.
    """
    if len(ref) != len(est):
        raise ValueError(f"trajectories differ in length: {len(ref)} vs {len(est)}")
    starts = np.arange(len(ref) - delta) if all_pairs else np.arange(0, len(ref), delta)[:-1]
    Q, P = ref.matrices(), est.matrices()
    i, j = starts, starts + delta
    E = np.linalg.inv(np.linalg.inv(Q[i]) @ Q[j]) @ (np.linalg.inv(P[i]) @ P[j])
    cos = np.clip((np.trace(E[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(np.arccos(cos))


# --------------------------------------------------------------------------- per-sequence results -> report


@dataclass
class SequenceResult:
    """Everything measured on one sequence of ``N`` frames.

    Poses are ``T_wc`` (``t (N, 3)`` m, ``q (N, 4)`` ``(w, x, y, z)``). ``rel_t``/``rel_q`` are the
    predicted ``T_{k-1}^{-1} T_k`` (row 0 ignored) or None when there is no odometry. ``confusion``
    ``(C, C)`` is accumulated over frames (label maps are not kept: they would not fit in memory on
    long sequences) or None without labels; ``ms (N,)`` per-frame time or None. ``samples`` are a
    few ``(image (H, W, 3) uint8, predicted (H, W), true (H, W) | None)`` for the plots.
    """

    name: str
    stamps: np.ndarray
    true_t: np.ndarray
    true_q: np.ndarray
    pred_t: np.ndarray
    pred_q: np.ndarray
    rel_t: np.ndarray | None = None
    rel_q: np.ndarray | None = None
    confusion: np.ndarray | None = None
    ms: np.ndarray | None = None
    samples: tuple = ()

    def ground_truth(self) -> Trajectory:
        return Trajectory(self.stamps, self.true_t, self.true_q)

    def global_pose(self) -> Trajectory:
        return Trajectory(self.stamps, self.pred_t, self.pred_q)

    def odometry(self) -> Trajectory | None:
        """The relative poses chained from the ground-truth first pose, or None without odometry."""
        if self.rel_t is None or self.rel_q is None or len(self.stamps) == 0:
            return None
        t, q = accumulate_odometry(self.true_t[0], self.true_q[0], self.rel_t, self.rel_q)
        return Trajectory(self.stamps, t, q)


class SequenceRecorder:
    """Collects one sequence frame by frame (``add``, ``add_labels``, ``add_sample``) into a :class:`SequenceResult`."""

    def __init__(self, name: str, num_classes: int = len(CLASS_NAMES)):
        self.name = name
        self.num_classes = num_classes
        self._rows: dict[str, list] = {
            k: [] for k in ("stamps", "true_t", "true_q", "pred_t", "pred_q", "rel_t", "rel_q", "ms")
        }
        self._confusion: np.ndarray | None = None
        self._samples: list = []

    def __len__(self) -> int:
        return len(self._rows["stamps"])

    def add(
        self, stamp: float, true_t, true_q, pred_t, pred_q, rel_t=None, rel_q=None, ms: float | None = None
    ) -> None:
        """One frame: ground-truth and predicted global pose, predicted relative pose (None on the first frame is
        fine)."""
        identity = rel_t is None and len(self) == 0
        rows = self._rows
        rows["stamps"].append(float(stamp))
        for key, value in (("true_t", true_t), ("true_q", true_q), ("pred_t", pred_t), ("pred_q", pred_q)):
            rows[key].append(np.asarray(value, np.float64))
        rows["rel_t"].append(np.zeros(3) if identity else rel_t)
        rows["rel_q"].append(np.array([1.0, 0, 0, 0]) if identity else rel_q)
        rows["ms"].append(ms)

    def add_labels(self, labels_true: np.ndarray, labels_pred: np.ndarray) -> None:
        """Accumulate one frame's label maps into the confusion matrix."""
        conf = confusion_matrix(labels_true, labels_pred, self.num_classes)
        self._confusion = conf if self._confusion is None else self._confusion + conf

    def add_sample(self, image: np.ndarray, labels_pred: np.ndarray, labels_true: np.ndarray | None) -> None:
        """Keep a frame for the segmentation strip plot."""
        self._samples.append(
            (np.asarray(image), np.asarray(labels_pred), None if labels_true is None else np.asarray(labels_true))
        )

    def result(self) -> SequenceResult:
        rows = self._rows
        has_rel = all(r is not None for r in rows["rel_t"]) and all(r is not None for r in rows["rel_q"])
        has_ms = all(m is not None for m in rows["ms"])
        n = len(self)

        def stack(key: str, width: int) -> np.ndarray:
            return np.asarray(rows[key], np.float64).reshape(n, width)

        return SequenceResult(
            name=self.name,
            stamps=np.asarray(rows["stamps"], np.float64),
            true_t=stack("true_t", 3),
            true_q=stack("true_q", 4),
            pred_t=stack("pred_t", 3),
            pred_q=stack("pred_q", 4),
            rel_t=stack("rel_t", 3) if has_rel else None,
            rel_q=stack("rel_q", 4) if has_rel else None,
            confusion=self._confusion,
            ms=np.asarray(rows["ms"], np.float64) if has_ms else None,
            samples=tuple(self._samples),
        )


def evaluate_sequences(
    results: Sequence[SequenceResult],
    thresholds: Sequence[tuple[float, float]] = DEFAULT_THRESHOLDS,
    odometry_lengths_m: Sequence[float] | None = None,
    class_names: Sequence[str] = CLASS_NAMES,
) -> dict:
    """The report ``{"overall": {...}, "per_sequence": {name: {...}}}``, each with ``pose``, ``odometry``,
    ``segmentation``, ``timing`` (see the module docstring). Overall numbers pool the frames (pose,
    timing), segments (odometry) and confusion matrices (segmentation) of all sequences.
    ``odometry_lengths_m`` None: :func:`default_odometry_lengths` of the ground-truth path lengths.
    """
    if odometry_lengths_m is None:
        odometry_lengths_m = default_odometry_lengths([r.ground_truth().path_length() for r in results])
    per_sequence: dict[str, dict] = {}
    pooled: dict[str, list] = {"trans": [], "rot": [], "t_seg": [], "r_seg": [], "steps": [], "ms": []}
    total_conf = None
    for r in results:
        trans, rot = pose_errors(r.pred_t, r.pred_q, r.true_t, r.true_q)
        odom = r.odometry()
        if odom is not None:
            t_seg, r_seg = kitti_segment_errors(pose_to_matrix(r.true_t, r.true_q), odom.matrices(), odometry_lengths_m)
            steps = step_ratios(r.true_t, r.rel_t)
        else:
            t_seg, r_seg, steps = np.zeros(0), np.zeros(0), np.zeros(0)
        per_sequence[r.name] = {
            "pose": pose_metrics(trans, rot, thresholds),
            "odometry": odometry_metrics(t_seg, r_seg, odometry_lengths_m, steps),
            "segmentation": segmentation_metrics(r.confusion, class_names),
            "timing": timing_metrics(r.ms),
        }
        for key, value in (
            ("trans", trans),
            ("rot", rot),
            ("t_seg", t_seg),
            ("r_seg", r_seg),
            ("steps", steps),
            ("ms", r.ms),
        ):
            if value is not None:
                pooled[key].append(value)
        if r.confusion is not None:
            total_conf = r.confusion if total_conf is None else total_conf + r.confusion

    def cat(key: str) -> np.ndarray:
        return np.concatenate(pooled[key]) if pooled[key] else np.zeros(0)

    overall = {
        "pose": pose_metrics(cat("trans"), cat("rot"), thresholds),
        "odometry": odometry_metrics(cat("t_seg"), cat("r_seg"), odometry_lengths_m, cat("steps")),
        "segmentation": segmentation_metrics(total_conf, class_names),
        "timing": timing_metrics(cat("ms") if pooled["ms"] else None),
    }
    return {"overall": overall, "per_sequence": per_sequence}

"""Scores of the refinement and of the structure-based baseline, on the frames a localizer was scored on.

* ``report["overall"]["pose_refined"]`` (and per sequence): the published pose (refined, propagated or the
  network's), with the keys of ``pose``; ``report["overall"]["refinement"]``: the share of frames per source, the
  fallback reasons, the median inlier count and the covariance calibration (:func:`calibration`).
* ``report["structure_baseline"]``: retrieval + SIFT + PnP without the network (:meth:`.refiner.Refiner.locate`),
  shaped like the retrieval ``baseline``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.evaluation.metrics import DEFAULT_THRESHOLDS, evaluate_sequences

STRUCTURE_NAME = "structure-based"
STRUCTURE_METHOD = (
    "the 4 map keyframes most similar to the image (gradient thumbnails), SIFT ratio-test matches, "
    "AP3P RANSAC + Levenberg-Marquardt; the most similar keyframe's pose under 20 inliers; no network"
)


@dataclass
class RefinedTrack:
    """One sequence's published poses (``t``, ``q`` ``T_map,cam``), their source, inliers and standard deviations
    ``(6,)`` (ROS pose-covariance order), one row per frame the localizer scored."""

    t: list = field(default_factory=list)
    q: list = field(default_factory=list)
    source: list = field(default_factory=list)
    status: list = field(default_factory=list)
    inliers: list = field(default_factory=list)
    sigma: list = field(default_factory=list)

    def add(self, out) -> None:
        """Record a :class:`~vlocnetpp_core.inference.localizer.LocalizerResult`."""
        self.t.append(out.t)
        self.q.append(out.q)
        self.source.append(out.source)
        self.status.append(out.refine_status)
        self.inliers.append(out.inliers)
        self.sigma.append(np.sqrt(np.diag(out.pose_covariance)))


def with_poses(results: Sequence, poses: Sequence[tuple[np.ndarray, np.ndarray]]) -> list:
    """``results`` (``SequenceResult``s) with ``poses[k] = (t (N_k, 3), q (N_k, 4))`` as the prediction, and no
    odometry, segmentation or timing: what the pose metrics of another localizer on the same frames need."""
    out = []
    for r, (t, q) in zip(results, poses, strict=True):
        if len(t) != len(r.stamps):
            raise ValueError(f"{r.name}: {len(t)} poses for {len(r.stamps)} frames")
        out.append(
            replace(
                r,
                pred_t=np.asarray(t, np.float64),
                pred_q=np.asarray(q, np.float64),
                rel_t=None,
                rel_q=None,
                confusion=None,
                ms=None,
                samples=(),
            )
        )
    return out


def normalised_errors(true_t, true_q, t, q, sigma) -> np.ndarray:
    """``(N, 6)`` errors of poses ``t, q`` against the truth, position and map-frame rotation vector
    (``R_true = exp([e]x) R``), divided by the claimed standard deviations ``sigma (N, 6)``."""
    dq = geometry.quat_mul(np.asarray(true_q, np.float64), geometry.quat_inverse(np.asarray(q, np.float64)))
    dq = dq * np.where(dq[:, :1] < 0, -1.0, 1.0)
    s = np.linalg.norm(dq[:, 1:], axis=1, keepdims=True)
    rotvec = dq[:, 1:] / np.maximum(s, 1e-12) * 2 * np.arctan2(s, dq[:, :1])
    return np.concatenate((np.asarray(true_t) - np.asarray(t), rotvec), axis=1) / np.asarray(sigma)


def calibration(errors: np.ndarray) -> dict:
    """How well covariances describe ``errors (N, 6)`` (normalised): the RMS of the normalised position and rotation
    errors (1 when calibrated) and the share within 1 and 2 sigma per axis (0.683, 0.954 for Gaussian errors)."""
    if len(errors) == 0:
        return {"frames": 0, "rms_position": None, "rms_rotation": None, "within_1_sigma": None, "within_2_sigma": None}
    return {
        "frames": len(errors),
        "rms_position": float(np.sqrt(np.mean(errors[:, :3] ** 2))),
        "rms_rotation": float(np.sqrt(np.mean(errors[:, 3:] ** 2))),
        "within_1_sigma": float(np.mean(np.abs(errors) <= 1)),
        "within_2_sigma": float(np.mean(np.abs(errors) <= 2)),
    }


def add_pose_refined(
    report: dict, results: Sequence, poses: Sequence[tuple[np.ndarray, np.ndarray]], thresholds=DEFAULT_THRESHOLDS
) -> dict:
    """Store the metrics of the published poses ``poses`` (per sequence ``(t (N_k, 3), q (N_k, 4))``) on the frames of
    ``results`` as ``pose_refined``, overall and per sequence (the keys of ``pose``)."""
    scored = evaluate_sequences(with_poses(results, poses), thresholds, [1.0])
    report["overall"]["pose_refined"] = scored["overall"]["pose"]
    for name, part in scored["per_sequence"].items():
        report["per_sequence"][name]["pose_refined"] = part["pose"]
    return report


def add_refined(report: dict, results: Sequence, tracks: Sequence[RefinedTrack], thresholds=DEFAULT_THRESHOLDS) -> dict:
    """Store the published poses' metrics as ``pose_refined`` (overall and per sequence) and ``overall.refinement``."""
    add_pose_refined(report, results, [(tr.t, tr.q) for tr in tracks], thresholds)
    sources = Counter(s for tr in tracks for s in tr.source)
    statuses = Counter(
        s for tr in tracks for s, src in zip(tr.status, tr.source, strict=True) if s is not None and src != "refined"
    )
    n = sum(sources.values())
    refined = [(r, tr, np.array(tr.source) == "refined") for r, tr in zip(results, tracks, strict=True)]
    errors = [
        normalised_errors(r.true_t[m], r.true_q[m], np.array(tr.t)[m], np.array(tr.q)[m], np.array(tr.sigma)[m])
        for r, tr, m in refined
        if m.any()
    ]
    inliers = [i for tr in tracks for i, s in zip(tr.inliers, tr.source, strict=True) if s == "refined"]
    report["overall"]["refinement"] = {
        "share": {s: sources.get(s, 0) / max(n, 1) for s in ("refined", "propagated", "network")},
        "fallback_reasons": dict(sorted(statuses.items())),
        "median_inliers": float(np.median(inliers)) if inliers else None,
        "calibration": calibration(np.concatenate(errors) if errors else np.zeros((0, 6))),
    }
    return report


def add_structure_baseline(
    report: dict,
    results: Sequence,
    poses: Sequence[tuple[np.ndarray, np.ndarray]],
    map_source: str,
    keyframes: int,
    thresholds=DEFAULT_THRESHOLDS,
) -> dict:
    """Score the structure-based baseline's ``poses`` (per sequence) on the frames of ``results`` as
    ``report["structure_baseline"]``."""
    report["structure_baseline"] = {
        "name": STRUCTURE_NAME,
        "method": STRUCTURE_METHOD,
        "map": map_source,
        "map_keyframes": keyframes,
        **scored_poses(results, poses, thresholds),
    }
    return report


def scored_poses(
    results: Sequence, poses: Sequence[tuple[np.ndarray, np.ndarray]], thresholds=DEFAULT_THRESHOLDS
) -> dict:
    """The pose metrics of ``poses[k] = (t (N_k, 3), q (N_k, 4))`` on the frames of ``results[k]``: ``overall`` and
    ``per_sequence``, each ``{"pose": ...}``."""
    scored = evaluate_sequences(with_poses(results, poses), thresholds, [1.0])
    return {
        "overall": {"pose": scored["overall"]["pose"]},
        "per_sequence": {name: {"pose": part["pose"]} for name, part in scored["per_sequence"].items()},
    }


def refinement_lines(report: dict) -> list[str]:
    """Lines for under the results table: the sources, fallback reasons, inliers and covariance calibration."""
    ref = report["overall"].get("refinement")
    if not ref:
        return []
    share, cal = ref["share"], ref["calibration"]
    lines = [
        f"refinement: {100 * share['refined']:.1f} % of frames refined, {100 * share['propagated']:.1f} % propagated, "
        f"{100 * share['network']:.1f} % the network's pose; median {ref['median_inliers'] or 0:.0f} inliers"
    ]
    if ref["fallback_reasons"]:
        lines.append("  not refined: " + ", ".join(f"{k} {v}" for k, v in ref["fallback_reasons"].items()))
    if cal["frames"]:
        lines.append(
            f"  covariance of refined poses: normalised RMS position {cal['rms_position']:.2f}, rotation "
            f"{cal['rms_rotation']:.2f} (1 = calibrated); within 1 / 2 sigma {100 * cal['within_1_sigma']:.0f} / "
            f"{100 * cal['within_2_sigma']:.0f} % (68 / 95 for Gaussian errors)"
        )
    return lines

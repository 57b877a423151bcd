"""Comparing two metric reports of ``evaluate_sequences`` (the bag tests' oracle), leaf by leaf.

Two cases:

* the same poses on both sides, up to float64 round trips (a pose written to a bag and read back,
  a quaternion normalised again): every number agrees to a relative ``1e-9``, far above the ~1e-15
  those round trips change (the default of :func:`assert_same_metrics`);
* poses that agree only to ``pose_atol`` per component (the node over DDS against the in-process
  replay, run with other thread counts): :func:`pose_tolerances` gives each metric the absolute
  tolerance that follows from that bound.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from vlocnetpp_core.bag.matched_frames import MatchedFrames
from vlocnetpp_core.evaluation.metrics import DEFAULT_THRESHOLDS, MIN_STEP_M, accuracy_key, pose_errors

SCORED_PARTS = ("pose", "odometry", "segmentation")  # a bag holds no step times, so "timing" is left out
# Rounding of an angle computed as acos of a float64 dot product or trace: near 1, acos(1 - d) ~ sqrt(2 d),
# so a few ulps (8 eps) of the argument move it by at most sqrt(2 * 8 eps) rad; 2 acos doubles that.
ACOS_ROUNDING_RAD = 2.0 * math.sqrt(2.0 * 8.0 * np.finfo(np.float64).eps)

Tolerance = Callable[[str, str, str], float]  # (scope "overall"/"seq-NN", part, leaf key) -> absolute tolerance


def assert_same_metrics(want: dict, got: dict, rel: float = 1e-9, tolerance: Tolerance | None = None) -> None:
    """``got`` equals ``want`` in every pose, odometry and segmentation number, per sequence and overall:
    to a relative ``rel`` (same poses, see module doc), or to the absolute ``tolerance(scope, part, key)``."""
    assert got["per_sequence"].keys() == want["per_sequence"].keys()
    pairs = [("overall", want["overall"], got["overall"])]
    pairs += [(name, part, got["per_sequence"][name]) for name, part in want["per_sequence"].items()]
    for name, w, g in pairs:
        for part in SCORED_PARTS:
            for key in w[part]:
                tol = None if tolerance is None else tolerance(name, part, key)
                _leaf_equal(w[part][key], g[part].get(key), f"{name}/{part}/{key}", rel, tol)
            assert g[part].keys() == w[part].keys(), f"{name}/{part}"


def _leaf_equal(w, g, path: str, rel: float, tol: float | None) -> None:
    if isinstance(w, dict):
        assert isinstance(g, dict) and w.keys() == g.keys(), path
        for k in w:
            _leaf_equal(w[k], g[k], f"{path}/{k}", rel, tol)
    elif isinstance(w, list):
        assert isinstance(g, list) and len(w) == len(g), path
        for i, (u, v) in enumerate(zip(w, g, strict=True)):
            _leaf_equal(u, v, f"{path}[{i}]", rel, tol)
    elif isinstance(w, float):
        if tol is None:
            assert g == pytest.approx(w, rel=rel, abs=1e-12), path
        else:
            assert isinstance(g, float) and abs(g - w) <= tol, (path, w, g, tol)
    else:
        assert g == w, path


def pose_tolerances(
    frames: MatchedFrames,
    lengths_m: list[float],
    pose_atol: float,
    thresholds: tuple[tuple[float, float], ...] = DEFAULT_THRESHOLDS,
) -> Tolerance:
    """Absolute tolerance of each metric when every component of the global and odometry poses (metres,
    unit quaternions) may differ by ``pose_atol`` between the two reports and the masks are equal.

    ``frames``: the matched frames of one of the two bags (ground truth, poses, sequences);
    ``lengths_m``: the odometry segment lengths of the report. With ``e = pose_atol``:

    * a position moves by at most ``sqrt(3) e``; an orientation, whose four components move by at
      most ``e`` (at most ``2 e`` in all), turns by at most ``theta = 4 asin(e)`` rad;
    * per-frame errors move by at most those amounts (triangle inequality), and so do their
      medians: ``median_translation_m`` by ``sqrt(3) e``, ``median_rotation_deg`` by ``theta``
      (plus the rounding of the acos that computes it);
    * an ``accuracy_*`` share changes only through frames whose error lies within that distance of
      its threshold: their number over the frames scored;
    * odometry: a segment compares ``O_s^-1 O_e`` of the accumulated poses with the truth; its
      translation moves by at most ``theta * D + 2 sqrt(3) e`` (``D``: the largest distance between two
      odometry positions) and its rotation by ``2 theta``, each divided by the segment length, at
      least the shortest one, and so does their mean over the segments; a predicted step length moves by at
      most ``2 sqrt(3) e``, so ``step_scale`` (a median of step ratios) by that over the shortest true step;
    * segmentation scores come from equal masks and the same labels: equal (tolerance 0);
      ``lengths_m`` follow from the ground truth alone: equal.
    """
    theta = 4.0 * math.asin(min(1.0, pose_atol))
    trans = math.sqrt(3.0) * pose_atol
    rot_deg = math.degrees(theta + ACOS_ROUNDING_RAD)
    odom = frames.odom_t[~np.isnan(frames.odom_t).any(axis=1)]
    diameter = float(np.linalg.norm(odom[:, None] - odom[None], axis=-1).max()) if len(odom) else 0.0
    shortest = min(lengths_m) if lengths_m else math.inf
    # the pairs metrics.step_ratios counts: consecutive frames of one sequence that moved at least MIN_STEP_M
    steps = np.concatenate(
        [np.zeros(0)]
        + [np.linalg.norm(np.diff(frames.true_t[r.start : r.stop], axis=0), axis=1) for r in frames.sequences]
    )
    moved = steps[steps >= MIN_STEP_M]
    min_step = float(moved.min()) if len(moved) else math.inf
    odometry = {
        "translation_error_percent": 100.0 * (theta * diameter + 2.0 * trans) / shortest,
        "rotation_error_deg_per_m": math.degrees(2.0 * theta + ACOS_ROUNDING_RAD) / shortest,
        "step_scale": 2.0 * trans / min_step,
    }
    t_err, r_err = pose_errors(frames.pred_t, frames.pred_q, frames.true_t, frames.true_q)
    scopes = {"overall": np.arange(len(frames.stamps))} | {
        f"seq-{k:02d}": np.asarray(r) for k, r in enumerate(frames.sequences)
    }
    accuracy = {}
    for scope, rows in scopes.items():
        for metres, degrees in thresholds:
            near = (np.abs(t_err[rows] - metres) <= trans) | (np.abs(r_err[rows] - degrees) <= rot_deg)
            accuracy[(scope, accuracy_key(metres, degrees))] = int(near.sum()) / max(1, len(rows))

    def tolerance(scope: str, part: str, key: str) -> float:
        if part == "pose":
            return {"median_translation_m": trans, "median_rotation_deg": rot_deg}.get(
                key, accuracy.get((scope, key), 0.0)
            )
        if part == "odometry":
            return odometry.get(key, 0.0)
        return 0.0

    return tolerance

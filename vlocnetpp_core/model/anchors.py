"""Anchors of the global pose head: k-means of the training positions (config ``global_pose_anchors``) and
of the training rotations (config ``global_rotation_anchors``)."""

from __future__ import annotations

import numpy as np
from scipy.cluster.vq import kmeans2

from vlocnetpp_core.geometry import quat_normalize


def kmeans_anchors(positions: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """``count`` anchor points ``(count, D)`` from training points ``(M, D)`` (positions: ``D = 3``, metres, world
    frame).

    The k-means centres of the positions (k-means++ start, ``seed`` fixes the result). With fewer
    distinct positions than ``count`` (a tiny dataset) every distinct position is an anchor and the
    list repeats to ``count``: a repeated anchor splits its score without changing the position.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or len(positions) == 0:
        raise ValueError(f"positions must be a non-empty (M, D) array, got shape {positions.shape}")
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    distinct = np.unique(positions, axis=0)
    if len(distinct) <= count:
        return distinct[np.arange(count) % len(distinct)]
    centres, labels = kmeans2(positions, count, minit="++", seed=seed)
    empty = np.setdiff1d(np.arange(count), labels)
    # an empty cluster keeps a meaningless centre: put it on the position farthest from every centre
    for k in empty:
        far = np.linalg.norm(positions[:, None] - np.delete(centres, k, axis=0)[None], axis=2).min(axis=1).argmax()
        centres[k] = positions[far]
    return centres


def rotation_anchors(quats: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """``count`` anchor rotations ``(count, 4)``, unit ``(w, x, y, z)`` with ``w >= 0``, from training
    quaternions ``(M, 4)`` (world frame): the k-means centres of the quaternions on the ``w >= 0``
    hemisphere (``q`` and ``-q`` are one rotation), normalised. Rotations near a half turn sit on
    both edges of that hemisphere and may get an anchor on each, which is harmless."""
    quats = np.asarray(quats, dtype=np.float64)
    if quats.ndim != 2 or quats.shape[1] != 4:
        raise ValueError(f"quats must be an (M, 4) array, got shape {quats.shape}")
    return quat_normalize(kmeans_anchors(quat_normalize(quats), count, seed))

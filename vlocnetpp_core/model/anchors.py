"""Position anchors of the global pose head (config ``global_pose_anchors``): k-means of training positions."""

from __future__ import annotations

import numpy as np
from scipy.cluster.vq import kmeans2


def kmeans_anchors(positions: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """``count`` anchor positions ``(count, 3)`` metres from training positions ``(M, 3)`` metres (world frame).

    The k-means centres of the positions (k-means++ start, ``seed`` fixes the result). With fewer
    distinct positions than ``count`` (a tiny dataset) every distinct position is an anchor and the
    list repeats to ``count``: a repeated anchor splits its score without changing the position.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) == 0:
        raise ValueError(f"positions must be a non-empty (M, 3) array, got shape {positions.shape}")
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

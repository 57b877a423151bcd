"""Local features of the map and of the query images: SIFT keypoints with uint8 descriptors, ratio-test matching.

Why SIFT (measured on the synthetic campus, 320x180 images, docs/results.md, refinement): against a map of
every 8th training frame, with keyframes chosen near a pose prior, SIFT put 97 % of the frames of a fresh
visit within 0.1 m / 1 deg (median 9 mm) and ORB (1500 features, FAST threshold 5) 88 % (median 42 mm, with
3x the features to match); SIFT costs about 15-25 ms an image on one core against ORB's 2-6 ms. OpenCV's
default contrast threshold (0.04) finds about 130 keypoints on these smooth rendered images, 0.02 about 300-450.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vlocnetpp_core.classes import CLASS_NAMES

DESCRIPTOR_SIZE = 128


@dataclass(frozen=True)
class FeatureConfig:
    """SIFT settings (OpenCV names): at most ``max_features`` keypoints of contrast above ``contrast_threshold``;
    matches kept where the nearest descriptor is closer than ``ratio`` times the second nearest (Lowe)."""

    max_features: int = 1500
    contrast_threshold: float = 0.02
    ratio: float = 0.8

    def to_dict(self) -> dict:
        return {
            "kind": "sift",
            "max_features": self.max_features,
            "contrast_threshold": self.contrast_threshold,
            "ratio": self.ratio,
        }

    @classmethod
    def from_dict(cls, d: dict) -> FeatureConfig:
        if d.get("kind", "sift") != "sift":
            raise ValueError(f"unknown feature kind {d.get('kind')!r} (this version reads 'sift')")
        return cls(int(d["max_features"]), float(d["contrast_threshold"]), float(d["ratio"]))


@dataclass
class Features:
    """``uv (N, 2) float32`` pixel coordinates and ``descriptors (N, 128) uint8`` of one image."""

    uv: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)

    def select(self, keep: np.ndarray) -> Features:
        """The features where ``keep (N,) bool``."""
        return Features(self.uv[keep], self.descriptors[keep])


DYNAMIC_CLASS = CLASS_NAMES.index(
    "Dynamic"
)  # cars and people: where they stood in the map says nothing of a later visit


def off_dynamic(uv: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """``(N,) bool``: the keypoints ``uv (N, 2)`` (pixels of an image of the size of ``labels``) at least 2 pixels away
    from the :data:`DYNAMIC_CLASS` pixels of the class-id map ``labels (H, W)``."""
    dynamic = cv2.dilate((labels == DYNAMIC_CLASS).astype(np.uint8), np.ones((5, 5), np.uint8))
    h, w = labels.shape
    col = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    return dynamic[row, col] == 0


def to_grey(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` RGB or ``(H, W)`` uint8 -> ``(H, W)`` uint8 grey."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


class FeatureExtractor:
    """SIFT on grey images. One instance per thread (OpenCV detectors keep state)."""

    def __init__(self, config: FeatureConfig = FeatureConfig()):
        self.config = config
        self._sift = cv2.SIFT_create(config.max_features, contrastThreshold=config.contrast_threshold)

    def __call__(self, grey: np.ndarray) -> Features:
        """``(H, W) uint8`` -> its :class:`Features` (none on a flat image)."""
        keypoints, descriptors = self._sift.detectAndCompute(grey, None)
        if descriptors is None or not keypoints:
            return Features(np.zeros((0, 2), np.float32), np.zeros((0, DESCRIPTOR_SIZE), np.uint8))
        uv = np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2)
        return Features(uv, np.clip(np.round(descriptors), 0, 255).astype(np.uint8))


def match(query: np.ndarray, train: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ratio-test matches of descriptors ``query (N, 128)`` against ``train (M, 128)`` (uint8): each query's nearest
    train descriptor in L2 where it is closer than ``ratio`` times the second nearest;
    ``(query_index (K,), train_index (K,), distance (K,))``. Brute force, as OpenCV's BFMatcher."""
    if len(query) == 0 or len(train) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
    q, t = query.astype(np.float32), train.astype(np.float32)
    # (N, M) squared distances; OpenCV's product rather than numpy's, whose BLAS threads would spin beside the network
    d2 = (
        cv2.gemm(q, t, -2.0, None, 0.0, flags=cv2.GEMM_2_T)
        + np.einsum("ij,ij->i", q, q)[:, None]
        + np.einsum("ij,ij->i", t, t)[None, :]
    )
    rows = np.arange(len(q))
    nearest = d2.argmin(axis=1)
    best = np.maximum(d2[rows, nearest], 0.0)
    d2[rows, nearest] = np.inf
    good = best < ratio * ratio * d2.min(axis=1)
    return rows[good].astype(np.int64), nearest[good].astype(np.int64), np.sqrt(best[good]).astype(np.float32)

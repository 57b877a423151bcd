"""The map: keyframes of the training images with their pose, intrinsics, local features and the features' 3D points.

File: one ``.npz`` (no pickle), written atomically (temporary file renamed into place), read back with
named errors. Arrays (``K`` keyframes, ``N`` features in all, keyframe ``k`` owning ``offsets[k]:offsets[k+1]``):

* ``t (K, 3)``, ``q (K, 4)``: ``T_map,cam`` of each keyframe; ``intrinsics (K, 4)``: ``fx, fy, cx, cy`` and
  ``image_sizes (K, 2)``: ``W, H`` of its image;
* ``uv (N, 2) float32`` keypoints in the keyframe's image, ``points (N, 3) float32`` their positions in the
  map frame (metres), ``descriptors (N, 128) uint8`` (:mod:`.features`);
* ``thumbnails (K, 288)``: the keyframe images' retrieval descriptors
  (:func:`vlocnetpp_core.evaluation.retrieval.describe`), which the structure-based baseline ranks keyframes by;
* ``meta``: JSON with the format version, the feature settings and the source datasets.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlocnetpp_core.errors import DataError
from vlocnetpp_core.mapping.features import DESCRIPTOR_SIZE, FeatureConfig

FORMAT_VERSION = 1
ANGLE_WEIGHT_M_PER_RAD = 4.0  # keyframe ranking near a prior: 1 m of distance weighs as much as 14 deg of viewing angle
_ARRAYS = ("t", "q", "intrinsics", "image_sizes", "offsets", "uv", "points", "descriptors", "thumbnails")


@dataclass
class KeyframeMap:
    """Keyframes (see the module docstring for the arrays' shapes and units)."""

    t: np.ndarray
    q: np.ndarray
    intrinsics: np.ndarray
    image_sizes: np.ndarray
    offsets: np.ndarray
    uv: np.ndarray
    points: np.ndarray
    descriptors: np.ndarray
    thumbnails: np.ndarray
    features: FeatureConfig = field(default_factory=FeatureConfig)
    source: str = ""

    def __post_init__(self) -> None:
        k, n = len(self.t), len(self.uv)
        shapes = {
            "t": (k, 3),
            "q": (k, 4),
            "intrinsics": (k, 4),
            "image_sizes": (k, 2),
            "offsets": (k + 1,),
            "uv": (n, 2),
            "points": (n, 3),
            "descriptors": (n, DESCRIPTOR_SIZE),
        }
        bad = [
            f"{name} {getattr(self, name).shape} (want {want})"
            for name, want in shapes.items()
            if getattr(self, name).shape != want
        ]
        if k == 0:
            bad.append("no keyframes")
        elif self.thumbnails.ndim != 2 or len(self.thumbnails) != k:
            bad.append(f"thumbnails {self.thumbnails.shape} (want ({k}, D))")
        elif self.offsets[0] != 0 or self.offsets[-1] != n or np.any(np.diff(self.offsets) < 0):
            bad.append("offsets do not partition the features")
        if bad:
            raise ValueError("inconsistent keyframe map: " + "; ".join(bad))
        self.axes = _optical_axes(self.q)  # (K, 3) unit viewing directions in the map frame

    def __len__(self) -> int:
        return len(self.t)

    @property
    def num_points(self) -> int:
        return len(self.uv)

    def keyframe(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keyframe ``k``'s ``uv (n, 2)``, ``points (n, 3)`` and ``descriptors (n, 128)``."""
        a, b = self.offsets[k], self.offsets[k + 1]
        return self.uv[a:b], self.points[a:b], self.descriptors[a:b]

    def near(self, t: np.ndarray, q: np.ndarray, count: int, max_distance_m: float, max_angle_deg: float) -> np.ndarray:
        """Up to ``count`` keyframes within ``max_distance_m`` of position ``t`` and ``max_angle_deg`` of the viewing
        direction of ``q``, closest first (distance plus :data:`ANGLE_WEIGHT_M_PER_RAD` times the angle)."""
        distance = np.linalg.norm(self.t - np.asarray(t, np.float64), axis=1)
        angle = np.arccos(np.clip(self.axes @ _optical_axes(np.asarray(q, np.float64)[None])[0], -1.0, 1.0))
        ok = np.flatnonzero((distance <= max_distance_m) & (angle <= np.radians(max_angle_deg)))
        score = distance[ok] + ANGLE_WEIGHT_M_PER_RAD * angle[ok]
        return ok[np.argsort(score, kind="stable")[:count]]

    def save(self, path: str | Path) -> Path:
        """Write the map to ``path`` (``.npz``), atomically; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp.npz")
        meta = {"format_version": FORMAT_VERSION, "features": self.features.to_dict(), "source": self.source}
        try:
            np.savez_compressed(tmp, meta=np.array(json.dumps(meta)), **{name: getattr(self, name) for name in _ARRAYS})
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return path

    @classmethod
    def load(cls, path: str | Path) -> KeyframeMap:
        """Read what :meth:`save` wrote; ``DataError`` naming the file when it is not such a map."""
        try:
            with np.load(path, allow_pickle=False) as f:
                meta = json.loads(str(f["meta"]))
                arrays = {name: f[name] for name in _ARRAYS}
        except FileNotFoundError:
            raise DataError(path, "no such map file (build one with 'vlocnetpp map build')") from None
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as err:
            raise DataError(path, f"not a keyframe map written by 'vlocnetpp map build' ({err})") from None
        if meta.get("format_version") != FORMAT_VERSION:
            raise DataError(
                path, f"map format version {meta.get('format_version')!r}, this version reads {FORMAT_VERSION}"
            )
        try:
            return cls(**arrays, features=FeatureConfig.from_dict(meta["features"]), source=str(meta.get("source", "")))
        except (ValueError, KeyError) as err:
            raise DataError(path, str(err)) from None


def _optical_axes(q: np.ndarray) -> np.ndarray:
    """``q (K, 4)`` ``(w, x, y, z)`` camera-to-world -> ``(K, 3)`` the camera z axes in the world frame."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack((2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)), axis=1)

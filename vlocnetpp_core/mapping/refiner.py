"""Refinement of a pose prior against the keyframe map, and the structure-based baseline (no network).

:meth:`Refiner.refine` (what the :class:`~vlocnetpp_core.inference.localizer.Localizer` runs): the keyframes near the
odometry's prediction from the last refined pose (when there is one) and near the network's pose are matched
with the frame's SIFT features (ratio test, per keyframe; of several matches of one keypoint the closest is
kept), and PnP (:mod:`.pnp`) solves for the pose. It is accepted only when it has at least ``min_inliers``
inliers, an inlier reprojection error of at most ``max_rms_px``, and agrees with the odometry's prediction
(``odometry_agreement``) or, without one or failing that, with the network's pose (``network_agreement``);
else the status says why and the caller keeps the network's pose.

:meth:`Refiner.locate` is the structure-based baseline: the same matching and PnP with the keyframes most similar
to the image (gradient thumbnails, :mod:`vlocnetpp_core.evaluation.retrieval`) instead of a prior, and the most similar
keyframe's pose when PnP finds fewer than ``min_inliers`` inliers (hloc's recipe, without a network).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlocnetpp_core.mapping.features import FeatureExtractor, Features, match, to_grey
from vlocnetpp_core.mapping.keyframe_map import KeyframeMap
from vlocnetpp_core.mapping.pnp import PoseSolution, solve_pnp

STATUSES = (
    "refined",
    "no_features",
    "no_keyframes",
    "too_few_matches",
    "no_solution",
    "too_few_inliers",
    "reprojection",
    "disagrees",
)


@dataclass(frozen=True)
class RefinerConfig:
    """Keyframe search around a prior, PnP settings and the acceptance checks (metres, degrees, pixels)."""

    keyframes: int = 4  # keyframes matched per frame
    search_radius_m: float = 8.0  # keyframes considered around a prior
    search_angle_deg: float = 35.0
    ransac_px: float = 2.0
    ransac_iterations: int = 300
    min_inliers: int = 20
    max_rms_px: float = 1.5
    odometry_agreement: tuple[float, float] = (0.5, 5.0)  # m, deg from the odometry's prediction
    network_agreement: tuple[float, float] = (3.0, 15.0)  # m, deg from the network's pose
    # standard-deviation factors of the PnP covariance's position and rotation blocks: 2 sigma then holds 95 % of the
    # errors of each on the validation visits (seed 11; docs/refinement.md, "Calibration")
    covariance_scale: tuple[float, float] = (2.0, 0.55)


@dataclass
class Refinement:
    """The outcome for one frame: ``status`` ``"refined"`` with its ``solution``, or why not (``STATUSES``;
    ``solution`` then holds the rejected solution, if PnP found one); ``inliers`` of the solution (0 without);
    ``keyframes`` the map keyframes matched."""

    status: str
    solution: PoseSolution | None
    keyframes: np.ndarray

    @property
    def accepted(self) -> bool:
        return self.status == "refined"

    @property
    def inliers(self) -> int:
        return 0 if self.solution is None else len(self.solution.inliers)


class Refiner:
    """PnP against a :class:`KeyframeMap`. :meth:`extract` may run on another thread than the rest (one at a time)."""

    def __init__(self, keyframe_map: KeyframeMap, config: RefinerConfig = RefinerConfig()):
        from vlocnetpp_core.evaluation.retrieval import ReferenceSet

        self.map = keyframe_map
        self.config = config
        self._extractor = FeatureExtractor(keyframe_map.features)
        self._thumbnails = ReferenceSet(
            keyframe_map.thumbnails.astype(np.float32), keyframe_map.t, keyframe_map.q, "map keyframes"
        )

    @classmethod
    def from_file(cls, path, config: RefinerConfig = RefinerConfig()) -> Refiner:
        return cls(KeyframeMap.load(path), config)

    def extract(self, grey: np.ndarray) -> Features:
        """The SIFT features of a ``(H, W) uint8`` image, with the map's settings."""
        return self._extractor(grey)

    def prepare(self, image: np.ndarray, intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """``(grey, K)``: an ``(H, W, 3)`` RGB / ``(H, W)`` image with its
        :class:`~vlocnetpp_core.camera.intrinsics.Intrinsics` as grey, shrunk to the width of the map's keyframes where
        it is wider (features cost less, match alike), and its ``K (3, 3)`` at that size."""
        import cv2

        h, w = image.shape[:2]
        width = int(np.median(self.map.image_sizes[:, 0]))
        grey = to_grey(image)
        if w > width:
            size = (width, max(1, round(h * width / w)))
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
            intrinsics = intrinsics.resized(*size)
        return grey, intrinsics.matrix()

    def refine(
        self,
        features: Features,
        K: np.ndarray,
        network: tuple[np.ndarray, np.ndarray],
        odometry: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Refinement:
        """Refine the frame with ``features`` and intrinsics ``K (3, 3)`` given the network's pose and the
        odometry's prediction (``(t (3,), q (4,))`` each, ``T_map,cam``)."""
        c = self.config
        near = [
            self.map.near(*prior, c.keyframes, c.search_radius_m, c.search_angle_deg)
            for prior in (odometry, network)
            if prior is not None
        ]
        keyframes = np.array(list(dict.fromkeys(np.concatenate(near).tolist()))[: c.keyframes], np.int64)
        result = self._solve(features, K, keyframes)
        if result.solution is None or result.status != "refined":
            return result
        s = result.solution
        agrees = [
            prior is not None and _within(s, prior, limits)
            for prior, limits in ((odometry, c.odometry_agreement), (network, c.network_agreement))
        ]
        if not any(agrees):
            return Refinement("disagrees", s, keyframes)
        return result

    def locate(
        self, features: Features, thumbnail: np.ndarray, K: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, Refinement]:
        """The structure-based baseline: ``(t, q, refinement)``, the PnP pose against the keyframes most similar to
        the image's retrieval descriptor ``thumbnail (288,)``, or the most similar keyframe's pose when PnP fails."""
        keyframes = self._thumbnails.ranked(thumbnail, self.config.keyframes)
        result = self._solve(features, K, keyframes)
        if result.accepted:
            return result.solution.t, result.solution.q, result
        return self.map.t[keyframes[0]].copy(), self.map.q[keyframes[0]].copy(), result

    def locate_image(
        self, image: np.ndarray, intrinsics, thumbnail: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, Refinement]:
        """:meth:`locate` of an ``(H, W, 3)`` RGB image with its :class:`~vlocnetpp_core.camera.intrinsics.Intrinsics`
        and retrieval descriptor ``thumbnail (288,)`` (:func:`vlocnetpp_core.evaluation.retrieval.describe` of it)."""
        grey, K = self.prepare(image, intrinsics)
        return self.locate(self.extract(grey), thumbnail, K)

    def _solve(self, features: Features, K: np.ndarray, keyframes: np.ndarray) -> Refinement:
        """Match ``features`` with ``keyframes``, PnP, and the inlier and reprojection checks."""
        c = self.config
        if len(features) < c.min_inliers:
            return Refinement("no_features", None, keyframes)
        if len(keyframes) == 0:
            return Refinement("no_keyframes", None, keyframes)
        uv, points = self._correspondences(features, keyframes)
        if len(uv) < c.min_inliers:
            return Refinement("too_few_matches", None, keyframes)
        solution = solve_pnp(uv, points, K, c.ransac_px, c.ransac_iterations)
        if solution is None:
            return Refinement("no_solution", None, keyframes)
        if len(solution.inliers) < c.min_inliers:
            return Refinement("too_few_inliers", solution, keyframes)
        if solution.rms_px > c.max_rms_px:
            return Refinement("reprojection", solution, keyframes)
        factors = np.repeat(np.asarray(c.covariance_scale, np.float64), 3)
        solution.covariance = factors[:, None] * solution.covariance * factors[None, :]
        return Refinement("refined", solution, keyframes)

    def _correspondences(self, features: Features, keyframes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``uv (n, 2)`` of the frame and ``points (n, 3)`` of the map: per query keypoint its closest ratio-test match
        over ``keyframes``."""
        best_distance = np.full(len(features), np.inf, np.float32)
        best_point = np.zeros((len(features), 3), np.float32)
        for k in keyframes:
            _, points, descriptors = self.map.keyframe(int(k))
            qi, ki, dist = match(features.descriptors, descriptors, self.map.features.ratio)
            closer = dist < best_distance[qi]
            best_distance[qi[closer]], best_point[qi[closer]] = dist[closer], points[ki[closer]]
        found = np.isfinite(best_distance)
        return features.uv[found], best_point[found]


def _within(solution: PoseSolution, prior: tuple[np.ndarray, np.ndarray], limits: tuple[float, float]) -> bool:
    """Whether ``solution`` is within ``limits`` (metres, degrees) of ``prior`` ``(t, q)``."""
    t, q = prior
    dot = abs(float(np.dot(solution.q, q)))
    return (
        float(np.linalg.norm(solution.t - t)) <= limits[0]
        and float(np.degrees(2 * np.arccos(min(dot, 1.0)))) <= limits[1]
    )

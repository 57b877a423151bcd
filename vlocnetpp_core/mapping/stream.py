"""Refinement over a stream of frames: what the :class:`~vlocnetpp_core.inference.localizer.Localizer` calls around
the network.

Per frame, :meth:`RefinedStream.start` (before the network runs) begins the frame's feature extraction on a
worker thread, so that SIFT and the network share the cores, and returns the job; :meth:`RefinedStream.finish`
(with the job, the network's pose and relative pose) matches and solves (:meth:`.refiner.Refiner.refine`) and returns
the pose to publish. ``finish`` calls come in the order of the ``start`` calls; the next ``start`` may run while a
``finish`` runs on another thread (it then decides from the state before that ``finish``):

* ``refined``: the PnP pose, with its calibrated covariance (keypoints on the moving objects of the network's own
  segmentation left out);
* ``propagated``: on the frames between refinements (``refine_every > 1``), the last refined pose moved on by
  the network's relative poses, its covariance grown by the odometry variance per step;
* ``network``: the network's pose, when refinement failed (the status says why) or nothing was refined yet.

The odometry's prediction (the last refined pose times the relative poses since) is kept as a prior for up to
:data:`MAX_PREDICTION_STEPS` frames after the last refined one, also across failed refinements; a reset of the
temporal state drops it.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.mapping.features import off_dynamic
from vlocnetpp_core.mapping.refiner import Refiner

MAX_PREDICTION_STEPS = 30
SOURCES = ("network", "refined", "propagated")


@dataclass
class StreamPose:
    """The pose to publish: ``t (3,)``, ``q (4,)`` ``T_map,cam``; ``covariance (6, 6)`` or None (the network's own);
    ``source`` (:data:`SOURCES`); ``status`` of the refinement tried on this frame (None when none was);
    ``inliers`` of its PnP solution (0 without)."""

    t: np.ndarray
    q: np.ndarray
    covariance: np.ndarray | None
    source: str
    status: str | None
    inliers: int


@dataclass
class FeatureJob:
    """A frame's features on the worker: ``future`` of its :class:`~.features.Features`, ``K (3, 3)`` and the width
    of the grey image they come from."""

    future: Future
    K: np.ndarray
    width: int


class RefinedStream:
    """Refinement state of one stream (see the module docstring); ``refine_every`` k refines every k-th frame."""

    def __init__(self, refiner: Refiner, refine_every: int = 1, odometry_variance: np.ndarray | None = None):
        if refine_every < 1:
            raise ValueError(f"refine_every must be >= 1, got {refine_every}")
        self.refiner = refiner
        self.refine_every = int(refine_every)
        self.odometry_variance = np.zeros(6) if odometry_variance is None else np.asarray(odometry_variance, np.float64)
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vlocnetpp-features")
        self.reset()

    def reset(self) -> None:
        """Forget the last refined pose (after a reset of the temporal state)."""
        self._anchor: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # t, q, covariance
        self._steps = 0  # frames since the anchor was refined

    def start(self, image: np.ndarray, intrinsics) -> FeatureJob | None:
        """Begin the frame ``image`` (``(H, W, 3)`` RGB) with its
        :class:`~vlocnetpp_core.camera.intrinsics.Intrinsics`: its feature job, or None on a frame to propagate."""
        if self._anchor is not None and (self._steps + 1) % self.refine_every != 0:
            return None
        grey, K = self.refiner.prepare(image, intrinsics)
        return FeatureJob(self._worker.submit(self.refiner.extract, grey), K, grey.shape[1])

    @staticmethod
    def cancel(job: FeatureJob | None) -> None:
        """Drop a started frame (e.g. the network rejected it)."""
        if job is not None:
            job.future.result()

    def finish(
        self,
        job: FeatureJob | None,
        net_t: np.ndarray,
        net_q: np.ndarray,
        rel_t: np.ndarray,
        rel_q: np.ndarray,
        continued: bool,
        mask: np.ndarray | None = None,
    ) -> StreamPose:
        """The pose of the frame of ``job`` (:meth:`start`'s) given the network's pose and relative pose;
        ``continued`` False on a first frame (the relative pose means nothing); ``mask (H, W)``: the network's class
        ids at the image's resolution, whose moving objects are left out of the matching (None: a pose-only model)."""
        if not continued:
            self.reset()
        prediction = None
        if self._anchor is not None:
            self._steps += 1
            t, q = geometry.pose_compose(self._anchor[0], self._anchor[1], rel_t, rel_q)
            covariance = self._anchor[2] + np.diag(self.odometry_variance)
            prediction = (t, geometry.quat_normalize(q), covariance)
        if job is None:  # between refinements
            self._anchor = prediction
            if prediction is None:  # started before a reset (a pipeline's next frame): nothing to propagate
                return StreamPose(net_t, net_q, None, "network", None, 0)
            return StreamPose(prediction[0], prediction[1], prediction[2], "propagated", None, 0)
        features = job.future.result()
        if mask is not None:
            scale = mask.shape[1] / job.width
            features = features.select(off_dynamic(features.uv * scale, mask))
        result = self.refiner.refine(features, job.K, (net_t, net_q), None if prediction is None else prediction[:2])
        if result.accepted:
            s = result.solution
            self._anchor, self._steps = (s.t, s.q, s.covariance), 0
            return StreamPose(s.t, s.q, s.covariance, "refined", result.status, result.inliers)
        self._anchor = prediction if prediction is not None and self._steps < MAX_PREDICTION_STEPS else None
        return StreamPose(net_t, net_q, None, "network", result.status, result.inliers)

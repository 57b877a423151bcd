"""Streaming VLocNet++ inference, one camera frame at a time (no ROS): the one code path of the
ROS node, ``vlocnetpp evaluate`` and bag replay, so offline and online results are identical.

Per frame (:meth:`Localizer.step`):

* The image (any size, one of :data:`~vlocnetpp_core.inference.preprocess.IMAGE_ENCODINGS`) is resized to
  the network input size of the checkpoint, anisotropically when the aspect ratio differs (no
  crop), with the intrinsics scaled by :meth:`Intrinsics.resized`. Intrinsics given with the frame
  describe the camera image (any resolution with the same field of view); without them the
  checkpoint's default intrinsics (at network input size) are used.
* The model runs one streaming step, fusing the previous frame's Res5a, odometry Res4 and
  semantic Res4f / Res5c features kept from the last call (the model's ``StreamState``) instead
  of recomputing the previous frame.
* Backends: ``torch`` (default) runs ``VLocNetPP.step``; ``onnx`` runs the same step exported to
  ONNX (:mod:`vlocnetpp_core.inference.onnx_export`) with ONNX Runtime (:mod:`vlocnetpp_core.inference.onnx_backend`),
  faster on CPU (docs/performance.md); outputs agree to about 1e-5.
* Outputs: global pose ``T_map,cam``; relative pose ``T_rel = T_{k-1}^{-1} T_k``; accumulated
  odometry ``T_odom,k = T_odom,k-1 T_rel,k`` (identity at construction, in the ``odom`` frame);
  twist = relative motion / dt in the current camera frame (linear ``R_rel^T t_rel / dt`` m/s,
  angular = rotation vector of ``R_rel`` / dt rad/s); 6x6 covariances from the checkpoint
  calibration; the class-id mask at the resolution of the given image (argmax at network
  resolution after the calibration's per-class offsets, if any: :mod:`~vlocnetpp_core.inference.class_offsets`;
  brought back with exact nearest neighbour), or ``None`` for a pose-only model (no
  semantic stream: :attr:`Localizer.has_segmentation` is False).

Temporal state is reset (the next frame is a first frame: global pose from the image alone,
relative pose identity, odometry holds where it was, twist zero with unknown covariance) at
start, on :meth:`Localizer.reset`, when the stamp does not increase, when the gap to the
previous frame exceeds ``max_gap_s``, when the image resolution or the intrinsics change, and
after a frame rejected for non-finite network outputs. The result names the reason in
``reset_reason`` (``None`` when the frame continued the stream).

Covariances (ROS order x, y, z, rotation about x, y, z; variances floored at
:data:`MIN_VARIANCE` so no covariance is ever all zeros): global pose = the calibration's
``pose_variance``; odometry pose = ``odometry_variance`` times (1 + the number of relative
motions accumulated), a random walk; twist = ``odometry_variance / dt^2``, or
:data:`UNKNOWN_VARIANCE` on a first frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.checkpoint import calibration_variances, checkpoint_paths, load_checkpoint
from vlocnetpp_core.inference.class_offsets import offsets_of
from vlocnetpp_core.inference.network_input import network_input
from vlocnetpp_core.inference.pose_fusion import OdometryFusion
from vlocnetpp_core.inference.preprocess import FrameError, to_rgb

BACKENDS = ("torch", "onnx")
RESET_REASONS = ("start", "request", "stamp_backwards", "gap", "resolution_change", "intrinsics_change", "nan_output")
MIN_VARIANCE = 1e-6
UNKNOWN_VARIANCE = 1e6
_IDENTITY_T = np.zeros(3)
_IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])


@dataclass
class LocalizerResult:
    """One frame's outputs. Poses are ``t (3,)`` metres and ``q (4,)`` ``(w, x, y, z)``, float64."""

    stamp: float  # seconds, as given
    t: np.ndarray  # global pose T_map,cam
    q: np.ndarray
    rel_t: np.ndarray  # T_rel = T_{k-1}^{-1} T_k (identity on a first frame)
    rel_q: np.ndarray
    odom_t: np.ndarray  # T_odom,cam accumulated from the relative poses
    odom_q: np.ndarray
    linear: np.ndarray  # (3,) m/s in the current camera frame
    angular: np.ndarray  # (3,) rad/s in the current camera frame
    dt: float  # seconds since the previous frame (0 on a first frame)
    pose_covariance: np.ndarray  # (6, 6) of the global pose
    odom_covariance: np.ndarray  # (6, 6) of the odometry pose
    twist_covariance: np.ndarray  # (6, 6)
    mask: (
        np.ndarray | None
    )  # (H, W) uint8 class ids at the resolution of the given image; None: the model has no semantic stream
    reset_reason: str | None  # why the temporal state was reset before this frame, None when it was not
    seconds: float  # wall time of the step
    network_t: np.ndarray  # the network's global pose, fused with its odometry (t, q above when source is "network")
    network_q: np.ndarray
    frame_t: np.ndarray  # the network's global pose of this frame alone (network_t without fuse_odometry)
    frame_q: np.ndarray
    source: str = "network"  # of t, q and pose_covariance: "network", "refined" or "propagated" (mapping.stream)
    refine_status: str | None = None  # the refinement tried on this frame: "refined" or why not; None: none tried
    inliers: int = 0  # PnP inliers of the refinement tried (0 without)


@dataclass
class StepInProgress:
    """A frame between :meth:`Localizer.begin` and :meth:`Localizer.finish`: its result with the network's pose,
    the class ids ``(h, w) uint8`` at network resolution (None: no semantic stream), the image's ``shape (H, W)``,
    the refinement's feature job (:meth:`~vlocnetpp_core.mapping.stream.RefinedStream.start`) and when it began
    (``time.perf_counter``)."""

    result: LocalizerResult
    ids: np.ndarray | None
    shape: tuple[int, int]
    features: object
    started: float


class Localizer:
    """Streaming inference with temporal state. Build with :meth:`from_checkpoint`."""

    def __init__(
        self,
        model: torch.nn.Module,
        meta: dict,
        device: str | torch.device = "cpu",
        max_gap_s: float = 1.0,
        num_threads: int = 0,
        backend: str = "torch",
        onnx_path: str | Path | None = None,
        refiner=None,
        refine_every: int = 1,
        fuse_odometry: bool = True,
    ):
        """``backend``: ``"torch"`` runs ``model.step`` with the process's torch threads (set by the program:
        :func:`vlocnetpp_core.threads.use_threads`); ``"onnx"`` runs the exported step with ONNX Runtime in
        a session of ``num_threads`` threads (:mod:`vlocnetpp_core.threads`; ``onnx_path`` if it matches these
        weights, else a cached export; see :mod:`vlocnetpp_core.inference.onnx_backend`). ``refiner``: a
        :class:`~vlocnetpp_core.mapping.refiner.Refiner` to refine the global pose against its map every
        ``refine_every``-th frame (:mod:`vlocnetpp_core.mapping.stream`); None: the network's pose.
        ``fuse_odometry``: the network's pose fused with its own odometry over the frames
        (:mod:`vlocnetpp_core.inference.pose_fusion`); False: every frame's global pose alone."""
        if backend not in BACKENDS:
            raise UserError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        self.backend = backend
        self._step_fn = self.model.step
        if backend == "onnx":
            from vlocnetpp_core.inference.onnx_backend import onnx_step_for

            self._step_fn = onnx_step_for(self.model, meta, self.device, num_threads, next_to=onnx_path)
        self.meta = meta
        self.max_gap_s = float(max_gap_s)
        self.input_size: tuple[int, int] = tuple(model.config.input_size)  # (W, H)
        self.num_classes: int = model.config.num_classes
        self.class_names: list[str] = list(meta.get("class_names", []))
        self.default_intrinsics = Intrinsics.from_dict(meta["intrinsics"]).resized(*self.input_size)
        offsets = offsets_of(meta)
        self.class_offsets = None if offsets is None else offsets.to(self.device)[:, None, None]  # (C, 1, 1)
        pose_var, odo_var = calibration_variances(meta)
        self.pose_variance = np.maximum(pose_var, MIN_VARIANCE)
        self.odometry_variance = np.maximum(odo_var, MIN_VARIANCE)
        self.fusion = OdometryFusion(self.pose_variance) if fuse_odometry else None
        self._odom_t, self._odom_q = _IDENTITY_T.copy(), _IDENTITY_Q.copy()
        self._odom_steps = 0
        self.refinement = None
        if refiner is not None:
            from vlocnetpp_core.mapping.stream import RefinedStream

            self.refinement = RefinedStream(refiner, refine_every, self.odometry_variance)
        self.reset("start")

    @classmethod
    def from_checkpoint(
        cls,
        path: str | Path,
        device: str = "cpu",
        max_gap_s: float = 1.0,
        num_threads: int = 0,
        backend: str = "torch",
        map_path: str | Path | None = None,
        refine_every: int = 1,
        fuse_odometry: bool = True,
    ) -> Localizer:
        """Load ``NAME.safetensors`` + ``NAME.json`` (see :mod:`vlocnetpp_core.inference.checkpoint`); the onnx
        backend uses ``NAME.onnx`` next to them when it was exported from these weights. ``map_path``: a keyframe
        map (``vlocnetpp map build``) to refine against; None: no refinement."""
        refiner = None
        if map_path is not None:
            from vlocnetpp_core.mapping.refiner import Refiner

            refiner = Refiner.from_file(map_path)
        if str(device).startswith("cuda") and not torch.cuda.is_available():
            raise UserError(f"device {device!r} requested but CUDA is not available (use device 'cpu')")
        model, meta = load_checkpoint(path, device=device)
        return cls(
            model,
            meta,
            device=device,
            max_gap_s=max_gap_s,
            num_threads=num_threads,
            backend=backend,
            onnx_path=checkpoint_paths(path)[0].with_suffix(".onnx"),
            refiner=refiner,
            refine_every=refine_every,
            fuse_odometry=fuse_odometry,
        )

    @property
    def has_segmentation(self) -> bool:
        """Whether the loaded model produces a class-id mask (:attr:`LocalizerResult.mask` not None): its config
        runs ``seg`` (the rule replay's ``checkpoint_output_types`` reads too). False for a pose-only model
        (``lite_pose``)."""
        return "seg" in self.model.config.tasks

    def reset(self, reason: str = "request", clear_odometry: bool = False) -> None:
        """Forget the temporal state; the next frame is a first frame reported with ``reason``.
        ``clear_odometry`` also moves the accumulated odometry back to identity."""
        self._state = None
        self._pending_reset = reason
        self._prev_stamp: float | None = None
        self._prev_shape: tuple[int, int] | None = None
        self._prev_intrinsics: Intrinsics | None = None
        if clear_odometry:
            self._odom_t, self._odom_q = _IDENTITY_T.copy(), _IDENTITY_Q.copy()
            self._odom_steps = 0

    def step(
        self,
        image: np.ndarray,
        encoding: str,
        stamp: float,
        depth: np.ndarray | None = None,
        intrinsics: Intrinsics | None = None,
    ) -> LocalizerResult:
        """Process one frame: :meth:`finish` of :meth:`begin`.

        Args:
            image: ``(H, W, C)`` / ``(H, W)`` uint8 array in ``encoding`` (rgb8, bgr8, rgba8, bgra8, mono8).
            stamp: seconds (the camera's stamp; only differences matter).
            depth: ``(H, W) float32`` metres aligned with ``image`` (0 = invalid), replacing the
                predicted depth for warping; None to use the prediction.
            intrinsics: of the camera image; None for the checkpoint default.

        Raises:
            FrameError: the frame is unusable (``reason``: see ``preprocess.REASONS``, or
                ``nan_output`` after non-finite network outputs, which also resets the state).
        """
        return self.finish(self.begin(image, encoding, stamp, depth, intrinsics))

    def begin(
        self,
        image: np.ndarray,
        encoding: str,
        stamp: float,
        depth: np.ndarray | None = None,
        intrinsics: Intrinsics | None = None,
    ) -> StepInProgress:
        """The network's part of :meth:`step` (same arguments and errors): the frame's features start on the
        refinement's worker, the network runs, the temporal state and the odometry move on. Pass the result to
        :meth:`finish`, in the order of the ``begin`` calls; the next ``begin`` may run while a ``finish`` runs on
        another thread (a pipeline of two stages: the node's)."""
        start = time.perf_counter()
        rgb = to_rgb(image, encoding)
        net_intrinsics = self.default_intrinsics if intrinsics is None else intrinsics.resized(*self.input_size)
        x, K, d = network_input(rgb, self.input_size, net_intrinsics, depth)
        stamp = float(stamp)
        shape = rgb.shape[:2]
        reason = self._reset_reason(stamp, shape, net_intrinsics)
        if reason is not None:
            self._state = None
        features = None
        if self.refinement is not None:
            features = self.refinement.start(
                rgb, self.default_intrinsics.resized(shape[1], shape[0]) if intrinsics is None else intrinsics
            )
        with torch.inference_mode():
            out, state = self._step_fn(
                x.to(self.device), self._state, K.to(self.device), None if d is None else d.to(self.device)
            )
            outputs = (out.xyz, out.quat, out.rel_xyz, out.rel_quat, out.seg_logits)
            finite = all(bool(torch.isfinite(v).all()) for v in outputs if v is not None)
            if finite:
                ids = None if out.seg_logits is None else self._class_ids(out.seg_logits[0])
                xyz, quat, rel_xyz, rel_quat = (v[0].double().cpu().numpy() for v in outputs[:4])
        if not finite:
            if self.refinement is not None:
                self.refinement.cancel(features)
            self.reset("nan_output")
            raise FrameError(
                "nan_output", "the network produced NaN or infinite outputs; frame rejected and temporal state reset"
            )
        dt = 0.0 if self._prev_stamp is None or reason is not None else stamp - self._prev_stamp
        self._state = state
        self._pending_reset = None
        self._prev_stamp, self._prev_shape, self._prev_intrinsics = stamp, shape, net_intrinsics
        return StepInProgress(
            self._network_result(stamp, xyz, quat, rel_xyz, rel_quat, dt, reason), ids, shape, features, start
        )

    def _class_ids(self, scores: torch.Tensor) -> np.ndarray:
        """``scores (C, H, W)`` -> ``(H, W) uint8`` class ids: the argmax after the calibration's class offsets."""
        if self.class_offsets is not None:
            scores = scores.float() + self.class_offsets
        return scores.argmax(0).to(torch.uint8).cpu().numpy()

    def finish(self, step: StepInProgress) -> LocalizerResult:
        """The rest of :meth:`step` for a :meth:`begin`'s result: the class ids at the image's resolution and, with a
        map, the refinement (the published pose and its covariance)."""
        result, ids, shape = step.result, step.ids, step.shape
        if ids is not None and ids.shape != shape:
            ids = cv2.resize(ids, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST_EXACT)
        result.mask = ids
        if self.refinement is not None:  # refined from the frame's own pose; where it falls back, the fused one stays
            p = self.refinement.finish(
                step.features,
                result.frame_t,
                result.frame_q,
                result.rel_t,
                result.rel_q,
                result.reset_reason is None,
                ids,
            )
            if p.source != "network":
                result.t, result.q = p.t, p.q
            result.source, result.refine_status, result.inliers = p.source, p.status, p.inliers
            if p.covariance is not None:
                result.pose_covariance = p.covariance + np.diag(np.full(6, MIN_VARIANCE))
        result.seconds = time.perf_counter() - step.started
        return result

    def _network_result(
        self,
        stamp: float,
        xyz: np.ndarray,
        quat: np.ndarray,
        rel_xyz: np.ndarray,
        rel_quat: np.ndarray,
        dt: float,
        reason: str | None,
    ) -> LocalizerResult:
        """The frame's result from the network's outputs, the odometry moved on by its relative pose (mask, refinement
        and time are :meth:`finish`'s)."""
        frame_q = geometry.quat_normalize(quat)
        if reason is None:
            rel_t, rel_q = rel_xyz, geometry.quat_normalize(rel_quat)
            self._odom_t, self._odom_q = geometry.pose_compose(self._odom_t, self._odom_q, rel_t, rel_q)
            self._odom_steps += 1
            linear = geometry.quat_rotate(geometry.quat_inverse(rel_q), rel_t) / dt
            angular = _rotation_vector(rel_q) / dt
            twist_var = self.odometry_variance / dt**2
        else:
            rel_t, rel_q = _IDENTITY_T.copy(), _IDENTITY_Q.copy()
            linear, angular = np.zeros(3), np.zeros(3)
            twist_var = np.full(6, UNKNOWN_VARIANCE)
        t, q = xyz, frame_q
        if self.fusion is not None:
            t, q = self.fusion.update(xyz, frame_q, rel_t, rel_q, continued=reason is None)
        return LocalizerResult(
            stamp=stamp,
            t=t,
            q=q,
            rel_t=rel_t,
            rel_q=rel_q,
            odom_t=self._odom_t.copy(),
            odom_q=self._odom_q.copy(),
            linear=linear,
            angular=angular,
            dt=dt,
            pose_covariance=np.diag(self.pose_variance),
            odom_covariance=np.diag(self.odometry_variance * (1 + self._odom_steps)),
            twist_covariance=np.diag(twist_var),
            mask=None,
            reset_reason=reason,
            seconds=0.0,
            network_t=t,
            network_q=q,
            frame_t=xyz,
            frame_q=frame_q,
        )

    def _reset_reason(self, stamp: float, shape: tuple[int, int], intrinsics: Intrinsics) -> str | None:
        if self._pending_reset is not None or self._prev_stamp is None:
            return self._pending_reset or "start"
        if stamp <= self._prev_stamp:
            return "stamp_backwards"
        if stamp - self._prev_stamp > self.max_gap_s:
            return "gap"
        if shape != self._prev_shape:
            return "resolution_change"
        if intrinsics != self._prev_intrinsics:
            return "intrinsics_change"
        return None


def _rotation_vector(q: np.ndarray) -> np.ndarray:
    """Axis * angle (rad) of a unit quaternion ``(w, x, y, z)`` with ``w >= 0``."""
    v = q[1:]
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return 2.0 * v  # first order
    return v / s * (2.0 * np.arctan2(s, q[0]))

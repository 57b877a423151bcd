"""The network's global poses fused with its own odometry over time: a causal error-state Kalman filter, one frame at
a time, that also learns the odometry's bias.

The global stream's error on a frame is only partly shared with the next frames' (on the campus the correlation of
the position errors of frames 1 m apart is about 0.7, 2 m apart about 0.45). The odometry between them is noisy
(about 12 % of each step along the view, 4 % across it) and, on one drive, biased: its translation's direction
and its turn rate are off by a few per cent, consistently over hundreds of metres, because the network confuses a
sideways step with a turn. The filter's state is the pose and that bias:

* ``x = (t (3), theta (3), b_t (3), b_r (3))``: the position ``t`` in the map; the rotation ``R = Exp(theta) R_est``
  (an error about the map axes); ``b_t`` the odometry's translation bias per metre travelled (camera axes, m/m),
  ``b_r`` its rotation bias per metre (camera axes, rad/m).
* Predict with the relative pose ``T_rel = T_{k-1}^{-1} T_k`` less its bias, ``s = |t_rel|`` metres travelled:
  ``t += R (t_rel - b_t s)``, ``R = R R_rel Exp(-b_r s)``; the position and rotation uncertainty grow by
  ``(TRANSLATION_NOISE_PER_M s)^2`` and ``(ROTATION_NOISE_PER_M s)^2`` per axis, the biases' by
  ``(BIAS_WALK_PER_M s)^2`` (they may change slowly on a long run).
* Update with the frame's global pose, measurement ``(t_net - t, Log(R_net R^T))``, its covariance the calibrated
  per-frame variances (position per map axis, rotation the mean of the three).

So the gain depends on how far the camera went, not on the frame rate; standing still (or turning on the spot),
the fused pose is the mean of the frames since it stopped. The constants were chosen on validation visits
(docs/results.md, 2026-12-07, fifth). This is the paper's previous-pose fusion done at test time with the odometry
the network predicts anyway. The published covariance stays the calibrated one of a single frame (conservative:
the fused pose's errors are smaller, and they are correlated with ``vlocnet/odometry``, which an estimator fusing
both must know: ``fuse_odometry: false`` publishes every frame's own pose).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vlocnetpp_core import geometry

TRANSLATION_NOISE_PER_M = 0.1  # m of position uncertainty added per metre of travel
ROTATION_NOISE_PER_M = 0.005  # rad of rotation uncertainty added per metre of travel
TRANSLATION_BIAS_PRIOR = 0.04  # m/m: the spread of the odometry's translation bias on a fresh drive
ROTATION_BIAS_PRIOR = 0.003  # rad/m: the spread of its rotation bias
BIAS_WALK_PER_M = 1e-4  # how much either bias may change per metre of travel (its units per metre)

_T, _R, _BT, _BR = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


class OdometryFusion:
    """Fused global pose of one stream (see the module docstring). ``pose_variance (6,)``: the network's calibrated
    per-frame variances, x, y, z (m^2) and rotation about x, y, z (rad^2)."""

    def __init__(self, pose_variance: np.ndarray):
        pose_variance = np.asarray(pose_variance, np.float64)
        if pose_variance.shape != (6,) or not np.all(pose_variance > 0):
            raise ValueError(f"pose_variance must be 6 positive variances, got {pose_variance}")
        self.measurement_covariance = np.diag(np.r_[pose_variance[:3], np.full(3, pose_variance[3:].mean())])
        self.reset()

    def reset(self) -> None:
        """Forget the fused pose and the odometry's bias: the next frame starts from its own global pose."""
        self._t: np.ndarray | None = None
        self._r = np.eye(3)
        self._bias_t, self._bias_r = np.zeros(3), np.zeros(3)
        self._p = np.zeros((12, 12))
        self._p[:6, :6] = self.measurement_covariance
        self._p[_BT, _BT] = np.eye(3) * TRANSLATION_BIAS_PRIOR**2
        self._p[_BR, _BR] = np.eye(3) * ROTATION_BIAS_PRIOR**2

    @property
    def odometry_bias(self) -> tuple[np.ndarray, np.ndarray]:
        """The odometry's estimated bias: translation (3,) in m/m and rotation (3,) in rad/m, camera axes."""
        return self._bias_t.copy(), self._bias_r.copy()

    def update(
        self, t: np.ndarray, q: np.ndarray, rel_t: np.ndarray, rel_q: np.ndarray, continued: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """The fused ``T_map,cam`` (``t (3,)``, unit ``q (4,)`` ``(w, x, y, z)``) after the frame with global pose
        ``t, q`` and relative pose ``T_rel = T_{k-1}^{-1} T_k``; ``continued`` False on a first frame (restart)."""
        t = np.asarray(t, np.float64)
        r_net = geometry.quat_to_matrix(geometry.quat_normalize(np.asarray(q, np.float64)))
        if not continued or self._t is None:
            self.reset()
            self._t, self._r = t.copy(), r_net
            return self._t.copy(), geometry.matrix_to_quat(self._r)
        self._predict(np.asarray(rel_t, np.float64), geometry.quat_to_matrix(np.asarray(rel_q, np.float64)))
        residual = np.r_[t - self._t, Rotation.from_matrix(r_net @ self._r.T).as_rotvec()]
        gain = self._p[:, :6] @ np.linalg.inv(self._p[:6, :6] + self.measurement_covariance)
        dx = gain @ residual
        self._t = self._t + dx[_T]
        self._r = Rotation.from_rotvec(dx[_R]).as_matrix() @ self._r
        self._bias_t, self._bias_r = self._bias_t + dx[_BT], self._bias_r + dx[_BR]
        self._p = self._p - gain @ self._p[:6, :]
        self._p = 0.5 * (self._p + self._p.T)
        return self._t.copy(), geometry.matrix_to_quat(self._r)

    def _predict(self, rel_t: np.ndarray, rel_r: np.ndarray) -> None:
        """Move the state on by the bias-corrected relative pose and grow its covariance (module docstring)."""
        travel = float(np.linalg.norm(rel_t))
        r_prev = self._r
        step = r_prev @ (rel_t - self._bias_t * travel)
        self._t = self._t + step
        self._r = r_prev @ rel_r @ Rotation.from_rotvec(-self._bias_r * travel).as_matrix()
        jacobian = np.eye(12)
        jacobian[_T, _R] = -_skew(step)
        jacobian[_T, _BT] = -r_prev * travel
        jacobian[_R, _BR] = -self._r * travel
        noise = np.zeros(12)
        noise[_T], noise[_R] = (TRANSLATION_NOISE_PER_M * travel) ** 2, (ROTATION_NOISE_PER_M * travel) ** 2
        noise[6:] = (BIAS_WALK_PER_M * travel) ** 2
        self._p = jacobian @ self._p @ jacobian.T + np.diag(noise)

"""Camera pose from 2D-3D correspondences: AP3P in RANSAC, Levenberg-Marquardt on the inliers, the inliers again
of the refined pose and Levenberg-Marquardt on them, and the covariance.

AP3P rather than EPnP as RANSAC's minimal solver (docs/refinement.md, "PnP"): as accurate on the validation visits at
a third of the time (a faster solver on 4 points instead of 5, so fewer iterations for the same confidence).

The covariance is the Gauss-Newton one, ``sigma^2 (J^T J)^-1`` with ``sigma^2`` the inliers' mean squared
reprojection residual (``2n - 6`` degrees of freedom), in the parameters of ROS's ``pose_with_covariance``:
the camera position in the map frame (x, y, z) and small rotations about the map frame's x, y, z axes
(``R_map,cam <- exp([d]x) R_map,cam``). It describes the noise of the keypoints only; the refiner scales it by a
factor calibrated on validation visits (:mod:`.refiner`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vlocnetpp_core.geometry import matrix_to_quat

MIN_CORRESPONDENCES = 6


@dataclass
class PoseSolution:
    """``T_map,cam`` as ``t (3,)`` metres, ``q (4,)`` ``(w, x, y, z)``; ``inliers (n,)`` indices into the
    correspondences; ``rms_px`` their reprojection error; ``covariance (6, 6)`` (see the module docstring)."""

    t: np.ndarray
    q: np.ndarray
    inliers: np.ndarray
    rms_px: float
    covariance: np.ndarray


def solve_pnp(
    uv: np.ndarray, points: np.ndarray, K: np.ndarray, ransac_px: float = 2.0, iterations: int = 300
) -> PoseSolution | None:
    """The pose of the camera with intrinsics ``K (3, 3)`` that sees map points ``points (N, 3)`` at pixels
    ``uv (N, 2)``; None when there are too few correspondences or RANSAC finds no consistent set."""
    if len(uv) < MIN_CORRESPONDENCES:
        return None
    obj, img = np.ascontiguousarray(points, np.float64), np.ascontiguousarray(uv, np.float64)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        obj,
        img,
        K,
        None,
        iterationsCount=iterations,
        reprojectionError=ransac_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_AP3P,
    )
    if not ok or inliers is None or len(inliers) < MIN_CORRESPONDENCES:
        return None
    inliers = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(obj[inliers], img[inliers], K, None, rvec, tvec)
    # the inliers again, of the refined pose rather than of RANSAC's best minimal sample (whose own error leaves out
    # the tails of the true residuals and so shrinks the covariance), and the pose refined on them
    projected, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
    inliers = np.flatnonzero(np.linalg.norm(projected[:, 0] - img, axis=1) < ransac_px)
    if len(inliers) < MIN_CORRESPONDENCES:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj[inliers], img[inliers], K, None, rvec, tvec)
    R_cw, _ = cv2.Rodrigues(rvec)
    R_wc, centre = R_cw.T, -R_cw.T @ tvec[:, 0]
    residual, jacobian = _residuals_and_jacobian(obj[inliers], img[inliers], K, R_wc, centre)
    if residual is None:
        return None
    dof = max(2 * len(inliers) - 6, 1)
    sigma2 = float(residual @ residual) / dof
    try:
        covariance = sigma2 * np.linalg.inv(jacobian.T @ jacobian)
    except np.linalg.LinAlgError:
        return None
    rms = float(np.sqrt(np.mean(np.sum(residual.reshape(-1, 2) ** 2, axis=1))))
    return PoseSolution(centre, matrix_to_quat(R_wc), inliers, rms, 0.5 * (covariance + covariance.T))


def _residuals_and_jacobian(X: np.ndarray, uv: np.ndarray, K: np.ndarray, R_wc: np.ndarray, c: np.ndarray):
    """Reprojection residuals ``(2n,)`` and their Jacobian ``(2n, 6)`` w.r.t. (position, map-frame rotation);
    ``(None, None)`` when a point lies behind the camera."""
    d = X - c  # (n, 3) in the map frame
    p = d @ R_wc  # (n, 3) camera frame: R_wc^T d
    z = p[:, 2]
    if np.any(z <= 1e-6):
        return None, None
    fx, fy = K[0, 0], K[1, 1]
    proj = np.stack((fx * p[:, 0] / z + K[0, 2], fy * p[:, 1] / z + K[1, 2]), 1)
    residual = (proj - uv).ravel()
    zero = np.zeros_like(z)
    d_proj = np.stack(
        (np.stack((fx / z, zero, -fx * p[:, 0] / z**2), 1), np.stack((zero, fy / z, -fy * p[:, 1] / z**2), 1)), 1
    )  # (n, 2, 3) d pixel / d camera point
    skew = np.zeros((len(d), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -d[:, 2], d[:, 1], -d[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = d[:, 2], -d[:, 1], d[:, 0]
    d_point = np.concatenate((np.broadcast_to(-R_wc.T, (len(d), 3, 3)), R_wc.T @ skew), axis=2)  # (n, 3, 6)
    return residual, (d_proj @ d_point).reshape(-1, 6)

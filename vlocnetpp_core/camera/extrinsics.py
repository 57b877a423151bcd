"""The localizer's outputs for a frame rigidly attached to the camera (a robot's ``base_link``). No ROS here.

Frames: ``map`` (world), ``odom`` (where the odometry started), ``camera`` (the optical frame the
network localises: x right, y down, z forward) and ``base`` (the robot body). The extrinsics
``T_base,camera`` are the camera's pose in ``base``: translation ``t`` in metres and a unit
quaternion ``q = (w, x, y, z)``, ``w >= 0`` (docs/conventions.md, Poses and frames).

* Global pose: ``T_map,base = T_map,camera T_camera,base`` with ``T_camera,base = T_base,camera^{-1}``.
* Odometry: the odometry of the camera starts at identity, so its ``odom`` frame is the camera's
  pose at the start. The base's odometry uses the base's start pose instead (a ``z``-up ``odom``
  for a ``z``-up base): ``T_odom,base = T_base,camera T_odom,camera T_camera,base``, identity at
  the start like the camera's. Relative poses are conjugated the same way.
* Twist (body frame, linear m/s then angular rad/s): ``V_base = Ad(T_base,camera) V_camera``.

Covariance convention (6x6, ROS order x, y, z, rotation about x, y, z): that of
:class:`~vlocnetpp_core.inference.localizer.Localizer`, whose variances are the validation errors measured
by ``vlocnetpp train`` (``trainer._pose_residual``): for a pose ``(p, R)`` of a frame in a parent
frame the error is ``(dp, dtheta)`` with ``p_est = p_true + dp``, ``dp`` in the **parent** frame
(map or odom; metres), and ``R_est = R_true Exp(dtheta)``, ``dtheta`` a rotation vector about the
axes of the **frame itself** (camera, or base once transformed; radians). For ``T' = A T B`` (A and
B fixed) the first-order error is ``(dp', dtheta') = J (dp, dtheta)`` with
``J = diag(R', I) Ad(B^{-1}) diag(R^T, I)``: the SE(3) adjoint of the fixed transform between the
body-frame (right-perturbation) errors, with the translation part carried into and out of the
parent frame. Here ``J = [[R_A, -R_A R [t_B]x], [0, R_B^T]]``: a lever arm couples the rotation
uncertainty into the position, and the rotation block is re-expressed in the new frame's axes.
Twist covariances are body-frame, so for them ``J = Ad(T_base,camera)``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.errors import UserError

if TYPE_CHECKING:  # an annotation only: extract (which reads extrinsics) does not load the localizer
    from vlocnetpp_core.inference.localizer import LocalizerResult

QUAT_NORM_TOLERANCE = 1e-3  # |‖q‖ - 1| accepted in the parameter (then normalised): 3-decimal quaternions pass
IDENTITY_VALUES = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)  # x, y, z, qw, qx, qy, qz


@dataclass(frozen=True, eq=False)
class CameraExtrinsics:
    """``T_base,camera``: the camera's pose in the base frame, ``t (3,)`` metres, ``q (4,)`` ``(w, x, y, z)``,
    ``w >= 0``."""

    t: np.ndarray
    q: np.ndarray

    @classmethod
    def identity(cls) -> CameraExtrinsics:
        """The camera is the base."""
        return cls.from_values(IDENTITY_VALUES)

    @classmethod
    def from_text(cls, text: str, name: str) -> CameraExtrinsics:
        """From ``"X,Y,Z,QW,QX,QY,QZ"`` (a command-line flag ``name``), checked as :meth:`from_values`."""
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            raise UserError(f"{name} must be 7 comma-separated numbers X,Y,Z,QW,QX,QY,QZ, got {text!r}") from None
        return cls.from_values(values, name)

    @classmethod
    def from_values(
        cls, values: object, name: str = "parameter camera_extrinsics", tolerance: float = QUAT_NORM_TOLERANCE
    ) -> CameraExtrinsics:
        """From 7 numbers ``x, y, z, qw, qx, qy, qz``; the quaternion must be unit-norm within ``tolerance``
        (it is then normalised). Raises :class:`UserError` naming ``name`` otherwise."""
        what = (
            f"{name} must be 7 numbers [x, y, z, qw, qx, qy, qz] "
            "(the camera's pose in base_frame: metres, unit quaternion)"
        )
        if isinstance(values, (str, bytes)) or not isinstance(values, Sequence | np.ndarray):
            raise UserError(f"{what}, got {values!r}")
        items = list(values)
        if len(items) != 7 or not all(
            isinstance(v, int | float | np.number) and not isinstance(v, bool) for v in items
        ):
            raise UserError(f"{what}, got {len(items)} value(s): {items!r}")
        v = np.asarray(items, dtype=np.float64)
        if not np.isfinite(v).all():
            raise UserError(f"{what}, got non-finite values: {v.tolist()}")
        norm = float(np.linalg.norm(v[3:]))
        if not math.isclose(norm, 1.0, abs_tol=tolerance):
            raise UserError(
                f"{what}: the quaternion (qw, qx, qy, qz) = {v[3:].tolist()} has norm {norm:.6g}, "
                f"not 1 within {tolerance:g}"
            )
        return cls(t=v[:3].copy(), q=geometry.quat_normalize(v[3:]))

    @property
    def is_identity(self) -> bool:
        """Exactly the identity (the default parameter)."""
        return bool(np.all(self.t == 0.0) and np.all(self.q == (1.0, 0.0, 0.0, 0.0)))

    @cached_property
    def matrix(self) -> np.ndarray:
        """``(4, 4)`` ``T_base,camera``."""
        return geometry.pose_to_matrix(self.t, self.q)

    @cached_property
    def inverse(self) -> np.ndarray:
        """``(4, 4)`` ``T_camera,base``."""
        return geometry.pose_to_matrix(*geometry.pose_inverse(self.t, self.q))

    @cached_property
    def adjoint(self) -> np.ndarray:
        """``(6, 6)`` ``Ad(T_base,camera)`` acting on ``(translation, rotation)`` 6-vectors:
        ``[[R, [t]x R], [0, R]]``."""
        return _adjoint(self.matrix[:3, :3], self.t)

    def values(self) -> list[float]:
        """The 7 numbers ``x, y, z, qw, qx, qy, qz`` (normalised quaternion)."""
        return [float(x) for x in (*self.t, *self.q)]


def frame_change_jacobian(R: np.ndarray, R_new: np.ndarray, ad_b_inverse: np.ndarray) -> np.ndarray:
    """``(6, 6)`` first-order map of the errors of a pose with rotation ``R`` to those of ``T' = A T B`` (A, B
    fixed; ``R_new`` the rotation of ``T'``, ``ad_b_inverse = Ad(B^{-1})``), in the module's convention (position
    error in the parent frame, rotation error in the body frame): ``diag(R_new, I) Ad(B^{-1}) diag(R^T, I)``."""
    into_body, out_of_body = np.eye(6), np.eye(6)
    into_body[:3, :3], out_of_body[:3, :3] = np.asarray(R).T, R_new
    return out_of_body @ ad_b_inverse @ into_body


def transform_covariance(covariance: np.ndarray, jacobian: np.ndarray) -> np.ndarray:
    """``J C J^T`` of a ``(6, 6)`` covariance, made exactly symmetric."""
    c = jacobian @ np.asarray(covariance, dtype=np.float64) @ jacobian.T
    return 0.5 * (c + c.T)


def base_pose(t_wc: np.ndarray, q_wc: np.ndarray, ext: CameraExtrinsics) -> tuple[np.ndarray, np.ndarray]:
    """``T_world,base = T_world,camera T_base,camera^{-1}`` as ``(t, q)``."""
    return _moved(t_wc, q_wc, np.eye(4), ext)


def base_pose_covariance(covariance: np.ndarray, q_wc: np.ndarray, ext: CameraExtrinsics) -> np.ndarray:
    """Covariance of :func:`base_pose` from that of the camera pose with orientation ``q_wc`` (module convention)."""
    R = geometry.quat_to_matrix(np.asarray(q_wc, dtype=np.float64))
    return transform_covariance(covariance, frame_change_jacobian(R, R @ ext.inverse[:3, :3], ext.adjoint))


def base_odometry(t_oc: np.ndarray, q_oc: np.ndarray, ext: CameraExtrinsics) -> tuple[np.ndarray, np.ndarray]:
    """``T_base,camera T_odom,camera T_camera,base``: the odometry (or a relative pose) of the base, identity at
    identity."""
    return _moved(t_oc, q_oc, ext.matrix, ext)


def base_odometry_covariance(covariance: np.ndarray, q_oc: np.ndarray, ext: CameraExtrinsics) -> np.ndarray:
    """Covariance of :func:`base_odometry` from that of the camera odometry with orientation ``q_oc``."""
    R = geometry.quat_to_matrix(np.asarray(q_oc, dtype=np.float64))
    R_e = ext.matrix[:3, :3]
    return transform_covariance(covariance, frame_change_jacobian(R, R_e @ R @ R_e.T, ext.adjoint))


def base_twist(linear: np.ndarray, angular: np.ndarray, ext: CameraExtrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Body twist of the base (m/s, rad/s, base axes) from the camera's: ``Ad(T_base,camera) V_camera``."""
    v = ext.adjoint @ np.concatenate((np.asarray(linear, dtype=np.float64), np.asarray(angular, dtype=np.float64)))
    return v[:3], v[3:]


def to_base_frame(result: LocalizerResult, ext: CameraExtrinsics) -> LocalizerResult:
    """A copy of ``result`` with every pose, twist and covariance of the base instead of the camera.

    The mask, stamp, ``dt`` and the reset reason are unchanged. The three poses go through the geometry
    helpers as one batch, the covariances through :func:`base_pose_covariance` and :func:`base_odometry_covariance`.
    """
    left = np.stack((np.eye(4), ext.matrix, ext.matrix))  # global pose: T ext^-1; odometry, relative: ext T ext^-1
    t, q = _moved(
        np.stack((result.t, result.odom_t, result.rel_t)), np.stack((result.q, result.odom_q, result.rel_q)), left, ext
    )
    linear, angular = base_twist(result.linear, result.angular, ext)
    return dataclasses.replace(
        result,
        t=t[0],
        q=q[0],
        odom_t=t[1],
        odom_q=q[1],
        rel_t=t[2],
        rel_q=q[2],
        linear=linear,
        angular=angular,
        pose_covariance=base_pose_covariance(result.pose_covariance, result.q, ext),
        odom_covariance=base_odometry_covariance(result.odom_covariance, result.odom_q, ext),
        twist_covariance=transform_covariance(result.twist_covariance, ext.adjoint),
    )


def _moved(t: np.ndarray, q: np.ndarray, left: np.ndarray, ext: CameraExtrinsics) -> tuple[np.ndarray, np.ndarray]:
    """``left T ext^-1`` for poses ``T = (t (..., 3), q (..., 4))``, as ``(t', q')``."""
    T = geometry.pose_to_matrix(np.asarray(t, dtype=np.float64), np.asarray(q, dtype=np.float64))
    return geometry.matrix_to_pose(left @ T @ ext.inverse)


def _adjoint(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    ad = np.zeros((6, 6))
    ad[:3, :3] = ad[3:, 3:] = R
    ad[:3, 3:] = _skew(t) @ R
    return ad


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]x``: the matrix of ``v x .``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])

"""The pose algebra of :mod:`vlocnetpp_core.geometry` (quaternions, SE(3), pose errors) on numpy arrays, without torch.

Same conventions (``geometry``'s docstring): ``t (..., 3)`` metres, ``q (..., 4)`` ``(w, x, y, z)``, ``w >= 0``; any
leading batch dimensions. Inputs are taken as float64 and results are float64 arrays. ``geometry`` routes its numpy
inputs here, so this is the one implementation for numpy callers; torch tensors keep the torch formulas there
(autograd, GPU), which ``test/test_geometry.py`` checks against these. Modules that must not load torch (``vlocnetpp
extract``, the camera extrinsics) import this module directly.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike

Indexable = TypeVar("Indexable")  # a numpy array or a torch tensor: the ROS order helpers only index

__all__ = [
    "quat_normalize",
    "quat_mul",
    "quat_inverse",
    "quat_rotate",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_to_ros",
    "quat_from_ros",
    "pose_to_matrix",
    "matrix_to_pose",
    "pose_compose",
    "pose_inverse",
    "relative_pose",
    "translation_error",
    "rotation_error_deg",
]


def _f64(a: ArrayLike) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


def _norm(a: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis, kept as a length-1 axis."""
    return np.sqrt((a * a).sum(-1, keepdims=True))


# --------------------------------------------------------------------------- quaternions


def quat_normalize(q: ArrayLike, eps: float = 1e-12) -> np.ndarray:
    """Unit quaternion ``(..., 4)`` in ``(w, x, y, z)`` on the ``w >= 0`` hemisphere.

    Canonical: when ``w == 0`` the first non-zero of ``x, y, z`` is made positive, so that
    equal rotations get equal quaternions.
    """
    q = _f64(q)
    q = q / np.maximum(_norm(q), eps)
    key = q[..., 3]
    for i in (2, 1, 0):
        key = np.where(np.abs(q[..., i]) > 1e-12, q[..., i], key)
    q = q * np.where(key < 0, -1.0, 1.0)[..., None]
    return np.concatenate((np.abs(q[..., :1]), q[..., 1:]), -1)  # only flips a |w| <= 1e-12


def quat_mul(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """Hamilton product ``a * b`` of ``(..., 4)`` quaternions ``(w, x, y, z)`` (not re-normalised)."""
    a, b = _f64(a), _f64(b)
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return np.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        axis=-1,
    )


def quat_inverse(q: ArrayLike) -> np.ndarray:
    """Inverse of a unit quaternion (its conjugate), ``(..., 4)``."""
    return _f64(q) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_rotate(q: ArrayLike, v: ArrayLike) -> np.ndarray:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``."""
    q = _f64(q)
    u, v = np.broadcast_arrays(q[..., 1:], _f64(v))
    uv = np.cross(u, v)
    return v + 2.0 * (q[..., :1] * uv + np.cross(u, uv))


def quat_to_matrix(q: ArrayLike) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of (normalised) quaternions ``(..., 4)``."""
    q = _f64(q)
    q = q / np.maximum(_norm(q), 1e-12)
    w, x, y, z = (q[..., i] for i in range(4))
    return np.stack(
        (
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ),
        axis=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: ArrayLike) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (``w >= 0``) of rotation matrices ``(..., 3, 3)``.

    Uses the numerically stable branch on the largest diagonal term.
    """
    m = _f64(R)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = np.stack(
        (
            (1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]),
            (
                m[..., 2, 1] - m[..., 1, 2],
                1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                m[..., 0, 1] + m[..., 1, 0],
                m[..., 0, 2] + m[..., 2, 0],
            ),
            (
                m[..., 0, 2] - m[..., 2, 0],
                m[..., 0, 1] + m[..., 1, 0],
                1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                m[..., 1, 2] + m[..., 2, 1],
            ),
            (
                m[..., 1, 0] - m[..., 0, 1],
                m[..., 0, 2] + m[..., 2, 0],
                m[..., 1, 2] + m[..., 2, 1],
                1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
            ),
        )
    )  # (4 candidates, 4, ...)
    cands = np.moveaxis(cands, (0, 1), (-2, -1))  # (..., 4 candidates, 4)
    diag = np.stack((trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]), -1)
    best = diag.argmax(-1)[..., None, None]
    return quat_normalize(np.take_along_axis(cands, best, -2)[..., 0, :])


def quat_to_ros(q: Indexable) -> Indexable:
    """Core ``(w, x, y, z)`` -> ROS ``(x, y, z, w)``, ``(..., 4)``; indexing only, so tensors too (``geometry``)."""
    return q[..., [1, 2, 3, 0]]


def quat_from_ros(q: Indexable) -> Indexable:
    """ROS ``(x, y, z, w)`` -> core ``(w, x, y, z)``, ``(..., 4)``; indexing only, so tensors too (``geometry``)."""
    return q[..., [3, 0, 1, 2]]


# --------------------------------------------------------------------------- SE(3)


def pose_to_matrix(t: ArrayLike, q: ArrayLike) -> np.ndarray:
    """Homogeneous ``(..., 4, 4)`` matrices of poses ``t (..., 3)``, ``q (..., 4)``."""
    t = _f64(t)
    T = np.zeros(t.shape[:-1] + (4, 4))
    T[..., :3, :3] = quat_to_matrix(q)
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def matrix_to_pose(T: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``(t (..., 3), q (..., 4))`` of homogeneous matrices ``(..., 4, 4)``."""
    T = _f64(T)
    return T[..., :3, 3].copy(), matrix_to_quat(T[..., :3, :3])


def pose_compose(t1: ArrayLike, q1: ArrayLike, t2: ArrayLike, q2: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``T1 T2``: apply ``T2`` then ``T1``. Returns ``(t, q)`` with ``q`` normalised, ``w >= 0``."""
    return _f64(t1) + quat_rotate(q1, t2), quat_normalize(quat_mul(q1, q2))


def pose_inverse(t: ArrayLike, q: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``T^{-1}`` as ``(t, q)``."""
    qi = quat_inverse(q)
    return -quat_rotate(qi, t), quat_normalize(qi)


def relative_pose(
    t_prev: ArrayLike, q_prev: ArrayLike, t_cur: ArrayLike, q_cur: ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """``T_rel = T_prev^{-1} T_cur``: camera t expressed in camera t-1 (SE(3) form, docs/conventions.md, Relative
    pose)."""
    ti, qi = pose_inverse(t_prev, q_prev)
    return pose_compose(ti, qi, t_cur, q_cur)


def translation_error(t1: ArrayLike, t2: ArrayLike) -> np.ndarray:
    """Euclidean distance ``(...)`` in metres."""
    return _norm(_f64(t1) - _f64(t2))[..., 0]


def rotation_error_deg(q1: ArrayLike, q2: ArrayLike) -> np.ndarray:
    """Angle ``2 acos(|<q1, q2>|)`` in degrees between (normalised) quaternions, ``(...)``."""
    q1, q2 = _f64(q1), _f64(q2)
    q1 = q1 / np.maximum(_norm(q1), 1e-12)
    q2 = q2 / np.maximum(_norm(q2), 1e-12)
    d = np.minimum(np.abs((q1 * q2).sum(-1)), 1.0)
    return np.asarray(np.rad2deg(2.0 * np.arccos(d)))

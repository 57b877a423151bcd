"""Rigid-body geometry shared by the network, the data readers, the metrics and the node.

Conventions (docs/conventions.md, Poses and frames; Relative pose), pinned here and by ``test/test_geometry.py``:

* A pose is camera-to-world ``T_wc``: translation ``t`` in metres ``(..., 3)`` and a unit
  quaternion ``q = (w, x, y, z)`` ``(..., 4)`` with ``w >= 0``. ROS messages use
  ``(x, y, z, w)``: convert with :func:`quat_to_ros` / :func:`quat_from_ros` at the boundary only.
* Camera frame is the optical frame: x right, y down, z forward.
* Relative pose ``T_rel = T_{t-1}^{-1} T_t`` (camera t expressed in camera t-1), the SE(3)
  form, used for the odometry target, the geometric consistency loss and warping.
* Rotation error ``2 acos(|<q1, q2>|)`` in degrees; translation error is Euclidean metres.

Every function takes torch tensors or numpy arrays with any number of leading batch
dimensions and returns the same kind it was given. Each formula is written once against the
array namespace of its inputs (:func:`_xp`): tensors stay tensors (dtype, device and autograd
kept), numpy inputs run in numpy as float64 and come back as float64 arrays, and a call with a
numpy array among its inputs takes the numpy path. Importing this module loads no torch
(``vlocnetpp extract`` relies on it); only the warping functions, which are torch-only, import it.
"""

from __future__ import annotations

import sys
from types import ModuleType
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

if TYPE_CHECKING:
    import torch

Array = TypeVar("Array", "torch.Tensor", np.ndarray)

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
    "project",
    "backproject",
    "pixel_grid",
    "warp_grid",
    "pool_warp_grid",
    "warp_features",
]


# --------------------------------------------------------------------------- array namespace


def _is_tensor(x: object) -> bool:
    """Whether ``x`` is a torch tensor, without importing torch (a tensor means torch is loaded already)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _xp(*xs: Any) -> tuple[ModuleType, tuple[Any, ...]]:
    """The namespace of the inputs and the inputs to compute with.

    Torch and the tensors unchanged when at least one input is a tensor and none is a numpy array; numpy and the
    inputs as float64 arrays otherwise. ``np.linalg.cross``, ``concatenate``, ``stack``, ``where``, ``clip``,
    ``arccos`` and ``rad2deg`` are spelled alike in both; the helpers below cover where they differ.
    """
    if any(_is_tensor(x) for x in xs) and not any(isinstance(x, np.ndarray) for x in xs):
        return sys.modules["torch"], xs
    return np, tuple(np.asarray(x, dtype=np.float64) for x in xs)


def _norm(x: Array) -> Array:
    """Euclidean norm over the last axis, kept as a length-1 axis."""
    return x.norm(dim=-1, keepdim=True) if _is_tensor(x) else np.linalg.norm(x, axis=-1, keepdims=True)


def _copy(x: Array) -> Array:
    return x.clone() if _is_tensor(x) else x.copy()


def _zeros(like: Array, shape: tuple[int, ...]) -> Array:
    """Zeros of ``shape`` with the dtype (and device) of ``like``."""
    return like.new_zeros(shape) if _is_tensor(like) else np.zeros(shape, dtype=like.dtype)


def _take_along_last_but_one(x: Array, index: Array) -> Array:
    """``x[..., index, :]`` per batch element: ``x (..., n, m)``, ``index (...)`` -> ``(..., m)``."""
    index = index[..., None, None]
    picked = x.take_along_dim(index, dim=-2) if _is_tensor(x) else np.take_along_axis(x, index, -2)
    return picked[..., 0, :]


def _numpy_0d(x: Array) -> Array:
    """Keep a numpy result an array when a reduction made it a scalar (tensors pass through)."""
    return x if _is_tensor(x) else np.asarray(x)


# --------------------------------------------------------------------------- quaternions


def quat_normalize(q: Array, eps: float = 1e-12) -> Array:
    """Unit quaternion ``(..., 4)`` in ``(w, x, y, z)`` on the ``w >= 0`` hemisphere.

    Canonical: when ``w == 0`` the first non-zero of ``x, y, z`` is made positive, so that
    equal rotations get equal quaternions.
    """
    xp, (q,) = _xp(q)
    q = q / xp.clip(_norm(q), eps, None)
    key = q[..., 3]
    for i in (2, 1, 0):
        key = xp.where(abs(q[..., i]) > 1e-12, q[..., i], key)
    q = xp.where(key[..., None] < 0, -q, q)
    return xp.concatenate((abs(q[..., :1]), q[..., 1:]), -1)  # only flips a |w| <= 1e-12


def quat_mul(a: Array, b: Array) -> Array:
    """Hamilton product ``a * b`` of ``(..., 4)`` quaternions ``(w, x, y, z)`` (not re-normalised)."""
    xp, (a, b) = _xp(a, b)
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return xp.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        -1,
    )


def quat_inverse(q: Array) -> Array:
    """Inverse of a unit quaternion (its conjugate), ``(..., 4)``."""
    xp, (q,) = _xp(q)
    return xp.concatenate((q[..., :1], -q[..., 1:]), -1)


def quat_rotate(q: Array, v: Array) -> Array:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``."""
    xp, (q, v) = _xp(q, v)
    u = q[..., 1:]
    uv = xp.linalg.cross(u, v)
    return v + 2.0 * (q[..., :1] * uv + xp.linalg.cross(u, uv))


def quat_to_matrix(q: Array) -> Array:
    """Rotation matrices ``(..., 3, 3)`` of (normalised) quaternions ``(..., 4)``."""
    xp, (q,) = _xp(q)
    q = q / xp.clip(_norm(q), 1e-12, None)
    w, x, y, z = (q[..., i] for i in range(4))
    return xp.stack(
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
        -1,
    ).reshape(tuple(q.shape[:-1]) + (3, 3))


def matrix_to_quat(R: Array) -> Array:
    """Unit quaternions ``(..., 4)`` (``w >= 0``) of rotation matrices ``(..., 3, 3)``.

    Uses the numerically stable branch on the largest diagonal term.
    """
    xp, (m,) = _xp(R)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    rows = (
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
    cands = xp.stack([xp.stack(row, -1) for row in rows], -2)  # (..., 4 candidates, 4)
    diag = xp.stack((trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]), -1)
    return quat_normalize(_take_along_last_but_one(cands, diag.argmax(-1)))


def quat_to_ros(q: Array) -> Array:
    """Core ``(w, x, y, z)`` -> ROS ``(x, y, z, w)``."""
    return q[..., [1, 2, 3, 0]]


def quat_from_ros(q: Array) -> Array:
    """ROS ``(x, y, z, w)`` -> core ``(w, x, y, z)``."""
    return q[..., [3, 0, 1, 2]]


# --------------------------------------------------------------------------- SE(3)


def pose_to_matrix(t: Array, q: Array) -> Array:
    """Homogeneous ``(..., 4, 4)`` matrices of poses ``t (..., 3)``, ``q (..., 4)``."""
    _, (t, q) = _xp(t, q)
    T = _zeros(t, tuple(t.shape[:-1]) + (4, 4))
    T[..., :3, :3] = quat_to_matrix(q)
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def matrix_to_pose(T: Array) -> tuple[Array, Array]:
    """``(t (..., 3), q (..., 4))`` of homogeneous matrices ``(..., 4, 4)``."""
    _, (T,) = _xp(T)
    return _copy(T[..., :3, 3]), matrix_to_quat(T[..., :3, :3])


def pose_compose(t1: Array, q1: Array, t2: Array, q2: Array) -> tuple[Array, Array]:
    """``T1 T2``: apply ``T2`` then ``T1``. Returns ``(t, q)`` with ``q`` normalised, ``w >= 0``."""
    _, (t1, q1, t2, q2) = _xp(t1, q1, t2, q2)
    return t1 + quat_rotate(q1, t2), quat_normalize(quat_mul(q1, q2))


def pose_inverse(t: Array, q: Array) -> tuple[Array, Array]:
    """``T^{-1}`` as ``(t, q)``."""
    _, (t, q) = _xp(t, q)
    qi = quat_inverse(q)
    return -quat_rotate(qi, t), quat_normalize(qi)


def relative_pose(t_prev: Array, q_prev: Array, t_cur: Array, q_cur: Array) -> tuple[Array, Array]:
    """``T_rel = T_prev^{-1} T_cur``: camera t expressed in camera t-1 (SE(3) form, docs/conventions.md, Relative
    pose)."""
    _, (t_prev, q_prev, t_cur, q_cur) = _xp(t_prev, q_prev, t_cur, q_cur)
    ti, qi = pose_inverse(t_prev, q_prev)
    return pose_compose(ti, qi, t_cur, q_cur)


def translation_error(t1: Array, t2: Array) -> Array:
    """Euclidean distance ``(...)`` in metres."""
    _, (t1, t2) = _xp(t1, t2)
    return _norm(t1 - t2)[..., 0]


def rotation_error_deg(q1: Array, q2: Array) -> Array:
    """Angle ``2 acos(|<q1, q2>|)`` in degrees between (normalised) quaternions, ``(...)``."""
    xp, (q1, q2) = _xp(q1, q2)
    q1 = q1 / xp.clip(_norm(q1), 1e-12, None)
    q2 = q2 / xp.clip(_norm(q2), 1e-12, None)
    d = xp.clip(abs((q1 * q2).sum(-1)), None, 1.0)
    return _numpy_0d(xp.rad2deg(2.0 * xp.arccos(d)))


# --------------------------------------------------------------------------- pinhole camera


def _split_k(K: Array) -> tuple[Array, Array, Array, Array]:
    """``fx, fy, cx, cy`` of intrinsics ``(..., 3, 3)``, each with a trailing length-1 axis (broadcasts over N)."""
    return K[..., 0, 0, None], K[..., 1, 1, None], K[..., 0, 2, None], K[..., 1, 2, None]


def project(points: Array, K: Array, eps: float = 1e-6) -> tuple[Array, Array]:
    """Project camera-frame points ``(..., N, 3)`` with intrinsics ``K (..., 3, 3)``.

    Returns pixel coordinates ``(..., N, 2)`` (x right, y down; pixel centres at integers)
    and the depth ``z`` ``(..., N)``. Points with ``z <= eps`` get non-finite-free but
    meaningless pixels; callers mask them with the returned depth.
    """
    xp, (points, K) = _xp(points, K)
    fx, fy, cx, cy = _split_k(K)
    z = points[..., 2]
    zs = xp.where(abs(z) < eps, eps, z)
    u = fx * points[..., 0] / zs + cx
    v = fy * points[..., 1] / zs + cy
    return xp.stack((u, v), -1), z


def backproject(pixels: Array, depth: Array, K: Array) -> Array:
    """Back-project pixels ``(..., N, 2)`` with depth ``(..., N)`` (metres along z) to camera points ``(..., N, 3)``."""
    xp, (pixels, depth, K) = _xp(pixels, depth, K)
    fx, fy, cx, cy = _split_k(K)
    x = (pixels[..., 0] - cx) / fx * depth
    y = (pixels[..., 1] - cy) / fy * depth
    return xp.stack((x, y, depth), -1)


# --------------------------------------------------------------------------- warping (torch only)


def pixel_grid(
    height: int, width: int, dtype: torch.dtype | None = None, device: torch.device | str | None = None
) -> torch.Tensor:
    """Pixel coordinates ``(H*W, 2)`` in row-major order, ``(u, v)`` with pixel centres at integers.

    ``dtype`` defaults to ``torch.float32``.
    """
    import torch

    dtype = torch.float32 if dtype is None else dtype
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device), torch.arange(width, dtype=dtype, device=device), indexing="ij"
    )
    return torch.stack((u.reshape(-1), v.reshape(-1)), -1)


def warp_grid(
    depth: torch.Tensor, T_rel: torch.Tensor, K: torch.Tensor, min_depth: float = 1e-3
) -> tuple[torch.Tensor, torch.Tensor]:
    """Backward-warp sampling grid from frame t into frame t-1 (paper Eq. 4, docs/conventions.md, Warping).

    For every pixel ``u`` of frame t: back-project with ``D_t(u)``, move the point into camera
    t-1 with ``T_rel = T_{t-1}^{-1} T_t`` and project with ``K``.

    Args:
        depth: ``(B, 1, H, W)`` depth of frame t in metres; ``<= min_depth`` or non-finite is invalid.
        T_rel: ``(B, 4, 4)`` relative pose (camera t in camera t-1).
        K: ``(B, 3, 3)`` intrinsics at this ``H x W`` resolution.

    Returns:
        grid: ``(B, H, W, 2)`` normalised coordinates for ``F.grid_sample(..., align_corners=False)``;
            invalid pixels get their own (identity) location so that average pooling stays sane.
        valid: ``(B, 1, H, W)`` float, 1 where depth is valid, the point is in front of camera t-1
            and it lands inside frame t-1.
    """
    import torch

    B, _, H, W = depth.shape
    pix = pixel_grid(H, W, dtype=depth.dtype, device=depth.device).expand(B, H * W, 2)
    d = depth.reshape(B, H * W)
    ok = torch.isfinite(d) & (d > min_depth)
    d_safe = torch.where(ok, d, torch.ones_like(d))
    pts = backproject(pix, d_safe, K)  # (B, N, 3) in camera t
    R = T_rel[:, :3, :3]
    tr = T_rel[:, :3, 3]
    pts_prev = pts @ R.transpose(1, 2) + tr[:, None, :]
    uv, z = project(pts_prev, K)
    inside = (uv[..., 0] > -0.5) & (uv[..., 0] < W - 0.5) & (uv[..., 1] > -0.5) & (uv[..., 1] < H - 0.5)
    ok = ok & (z > min_depth) & inside
    uv = torch.where(ok[..., None], uv, pix)
    gx = (2.0 * uv[..., 0] + 1.0) / W - 1.0
    gy = (2.0 * uv[..., 1] + 1.0) / H - 1.0
    grid = torch.stack((gx, gy), -1).reshape(B, H, W, 2)
    return grid, ok.reshape(B, 1, H, W).to(depth.dtype)


def pool_warp_grid(grid: torch.Tensor, valid: torch.Tensor, size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Average-pool an input-resolution grid ``(B, H, W, 2)`` and mask ``(B, 1, H, W)`` to feature ``size (h, w)``.

    With ``align_corners=False`` normalised coordinates, the mean over a ``s x s`` block is
    exactly the coarse pixel centre under identity motion, so one grid serves every scale.
    """
    from torch.nn.functional import adaptive_avg_pool2d

    g = adaptive_avg_pool2d(grid.permute(0, 3, 1, 2), size).permute(0, 2, 3, 1)
    m = adaptive_avg_pool2d(valid, size)
    return g, m


def warp_features(
    features: torch.Tensor, grid: torch.Tensor, valid: torch.Tensor, threshold: float = 0.5
) -> torch.Tensor:
    """Bilinearly sample previous-frame ``features (B, C, h, w)`` at ``grid (B, h, w, 2)``.

    ``valid (B, 1, h, w)`` is the pooled mask; samples where less than ``threshold`` of the
    block was valid are zero. Differentiable with respect to ``features`` and ``grid``.
    """
    from torch.nn.functional import grid_sample

    out = grid_sample(features, grid.to(features.dtype), mode="bilinear", padding_mode="zeros", align_corners=False)
    return out * (valid >= threshold).to(out.dtype)

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
dimensions and returns the same kind it was given (numpy in, numpy out, float64). Numpy inputs of
the pose algebra (quaternions, SE(3), errors) run in :mod:`vlocnetpp_core.geometry_np`, the one
numpy implementation, which loads no torch (``vlocnetpp extract`` imports it directly); the torch
bodies here serve tensors (autograd, GPU). The two agree to ~1e-14 (torch's ``cross``, 3-vector
``norm`` and ``acos`` round differently in the last bit; ``test/test_geometry.py``). The pinhole
functions run numpy inputs in torch, float64.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import numpy as np
import torch

from vlocnetpp_core import geometry_np
from vlocnetpp_core.geometry_np import quat_from_ros, quat_to_ros

Array = TypeVar("Array", torch.Tensor, np.ndarray)

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


def _numpy_in_geometry_np(fn: Callable) -> Callable:
    """Send a call with numpy arrays to the function of the same name in :mod:`geometry_np`; tensors run ``fn``."""
    numpy_fn = getattr(geometry_np, fn.__name__)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if any(isinstance(a, np.ndarray) for a in args):
            return numpy_fn(*args, **kwargs)
        return fn(*args, **kwargs)

    return wrapper


def _numpy_compatible(fn: Callable) -> Callable:
    """Let a torch function (the pinhole ones) accept numpy arrays: numpy inputs run in float64 and come back as
    numpy."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if not any(isinstance(a, np.ndarray) for a in args):
            return fn(*args, **kwargs)
        targs = [torch.from_numpy(np.asarray(a, dtype=np.float64)) if isinstance(a, np.ndarray) else a for a in args]
        out = fn(*targs, **kwargs)
        if isinstance(out, tuple):
            return tuple(o.numpy() if isinstance(o, torch.Tensor) else o for o in out)
        return out.numpy()

    return wrapper


# --------------------------------------------------------------------------- quaternions


@_numpy_in_geometry_np
def quat_normalize(q: Array, eps: float = 1e-12) -> Array:
    """Unit quaternion ``(..., 4)`` in ``(w, x, y, z)`` on the ``w >= 0`` hemisphere.

    Canonical: when ``w == 0`` the first non-zero of ``x, y, z`` is made positive, so that
    equal rotations get equal quaternions.
    """
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(eps)
    key = q[..., 3]
    for i in (2, 1, 0):
        key = torch.where(q[..., i].abs() > 1e-12, q[..., i], key)
    q = q * torch.where(key < 0, -1.0, 1.0).to(q.dtype)[..., None]
    return torch.cat((q[..., :1].abs(), q[..., 1:]), -1)  # only flips a |w| <= 1e-12


@_numpy_in_geometry_np
def quat_mul(a: Array, b: Array) -> Array:
    """Hamilton product ``a * b`` of ``(..., 4)`` quaternions ``(w, x, y, z)`` (not re-normalised)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


@_numpy_in_geometry_np
def quat_inverse(q: Array) -> Array:
    """Inverse of a unit quaternion (its conjugate), ``(..., 4)``."""
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


@_numpy_in_geometry_np
def quat_rotate(q: Array, v: Array) -> Array:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``."""
    u, v = torch.broadcast_tensors(q[..., 1:], v)
    uv = torch.cross(u, v, dim=-1)
    return v + 2.0 * (q[..., :1] * uv + torch.cross(u, uv, dim=-1))


@_numpy_in_geometry_np
def quat_to_matrix(q: Array) -> Array:
    """Rotation matrices ``(..., 3, 3)`` of (normalised) quaternions ``(..., 4)``."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
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
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


@_numpy_in_geometry_np
def matrix_to_quat(R: Array) -> Array:
    """Unit quaternions ``(..., 4)`` (``w >= 0``) of rotation matrices ``(..., 3, 3)``.

    Uses the numerically stable branch on the largest diagonal term.
    """
    m = R
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack(
        (
            torch.stack(
                (1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]), -1
            ),
            torch.stack(
                (
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ),
                -1,
            ),
            torch.stack(
                (
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                    m[..., 1, 2] + m[..., 2, 1],
                ),
                -1,
            ),
            torch.stack(
                (
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
                ),
                -1,
            ),
        ),
        dim=-2,
    )  # (..., 4 candidates, 4)
    diag = torch.stack((trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]), -1)
    best = diag.argmax(-1, keepdim=True)
    q = torch.gather(cands, -2, best[..., None].expand(best.shape + (4,))).squeeze(-2)
    return quat_normalize(q)


# --------------------------------------------------------------------------- SE(3)


@_numpy_in_geometry_np
def pose_to_matrix(t: Array, q: Array) -> Array:
    """Homogeneous ``(..., 4, 4)`` matrices of poses ``t (..., 3)``, ``q (..., 4)``."""
    T = torch.zeros(t.shape[:-1] + (4, 4), dtype=t.dtype, device=t.device)
    T[..., :3, :3] = quat_to_matrix(q)
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


@_numpy_in_geometry_np
def matrix_to_pose(T: Array) -> tuple[Array, Array]:
    """``(t (..., 3), q (..., 4))`` of homogeneous matrices ``(..., 4, 4)``."""
    return T[..., :3, 3].clone(), matrix_to_quat(T[..., :3, :3])


@_numpy_in_geometry_np
def pose_compose(t1: Array, q1: Array, t2: Array, q2: Array) -> tuple[Array, Array]:
    """``T1 T2``: apply ``T2`` then ``T1``. Returns ``(t, q)`` with ``q`` normalised, ``w >= 0``."""
    return t1 + quat_rotate(q1, t2), quat_normalize(quat_mul(q1, q2))


@_numpy_in_geometry_np
def pose_inverse(t: Array, q: Array) -> tuple[Array, Array]:
    """``T^{-1}`` as ``(t, q)``."""
    qi = quat_inverse(q)
    return -quat_rotate(qi, t), quat_normalize(qi)


@_numpy_in_geometry_np
def relative_pose(t_prev: Array, q_prev: Array, t_cur: Array, q_cur: Array) -> tuple[Array, Array]:
    """``T_rel = T_prev^{-1} T_cur``: camera t expressed in camera t-1 (SE(3) form, docs/conventions.md, Relative
    pose)."""
    ti, qi = pose_inverse(t_prev, q_prev)
    return pose_compose(ti, qi, t_cur, q_cur)


@_numpy_in_geometry_np
def translation_error(t1: Array, t2: Array) -> Array:
    """Euclidean distance ``(...)`` in metres."""
    return (t1 - t2).norm(dim=-1)


@_numpy_in_geometry_np
def rotation_error_deg(q1: Array, q2: Array) -> Array:
    """Angle ``2 acos(|<q1, q2>|)`` in degrees between (normalised) quaternions, ``(...)``."""
    q1 = q1 / q1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    q2 = q2 / q2.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    d = (q1 * q2).sum(-1).abs().clamp(max=1.0)
    return torch.rad2deg(2.0 * torch.acos(d))


# --------------------------------------------------------------------------- pinhole camera


def _split_k(K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    return K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]


@_numpy_compatible
def project(points: Array, K: Array, eps: float = 1e-6) -> tuple[Array, Array]:
    """Project camera-frame points ``(..., N, 3)`` with intrinsics ``K (..., 3, 3)``.

    Returns pixel coordinates ``(..., N, 2)`` (x right, y down; pixel centres at integers)
    and the depth ``z`` ``(..., N)``. Points with ``z <= eps`` get non-finite-free but
    meaningless pixels; callers mask them with the returned depth.
    """
    fx, fy, cx, cy = (v[..., None] for v in _split_k(K))
    z = points[..., 2]
    zs = torch.where(z.abs() < eps, torch.full_like(z, eps), z)
    u = fx * points[..., 0] / zs + cx
    v = fy * points[..., 1] / zs + cy
    return torch.stack((u, v), -1), z


@_numpy_compatible
def backproject(pixels: Array, depth: Array, K: Array) -> Array:
    """Back-project pixels ``(..., N, 2)`` with depth ``(..., N)`` (metres along z) to camera points ``(..., N, 3)``."""
    fx, fy, cx, cy = (v[..., None] for v in _split_k(K))
    x = (pixels[..., 0] - cx) / fx * depth
    y = (pixels[..., 1] - cy) / fy * depth
    return torch.stack((x, y, depth), -1)


def pixel_grid(height: int, width: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Pixel coordinates ``(H*W, 2)`` in row-major order, ``(u, v)`` with pixel centres at integers."""
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
    g = torch.nn.functional.adaptive_avg_pool2d(grid.permute(0, 3, 1, 2), size).permute(0, 2, 3, 1)
    m = torch.nn.functional.adaptive_avg_pool2d(valid, size)
    return g, m


def warp_features(
    features: torch.Tensor, grid: torch.Tensor, valid: torch.Tensor, threshold: float = 0.5
) -> torch.Tensor:
    """Bilinearly sample previous-frame ``features (B, C, h, w)`` at ``grid (B, h, w, 2)``.

    ``valid (B, 1, h, w)`` is the pooled mask; samples where less than ``threshold`` of the
    block was valid are zero. Differentiable with respect to ``features`` and ``grid``.
    """
    out = torch.nn.functional.grid_sample(
        features, grid.to(features.dtype), mode="bilinear", padding_mode="zeros", align_corners=False
    )
    return out * (valid >= threshold).to(out.dtype)

"""Trajectories: TUM files, odometry accumulation and Umeyama alignment (numpy; rotations from ``geometry``).

A :class:`Trajectory` is ``N`` stamped camera-to-world poses ``T_wc`` (docs/conventions.md, Poses and frames):
``stamps (N,)`` seconds, ``t (N, 3)`` metres, ``q (N, 4)`` unit quaternions ``(w, x, y, z)``
with ``w >= 0``. TUM files hold one pose a line, ``t tx ty tz qx qy qz qw`` (ROS quaternion
order), which is what ``evo`` reads (``evo_ape tum ref.tum est.tum``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlocnetpp_core.errors import DataError
from vlocnetpp_core.geometry import matrix_to_quat, pose_to_matrix, quat_to_matrix

__all__ = [
    "Trajectory",
    "read_tum",
    "write_tum",
    "accumulate_odometry",
    "umeyama_alignment",
    "align_trajectory",
]


@dataclass
class Trajectory:
    """``N`` stamped poses ``T_wc``: ``stamps (N,)`` s, ``t (N, 3)`` m, ``q (N, 4)`` ``(w, x, y, z)``, ``w >= 0``."""

    stamps: np.ndarray
    t: np.ndarray
    q: np.ndarray

    def __post_init__(self) -> None:
        self.stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(self.q, dtype=np.float64).reshape(-1, 4)
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        self.q = np.where(q[:, :1] < 0, -q, q)
        if not len(self.stamps) == len(self.t) == len(self.q):
            raise ValueError(f"stamps, t and q differ in length: {len(self.stamps)}, {len(self.t)}, {len(self.q)}")

    def __len__(self) -> int:
        return len(self.stamps)

    @classmethod
    def from_matrices(cls, stamps: np.ndarray, T: np.ndarray) -> Trajectory:
        """From homogeneous matrices ``(N, 4, 4)``."""
        T = np.asarray(T, dtype=np.float64)
        return cls(stamps, T[:, :3, 3], matrix_to_quat(T[:, :3, :3]))

    def matrices(self) -> np.ndarray:
        """Homogeneous ``(N, 4, 4)`` matrices."""
        return pose_to_matrix(self.t, self.q)

    def path_length(self) -> float:
        """Length in metres of the polyline through the positions."""
        return float(np.linalg.norm(np.diff(self.t, axis=0), axis=1).sum()) if len(self) > 1 else 0.0


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write ``traj`` as a TUM file (``t tx ty tz qx qy qz qw``, full float precision).

    The file is written next to its destination and renamed into place, so an interrupted
    write never leaves a half-written file; parent folders are created.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = np.column_stack((traj.stamps, traj.t, traj.q[:, [1, 2, 3, 0]]))
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        np.savetxt(f, rows, fmt="%.17g")
    os.replace(tmp, path)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM file (``#`` comments and blank lines allowed; space or comma separated).

    Raises ``DataError`` naming the file and line for a missing file, a line without eight
    finite numbers, or a zero quaternion.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as err:
        raise DataError(path, f"cannot read TUM trajectory ({err.strerror or err})") from err
    rows = []
    for lineno, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        try:
            values = [float(v) for v in fields]
        except ValueError:
            values = []
        if len(values) != 8 or not np.all(np.isfinite(values)):
            raise DataError(path, f"expected 8 numbers 't tx ty tz qx qy qz qw', got {line[:80]!r}", lineno)
        if np.linalg.norm(values[4:]) < 1e-9:
            raise DataError(path, "zero quaternion", lineno)
        rows.append(values)
    data = np.array(rows, dtype=np.float64).reshape(-1, 8)
    return Trajectory(data[:, 0], data[:, 1:4], data[:, [7, 4, 5, 6]])


def accumulate_odometry(
    t0: np.ndarray, q0: np.ndarray, rel_t: np.ndarray, rel_q: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Chain relative poses: ``T_0 = (t0, q0)``, ``T_k = T_{k-1} T_rel,k``.

    ``rel_t (N, 3)``, ``rel_q (N, 4)`` hold ``T_rel,k = T_{k-1}^{-1} T_k`` for frame ``k``; row 0
    (the first frame has no predecessor) is ignored. Returns ``t (N, 3)``, ``q (N, 4)``.
    """
    rel = pose_to_matrix(rel_t, rel_q)
    T = np.empty_like(rel)
    T[0] = pose_to_matrix(np.asarray(t0)[None], np.asarray(q0)[None])[0]
    for k in range(1, len(rel)):
        T[k] = T[k - 1] @ rel[k]
    return T[:, :3, 3].copy(), matrix_to_quat(T[:, :3, :3])


def umeyama_alignment(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991) of point sets ``(N, 3)``.

    Returns ``R (3, 3)``, ``t (3,)``, ``s`` (1.0 unless ``with_scale``). Needs ``N >= 3``
    non-collinear points for a unique rotation; with fewer the result is one valid solution.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    return R, mu_d - s * R @ mu_s, s


def align_trajectory(est: Trajectory, ref: Trajectory, with_scale: bool = False) -> Trajectory:
    """``est`` moved by the Umeyama transform of its positions onto ``ref``'s (same length, same order).

    Positions become ``s R t + t_a`` and orientations ``R R_k``, as ``evo``'s ``align`` does.
    """
    if len(est) != len(ref):
        raise ValueError(f"trajectories differ in length: {len(est)} vs {len(ref)}")
    R, ta, s = umeyama_alignment(est.t, ref.t, with_scale)
    rot = R @ quat_to_matrix(est.q)
    return Trajectory(est.stamps, s * est.t @ R.T + ta, matrix_to_quat(rot))

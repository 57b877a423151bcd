"""Dataset fixtures for the data tests: a textured plane rendered exactly from known poses.

The world holds one textured plane ``Z_w = PLANE_Z``; a camera ``T_wc`` sees it with exact depth,
so warping one rendered frame into another with the true relative pose reproduces it (up to
interpolation). Labels are class ids of stripes on the plane. Writers lay the frames out as a
DeepLoc or 7-Scenes dataset on disk.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.data.pfm import write_pfm

PLANE_Z = 8.0
K_SMALL = Intrinsics(fx=80.0, fy=80.0, cx=47.5, cy=35.5, width=96, height=72)


def render_plane(t: np.ndarray, q: np.ndarray, K: Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rgb (H, W, 3) uint8, depth (H, W) float32 metres, labels (H, W) uint8)`` of the plane seen from ``T_wc``."""
    pix = geometry.pixel_grid(K.height, K.width, dtype=torch.float64).numpy()
    rays_c = geometry.backproject(pix, np.ones(len(pix)), K.matrix())
    R = geometry.quat_to_matrix(np.asarray(q, dtype=np.float64))
    rays_w = rays_c @ R.T
    s = (PLANE_Z - t[2]) / rays_w[:, 2]  # ray parameter == camera depth because rays have z = 1
    P = t + s[:, None] * rays_w
    X, Y = P[:, 0], P[:, 1]
    base = (
        0.5
        + 0.2 * np.sin(2.1 * X + 0.3) * np.cos(1.7 * Y)
        + 0.15 * np.sin(5.3 * X - 3.1 * Y)
        + 0.1 * np.cos(7.7 * Y + 1.3 * X)
    )
    rgb = np.stack((base, 0.8 * base + 0.1 * np.sin(3.3 * X), 1.0 - base), -1)
    rgb = np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8).reshape(K.height, K.width, 3)
    labels = (np.floor(X * 2).astype(np.int64) % 10).astype(np.uint8).reshape(K.height, K.width)
    return rgb, s.astype(np.float32).reshape(K.height, K.width), labels


def trajectory(n: int, start: float = 0.0, yaw_deg: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` poses of a camera moving sideways and forward while yawing and rolling a little."""
    k = np.arange(n) + start
    t = np.stack((0.15 * k, 0.03 * k, 0.1 * k), -1)
    yaw = np.deg2rad(yaw_deg * k)
    roll = np.deg2rad(1.0 * k)
    q_yaw = np.stack((np.cos(yaw / 2), 0 * yaw, np.sin(yaw / 2), 0 * yaw), -1)  # about camera y (down)
    q_roll = np.stack((np.cos(roll / 2), 0 * roll, 0 * roll, np.sin(roll / 2)), -1)  # about camera z
    return t, geometry.quat_normalize(geometry.quat_mul(q_yaw, q_roll))


def write_png(path: Path, rgb: np.ndarray, alpha: bool = False) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGRA if alpha else cv2.COLOR_RGB2BGR)
    if alpha:
        bgr[..., 3] = 200
    assert cv2.imwrite(str(path), bgr)


def write_depth_png_mm(path: Path, depth: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.round(depth * 1000).astype(np.uint16))


def write_deeploc_split(
    root: Path,
    split: str,
    ids: list[int],
    t: np.ndarray,
    q: np.ndarray,
    *,
    header: tuple[str, ...] = ("# DeepLoc poses", "ImageName x y z qw qx qy qz"),
    order: str = "wxyz",
    depth: str | None = "png",
    labels: bool = True,
    K: Intrinsics = K_SMALL,
    line_order: list[int] | None = None,
) -> dict[int, dict]:
    """Render and write one DeepLoc split (RGBA images); returns the ground truth per id.

    ``line_order`` permutes the poses.txt lines; quaternions are written with a negative ``w``
    on every other line (the same rotation) to exercise normalisation.
    """
    split_dir = root / "DeepLoc" / split
    truth = {}
    lines = list(header)
    body = []
    for k, n in enumerate(ids):
        rgb, d, lab = render_plane(t[k], q[k], K)
        write_png(split_dir / "LeftImages" / f"Image_{n}.png", rgb, alpha=True)
        if labels:
            (split_dir / "labels").mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(split_dir / "labels" / f"Image_{n}.png"), lab)
        if depth == "png":
            write_depth_png_mm(root / "DeepLoc_stereo" / split / "DepthImages" / f"Image_{n}.png", d)
            d = np.round(d * 1000).astype(np.float32) / 1000
        elif depth == "pfm":
            (root / "DeepLoc_stereo" / split / "DepthImages").mkdir(parents=True, exist_ok=True)
            write_pfm(root / "DeepLoc_stereo" / split / "DepthImages" / f"Image_{n}.pfm", d)
        qq = q[k] if k % 2 == 0 else -q[k]
        qcols = qq if order == "wxyz" else qq[[1, 2, 3, 0]]
        body.append(f"Image_{n}.png " + " ".join(f"{v:.9f}" for v in (*t[k], *qcols)))
        truth[n] = {"rgb": rgb, "depth": d if depth else None, "labels": lab if labels else None, "t": t[k], "q": q[k]}
    if line_order is not None:
        body = [body[i] for i in line_order]
    (split_dir / "poses.txt").write_text("\n".join(lines + body) + "\n")
    return truth


def write_sevenscenes(
    root: Path, seqs: dict[int, int], train: list[int], test: list[int], K: Intrinsics = K_SMALL
) -> dict[str, dict]:
    """Render a 7-Scenes scene folder with ``seqs`` {sequence number: frame count}; some depth
    pixels are set to the invalid values 0 and 65535. Returns the ground truth per frame id."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "TrainSplit.txt").write_text("".join(f"sequence{n}\n" for n in train))
    (root / "TestSplit.txt").write_text("".join(f"sequence{n}\n" for n in test))
    truth = {}
    for n, count in seqs.items():
        t, q = trajectory(count, start=3 * n)
        for k in range(count):
            rgb, d, _ = render_plane(t[k], q[k], K)
            mm = np.round(d * 1000).astype(np.uint16)
            mm[0, :5] = 0
            mm[1, :5] = 65535
            stem = root / f"seq-{n:02d}" / f"frame-{k:06d}"
            write_png(stem.with_name(stem.name + ".color.png"), rgb)
            assert cv2.imwrite(str(stem.with_name(stem.name + ".depth.png")), mm)
            T = geometry.pose_to_matrix(t[k], q[k])
            np.savetxt(stem.with_name(stem.name + ".pose.txt"), T, fmt="%.10e", delimiter="\t")
            expect = mm.astype(np.float32) * np.float32(0.001)
            expect[mm == 65535] = 0
            truth[f"seq-{n:02d}/frame-{k:06d}"] = {"rgb": rgb, "depth": expect, "t": t[k], "q": q[k], "sequence": n}
    return truth

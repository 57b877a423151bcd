"""Render one frame of the campus: RGB, class ids and depth that agree exactly with the pose.

Method (2.5D ray casting, all numpy/OpenCV):

1. The pose ``T_wc`` is split into a *level* camera (same centre, same heading, optical axis
   horizontal, image y axis vertical) and a small tilt ``R_tilt`` (pitch / roll) so that
   ``R_wc = R_level(yaw) R_tilt``.
2. The level camera is ray cast column by column (``raycast``) and coloured (``shade``).
3. The level render (a little wider than the output so that no border is empty) is mapped into
   the tilted camera by the homography ``K R_tilt^-1 K^-1`` (bilinear for colour, nearest for
   class ids). Depth is recomputed exactly per output pixel by intersecting the output pixel's
   own ray with the surface found at the nearest level pixel, so ``depth``, ``labels`` and the
   pose agree to within the half-pixel of the label sampling.

Depth is the z coordinate in the camera (optical) frame, metres; the sky has depth 0 (invalid).
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.synth.campus import Campus, DynamicObject
from vlocnetpp_core.synth.layout import HILLS_RADIUS
from vlocnetpp_core.synth.lighting import DEFAULT_LIGHTING, Lighting
from vlocnetpp_core.synth.prims import CYLINDER, Prims
from vlocnetpp_core.synth.raycast import E_OFFSET, GROUND, HILLS, SKY_CODE, LevelCamera, LevelImage, cast
from vlocnetpp_core.synth.shade import shade

MAX_TILT_DEG = 25.0  # pitch/roll the level render + homography supports


def level_rotation(yaw: float) -> np.ndarray:
    """``R_wc`` of a level camera looking along world heading ``yaw`` (x right, y down, z forward)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])


def split_pose_rotation(R: np.ndarray) -> tuple[float, np.ndarray]:
    """``(yaw, R_tilt)`` with ``R = level_rotation(yaw) @ R_tilt`` and the smallest tilt."""
    yaw = math.atan2(R[1, 2], R[0, 2])
    return yaw, level_rotation(yaw).T @ R


def render_frame(
    campus: Campus,
    pose_t,
    pose_q,
    intrinsics: Intrinsics,
    lighting: Lighting = DEFAULT_LIGHTING,
    dynamic_objects: tuple[DynamicObject, ...] | list[DynamicObject] = (),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render the camera with pose ``T_wc = (pose_t (3,), pose_q (4,) w,x,y,z)``.

    Returns ``rgb (H, W, 3) uint8``, ``labels (H, W) uint8`` (class ids 0..9) and
    ``depth (H, W) float32`` (metres along the optical axis, 0 for the sky), ``H x W`` being
    the size of ``intrinsics``. Pitch and roll must stay within ``MAX_TILT_DEG``.
    """
    t = np.asarray(pose_t, np.float64).reshape(3)
    R = geometry.quat_to_matrix(np.asarray(pose_q, np.float64).reshape(4))
    yaw, Rt = split_pose_rotation(R)
    tilt = math.degrees(math.acos(float(np.clip((np.trace(Rt) - 1) / 2, -1, 1))))
    if tilt > MAX_TILT_DEG:
        raise ValueError(f"camera pitch/roll of {tilt:.1f} deg exceeds the renderer's {MAX_TILT_DEG} deg")
    if not t[2] > 0.05:
        raise ValueError(f"camera height must be above the ground, got z = {t[2]:.3f} m")
    if math.hypot(t[0] - campus.center[0], t[1] - campus.center[1]) > HILLS_RADIUS - 20:
        raise ValueError(
            f"camera at ({t[0]:.1f}, {t[1]:.1f}) is outside the rendered world "
            f"(within {HILLS_RADIUS - 20:.0f} m of the campus)"
        )
    W, H = intrinsics.width, intrinsics.height
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    rays = _pixel_rays(W, H, fx, fy, cx, cy)  # (3, H*W) output pixel rays, z = 1
    dl = Rt.astype(np.float32) @ rays  # the same rays in the level camera
    ul = fx * dl[0] / dl[2] + cx
    vl = fy * dl[1] / dl[2] + cy
    u0, u1 = int(math.floor(ul.min())) - 1, int(math.ceil(ul.max())) + 1
    v0, v1 = int(math.floor(vl.min())) - 1, int(math.ceil(vl.max())) + 1
    level = LevelCamera(t, yaw, fx, fy, cx - u0, cy - v0, u1 - u0 + 1, v1 - v0 + 1)
    prims = campus.prims
    if dynamic_objects:
        prims = Prims.concat([prims, campus.dynamic_prims(dynamic_objects)])
    out = cast(campus, prims, level)
    shade(campus, level, out, lighting)
    map_x, map_y = (ul - u0).reshape(H, W), (vl - v0).reshape(H, W)
    rgb = cv2.remap(out.rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ci = np.clip(np.rint(ul - u0), 0, level.width - 1).astype(np.intp)
    ri = np.clip(np.rint(vl - v0), 0, level.height - 1).astype(np.intp)
    nearest = ri * level.width + ci  # flat index of each output pixel's nearest level pixel
    labels = out.labels.ravel()[nearest].reshape(H, W)
    depth = _exact_depth(campus, out, level, R.astype(np.float32) @ rays, nearest, dl[2])
    return rgb, labels, depth.reshape(H, W)


@functools.lru_cache(maxsize=8)
def _pixel_rays(W: int, H: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """``(3, H*W)`` float32 rays ``((u - cx) / fx, (v - cy) / fy, 1)`` of the pixels in row-major order."""
    u, v = np.meshgrid((np.arange(W) - cx) / fx, (np.arange(H) - cy) / fy)
    rays = np.stack([u.ravel(), v.ravel(), np.ones(W * H)]).astype(np.float32)
    rays.setflags(write=False)
    return rays


def _exact_depth(
    campus: Campus, img: LevelImage, cam: LevelCamera, dw: np.ndarray, nearest: np.ndarray, dz_level: np.ndarray
) -> np.ndarray:
    """Depth ``(N,)`` along the optical axis of each output pixel's own ray, on the surface its label came from.

    ``dw (3, N)``: world directions of the output rays (camera z = 1, so the ray parameter is the
    depth); ``nearest (N,)``: flat index of the nearest level pixel; ``dz_level (N,)``: z of the
    rays in the level camera (to move a level depth onto the output ray, the fallback).
    """
    code = img.code.ravel()[nearest]
    fallback = img.zbuf.ravel()[nearest] / dz_level
    depth = np.zeros(code.shape, np.float32)
    h = np.float32(cam.h)
    with np.errstate(divide="ignore", invalid="ignore"):
        np.divide(-h, dw[2], out=depth, where=code == GROUND)
        m = np.nonzero(code == HILLS)[0]
        if len(m):
            ox, oy = cam.x - campus.center[0], cam.y - campus.center[1]
            dx, dy = dw[0, m], dw[1, m]
            A, B = dx * dx + dy * dy, ox * dx + oy * dy
            depth[m] = (-B + np.sqrt(np.maximum(B * B - A * (ox * ox + oy * oy - HILLS_RADIUS**2), 0))) / A
        P = img.slots.get("P")
        m = np.nonzero((code >= 0) & (code < E_OFFSET))[0]
        if P and len(m):
            s = code[m]
            dx, dy, dz = dw[0, m], dw[1, m], dw[2, m]
            nx, ny = P["nx"][s], P["ny"][s]
            t_plane = (P["off"][s] - (nx * cam.x + ny * cam.y)) / (nx * dx + ny * dy)
            qx, qy = cam.x - P["cx"][s], cam.y - P["cy"][s]
            A, B = dx * dx + dy * dy, qx * dx + qy * dy
            t_cyl = (-B - np.sqrt(B * B - A * (qx * qx + qy * qy - P["a"][s] ** 2))) / A
            t_cap = (np.where(dz < 0, P["z1"][s], P["z0"][s]) - cam.h) / dz
            depth[m] = np.where(img.cap.ravel()[nearest[m]], t_cap, np.where(P["kind"][s] == CYLINDER, t_cyl, t_plane))
        E = img.slots.get("E")
        m = np.nonzero(code >= E_OFFSET)[0]
        if E and len(m):
            pr = E["prims"]
            p = E["pid"][code[m] - E_OFFSET]
            k = pr.a[p] / ((pr.z1[p] - pr.z0[p]) / 2)  # scale z so that the crown is a sphere
            q = np.stack([cam.x - pr.cx[p], cam.y - pr.cy[p], (cam.h - (pr.z0[p] + pr.z1[p]) / 2) * k])
            d = np.stack([dw[0, m], dw[1, m], dw[2, m] * k])
            A, B, C = (d * d).sum(0), (q * d).sum(0), (q * q).sum(0) - pr.a[p] ** 2
            depth[m] = (-B - np.sqrt(B * B - A * C)) / A
        good = (depth > 0) & (np.abs(depth - fallback) <= 0.25 * fallback + 0.1)  # False for NaN
        depth = np.where(good, depth, fallback)
    depth[(code == SKY_CODE) | ~np.isfinite(depth)] = 0.0
    return depth.astype(np.float32, copy=False)

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

import math

import cv2
import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.data.synth.campus import HILLS_RADIUS, Campus, DynamicObject
from vlocnetpp_core.data.synth.lighting import DEFAULT_LIGHTING, Lighting
from vlocnetpp_core.data.synth.prims import CYLINDER, Prims
from vlocnetpp_core.data.synth.raycast import E_OFFSET, GROUND, HILLS, SKY_CODE, LevelCamera, cast
from vlocnetpp_core.data.synth.shade import shade
from vlocnetpp_core.intrinsics import Intrinsics

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
        raise ValueError(f"camera at ({t[0]:.1f}, {t[1]:.1f}) is outside the rendered world (within {HILLS_RADIUS - 20:.0f} m of the campus)")
    W, H = intrinsics.width, intrinsics.height
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    # rays of the output pixels, in the output camera (z = 1) and in the level camera
    rx = ((np.arange(W) - cx) / fx).astype(np.float32)[None, :]
    ry = ((np.arange(H) - cy) / fy).astype(np.float32)[:, None]
    Rt32 = Rt.astype(np.float32)
    dl = [Rt32[i, 0] * rx + Rt32[i, 1] * ry + Rt32[i, 2] for i in range(3)]  # (H, W) each
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
    map_x, map_y = ul - u0, vl - v0
    rgb = cv2.remap(out.rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ci = np.clip(np.rint(map_x), 0, level.width - 1).astype(np.intp)
    ri = np.clip(np.rint(map_y), 0, level.height - 1).astype(np.intp)
    labels = out.labels[ri, ci]
    depth = _exact_depth(campus, prims, out, level, R.astype(np.float32), rx, ry, ri, ci, dl[2])
    return rgb, labels, depth


def _exact_depth(campus, prims, img, cam: LevelCamera, R, rx, ry, ri, ci, dz_level) -> np.ndarray:
    """Depth along the optical axis of each output pixel's own ray, on the surface its label came from."""
    codef = img.code[ri, ci]
    fallback = img.zbuf[ri, ci] / dz_level  # nearest level depth, moved onto this ray
    dwx = R[0, 0] * rx + R[0, 1] * ry + R[0, 2]
    dwy = R[1, 0] * rx + R[1, 1] * ry + R[1, 2]
    dwz = R[2, 0] * rx + R[2, 1] * ry + R[2, 2]
    h = np.float32(cam.h)
    depth = np.zeros(codef.shape, np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        np.divide(-h, dwz, out=depth, where=codef == GROUND)
        m = codef == HILLS
        if m.any():
            ox, oy = cam.x - campus.center[0], cam.y - campus.center[1]
            A = dwx[m] ** 2 + dwy[m] ** 2
            B = ox * dwx[m] + oy * dwy[m]
            C = ox * ox + oy * oy - HILLS_RADIUS**2
            depth[m] = (-B + np.sqrt(np.maximum(B * B - A * C, 0))) / A
        P = img.slots.get("P")
        m = (codef >= 0) & (codef < E_OFFSET)
        if P and m.any():
            s = codef[m]
            capf = img.cap[ri, ci][m]
            kind = P["kind"][s]
            px, py = dwx[m], dwy[m]
            t_plane = (P["off"][s] - (P["nx"][s] * cam.x + P["ny"][s] * cam.y)) / (P["nx"][s] * px + P["ny"][s] * py)
            qx, qy = cam.x - P["cx"][s], cam.y - P["cy"][s]
            A = px * px + py * py
            B = qx * px + qy * py
            C = qx * qx + qy * qy - P["a"][s] ** 2
            t_cyl = (-B - np.sqrt(B * B - A * C)) / A
            zp = np.where(dwz[m] < 0, P["z1"][s], P["z0"][s])
            t_cap = (zp - cam.h) / dwz[m]
            depth[m] = np.where(capf, t_cap, np.where(kind == CYLINDER, t_cyl, t_plane))
        E = img.slots.get("E")
        m = codef >= E_OFFSET
        if E and m.any():
            pr = E["prims"]
            p = E["pid"][codef[m] - E_OFFSET]
            k = pr.a[p] / ((pr.z1[p] - pr.z0[p]) / 2)
            q = np.stack([cam.x - pr.cx[p], cam.y - pr.cy[p], (cam.h - (pr.z0[p] + pr.z1[p]) / 2) * k])
            d = np.stack([dwx[m], dwy[m], dwz[m] * k])
            A = (d * d).sum(0)
            B = (q * d).sum(0)
            C = (q * q).sum(0) - pr.a[p] ** 2
            depth[m] = (-B - np.sqrt(B * B - A * C)) / A
        good = (depth > 0) & (np.abs(depth - fallback) <= 0.25 * fallback + 0.1)  # False for NaN
        depth = np.where(good, depth, fallback)
    depth[(codef == SKY_CODE) | ~np.isfinite(depth)] = 0.0
    return depth.astype(np.float32, copy=False)

"""Render one frame of the campus: RGB, class ids and depth that agree exactly with the pose.

Method (2.5D ray casting, all numpy/OpenCV):

1. The pose ``T_wc`` is split into a *level* camera (same centre, same heading, optical axis
   horizontal, image y axis vertical) and a small tilt ``R_tilt`` (pitch / roll) so that
   ``R_wc = R_level(yaw) R_tilt``.
2. The level camera sees every image column as a vertical plane through the camera centre, so
   one 2D ray per column is intersected with every primitive footprint (boxes by slabs,
   cylinders and crowns by circles). Per pixel row, the height range ``[z0, z1]`` of a prism
   turns into a range of the ray parameter, giving exact entry depths for sides *and* tops;
   crowns are ellipsoids solved per pixel. The nearest ``K`` footprint hits of each column are
   z-buffered layer by layer; the ground is the plane z = 0, the hills a vertical cylinder of
   varying height around the campus, the sky everything else.
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
from vlocnetpp_core.data.synth.campus import HILLS_MAX_M, HILLS_RADIUS, SKY, Campus, DynamicObject
from vlocnetpp_core.data.synth.ground import MIP_LEVELS, OUTSIDE_RGB, RES
from vlocnetpp_core.data.synth.lighting import DEFAULT_LIGHTING, Lighting
from vlocnetpp_core.data.synth.prims import BOX, CYLINDER, ELLIPSOID, Prims
from vlocnetpp_core.data.synth.textures import LEVELS, PPM
from vlocnetpp_core.intrinsics import Intrinsics

MAX_TILT_DEG = 25.0  # pitch/roll the level render + homography supports
NEAR = 0.05  # metres
KMAX = 24  # footprint hits z-buffered per column (nearest first)
GROUND, SKY_CODE, HILLS = -1, -2, -3
_E_OFFSET = 1 << 24  # slot codes of ellipsoid hits start here


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
    level = _LevelCamera(t, yaw, fx, fy, cx - u0, cy - v0, u1 - u0 + 1, v1 - v0 + 1)
    prims = campus.prims
    if dynamic_objects:
        prims = Prims.concat([prims, campus.dynamic_prims(dynamic_objects)])
    out = _render_level(campus, prims, level, lighting)
    map_x, map_y = ul - u0, vl - v0
    rgb = cv2.remap(out.rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ci = np.clip(np.rint(map_x), 0, level.width - 1).astype(np.intp)
    ri = np.clip(np.rint(map_y), 0, level.height - 1).astype(np.intp)
    labels = out.labels[ri, ci]
    depth = _exact_depth(campus, prims, out, level, R.astype(np.float32), rx, ry, ri, ci, dl[2])
    return rgb, labels, depth


class _LevelCamera:
    """The level (zero pitch/roll) pinhole camera the scene is ray cast with."""

    def __init__(self, t: np.ndarray, yaw: float, fx: float, fy: float, cx: float, cy: float, width: int, height: int):
        self.x, self.y, self.h = float(t[0]), float(t[1]), float(t[2])
        self.yaw, self.fx, self.fy, self.cx, self.cy = yaw, fx, fy, cx, cy
        self.width, self.height = width, height
        c, s = math.cos(yaw), math.sin(yaw)
        self.a_u = (np.arange(width) - cx) / fx  # (W,) tan of the column angle
        self.dx = self.a_u * s + c  # world direction of each column's ray per unit depth
        self.dy = -self.a_u * c + s
        self.n_u = np.sqrt(1.0 + self.a_u**2)  # horizontal distance per unit depth
        self.s_v = ((np.arange(height) - cy) / fy).astype(np.float32)  # downward slope per unit depth
        sigma = self.s_v[:, None] / self.n_u[None, :].astype(np.float32)
        sigma[sigma == 0] = 1e-9
        self.sigma = sigma  # (H, W) downward slope per metre of horizontal distance
        self.inv_sigma = (1.0 / sigma).astype(np.float32)


class _LevelImage:
    """Buffers of a level render: ``zbuf`` (depth), ``code`` (surface per pixel: GROUND, SKY_CODE,
    HILLS, a prism slot >= 0 or an ellipsoid slot >= _E_OFFSET), ``slots`` (per-slot surface data),
    ``rgb``, ``labels`` and ``cap`` (pixel shows a horizontal face of a prism)."""


def _intersect_footprints(P: Prims, cam: _LevelCamera):
    """Per column and prism: entry/exit distance (horizontal metres) and the entry parameter ``tn``."""
    ex = (cam.dx / cam.n_u)[:, None]
    ey = (cam.dy / cam.n_u)[:, None]
    ox, oy = cam.x - P.cx, cam.y - P.cy
    n = len(P)
    tn = np.full((cam.width, n), np.inf)
    tf = np.full((cam.width, n), -np.inf)
    box = P.kind == BOX
    if box.any():
        c, s, a, b = P.cos[box], P.sin[box], P.a[box], P.b[box]
        olx, oly = c * ox[box] + s * oy[box], -s * ox[box] + c * oy[box]
        elx, ely = ex * c + ey * s, -ex * s + ey * c
        elx = np.where(np.abs(elx) < 1e-12, 1e-12, elx)
        ely = np.where(np.abs(ely) < 1e-12, 1e-12, ely)
        with np.errstate(over="ignore"):
            t1, t2 = (-a - olx) / elx, (a - olx) / elx
            t3, t4 = (-b - oly) / ely, (b - oly) / ely
        tn[:, box] = np.maximum(np.minimum(t1, t2), np.minimum(t3, t4))
        tf[:, box] = np.minimum(np.maximum(t1, t2), np.maximum(t3, t4))
    rnd = ~box
    if rnd.any():
        bb = ex * ox[rnd] + ey * oy[rnd]
        cc = ox[rnd] ** 2 + oy[rnd] ** 2 - P.a[rnd] ** 2
        disc = bb * bb - cc
        sq = np.sqrt(np.maximum(disc, 0.0))
        ok = disc >= 0
        tn[:, rnd] = np.where(ok, -bb - sq, np.inf)
        tf[:, rnd] = np.where(ok, -bb + sq, -np.inf)
    hit = tf >= np.maximum(tn, 0.0) + 1e-9
    hit &= tf > NEAR
    return hit, tn, tf, ex, ey


def _nearest_layers(hit: np.ndarray, key: np.ndarray):
    """Column-wise indices of the nearest ``K`` hits (sorted), the count per column and K."""
    nh = hit.sum(1)
    K = int(min(nh.max(initial=0), KMAX))
    if K == 0:
        return None, nh, 0
    key = np.where(hit, key, np.inf)
    if key.shape[1] > K:
        part = np.argpartition(key, K - 1, axis=1)[:, :K]
        sub = np.take_along_axis(key, part, 1)
        order = np.take_along_axis(part, np.argsort(sub, axis=1, kind="stable"), 1)
    else:
        order = np.argsort(key, axis=1, kind="stable")
    return order, np.minimum(nh, K), K


def _render_level(campus: Campus, prims: Prims, cam: _LevelCamera, lighting: Lighting) -> _LevelImage:
    Hl, Wl = cam.height, cam.width
    h = cam.h
    zbuf = np.full((Hl, Wl), np.inf, np.float32)
    code = np.full((Hl, Wl), SKY_CODE, np.int32)
    sigma = cam.sigma
    n_u32 = cam.n_u.astype(np.float32)
    inv_n = (1.0 / cam.n_u).astype(np.float32)
    # ---- ground (rows below the horizon) and hills
    g_row0 = int(np.searchsorted(cam.s_v, 0.0, side="right"))
    zg = (h / cam.s_v[g_row0:]).astype(np.float32)
    zbuf[g_row0:] = zg[:, None]
    code[g_row0:] = GROUND
    ox, oy = cam.x - campus.center[0], cam.y - campus.center[1]
    ex, ey = cam.dx / cam.n_u, cam.dy / cam.n_u
    bb = ex * ox + ey * oy
    rho_h = -bb + np.sqrt(np.maximum(bb * bb - (ox * ox + oy * oy - HILLS_RADIUS**2), 0.0))
    hx, hy = ox + rho_h * ex, oy + rho_h * ey
    theta = np.mod(np.arctan2(hy, hx), 2 * math.pi)
    nb = len(campus.hills)
    fpos = theta / (2 * math.pi) * nb
    i0 = np.floor(fpos).astype(int) % nb
    w = fpos - np.floor(fpos)
    hill_top = campus.hills[i0] * (1 - w) + campus.hills[(i0 + 1) % nb] * w
    z_h = (rho_h * inv_n).astype(np.float32)
    hills = (sigma >= ((h - hill_top) / rho_h).astype(np.float32)[None, :]) & (z_h[None, :] < zbuf)
    zbuf = np.where(hills, z_h[None, :], zbuf)
    code[hills] = HILLS
    # ---- prisms (boxes, cylinders) and ellipsoids
    lt = lighting
    slots = {}
    if len(prims):
        rel_x, rel_y = prims.cx - cam.x, prims.cy - cam.y
        c, s = math.cos(cam.yaw), math.sin(cam.yaw)
        zc, xc = rel_x * c + rel_y * s, rel_x * s - rel_y * c
        tan_half = float(np.abs(cam.a_u).max())
        r = prims.radius
        keep = (zc > -r) & (np.abs(xc) - tan_half * zc <= r * math.sqrt(1 + tan_half**2))
        idx_all = np.nonzero(keep)[0]
        P = prims.take(idx_all)
        is_e = P.kind == ELLIPSOID
        if (~is_e).any():
            slots["P"] = _zbuffer_prisms(P.take(np.nonzero(~is_e)[0]), cam, zbuf, code, inv_n, campus.cutout)
        if is_e.any():
            slots["E"] = _zbuffer_ellipsoids(P.take(np.nonzero(is_e)[0]), cam, zbuf, code, inv_n)
    img = _LevelImage()
    img.zbuf, img.code, img.slots = zbuf, code, slots
    img.g_row0 = g_row0
    img.rho_h, img.theta = rho_h, theta
    _shade(campus, cam, img, lt, n_u32)
    return img


def _zbuffer_prisms(P: Prims, cam: _LevelCamera, zbuf: np.ndarray, code: np.ndarray, inv_n: np.ndarray, cutout: np.ndarray) -> dict:
    hit, tn, tf, ex, ey = _intersect_footprints(P, cam)
    order, nh, K = _nearest_layers(hit, np.maximum(tn, 0.0))
    if K == 0:
        return {}
    pid = order  # (W, K) index into P
    take = lambda a: np.take_along_axis(a, order, 1)  # noqa: E731
    TN, TF = take(tn), take(tf)
    R1 = np.maximum(TN, 0.0)
    Wl = cam.width
    h = cam.h
    isg = cam.inv_sigma
    z0 = P.z0[pid].astype(np.float32)
    z1 = P.z1[pid].astype(np.float32)
    cut = P.cutout[pid]
    # side-face attributes of every slot (slot = k * W + column)
    TNf = np.where(np.isfinite(TN), TN, 0.0)  # missed slots are never read
    ent_x, ent_y = cam.x + TNf * ex, cam.y + TNf * ey  # entry point (world)
    kind = P.kind[pid]
    cx, cy = P.cx[pid], P.cy[pid]
    co, si = P.cos[pid], P.sin[pid]
    a, b = P.a[pid], P.b[pid]
    lx, ly = co * (ent_x - cx) + si * (ent_y - cy), -si * (ent_x - cx) + co * (ent_y - cy)
    xface = np.abs(lx) * b >= np.abs(ly) * a  # entry on an x' face (compare normalised coordinates)
    u_box = np.where(xface, np.where(lx > 0, ly + b, 2 * b + 2 * a + (b - ly)), np.where(ly > 0, 2 * b + (a - lx), 4 * b + 2 * a + (lx + a)))
    nlx = np.where(xface, np.where(lx > 0, 1.0, -1.0), 0.0)
    nly = np.where(xface, 0.0, np.where(ly > 0, 1.0, -1.0))
    nbx, nby = co * nlx - si * nly, si * nlx + co * nly
    rx, ry = ent_x - cx, ent_y - cy
    rn = np.maximum(np.hypot(rx, ry), 1e-9)
    is_box = kind == BOX
    nx = np.where(is_box, nbx, rx / rn)
    ny = np.where(is_box, nby, ry / rn)
    ang = np.mod(np.arctan2(ry, rx), 2 * math.pi)
    u = np.where(is_box, u_box, ang / (2 * math.pi) * P.tw[pid])
    for k in range(K):
        win_ = _layer_window(cam, nh, k, R1[:, k], TF[:, k], z0[:, k], z1[:, k], inv_n)
        if win_ is None:
            break
        rows, cols, full = win_
        r1 = R1[cols, k].astype(np.float32)
        r2 = TF[cols, k].astype(np.float32)
        isg_c = isg[rows] if full else isg[rows, cols]
        A = (h - z1[cols, k]) * isg_c
        B = (h - z0[cols, k]) * isg_c
        ent = np.maximum(np.minimum(A, B), r1)
        ext = np.minimum(np.maximum(A, B), r2)
        Z = ent * inv_n[cols]
        zb = zbuf[rows] if full else zbuf[rows, cols]
        win = (ent <= ext) & (ent > NEAR) & (Z < zb)
        cc = cut[cols, k]
        if cc.any():
            win &= ~_holes(P, pid, rows, cols, k, cc, ent, r1, u, cam, win, cutout)
        _commit(zbuf, code, rows, cols, full, win, Z, k * Wl)
    flat = lambda a: np.ascontiguousarray(a.T).reshape(-1)  # noqa: E731  (K, W) -> slot order
    return {
        "K": K, "r1": flat(R1).astype(np.float32), "label": flat(P.label[pid]), "z0": flat(z0), "z1": flat(z1),
        "ax": flat(P.tx[pid] + u * PPM - 0.5).astype(np.float32),  # atlas x of the side texel hit
        "ay": flat(P.ty[pid] + z1 * PPM - 0.5).astype(np.float32),  # atlas y of height 0 on the side strip
        "nx": flat(nx), "ny": flat(ny),
        "cap_x": flat(P.cap_x[pid]).astype(np.float32), "cap_y": flat(P.cap_y[pid]).astype(np.float32), "kind": flat(kind),
        "off": flat(nx * ent_x + ny * ent_y), "cx": flat(cx), "cy": flat(cy), "a": flat(a),
    }


def _layer_window(cam: _LevelCamera, nh, k, r1, r2, z0, z1, inv_n):
    """Rows (a slice) and columns (slice or indices) that layer ``k`` can touch, or None when empty.

    A hit between horizontal distances ``[r1, r2]`` spanning heights ``[z0, z1]`` projects
    between the rows of those heights at the near and far depth.
    """
    active = nh > k
    if not active.any():
        return None
    full = bool(active.all())
    cols = slice(None) if full else np.nonzero(active)[0]
    d1 = np.maximum(r1[cols], NEAR) * inv_n[cols]
    d2 = np.maximum(r2[cols], NEAR) * inv_n[cols]
    hz0, hz1 = cam.h - z0[cols], cam.h - z1[cols]
    v = np.concatenate([hz0 / d1, hz0 / d2, hz1 / d1, hz1 / d2]) * cam.fy + cam.cy
    lo = max(int(math.floor(float(v.min()))) - 1, 0)
    hi = min(int(math.ceil(float(v.max()))) + 2, cam.height)
    if hi <= lo:
        return None
    return slice(lo, hi), cols, full


def _commit(zbuf, code, rows, cols, full, win, Z, base) -> None:
    """Write the winning pixels of a layer window into the z-buffer and the surface codes."""
    if full:
        np.copyto(zbuf[rows], Z, where=win)
        np.copyto(code[rows], np.arange(base, base + code.shape[1], dtype=np.int32)[None, :], where=win)
    else:
        zbuf[rows, cols] = np.where(win, Z, zbuf[rows, cols])
        code[rows, cols] = np.where(win, (base + cols).astype(np.int32)[None, :], code[rows, cols])


def _holes(P, pid, rows, cols, k, cc, ent, r1, u, cam, win, mask: np.ndarray) -> np.ndarray:
    """Cut-out texels (fence holes, ``mask`` > 0 in the atlas) hit by the winning side pixels of layer ``k``."""
    hole = np.zeros_like(win)
    sel = win & cc[None, :] & (ent <= r1[None, :] + 1e-4)
    ys, xs = np.nonzero(sel)
    if len(ys) == 0:
        return hole
    colidx = np.arange(cam.width)[cols][xs]
    hgt = cam.h - ent[ys, xs] * cam.sigma[ys + rows.start, colidx]
    ax = P.tx[pid[colidx, k]] + u[colidx, k] * PPM - 0.5
    ay = P.ty[pid[colidx, k]] + (P.z1[pid[colidx, k]] - hgt) * PPM - 0.5
    ai = np.clip(np.rint(ax), 0, mask.shape[1] - 1).astype(np.intp)
    aj = np.clip(np.rint(ay), 0, mask.shape[0] - 1).astype(np.intp)
    hole[ys, xs] = mask[aj, ai] > 0
    return hole


def _zbuffer_ellipsoids(E: Prims, cam: _LevelCamera, zbuf: np.ndarray, code: np.ndarray, inv_n: np.ndarray) -> dict:
    hit, tn, tf, ex, ey = _intersect_footprints(E, cam)
    order, nh, K = _nearest_layers(hit, np.maximum(tn, 0.0))
    if K == 0:
        return {}
    pid = order
    TN = np.take_along_axis(tn, order, 1)
    TF = np.take_along_axis(tf, order, 1)
    miss = ~np.isfinite(TN)
    TN, TF = np.where(miss, 0.0, TN), np.where(miss, 0.0, TF)  # never read: those slots are inactive
    rho_m = ((TN + TF) / 2).astype(np.float32)
    w2 = (((TF - TN) / 2) ** 2).astype(np.float32)
    bv = (E.z1 - E.z0) / 2
    k2 = ((E.a / bv) ** 2)[pid].astype(np.float32)
    delta = (cam.h - (E.z0 + E.z1)[pid] / 2).astype(np.float32)
    z0, z1 = E.z0[pid], E.z1[pid]
    sigma = cam.sigma
    Wl = cam.width
    for k in range(K):
        win_ = _layer_window(cam, nh, k, TN[:, k], TF[:, k], z0[:, k], z1[:, k], inv_n)
        if win_ is None:
            break
        rows, cols, full = win_
        sg = sigma[rows] if full else sigma[rows, cols]
        kk, dd, rm = k2[cols, k], delta[cols, k], rho_m[cols, k]
        A = 1.0 + kk * sg * sg
        B = rm + kk * dd * sg
        C = rm * rm + kk * dd * dd - w2[cols, k]
        D = B * B - A * C
        rho = (B - np.sqrt(np.maximum(D, 0.0))) / A
        Z = rho * inv_n[cols]
        zb = zbuf[rows] if full else zbuf[rows, cols]
        win = (D >= 0) & (rho > NEAR) & (Z < zb)
        _commit(zbuf, code, rows, cols, full, win, Z, _E_OFFSET + k * Wl)
    flat = lambda a: np.ascontiguousarray(a.T).reshape(-1)  # noqa: E731
    return {"K": K, "pid": flat(pid), "prims": E}


def _sample_atlas(campus: Campus, ax: np.ndarray, ay: np.ndarray, lod: np.ndarray) -> np.ndarray:
    """Bilinear, mip-blended atlas RGBA (N, 4) float32 in [0, 1] at level-0 texel coords."""
    out = np.zeros((len(ax), 4), np.float32)
    lod = np.clip(lod, 0, LEVELS - 1)
    for L in range(LEVELS):
        w = np.clip(1.0 - np.abs(lod - L), 0.0, 1.0)
        if not (w > 0).any():
            continue
        s = 2.0**L
        mx = ((ax + 0.5) / s - 0.5).astype(np.float32)[None, :]
        my = ((ay + 0.5) / s - 0.5).astype(np.float32)[None, :]
        smp = cv2.remap(campus.atlas[L], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
        out += smp.astype(np.float32) * (w / 255.0)[:, None]
    return out


def _shade(campus: Campus, cam: _LevelCamera, img: _LevelImage, lt: Lighting, n_u32: np.ndarray) -> None:
    """Colour and class of every level pixel from its surface code (sky, ground, hills, prisms, crowns)."""
    Hl, Wl = cam.height, cam.width
    h = cam.h
    zbuf, code = img.zbuf, img.code
    col = np.empty((Hl, Wl, 3), np.float32)
    labels = np.empty((Hl, Wl), np.uint8)
    cap = np.zeros((Hl, Wl), bool)
    sd = lt.sun_direction().astype(np.float32)
    tint = np.asarray(lt.tint, np.float32)
    r0 = img.g_row0  # rows >= r0 look below the horizon: sky above, ground below; the rest overwrite
    if r0 > 0:
        az = np.broadcast_to(np.arctan2(cam.dy, cam.dx).astype(np.float32)[None, :], (r0, Wl))
        col[:r0] = _sky(campus, lt, np.arctan(-cam.sigma[:r0]), az)
        labels[:r0] = SKY
    if r0 < Hl:
        col[r0:], labels[r0:] = _ground(campus, cam, lt, r0, tint)
    hil = code == HILLS
    if hil.any():
        ys, xs = np.nonzero(hil)
        hgt = h - img.rho_h[xs] * cam.sigma[ys, xs]
        tex = campus.hills_rgb
        mx = (img.theta[xs] / (2 * math.pi) * tex.shape[1] - 0.5).astype(np.float32)[None, :]
        my = ((1 - hgt / HILLS_MAX_M) * tex.shape[0] - 0.5).astype(np.float32)[None, :]
        c = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0].astype(np.float32)
        col[ys, xs] = c * (tint * np.float32((lt.ambient + 0.6 * lt.sun) / 255.0))
        labels[ys, xs] = 0
    P = img.slots.get("P")
    if P:
        ys, xs = np.nonzero((code >= 0) & (code < _E_OFFSET))
        s = code[ys, xs]
        Z = zbuf[ys, xs]
        is_cap = Z * n_u32[xs] > P["r1"][s] * np.float32(1 + 1e-4) + np.float32(1e-4)
        cap[ys, xs] = is_cap
        side_light = (lt.ambient + lt.sun * np.maximum(P["nx"] * sd[0] + P["ny"] * sd[1], 0.0)).astype(np.float32)  # per slot
        down = cam.s_v[ys] > 0
        light = np.where(is_cap, np.where(down, np.float32(lt.ambient + lt.sun * max(sd[2], 0.0)), np.float32(lt.ambient)), side_light[s])
        ax = np.where(is_cap, P["cap_x"][s], P["ax"][s])
        ay = np.where(is_cap, P["cap_y"][s], P["ay"][s] - (h - Z * cam.s_v[ys]) * np.float32(PPM))
        tex = _sample_atlas(campus, ax, ay, np.log2(np.maximum(Z * np.float32(PPM / cam.fx), 1e-6)))
        c = tex[:, :3] * light[:, None]
        refl = np.where(is_cap, np.float32(0.0), tex[:, 3])
        m = np.nonzero(refl > 0.02)[0]
        if len(m):
            r = refl[m, None]
            c[m] = c[m] * (1 - r) + r * _reflection(campus, cam, lt, ys[m], xs[m], P["nx"][s[m]], P["ny"][s[m]])
        col[ys, xs] = c * tint
        labels[ys, xs] = P["label"][s]
    E = img.slots.get("E")
    if E:
        ys, xs = np.nonzero(code >= _E_OFFSET)
        pr = E["prims"]
        p = E["pid"][code[ys, xs] - _E_OFFSET]
        Z = zbuf[ys, xs]
        X = cam.x + Z * cam.dx[xs] - pr.cx[p]
        Y = cam.y + Z * cam.dy[xs] - pr.cy[p]
        zz = h - Z * cam.s_v[ys]
        bv = (pr.z1[p] - pr.z0[p]) / 2
        az = np.mod(np.arctan2(Y, X), 2 * math.pi)
        ax = pr.tx[p] + az / (2 * math.pi) * pr.tw[p] * PPM - 0.5
        ay = pr.ty[p] + np.clip((pr.z1[p] - zz) / (2 * bv), 0, 1) * pr.th[p] * PPM - 0.5
        tex = _sample_atlas(campus, ax, ay, np.log2(np.maximum(Z * PPM / cam.fx, 1e-6)))
        a2 = pr.a[p] ** 2
        nx, ny, nz = X / a2, Y / a2, (zz - pr.z0[p] - bv) / bv**2
        lam = np.maximum((nx * sd[0] + ny * sd[1] + nz * sd[2]) / np.sqrt(nx * nx + ny * ny + nz * nz), 0.0)
        col[ys, xs] = tex[:, :3] * (lt.ambient + lt.sun * lam).astype(np.float32)[:, None] * tint
        labels[ys, xs] = pr.label[p]
    # haze: c = c * f + horizon * (1 - f) with f = exp(-distance / haze); the sky keeps f = 1
    f = np.exp(np.where(code != SKY_CODE, zbuf, np.float32(0.0)) * (n_u32 / np.float32(-lt.haze_m))[None, :])
    hor = np.empty_like(col)
    hor[:] = np.asarray(lt.sky_horizon, np.float32)
    col = cv2.blendLinear(col, hor, f, np.float32(1.0) - f)
    img.rgb = cv2.convertScaleAbs(col, alpha=255.0)
    img.labels = labels
    img.cap = cap


def _ground(campus: Campus, cam: _LevelCamera, lt: Lighting, r0: int, tint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour (lit, tinted) and class ids of the ground seen by level rows ``r0:``, mip-mapped by distance."""
    g = campus.ground
    h = cam.h
    zg = (h / cam.s_v[r0:])[:, None]
    gx = (cam.x + zg * cam.dx[None, :]).astype(np.float32)
    gy = (cam.y + zg * cam.dy[None, :]).astype(np.float32)
    mc = ((gx - g.x0) / RES - 0.5).astype(np.float32)
    mr = ((gy - g.y0) / RES - 0.5).astype(np.float32)
    fp = zg[:, 0] / math.sqrt(cam.fx * cam.fy) * np.sqrt(np.maximum(zg[:, 0] / h, 1.0))  # metres per pixel
    lod = np.clip(np.log2(np.maximum(fp / RES, 1e-6)), 0, MIP_LEVELS - 1).astype(np.float32)
    alb = np.zeros(gx.shape + (3,), np.float32)
    border = tuple(int(v) for v in OUTSIDE_RGB)
    for L in range(MIP_LEVELS):
        w = np.clip(1.0 - np.abs(lod - L), 0, 1)
        rows = np.nonzero(w > 0)[0]
        if len(rows) == 0:
            continue
        a, b = rows[0], rows[-1] + 1
        s = 2.0**L
        smp = cv2.remap(g.mips[L], (mc[a:b] + 0.5) / s - 0.5, (mr[a:b] + 0.5) / s - 0.5, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=border)
        alb[a:b] += smp.astype(np.float32) * (w[a:b] / 255.0)[:, None, None]
    outside_light = lt.ambient + lt.sun * max(0.0, math.sin(lt.sun_elevation))
    shade = cv2.remap(campus.ground_light(lt), (mc + 0.5) / 2 - 0.5, (mr + 0.5) / 2 - 0.5, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=outside_light)
    labels = cv2.remap(g.labels, np.rint(mc), np.rint(mr), cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    alb *= shade[..., None]
    alb *= tint
    return alb, labels


def _sky(campus: Campus, lt: Lighting, elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """Sky colour ``(N, 3)`` float32 for directions (radians), looked up in the lighting's sky panorama."""
    pano = campus.sky_panorama(lt)
    flat = np.ndim(azimuth) == 1
    mx = (np.mod(azimuth, 2 * math.pi) * (pano.shape[1] / (2 * math.pi)) - 0.5).astype(np.float32)
    my = np.clip(elevation * (pano.shape[0] / (math.pi / 2)) - 0.5, 0, pano.shape[0] - 1).astype(np.float32)
    out = cv2.remap(pano, mx[None, :] if flat else mx, my[None, :] if flat else my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out[0] if flat else out


def _reflection(campus: Campus, cam: _LevelCamera, lt: Lighting, ys, xs, nx, ny) -> np.ndarray:
    """What a vertical mirror with horizontal normal ``(nx, ny)`` shows at level pixels ``(ys, xs)``."""
    vx, vy, vz = cam.dx[xs].astype(np.float32), cam.dy[xs].astype(np.float32), -cam.s_v[ys]
    dot = vx * nx + vy * ny
    rx, ry = vx - 2 * dot * nx, vy - 2 * dot * ny
    el = np.arctan2(vz, np.hypot(rx, ry))
    az = np.arctan2(ry, rx)
    sky = _sky(campus, lt, el, az)
    nb = len(campus.skyline)
    line = campus.skyline[(np.mod(az, 2 * math.pi) / (2 * math.pi) * nb).astype(int) % nb]
    fac = np.float32(lt.ambient + 0.4 * lt.sun)
    below = np.where((el < 0)[:, None], np.array([0.30, 0.34, 0.26], np.float32), np.array([0.42, 0.40, 0.38], np.float32)) * fac
    return np.where((el > line)[:, None], sky, below)


def _exact_depth(campus, prims, img, cam: _LevelCamera, R, rx, ry, ri, ci, dz_level) -> np.ndarray:
    """Depth along the optical axis of each output pixel's own ray, on the surface its label came from."""
    codef = img.code[ri, ci]
    fallback = img.zbuf[ri, ci] / dz_level  # nearest level depth, moved onto this ray
    dwx = R[0, 0] * rx + R[0, 1] * ry + R[0, 2]
    dwy = R[1, 0] * rx + R[1, 1] * ry + R[1, 2]
    dwz = R[2, 0] * rx + R[2, 1] * ry + R[2, 2]
    h = np.float32(cam.h)
    depth = np.zeros(codef.shape, np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = codef == GROUND
        depth[g] = -h / dwz[g]
        m = codef == HILLS
        if m.any():
            ox, oy = cam.x - campus.center[0], cam.y - campus.center[1]
            A = dwx[m] ** 2 + dwy[m] ** 2
            B = ox * dwx[m] + oy * dwy[m]
            C = ox * ox + oy * oy - HILLS_RADIUS**2
            depth[m] = (-B + np.sqrt(np.maximum(B * B - A * C, 0))) / A
        P = img.slots.get("P")
        m = (codef >= 0) & (codef < _E_OFFSET)
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
        m = codef >= _E_OFFSET
        if E and m.any():
            pr = E["prims"]
            p = E["pid"][codef[m] - _E_OFFSET]
            k = pr.a[p] / ((pr.z1[p] - pr.z0[p]) / 2)
            q = np.stack([cam.x - pr.cx[p], cam.y - pr.cy[p], (cam.h - (pr.z0[p] + pr.z1[p]) / 2) * k])
            d = np.stack([dwx[m], dwy[m], dwz[m] * k])
            A = (d * d).sum(0)
            B = (q * d).sum(0)
            C = (q * q).sum(0) - pr.a[p] ** 2
            depth[m] = (-B - np.sqrt(B * B - A * C)) / A
        bad = ~np.isfinite(depth) | (depth <= 0) | (np.abs(depth - fallback) > 0.25 * fallback + 0.1)
        depth = np.where(bad, fallback, depth)
    depth[codef == SKY_CODE] = 0.0
    depth[~np.isfinite(depth)] = 0.0
    return depth.astype(np.float32)

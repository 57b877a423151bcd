"""Ray casting of the campus with a *level* camera (optical axis horizontal, image y axis vertical).

Every image column of a level camera is a vertical plane through the camera centre, so one 2D
ray per column is intersected with every primitive footprint (boxes by slabs, cylinders and
crown footprints by circles). Per pixel row, a prism's height range ``[z0, z1]`` becomes a range
of the ray parameter, which gives exact entry depths for its sides and its top or bottom; crowns
are ellipsoids solved per pixel. The nearest ``KMAX`` footprint hits of each column are
z-buffered layer by layer, each layer only over the rows it can reach. The ground is the plane
z = 0, the hills a vertical cylinder of varying height around the campus, the sky the rest.

Horizontal distances are ``rho`` (metres along the ground); depth along the optical axis is
``Z = rho / n_u`` with ``n_u = sqrt(1 + ((u - cx) / fx)^2)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vlocnetpp_core.synth.campus import Campus
from vlocnetpp_core.synth.layout import HILLS_RADIUS
from vlocnetpp_core.synth.prims import BOX, ELLIPSOID, Prims
from vlocnetpp_core.synth.textures import PPM

NEAR = 0.05  # metres
KMAX = 24  # footprint hits z-buffered per column (nearest first)
GROUND, SKY_CODE, HILLS = -1, -2, -3
E_OFFSET = 1 << 24  # surface codes of ellipsoid hits start here


class LevelCamera:
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
        self.dx32, self.dy32, self.n_u32 = (v.astype(np.float32) for v in (self.dx, self.dy, self.n_u))
        self.s_v = ((np.arange(height) - cy) / fy).astype(np.float32)  # downward slope per unit depth
        sigma = self.s_v[:, None] / self.n_u[None, :].astype(np.float32)
        sigma[sigma == 0] = 1e-9
        self.sigma = sigma  # (H, W) downward slope per metre of horizontal distance
        self.inv_sigma = (1.0 / sigma).astype(np.float32)


@dataclass
class LevelImage:
    """Buffers of a level render.

    ``zbuf (H, W)`` depth; ``code (H, W)`` the surface of each pixel: GROUND, SKY_CODE, HILLS, a
    prism slot ``k * W + column`` (>= 0) or ``E_OFFSET +`` an ellipsoid slot; ``slots`` per-slot
    surface data (``"P"``: prisms, ``"E"``: ellipsoids); ``g_row0`` the first row below the
    horizon; ``rho_h`` / ``theta`` per column: distance and azimuth of the hills. Shading adds
    ``rgb``, ``labels`` and ``cap`` (pixel shows the top or bottom face of a prism).
    """

    zbuf: np.ndarray
    code: np.ndarray
    slots: dict
    g_row0: int
    rho_h: np.ndarray
    theta: np.ndarray
    rgb: np.ndarray | None = None
    labels: np.ndarray | None = None
    cap: np.ndarray | None = None


def cast(campus: Campus, prims: Prims, cam: LevelCamera) -> LevelImage:
    """Z-buffer the ground, the hills and every primitive in front of the level camera."""
    Hl, Wl = cam.height, cam.width
    h = cam.h
    zbuf = np.full((Hl, Wl), np.inf, np.float32)
    code = np.full((Hl, Wl), SKY_CODE, np.int32)
    sigma = cam.sigma
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
    return LevelImage(zbuf, code, slots, g_row0, rho_h, theta)


def _intersect_footprints(P: Prims, cam: LevelCamera):
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


def _zbuffer_prisms(
    P: Prims, cam: LevelCamera, zbuf: np.ndarray, code: np.ndarray, inv_n: np.ndarray, cutout: np.ndarray
) -> dict:
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
    u_box = np.where(
        xface,
        np.where(lx > 0, ly + b, 2 * b + 2 * a + (b - ly)),
        np.where(ly > 0, 2 * b + (a - lx), 4 * b + 2 * a + (lx + a)),
    )
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
        "K": K,
        "r1": flat(R1).astype(np.float32),
        "label": flat(P.label[pid]),
        "z0": flat(z0),
        "z1": flat(z1),
        "ax": flat(P.tx[pid] + u * PPM - 0.5).astype(np.float32),  # atlas x of the side texel hit
        "ay": flat(P.ty[pid] + z1 * PPM - 0.5).astype(np.float32),  # atlas y of height 0 on the side strip
        "nx": flat(nx),
        "ny": flat(ny),
        "cap_x": flat(P.cap_x[pid]).astype(np.float32),
        "cap_y": flat(P.cap_y[pid]).astype(np.float32),
        "kind": flat(kind),
        "off": flat(nx * ent_x + ny * ent_y),
        "cx": flat(cx),
        "cy": flat(cy),
        "a": flat(a),
    }


def _layer_window(cam: LevelCamera, nh, k, r1, r2, z0, z1, inv_n):
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


def _zbuffer_ellipsoids(E: Prims, cam: LevelCamera, zbuf: np.ndarray, code: np.ndarray, inv_n: np.ndarray) -> dict:
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
        _commit(zbuf, code, rows, cols, full, win, Z, E_OFFSET + k * Wl)
    flat = lambda a: np.ascontiguousarray(a.T).reshape(-1)  # noqa: E731
    return {"K": K, "pid": flat(pid), "prims": E}

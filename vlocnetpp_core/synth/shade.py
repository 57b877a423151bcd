"""Colours of a level render: sky, lit and shadowed ground, hills, textured prisms and crowns, haze.

Surfaces sample their albedo bilinearly from mip-mapped textures (the ground raster, the atlas),
are lit by ``Lighting`` (ambient + sun * max(0, n . l), ground shadows from the campus), glass
mixes in the mirrored sky/skyline, and everything fades to the horizon colour with distance.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from vlocnetpp_core.synth.campus import Campus
from vlocnetpp_core.synth.ground import DETAIL_FADE, DETAIL_RES, MIP_LEVELS, OUTSIDE_RGB, RES
from vlocnetpp_core.synth.layout import HILLS_MAX_M, SKY
from vlocnetpp_core.synth.lighting import Lighting
from vlocnetpp_core.synth.raycast import E_OFFSET, HILLS, SKY_CODE, LevelCamera, LevelImage
from vlocnetpp_core.synth.textures import LEVELS, PPM


def remap_points(src: np.ndarray, x: np.ndarray, y: np.ndarray, border: int) -> np.ndarray:
    """Bilinear samples ``(N, C)`` of ``src`` at pixel coordinates ``x, y (N,)`` (cv2.remap, in rows of 4096)."""
    n = len(x)
    width = 4096
    rows = max(1, -(-n // width))
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(src, mx.reshape(rows, width), my.reshape(rows, width), cv2.INTER_LINEAR, borderMode=border)
    return out.reshape(rows * width, -1)[:n]


def _sample_atlas(campus: Campus, ax: np.ndarray, ay: np.ndarray, lod: np.ndarray) -> np.ndarray:
    """Bilinear, mip-blended atlas RGBA (N, 4) float32 in [0, 1] at level-0 texel coords.

    Each point blends the two levels around its level of detail ``lod`` (log2 texels per pixel).
    """
    out = np.empty((len(ax), 4), np.float32)
    lod = np.clip(lod, 0, LEVELS - 1 - 1e-6).astype(np.float32)
    base = lod.astype(np.int64)  # floor
    frac = (lod - base)[:, None] * np.float32(1 / 255)
    for L in range(LEVELS - 1):
        idx = np.nonzero(base == L)[0]
        if len(idx) == 0:
            continue
        x, y, f = ax[idx], ay[idx], frac[idx]
        lo = remap_points(campus.atlas[L], (x + 0.5) / 2.0**L - 0.5, (y + 0.5) / 2.0**L - 0.5, cv2.BORDER_REPLICATE)
        hi = remap_points(
            campus.atlas[L + 1],
            (x + 0.5) / 2.0 ** (L + 1) - 0.5,
            (y + 0.5) / 2.0 ** (L + 1) - 0.5,
            cv2.BORDER_REPLICATE,
        )
        lo = lo.astype(np.float32)
        out[idx] = lo * np.float32(1 / 255) + (hi.astype(np.float32) - lo) * f
    return out


def shade(campus: Campus, cam: LevelCamera, img: LevelImage, lt: Lighting) -> None:
    """Colour (``img.rgb``) and class (``img.labels``) of every level pixel from its surface code."""
    Hl, Wl = cam.height, cam.width
    col = np.empty((Hl, Wl, 3), np.float32)
    labels = np.empty((Hl, Wl), np.uint8)
    img.cap = np.zeros((Hl, Wl), bool)
    tint = np.asarray(lt.tint, np.float32)
    r0 = img.g_row0  # rows >= r0 look below the horizon: sky above, ground below; the rest overwrite
    if r0 > 0:
        az = np.broadcast_to(np.arctan2(cam.dy, cam.dx).astype(np.float32)[None, :], (r0, Wl))
        col[:r0] = _sky(campus, lt, np.arctan(-cam.sigma[:r0]), az)
        labels[:r0] = SKY
    if r0 < Hl:
        col[r0:], labels[r0:] = _ground(campus, cam, lt, r0, tint)
    for part in (_hills, _prisms, _crowns):
        found = part(campus, cam, img, lt)
        if found is not None:
            ys, xs, c, lab = found
            col[ys, xs] = c * tint
            labels[ys, xs] = lab
    img.rgb = _haze(cam, img, lt, col)
    img.labels = labels


def _hills(campus: Campus, cam: LevelCamera, img: LevelImage, lt: Lighting):
    """``(rows, cols, colour (N, 3), class)`` of the pixels that see the distant hills, or None."""
    ys, xs = np.nonzero(img.code == HILLS)
    if len(ys) == 0:
        return None
    hgt = cam.h - img.rho_h[xs] * cam.sigma[ys, xs]
    tex = campus.hills_rgb
    c = remap_points(
        tex,
        img.theta[xs] / (2 * math.pi) * tex.shape[1] - 0.5,
        (1 - hgt / HILLS_MAX_M) * tex.shape[0] - 0.5,
        cv2.BORDER_REPLICATE,
    ).astype(np.float32)
    return ys, xs, c * np.float32((lt.ambient + 0.6 * lt.sun) / 255.0), 0


def _prisms(campus: Campus, cam: LevelCamera, img: LevelImage, lt: Lighting):
    """Textured, lit sides and caps of boxes and cylinders (glass mixes in its reflection)."""
    P = img.slots.get("P")
    if not P:
        return None
    ys, xs = np.nonzero((img.code >= 0) & (img.code < E_OFFSET))
    s = img.code[ys, xs]
    Z = img.zbuf[ys, xs]
    sd = lt.sun_direction().astype(np.float32)
    is_cap = Z * cam.n_u32[xs] > P["r1"][s] * np.float32(1 + 1e-4) + np.float32(1e-4)
    side_light = (lt.ambient + lt.sun * np.maximum(P["nx"] * sd[0] + P["ny"] * sd[1], 0.0)).astype(
        np.float32
    )  # per slot
    light = side_light[s]
    ax = P["ax"][s]
    ay = P["ay"][s] - (cam.h - Z * cam.s_v[ys]) * np.float32(PPM)
    if is_cap.any():  # tops (looking down) and bottoms (looking up) of prisms
        img.cap[ys, xs] = is_cap
        c_light = np.where(cam.s_v[ys] > 0, np.float32(lt.ambient + lt.sun * max(sd[2], 0.0)), np.float32(lt.ambient))
        light = np.where(is_cap, c_light, light)
        ax = np.where(is_cap, P["cap_x"][s], ax)
        ay = np.where(is_cap, P["cap_y"][s], ay)
    tex = _sample_atlas(campus, ax, ay, np.log2(np.maximum(Z * np.float32(PPM / cam.fx), 1e-6)))
    c = tex[:, :3] * light[:, None]
    refl = np.where(is_cap, np.float32(0.0), tex[:, 3])
    m = np.nonzero(refl > 0.02)[0]
    if len(m):
        r = refl[m, None]
        c[m] = c[m] * (1 - r) + r * _reflection(campus, cam, lt, ys[m], xs[m], P["nx"][s[m]], P["ny"][s[m]])
    return ys, xs, c, P["label"][s]


def _crowns(campus: Campus, cam: LevelCamera, img: LevelImage, lt: Lighting):
    """Textured, lit tree crowns (ellipsoids)."""
    E = img.slots.get("E")
    if not E:
        return None
    ys, xs = np.nonzero(img.code >= E_OFFSET)
    pr = E["prims"]
    p = E["pid"][img.code[ys, xs] - E_OFFSET]
    Z = img.zbuf[ys, xs]
    sd = lt.sun_direction().astype(np.float32)
    X = (cam.x - pr.cx[p]).astype(np.float32) + Z * cam.dx32[xs]  # hit point relative to the crown centre
    Y = (cam.y - pr.cy[p]).astype(np.float32) + Z * cam.dy32[xs]
    zc, bv, a = (
        ((pr.z0 + pr.z1) / 2)[p].astype(np.float32),
        ((pr.z1 - pr.z0) / 2)[p].astype(np.float32),
        pr.a[p].astype(np.float32),
    )
    dz = (cam.h - zc) - Z * cam.s_v[ys]
    az = np.arctan2(Y, X) * np.float32(1 / (2 * math.pi))
    az += az < 0
    ax = pr.tx[p] + az * pr.tw[p] * PPM - 0.5
    ay = pr.ty[p] + np.clip((bv - dz) / (2 * bv), 0, 1) * pr.th[p] * PPM - 0.5
    tex = _sample_atlas(campus, ax, ay, np.log2(np.maximum(Z * np.float32(PPM / cam.fx), 1e-6)))
    a2 = a * a
    nx, ny, nz = X / a2, Y / a2, dz / (bv * bv)
    lam = np.maximum((nx * sd[0] + ny * sd[1] + nz * sd[2]) / np.sqrt(nx * nx + ny * ny + nz * nz), 0.0)
    return ys, xs, tex[:, :3] * (lt.ambient + lt.sun * lam)[:, None], pr.label[p]


def _haze(cam: LevelCamera, img: LevelImage, lt: Lighting, col: np.ndarray) -> np.ndarray:
    """``uint8`` RGB of ``col * f + horizon * (1 - f)``, ``f = exp(-distance / haze)``; the sky keeps f = 1."""
    f = np.exp(
        np.where(img.code != SKY_CODE, img.zbuf, np.float32(0.0)) * (cam.n_u32 / np.float32(-lt.haze_m))[None, :]
    )
    hor = np.empty_like(col)
    hor[:] = np.asarray(lt.sky_horizon, np.float32)
    return cv2.convertScaleAbs(cv2.blendLinear(col, hor, f, np.float32(1.0) - f), alpha=255.0)


def _ground(campus: Campus, cam: LevelCamera, lt: Lighting, r0: int, tint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour (lit, tinted) and class ids of the ground seen by level rows ``r0:``, mip-mapped by distance."""
    g = campus.ground
    h = cam.h
    zg = (h / cam.s_v[r0:]).astype(np.float32)[:, None]  # depth of the ground seen by each row
    mc = zg * (cam.dx32 / np.float32(RES))[None, :] + np.float32((cam.x - g.x0) / RES - 0.5)  # raster column
    mr = zg * (cam.dy32 / np.float32(RES))[None, :] + np.float32((cam.y - g.y0) / RES - 0.5)  # raster row
    fp = zg[:, 0] / math.sqrt(cam.fx * cam.fy) * np.sqrt(np.maximum(zg[:, 0] / h, 1.0))  # metres per pixel
    lod = np.clip(np.log2(np.maximum(fp / RES, 1e-6)), 0, MIP_LEVELS - 1).astype(np.float32)
    alb = np.zeros(mc.shape + (3,), np.float32)
    border = tuple(int(v) for v in OUTSIDE_RGB)
    for L in range(MIP_LEVELS):
        w = np.clip(1.0 - np.abs(lod - L), 0, 1)
        rows = np.nonzero(w > 0)[0]
        if len(rows) == 0:
            continue
        a, b = rows[0], rows[-1] + 1
        s = 2.0**L
        smp = cv2.remap(
            g.mips[L],
            (mc[a:b] + 0.5) / s - 0.5,
            (mr[a:b] + 0.5) / s - 0.5,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=border,
        )
        alb[a:b] += smp.astype(np.float32) * (w[a:b] / 255.0)[:, None, None]
    outside_light = lt.ambient + lt.sun * max(0.0, math.sin(lt.sun_elevation))
    shade = cv2.remap(
        campus.ground_light(lt),
        (mc + 0.5) / 2 - 0.5,
        (mr + 0.5) / 2 - 0.5,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=outside_light,
    )
    labels = cv2.remap(
        g.labels, np.rint(mc), np.rint(mr), cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    near = np.nonzero(fp < DETAIL_FADE[1])[0]  # fine grain where a pixel is smaller than a raster cell
    if len(near):
        a = near[0]
        fade = np.clip((DETAIL_FADE[1] - fp[a:]) / (DETAIL_FADE[1] - DETAIL_FADE[0]), 0, 1).astype(np.float32)
        k = np.float32(RES / DETAIL_RES)
        grain = cv2.remap(
            g.detail,
            (mc[a:] + np.float32(0.5 + g.x0 / RES)) * k,
            (mr[a:] + np.float32(0.5 + g.y0 / RES)) * k,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP,
        )
        shade[a:] *= 1.0 + grain * g.detail_amount[labels[a:]] * fade[:, None]
    alb *= shade[..., None]
    alb *= tint
    return alb, labels


def _sky(campus: Campus, lt: Lighting, elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """Sky colour ``(..., 3)`` float32 in [0, 1] for directions (radians), from the lighting's sky panorama."""
    pano = campus.sky_panorama(lt)
    mx = (np.mod(azimuth, 2 * math.pi) * (pano.shape[1] / (2 * math.pi)) - 0.5).astype(np.float32)
    my = np.clip(elevation * (pano.shape[0] / (math.pi / 2)) - 0.5, 0, pano.shape[0] - 1).astype(np.float32)
    if np.ndim(mx) == 1:
        out = remap_points(pano, mx, my, cv2.BORDER_WRAP)
    else:
        out = cv2.remap(pano, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.astype(np.float32) * np.float32(1 / 255)


def _reflection(campus: Campus, cam: LevelCamera, lt: Lighting, ys, xs, nx, ny) -> np.ndarray:
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
    below = (
        np.where((el < 0)[:, None], np.array([0.30, 0.34, 0.26], np.float32), np.array([0.42, 0.40, 0.38], np.float32))
        * fac
    )
    return np.where((el > line)[:, None], sky, below)

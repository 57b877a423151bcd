"""The colour of the campus ground: albedo, patterns and road markings, and the shadows of the static scene per
lighting."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

from vlocnetpp_core.synth import textures as tx
from vlocnetpp_core.synth.ground import RES
from vlocnetpp_core.synth.layout import BACKGROUND, DEPTH_M, GRASS, ROAD, SIDEWALK, WIDTH_M
from vlocnetpp_core.synth.lighting import Lighting
from vlocnetpp_core.synth.prims import BOX, ELLIPSOID

if TYPE_CHECKING:
    from vlocnetpp_core.synth.campus import Campus


class GroundColour:
    """Part of :class:`~vlocnetpp_core.synth.campus.Campus`, which supplies the ground map (``ground``), the layout
    (roads, routes, plaza, parking) and the static geometry (``prims``) whose shadows fall on the ground."""

    def _paint_ground_albedo(self, rng: np.random.Generator) -> None:
        g = self.ground
        base = {
            BACKGROUND: (0x8A865E, 0.10, 0.16),
            ROAD: (0x5A5C5E, 0.10, 0.06),
            SIDEWALK: (0xA9A49A, 0.06, 0.05),
            GRASS: (0x5E8C3A, 0.16, 0.10),
        }
        X0, X1, Y0, Y1, Ym = self.X0, self.X1, self.Y0, self.Y1, self.Ym
        dash = []
        for route in (self.circuits["south"], self.circuits["north"]):
            dash.append(route.points)
        manholes = [(float(rng.uniform(X0, X1)), Y0 + rng.uniform(-1.5, 1.5)) for _ in range(3)]
        manholes += [(X0 + rng.uniform(-1.5, 1.5), float(rng.uniform(Y0, Y1))) for _ in range(3)]
        manholes += [(float(rng.uniform(X0, X1)), Ym + rng.uniform(-1.5, 1.5)) for _ in range(3)]
        patches = [
            (
                float(rng.uniform(X0 - 2, X1 + 2)),
                float(rng.uniform(Y0 - 2, Y1 + 2)),
                float(rng.uniform(1, 4)),
                float(rng.uniform(1, 3)),
            )
            for _ in range(25)
        ]

        def patterns(albedo: np.ndarray) -> None:
            L = g.labels
            x, y = g.world_grid()
            f = np.ones(L.shape, np.float32)  # brightness factor of the patterns below
            side = L == SIDEWALK
            f[side & ((np.mod(x, 0.6) < 0.04) | (np.mod(y, 0.6) < 0.04))] = 0.82  # tile joints
            f[(L == GRASS) & (np.mod(x + 0.3 * y, 3.0) < 1.5)] = 1.06  # mowing stripes
            outside = L == BACKGROUND
            quad = (x > WIDTH_M / 2) ^ (y > DEPTH_M / 2)
            f[outside & quad & (np.mod(x * 0.8 + y * 0.6, 1.6) < 0.5)] = 0.88  # crop rows
            f[outside & ~quad & (np.mod(y, 2.2) < 0.6)] = 1.07
            patch = np.zeros_like(L)
            for xx, yy, w, h in patches:
                g.rect(patch, xx, yy, float(rng.uniform(0, math.pi)), w, h, 1)
            f[(patch > 0) & (L == ROAD)] = 0.8  # asphalt repairs
            albedo *= f[..., None]
            px0, py0, px1, py1 = self.plaza
            r0, r1 = (int(v) for v in np.clip(np.round(g.to_raster(0, np.array([py0, py1]))[1]), 0, g.rows))
            c0, c1 = (int(v) for v in np.clip(np.round(g.to_raster(np.array([px0, px1]), 0)[0]), 0, g.cols))
            xs, ys = x[:, c0:c1], y[r0:r1]
            big = ((np.mod(xs - px0, 2.4) < 1.2) ^ (np.mod(ys - py0, 2.4) < 1.2)) & side[r0:r1, c0:c1]
            albedo[r0:r1, c0:c1][big] *= np.array([1.08, 1.0, 0.9], np.float32)  # plaza slabs
            curb = cv2.dilate(side.astype(np.uint8), np.ones((3, 3), np.uint8)) & (L == ROAD)
            albedo[curb > 0] = (0.72, 0.71, 0.68)
            canvas = albedo
            white = (0.86, 0.86, 0.84)
            yellow = (0.85, 0.72, 0.25)
            for pts in dash:  # dashed centre lines: 3 m dash, 3 m gap
                seg = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
                phase = np.floor(np.concatenate([[0], np.cumsum(seg)])[:-1] / 3.0).astype(int)
                for k in np.unique(phase[phase % 2 == 0]):
                    g.polyline(canvas, pts[phase == k], 0.14, yellow)
            for route in (self.car_routes[0],):
                for d in (-2.75, 2.75):
                    g.polyline(canvas, route.offset(d).points, 0.12, white, closed=True)
            g.polyline(canvas, [(X0 + 2.75, Ym - 2.75), (X1 - 2.75, Ym - 2.75)], 0.12, white)
            g.polyline(canvas, [(X0 + 2.75, Ym + 2.75), (X1 - 2.75, Ym + 2.75)], 0.12, white)
            # zebra crossings next to the junctions and entrances
            for x0, y0, ax in (
                (X0 + 9, Ym, "x"),
                (X1 - 9, Ym, "x"),
                (X0, Ym + 9, "y"),
                (X1, Ym - 9, "y"),
                (self.Xs + 8, Y0, "x"),
                (X1, self.Ye + 8, "y"),
            ):
                for k in np.arange(-2.5, 2.6, 1.0):
                    if ax == "x":
                        g.rect(canvas, x0, y0 + k, 0.0, 3.0, 0.5, white)
                    else:
                        g.rect(canvas, x0 + k, y0, 0.0, 0.5, 3.0, white)
            # parking bays
            pk = self.parking_box
            for yy in np.arange(pk[1] + 0.25, pk[3], 2.7):
                g.polyline(canvas, [(pk[0] + 2.2, yy), (pk[0] + 6.8, yy)], 0.1, white)
            for mx, my in manholes:
                g.circle(canvas, mx, my, 0.38, (0.22, 0.22, 0.23))
                g.circle(canvas, mx, my, 0.3, (0.32, 0.31, 0.3))
            # turn arrows on the cross street
            for x0, sgn in ((X0 + 16, 1), (X1 - 16, -1)):
                yy = Ym - 1.5 * sgn
                g.rect(canvas, x0, yy, 0.0, 3.0, 0.18, white)
                g.polygon(
                    canvas, [(x0 + 1.5 * sgn, yy - 0.45), (x0 + 2.3 * sgn, yy), (x0 + 1.5 * sgn, yy + 0.45)], white
                )

        g.paint_albedo(rng, base, patterns)
        g.detail = 0.6 * tx.tileable_noise(rng, 256, 1.2) + 0.8 * tx.tileable_noise(rng, 256, 4.0)
        for lab, amount in ((ROAD, 0.10), (SIDEWALK, 0.07), (GRASS, 0.22), (BACKGROUND, 0.18)):
            g.detail_amount[lab] = amount

    def ground_light(self, lighting: Lighting) -> np.ndarray:
        """Irradiance factor of the ground ``(rows/2, cols/2)`` float32 with the shadows of the static scene."""
        return self._cached("ground", lighting, lambda: _ground_light(self, lighting))


def _ground_light(campus: Campus, lighting: Lighting) -> np.ndarray:
    g = campus.ground
    shape = (g.rows // 2, g.cols // 2)
    shadow = np.zeros(shape, np.uint8)
    e = max(lighting.sun_elevation, math.radians(3.0))
    k = 1.0 / math.tan(e)
    sd = lighting.sun_direction()
    away = -np.array([sd[0], sd[1]]) / max(math.hypot(sd[0], sd[1]), 1e-9)
    P = campus.prims

    def to_px(xy: np.ndarray) -> np.ndarray:
        c, r = g.to_raster(xy[:, 0], xy[:, 1])
        return np.round(np.stack([(c + 0.5) / 2 - 0.5, (r + 0.5) / 2 - 0.5], -1) * 16).astype(np.int32)

    for i in range(len(P)):
        kind = P.kind[i]
        ctr = np.array([P.cx[i], P.cy[i]])
        if kind == ELLIPSOID:
            zc = (P.z0[i] + P.z1[i]) / 2
            bv = (P.z1[i] - P.z0[i]) / 2
            c = ctr + away * zc * k
            along = math.hypot(P.a[i], bv * k)
            ang = math.degrees(math.atan2(away[1], away[0]))
            cc = to_px(c[None])[0]
            cv2.ellipse(
                shadow,
                (int(cc[0]), int(cc[1])),
                (int(along / (2 * RES) * 16), int(P.a[i] / (2 * RES) * 16)),
                ang,
                0,
                360,
                1,
                -1,
                cv2.LINE_8,
                4,
            )
            continue
        if kind == BOX:
            ca, sa = P.cos[i], P.sin[i]
            ex, ey = np.array([ca, sa]) * P.a[i], np.array([-sa, ca]) * P.b[i]
            foot = np.array([ctr - ex - ey, ctr + ex - ey, ctr + ex + ey, ctr - ex + ey])
        else:
            ang = np.arange(8) * math.pi / 4
            foot = ctr + P.a[i] * np.stack([np.cos(ang), np.sin(ang)], 1) / math.cos(math.pi / 8)
        pts = np.vstack([foot + away * P.z0[i] * k, foot + away * P.z1[i] * k])
        cv2.fillConvexPoly(shadow, cv2.convexHull(to_px(pts).astype(np.int32)), 1, cv2.LINE_8, 4)
    soft = cv2.GaussianBlur(shadow.astype(np.float32), (5, 5), 1.2)
    direct = lighting.sun * max(0.0, math.sin(lighting.sun_elevation))
    return (lighting.ambient + direct * (1.0 - soft)).astype(np.float32)

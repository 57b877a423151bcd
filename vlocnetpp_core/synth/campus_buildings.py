"""Buildings and unique landmarks of the campus: rows of facades, the hall, tower and glass pavilion, the fountain,
kiosk, sculpture, billboard and bus shelter."""

from __future__ import annotations

import math

import numpy as np

from vlocnetpp_core.synth import facades, object_strips
from vlocnetpp_core.synth.layout import BUILDING, DEPTH_M, OTHER, POLE, WIDTH_M

STYLES = {
    "dorm": facades.FacadeStyle(
        wall=0xC9B99A, window=0x2E3A44, frame=0xF2EFE6, floor_height=3.0, window_width=1.2, window_height=1.4, pitch=2.7
    ),
    "brick": facades.FacadeStyle(
        wall=0x94472F, frame=0xE8E4DA, floor_height=3.6, window_width=1.5, window_height=1.9, pitch=3.3, band=0xB8A58C
    ),
    "concrete": facades.FacadeStyle(
        wall=0xA6A6A0, frame=0x5A5F63, floor_height=3.5, window_height=1.3, pitch=3.6, ribbon=True, window_refl=0.5
    ),
    "white": facades.FacadeStyle(
        wall=0xE4E2DA, frame=0x8A8F94, floor_height=3.3, window_height=1.5, pitch=3.0, ribbon=True, band=0x8A8F94
    ),
    "dark": facades.FacadeStyle(
        wall=0x4B4F54,
        frame=0xC9CCCF,
        floor_height=3.4,
        window_width=1.8,
        pitch=3.2,
        ground_floor="shop",
        window_refl=0.45,
    ),
    "yellow": facades.FacadeStyle(
        wall=0xD6B14E, frame=0xFFFFFF, floor_height=3.2, window_width=1.3, window_height=1.6, pitch=2.9
    ),
    "terracotta": facades.FacadeStyle(
        wall=0xB9603A, frame=0xF0E6D8, floor_height=3.2, window_width=1.0, window_height=1.8, pitch=2.2, band=0xE8D8C0
    ),
    "glass": facades.FacadeStyle(
        wall=0x6F7B80, window=0x35505E, frame=0xA8B0B4, floor_height=3.8, pitch=2.4, curtain=True
    ),
}


class Buildings:
    """Part of :class:`~vlocnetpp_core.synth.campus.Campus`, which supplies the builders (``_b``, ``_atlas``,
    ``_cap``), the free-space checks (``_free``, ``_free_along``, ``_occupy``) and the layout (roads, plaza,
    parking); fills ``buildings`` (footprints) and ``landmarks`` (name, x, y)."""

    # ================================================================= buildings
    def _building(self, rng, x, y, yaw, length, width, height, style: str, mural: int | None = None) -> None:
        strip = self._atlas.add(facades.building_strip(rng, length, width, height, STYLES[style], mural))
        self._b.box(x, y, yaw, length, width, 0.0, height, BUILDING, strip, self._cap(STYLES[style].wall))
        c, s = math.cos(yaw), math.sin(yaw)
        ex, ey = np.array([c, s]) * length / 2, np.array([-s, c]) * width / 2
        ctr = np.array([x, y])
        self.buildings.append(np.array([ctr - ex - ey, ctr + ex - ey, ctr + ex + ey, ctr - ex + ey]))
        self._occupy(x, y, yaw, length + 1.0, width + 1.0)

    def _row_of_buildings(
        self, rng, axis: str, lo: float, hi: float, c0: float, c1: float, styles: list[str], heights, skip=()
    ) -> None:
        """Buildings along ``axis`` ('x' or 'y') between ``lo`` and ``hi``, across-axis extent ``[c0, c1]``."""
        s = lo + rng.uniform(0, 2)
        k = 0
        while s + 12 <= hi:
            length = float(rng.uniform(16, 28))
            end = min(s + length, hi)
            blocked = [b for b in skip if b[0] < end and b[1] > s]
            if blocked:
                s = max(b[1] for b in blocked) + 1.0
                continue
            if end - s < 12:
                break
            depth = (c1 - c0) - rng.uniform(0, 2.0)
            mid_c = (c0 + c1) / 2
            h = float(rng.uniform(*heights))
            style = styles[k % len(styles)]
            mural = 1 if (k == 1 and style != "dorm") else None
            ctr = (s + end) / 2
            if axis == "y":
                self._building(rng, mid_c, ctr, math.pi / 2, end - s, depth, h, style, mural)
            else:
                self._building(rng, ctr, mid_c, 0.0, end - s, depth, h, style, mural)
            k += 1
            s = end + rng.uniform(5, 11)

    def _place_buildings(self, rng: np.random.Generator) -> None:
        X0, X1, Y0, Y1, Ym = self.X0, self.X1, self.Y0, self.Y1, self.Ym
        others = ["brick", "concrete", "white", "dark", "yellow"]
        rng.shuffle(others)
        # west: a row of identical dormitories (perceptual aliasing)
        self._row_of_buildings(rng, "y", 3, DEPTH_M - 3, 3, X0 - 9, ["dorm"], (9, 12))
        pk = self.parking_box
        self._row_of_buildings(
            rng,
            "y",
            3,
            DEPTH_M - 3,
            X1 + 9,
            WIDTH_M - 3,
            [others[0], others[1]],
            (8, 16),
            skip=[(pk[1] - 2, pk[3] + 2), (self.Ye - 9, self.Ye + 9)],
        )
        self._row_of_buildings(
            rng, "x", X0 - 5, X1 + 5, 3, Y0 - 9, [others[2], others[3]], (7, 14), skip=[(self.Xs - 10, self.Xs + 10)]
        )
        self._row_of_buildings(rng, "x", X0 - 5, X1 + 5, Y1 + 9, DEPTH_M - 3, [others[4], others[0]], (8, 15))
        # south block: the hall next to the plaza, with a mural
        px1 = self.plaza[2]
        hx0, hx1 = px1 + 2.5, X1 - 9.5
        hy0, hy1 = Y0 + 9.5, Ym - 9.5
        self._building(
            rng,
            (hx0 + hx1) / 2,
            (hy0 + hy1) / 2,
            0.0,
            hx1 - hx0,
            hy1 - hy0,
            float(rng.uniform(11, 14)),
            "concrete",
            mural=3,
        )
        self.landmarks.append(("hall", (hx0 + hx1) / 2, (hy0 + hy1) / 2))
        # north block: a tower and a glass pavilion
        tx_ = float(rng.uniform(X0 + 15, X0 + 20))
        ty_ = float(rng.uniform(Ym + 14, Y1 - 14))
        self._building(rng, tx_, ty_, 0.0, 10.0, 10.0, float(rng.uniform(28, 34)), "terracotta")
        self.landmarks.append(("tower", tx_, ty_))
        gx = float(rng.uniform(X1 - 18, X1 - 15))
        gy = float(rng.uniform(Ym + 13, Y1 - 13))
        self._building(
            rng, gx, gy, math.radians(float(rng.uniform(-12, 12))), 13.0, 8.5, float(rng.uniform(6.5, 8.5)), "glass"
        )
        self.landmarks.append(("glass pavilion", gx, gy))

    # ================================================================= unique landmarks
    def _place_landmarks(self, rng: np.random.Generator) -> None:
        """One-of-a-kind objects that make places recognisable (placed before trees and furniture)."""
        X0, X1, Y1, Ym = self.X0, self.X1, self.Y1, self.Ym
        b = self._b
        thin_strip = self._atlas.add(object_strips.metal_strip(rng, 0.08, 3.0, 0x8C9196))
        grey = self._cap(0x4A4F55)
        # plaza: fountain and kiosk
        px0, py0, px1, py1 = self.plaza
        cx, cy = (px0 + px1) / 2, (py0 + py1) / 2
        stone = self._atlas.add(object_strips.metal_strip(rng, 2.4, 0.6, 0xB5AFA3))
        if self._free(cx, cy, 2.4):
            b.cylinder(cx, cy, 2.4, 0.0, 0.55, OTHER, stone, self._cap(0x4F86A6))
            self._occupy(cx, cy, 0.0, 5.0, 5.0)
            self.landmarks.append(("fountain", cx, cy))
        kx, ky = px0 + 2.5, py1 - 3.0
        if self._free(kx, ky, 1.8):
            kiosk = self._atlas.add(
                object_strips.panel_strip(rng, 3.0, 2.2, 2.6, [0xE74C3C, 0xF9E79F, 0xE74C3C, 0xFFFFFF])
            )
            b.box(kx, ky, 0.0, 3.0, 2.2, 0.0, 2.6, OTHER, kiosk, self._cap(0x922B21))
            self._occupy(kx, ky, 0.0, 3.2, 2.4)
            self.landmarks.append(("kiosk", kx, ky))
        # sculpture on the north lawn
        for _ in range(40):
            sx, sy = float(rng.uniform(X0 + 10, X1 - 10)), float(rng.uniform(Ym + 9, Y1 - 9))
            if self._free(sx, sy, 2.0):
                red = self._atlas.add(object_strips.panel_strip(rng, 0.9, 0.9, 5.0, [0xC0392B, 0xE74C3C]))
                yel = self._atlas.add(object_strips.metal_strip(rng, 0.6, 3.4, 0xF4D03F))
                b.box(sx, sy, math.radians(30), 0.9, 0.9, 0.0, 5.0, OTHER, red, self._cap(0xC0392B))
                b.cylinder(sx + 1.4, sy + 0.4, 0.6, 0.0, 3.4, OTHER, yel, self._cap(0xF4D03F))
                self._occupy(sx, sy, 0.0, 4.0, 3.0)
                self.landmarks.append(("sculpture", sx, sy))
                break
        # billboard near the east entrance and a bus shelter near the south entrance
        bx_, by_ = X1 + 11.0, self.Ye + 7.4
        if self._free_along(np.array([bx_, by_]), np.array([1.0, 0.0]), 5.2):
            colors = [
                int(c)
                for c in rng.choice([0x1ABC9C, 0xE67E22, 0x9B59B6, 0x2C3E50, 0xF1C40F, 0xE74C3C], 4, replace=False)
            ]
            board = self._atlas.add(object_strips.panel_strip(rng, 5.0, 0.15, 2.5, colors))
            b.box(bx_, by_, 0.0, 5.0, 0.15, 2.4, 4.9, OTHER, board, self._cap(0x2C3E50))
            for sgn in (1, -1):
                b.cylinder(bx_ + sgn * 2.0, by_, 0.07, 0.0, 2.45, POLE, thin_strip, grey)
            self._occupy(bx_, by_, 0.0, 5.2, 0.6)
            self.landmarks.append(("billboard", bx_, by_))
        sx, sy = self.Xs + 12.0, self.Y0 - 6.9
        if self._free(sx, sy, 0.9, margin=0.1) and self._free_along(np.array([sx, sy]), np.array([1.0, 0.0]), 3.9):
            glass = self._atlas.add(object_strips.glass_strip(3.6, 0.05, 2.2))
            side = self._atlas.add(object_strips.glass_strip(1.4, 0.05, 2.2))
            roof = self._atlas.add(object_strips.panel_strip(rng, 3.9, 1.7, 0.12, [0xBFC5C9]))
            b.box(sx, sy - 0.6, 0.0, 3.6, 0.05, 0.1, 2.3, OTHER, glass, self._cap(0x9AA3A8))
            for sgn in (1, -1):
                b.box(sx + sgn * 1.8, sy + 0.05, math.pi / 2, 1.3, 0.05, 0.1, 2.3, OTHER, side, self._cap(0x9AA3A8))
            b.box(sx, sy, 0.0, 3.9, 1.7, 2.3, 2.42, OTHER, roof, self._cap(0xBFC5C9))
            self._occupy(sx, sy, 0.0, 4.0, 1.8)
            self.landmarks.append(("bus shelter", sx, sy))

"""Street furniture of the campus: lamps, signs, benches and bins, fences, bollards and bike racks."""

from __future__ import annotations

import math

import numpy as np

from vlocnetpp_core.synth import object_strips
from vlocnetpp_core.synth import textures as tx
from vlocnetpp_core.synth.layout import DEPTH_M, OTHER, POLE, WIDTH_M


class StreetFurniture:
    """Part of :class:`~vlocnetpp_core.synth.campus.Campus`, which supplies the builders (``_b``, ``_atlas``,
    ``_cap``), the free-space checks (``_free``, ``_free_along``, ``_occupy``) and the layout (roads, plaza,
    parking, buildings)."""

    def _place_furniture(self, rng: np.random.Generator) -> None:
        """Street furniture: lamps, signs, benches and bins, fences, bollards and bike racks. The order of the
        calls (and of their texture draws from ``rng``) defines the scene: keep it."""
        X0, X1, Y0, Y1, Ym = self.X0, self.X1, self.Y0, self.Y1, self.Ym
        strips = {
            "pole": self._atlas.add(object_strips.metal_strip(rng, 0.09, 6.0, 0x4A4F55)),
            "thin": self._atlas.add(object_strips.metal_strip(rng, 0.08, 3.0, 0x8C9196, bands=False)),
            "bollard": self._atlas.add(object_strips.metal_strip(rng, 0.1, 1.0, 0x3C3F44, bands=True)),
            "grey": self._cap(0x4A4F55),
            "head": self._atlas.add(object_strips.panel_strip(rng, 0.8, 0.3, 0.2, [0x3A3F45])),
        }
        sides = [
            ((X0, Y0), (X1, Y0)),
            ((X1, Y0), (X1, Y1)),
            ((X1, Y1), (X0, Y1)),
            ((X0, Y1), (X0, Y0)),
            ((X0, Ym), (X1, Ym)),
        ]
        self._place_lamps(sides, strips)
        self._place_signs(rng, strips)
        self._place_benches(rng, sides)
        self._place_fences(rng)
        self._place_bollards_and_racks(strips)

    def _place_lamps(self, sides: list, strips: dict) -> None:
        """Street lamps every 20 m along the roads, alternating sides (repetitive on purpose)."""
        b = self._b
        for i, ((ax, ay), (bx, by)) in enumerate(sides):
            d = np.array([bx - ax, by - ay])
            n_len = float(np.linalg.norm(d))
            d /= n_len
            nrm = np.array([-d[1], d[0]])
            for k, s in enumerate(np.arange(10.0 + 3 * i, n_len - 9.0, 20.0)):
                side = 1 if (k + i) % 2 == 0 else -1
                p = np.array([ax, ay]) + d * s + nrm * 6.4 * side
                if not self._free(float(p[0]), float(p[1]), 0.1, margin=0.3):
                    continue
                b.cylinder(float(p[0]), float(p[1]), 0.09, 0.0, 5.6, POLE, strips["pole"], strips["grey"])
                h = p - nrm * 0.45 * side
                b.box(
                    float(h[0]),
                    float(h[1]),
                    math.atan2(nrm[1], nrm[0]),
                    0.8,
                    0.3,
                    5.45,
                    5.65,
                    POLE,
                    strips["head"],
                    strips["grey"],
                )
                self._occupy(float(p[0]), float(p[1]), 0.0, 0.5, 0.5)

    def _place_signs(self, rng: np.random.Generator, strips: dict) -> None:
        """Traffic signs (pole + panel) at the junctions and entrances."""
        X0, X1, Y0, Y1, Ym = self.X0, self.X1, self.Y0, self.Y1, self.Ym
        sign_colors = [
            [0x1F5FAF, 0xFFFFFF],
            [0xC0392B, 0xFFFFFF, 0xC0392B],
            [0xF1C40F, 0x1C1C1C],
            [0xFFFFFF, 0x1F5FAF, 0xFFFFFF],
        ]
        sign_strips = [self._atlas.add(object_strips.panel_strip(rng, 0.75, 0.06, 0.75, c)) for c in sign_colors]
        spots = [
            (X0, Ym, 1, 1),
            (X1, Ym, -1, -1),
            (self.Xs, Y0, 1, -1),
            (X1, self.Ye, 1, -1),
            (X0, Y0, 1, 1),
            (X1, Y1, -1, -1),
        ]
        for k, (x, y, sx, sy) in enumerate(spots):
            px, py = x + sx * 6.6, y + sy * 6.6
            if not self._free(px, py, 0.1, margin=0.3):
                continue
            self._b.cylinder(px, py, 0.045, 0.0, 2.75, POLE, strips["thin"], strips["grey"])
            yaw = float(rng.uniform(0, math.pi))
            self._b.box(
                px + 0.08 * math.cos(yaw + math.pi / 2),
                py + 0.08 * math.sin(yaw + math.pi / 2),
                yaw,
                0.75,
                0.06,
                1.95,
                2.7,
                OTHER,
                sign_strips[k % len(sign_strips)],
                self._cap(0x9A9A9A),
            )
            self._occupy(px, py, 0.0, 1.0, 1.0)

    def _place_benches(self, rng: np.random.Generator, sides: list) -> None:
        """Benches (seat + back), some with a bin beside them, along the sidewalks."""
        b = self._b
        bench = self._atlas.add(object_strips.panel_strip(rng, 1.8, 0.6, 0.5, [0x8B5A2B, 0x6E4420]))
        back = self._atlas.add(object_strips.panel_strip(rng, 1.8, 0.08, 0.45, [0x8B5A2B, 0x6E4420, 0x8B5A2B]))
        bin_strip = self._atlas.add(object_strips.metal_strip(rng, 0.28, 1.0, 0x2F5D50, bands=True))
        for (ax, ay), (bx, by) in sides:
            d = np.array([bx - ax, by - ay])
            n_len = float(np.linalg.norm(d))
            d /= n_len
            nrm = np.array([-d[1], d[0]])
            for s in np.arange(18.0, n_len - 15, float(rng.uniform(22, 30))):
                side = 1 if rng.random() < 0.5 else -1
                p = np.array([ax, ay]) + d * s + nrm * 6.5 * side
                yaw = math.atan2(d[1], d[0])
                q = p + nrm * 0.4 * side
                if self._free(float(p[0]), float(p[1]), 1.0, margin=0.2):
                    b.box(float(p[0]), float(p[1]), yaw, 1.8, 0.6, 0.0, 0.48, OTHER, bench, self._cap(0x8B5A2B))
                    b.box(float(q[0]), float(q[1]), yaw, 1.8, 0.08, 0.48, 0.95, OTHER, back, self._cap(0x6E4420))
                    self._occupy(float(p[0]), float(p[1]), yaw, 2.0, 1.4)
                    r = p + d * 1.6
                    if self._free(float(r[0]), float(r[1]), 0.3, margin=0.1):
                        b.cylinder(float(r[0]), float(r[1]), 0.28, 0.0, 0.95, OTHER, bin_strip, self._cap(0x1F3D35))
                        self._occupy(float(r[0]), float(r[1]), 0.0, 0.7, 0.7)

    def _place_fences(self, rng: np.random.Generator) -> None:
        """The perimeter fence with gaps for the entrances, and a low railing beside the parking lot."""
        gaps = {"s": (self.Xs - 7, self.Xs + 7), "e": (self.Ye - 7, self.Ye + 7)}

        def fence(x0, y0, x1, y1, h=1.9, color=0x59636B, spacing=2.5, mesh=0.14):
            L = math.hypot(x1 - x0, y1 - y0)
            if L < 1.0:
                return
            strip = self._atlas.add(object_strips.fence_strip(rng, L, 0.06, h, color, spacing, mesh))
            self._b.box(
                (x0 + x1) / 2,
                (y0 + y1) / 2,
                math.atan2(y1 - y0, x1 - x0),
                L,
                0.06,
                0.0,
                h,
                POLE,
                strip,
                self._cap(color),
                cutout=True,
            )

        e = 0.6
        fence(e, e, gaps["s"][0], e)
        fence(gaps["s"][1], e, WIDTH_M - e, e)
        fence(WIDTH_M - e, e, WIDTH_M - e, gaps["e"][0])
        fence(WIDTH_M - e, gaps["e"][1], WIDTH_M - e, DEPTH_M - e)
        fence(WIDTH_M - e, DEPTH_M - e, e, DEPTH_M - e)
        fence(e, DEPTH_M - e, e, e)
        pk = self.parking_box
        fence(pk[2] - 0.3, pk[1] + 0.5, pk[2] - 0.3, pk[3] - 0.5, h=1.2, color=0x8C9196, spacing=2.0, mesh=0.5)

    def _place_bollards_and_racks(self, strips: dict) -> None:
        """Bollards along the plaza and bike racks beside every third building."""
        b = self._b
        px0, py0, px1, py1 = self.plaza
        for y in np.arange(py0 + 1.0, py1 - 0.5, 1.6):
            if self._free(px1 + 0.3, float(y), 0.1, margin=0.1):
                b.cylinder(px1 + 0.3, float(y), 0.1, 0.0, 0.9, POLE, strips["bollard"], strips["grey"])
        rack = tx.Canvas(2 * (4.0 + 0.08), 0.85, 0x9AA0A6)
        rack.rect(0, 0, rack.width_m, 0.85, hole=True)
        for u in np.arange(0.0, rack.width_m, 0.7):
            rack.rect(u, 0, u + 0.06, 0.85, hole=False)
        rack.rect(0, 0, rack.width_m, 0.06, hole=False)
        rack_strip = self._atlas.add(rack)
        for k, fp in enumerate(self.buildings):
            if k % 3 != 1:
                continue
            c = fp.mean(0)
            edge = fp[1] - fp[0]
            yaw = math.atan2(edge[1], edge[0])
            nrm = np.array([-math.sin(yaw), math.cos(yaw)])
            for sgn in (1, -1):
                p = c + nrm * sgn * (np.linalg.norm(fp[3] - fp[0]) / 2 + 1.8)
                if self._free(float(p[0]), float(p[1]), 2.1, margin=0.1):
                    b.box(
                        float(p[0]),
                        float(p[1]),
                        yaw,
                        4.0,
                        0.08,
                        0.0,
                        0.85,
                        OTHER,
                        rack_strip,
                        self._cap(0x9AA0A6),
                        cutout=True,
                    )
                    self._occupy(float(p[0]), float(p[1]), yaw, 4.2, 0.4)
                    break

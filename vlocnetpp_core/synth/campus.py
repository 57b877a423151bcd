"""The procedural campus: ground, buildings, vegetation, street furniture, distant hills, routes.

``Campus(scene)`` is a pure function of the scene name: the same name gives the same campus
(geometry, textures, routes), bit for bit. The campus is about 100 m (x, east) by 120 m
(y, north) like DeepLoc's 110 x 130 m: a ring road with a cross street splits it into a south
and a north block; rows of buildings with repetitive facades line the outside of the ring
(one row of identical dormitories), the blocks hold a large hall with a plaza, a tower, a glass
pavilion and lawns. Repeated trees, lamps and facades make places look alike; a few unique
landmarks (tower, glass pavilion, mural, fountain, sculpture, kiosk, billboard, bus shelter)
and unique ground marks (manholes, patches) keep it learnable. Outside the perimeter fence lie
fields and, 320 m out, a ring of hills (both Background).

Robot routes (``Campus.circuits``) go around the south and the north block along the ring road
and the cross street; cars use the roads, pedestrians the sidewalks.
"""

from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass

import cv2
import numpy as np

from vlocnetpp_core.synth import object_strips
from vlocnetpp_core.synth import textures as tx
from vlocnetpp_core.synth.campus_buildings import Buildings
from vlocnetpp_core.synth.campus_furniture import StreetFurniture
from vlocnetpp_core.synth.campus_ground import GroundColour
from vlocnetpp_core.synth.ground import RES, GroundMap
from vlocnetpp_core.synth.layout import (
    BACKGROUND,
    CAR_PAINTS,
    CAR_SIZE,
    DEPTH_M,
    DYNAMIC,
    GRASS,
    HILLS_MAX_M,
    PERSON_SIZE,
    ROAD,
    ROAD_HALF,
    SHIRTS,
    SIDEWALK,
    SIDEWALK_EDGE,
    VEGETATION,
    WIDTH_M,
)
from vlocnetpp_core.synth.lighting import Lighting, sky_color
from vlocnetpp_core.synth.prims import Prims, PrimsBuilder
from vlocnetpp_core.synth.route import rounded_rectangle


@functools.lru_cache(maxsize=2)
def load_campus(scene: str) -> Campus:
    """A shared :class:`Campus` per scene name (building one takes about a second)."""
    return Campus(scene)


def stable_seed(*parts) -> int:
    """A seed from strings/ints that does not depend on Python's hash randomisation."""
    return int.from_bytes(hashlib.sha256(repr(parts).encode()).digest()[:8], "little")


@dataclass(frozen=True)
class DynamicObject:
    """A car or a pedestrian at one instant: appearance index, centre (metres) and yaw (radians)."""

    kind: str  # "car" | "person"
    appearance: int
    x: float
    y: float
    yaw: float


class Campus(Buildings, StreetFurniture, GroundColour):
    """Everything static about one scene. Build once, render many frames from it.

    Attributes: ``prims`` (static geometry), ``ground`` (:class:`GroundMap`), ``atlas``
    (RGBA mip levels) and ``cutout`` (hole mask), ``circuits`` (robot routes, counter-clockwise
    centrelines), ``car_routes`` / ``walk_routes`` (for moving objects), ``parking`` (slots:
    ``(x, y, yaw)``), ``hills`` (height per azimuth bin), ``buildings`` (footprints for the map).
    """

    def __init__(self, scene: str = "campus"):
        if not scene or not isinstance(scene, str):
            raise ValueError("scene must be a non-empty string")
        self.scene = scene
        rng = np.random.default_rng(stable_seed("campus", scene))
        self._b = PrimsBuilder()
        self._atlas = tx.AtlasBuilder()
        self._caps: dict[int, tuple[float, float]] = {}
        self.buildings: list[np.ndarray] = []
        self.landmarks: list[tuple[str, float, float]] = []
        self._layout_roads(rng)
        self._paint_ground_labels(rng)
        self._compute_clearance()
        self._place_buildings(rng)
        self._place_landmarks(rng)
        self._place_vegetation(rng)
        self._place_furniture(rng)
        self._make_dynamic_appearances(rng)
        self._paint_ground_albedo(rng)
        self._make_far_field(rng)
        self.prims: Prims = self._b.build()
        self.atlas, self.cutout = self._atlas.build()
        del self._b, self._atlas, self.clearance, self._occupied

    # ================================================================= roads
    def _layout_roads(self, rng: np.random.Generator) -> None:
        j = lambda lo, hi: float(rng.uniform(lo, hi))  # noqa: E731
        self.X0, self.X1 = 22 + j(-2, 2), 78 + j(-2, 2)
        self.Y0, self.Y1 = 20 + j(-1.5, 1.5), 100 + j(-1.5, 1.5)
        self.Ym = 60 + j(-5, 5)
        self.Xs = j(self.X0 + 15, self.X1 - 15)  # south entrance
        self.Ye = j(self.Ym + 13, self.Y1 - 13)  # east entrance
        self.corner = 8.0
        X0, X1, Y0, Y1, Ym, r = self.X0, self.X1, self.Y0, self.Y1, self.Ym, self.corner
        ring = rounded_rectangle("ring", X0, Y0, X1, Y1, r)
        self.circuits = {
            "south": rounded_rectangle("south", X0, Y0, X1, Ym, r),
            "north": rounded_rectangle("north", X0, Ym, X1, Y1, r),
        }
        self.car_routes = [ring, self.circuits["south"], self.circuits["north"]]
        self.road_lines = [
            ring.points,
            np.array([[X0, Ym], [X1, Ym]]),
            np.array([[self.Xs, -80.0], [self.Xs, Y0]]),
            np.array([[X1, self.Ye], [180.0, self.Ye]]),
        ]
        self.walk_routes = [c.offset(d) for c in self.car_routes for d in (-4.25, 4.25)]

    def _paint_ground_labels(self, rng: np.random.Generator) -> None:
        g = self.ground = GroundMap(-45.0, -45.0, WIDTH_M + 90.0, DEPTH_M + 90.0, BACKGROUND)
        L = g.labels
        g.polygon(L, [(0, 0), (WIDTH_M, 0), (WIDTH_M, DEPTH_M), (0, DEPTH_M)], GRASS)
        for pts in self.road_lines + [c.points for c in self.circuits.values()]:  # circuits round the corners
            g.polyline(L, pts, 2 * SIDEWALK_EDGE, SIDEWALK, closed=len(pts) > 2)
        # plaza in the south block in front of the hall, path across the north lawn
        X0, X1, Ym = self.X0, self.X1, self.Ym
        self.plaza = (X0 + 6, self.Y0 + 6, X0 + 6 + rng.uniform(14, 18), Ym - 6)
        px0, py0, px1, py1 = self.plaza
        g.polygon(L, [(px0, py0), (px1, py0), (px1, py1), (px0, py1)], SIDEWALK)
        xp = float(rng.uniform(X0 + 14, X1 - 14))
        g.polyline(L, [(xp, Ym + 5), (xp, self.Y1 - 5)], 2.6, SIDEWALK)
        g.polyline(L, [(X1 - 5, self.Ye - 4), (xp, self.Ye - 4)], 2.6, SIDEWALK)
        # parking lot in the east band
        self.parking_y = float(rng.uniform(self.Y0 + 4, self.Ym - 30))
        pk = (X1 + 8.0, self.parking_y, min(WIDTH_M - 2.0, X1 + 17.5), self.parking_y + 26.0)
        self.parking_box = pk
        g.polygon(L, [(pk[0], pk[1]), (pk[2], pk[1]), (pk[2], pk[3]), (pk[0], pk[3])], ROAD)
        g.polyline(L, [(X1, pk[1] + 13), (pk[0] + 1, pk[1] + 13)], 6.0, ROAD)
        for pts in self.road_lines:
            g.polyline(L, pts, 2 * ROAD_HALF, ROAD, closed=len(pts) > 2)
        slots = []
        for y in np.arange(pk[1] + 1.6, pk[3] - 1.2, 2.7):
            if abs(y - (pk[1] + 13)) > 3.5:
                slots.append((pk[0] + 4.5, float(y), 0.0))
        self.parking = slots

    def _compute_clearance(self) -> None:
        """Distance (metres) from every ground cell to the nearest place the robot may drive."""
        g = self.ground
        corridor = np.zeros_like(g.labels)
        for c in self.car_routes:  # the robot circuits and the whole ring (pedestrians use its sidewalks)
            g.polyline(corridor, c.points, 2 * (SIDEWALK_EDGE - 0.2), 1, closed=True)
        self.clearance = cv2.distanceTransform((corridor == 0).astype(np.uint8), cv2.DIST_L2, 5) * RES
        self._occupied = np.zeros_like(g.labels)

    def label_at(self, x: float, y: float) -> int:
        """Ground class id at world ``(x, y)``."""
        c, r = self.ground.to_raster(x, y)
        ci, ri = int(round(float(c))), int(round(float(r)))
        if 0 <= ri < self.ground.rows and 0 <= ci < self.ground.cols:
            return int(self.ground.labels[ri, ci])
        return BACKGROUND

    def _free(self, x: float, y: float, radius: float, margin: float = 0.4) -> bool:
        c, r = self.ground.to_raster(x, y)
        ci, ri = int(round(float(c))), int(round(float(r)))
        if not (0 <= ri < self.clearance.shape[0] and 0 <= ci < self.clearance.shape[1]):
            return True
        if self.clearance[ri, ci] < radius + margin:
            return False
        rr = int(math.ceil((radius + margin) / RES))
        return not self._occupied[max(0, ri - rr) : ri + rr + 1, max(0, ci - rr) : ci + rr + 1].any()

    def _occupy(self, x: float, y: float, yaw: float, length: float, width: float) -> None:
        self.ground.rect(self._occupied, x, y, yaw, length, width, 1)

    def _cap(self, color: int) -> tuple[float, float]:
        if color not in self._caps:
            self._caps[color] = self._atlas.swatch(color)
        return self._caps[color]

    # ================================================================= vegetation
    def _place_vegetation(self, rng: np.random.Generator) -> None:
        greens = [0x3E6B2A, 0x4C7A30, 0x35602A, 0x5A8236]
        self._foliage = []
        for gcol in greens:
            for a, b in ((2.2, 2.6), (3.0, 3.4)):
                self._foliage.append((a, b, self._atlas.add(object_strips.foliage_strip(rng, a, 2 * b, gcol))))
        self._bark = self._atlas.add(object_strips.bark_strip(rng, 0.25, 9.0))
        hedge_strip = self._atlas.add(object_strips.foliage_strip(rng, 6.0, 1.3, 0x3B5E27))
        hedge_cap = self._cap(0x46692E)

        def tree(x, y, big: bool, shade: int | None = None) -> bool:
            a = float(rng.uniform(2.6, 3.2) if big else rng.uniform(1.8, 2.3))
            if not self._free(x, y, 0.3) or not self._free(x, y, 0.3 + 0.3 * a, margin=-0.2 * a):
                return False
            b = a * float(rng.uniform(1.05, 1.3))
            bottom = float(rng.uniform(2.4, 3.0))
            fi = (int(rng.integers(4)) if shade is None else shade) * 2 + (1 if big else 0)
            fa, fb, strip = self._foliage[fi]
            self._b.cylinder(
                x, y, float(rng.uniform(0.14, 0.22)), 0.0, bottom + b * 0.6, VEGETATION, self._bark, self._cap(0x5B4636)
            )
            self._b.ellipsoid(x, y, bottom + b, a, b, VEGETATION, strip)
            self._occupy(x, y, 0.0, 0.8, 0.8)
            return True

        # alleys along the ring and the cross street: same species, same spacing
        X0, X1, Y0, Y1, Ym = self.X0, self.X1, self.Y0, self.Y1, self.Ym
        sides = [
            ((X0, Y0), (X1, Y0)),
            ((X1, Y0), (X1, Y1)),
            ((X1, Y1), (X0, Y1)),
            ((X0, Y1), (X0, Y0)),
            ((X0, Ym), (X1, Ym)),
        ]
        for (ax, ay), (bx, by) in sides:
            d = np.array([bx - ax, by - ay])
            n_len = float(np.linalg.norm(d))
            d /= n_len
            nrm = np.array([-d[1], d[0]])
            shade = int(rng.integers(4))
            for off in (7.6, -7.6):
                for s in np.arange(12.0, n_len - 11.0, 10.0):
                    if rng.random() < 0.15:
                        continue
                    p = np.array([ax, ay]) + d * (s + rng.uniform(-0.7, 0.7)) + nrm * off
                    tree(float(p[0]), float(p[1]), big=False, shade=shade)
        # groups on the lawns and around the campus
        for _ in range(70):
            x, y = float(rng.uniform(2, WIDTH_M - 2)), float(rng.uniform(2, DEPTH_M - 2))
            if self.label_at(x, y) == GRASS:
                tree(x, y, big=bool(rng.random() < 0.6))
        # hedges along the inner lawns
        for (ax, ay), (bx, by) in sides:
            d = np.array([bx - ax, by - ay])
            n_len = float(np.linalg.norm(d))
            d /= n_len
            nrm = np.array([-d[1], d[0]])  # left of travel: the inner side for the counter-clockwise ring
            s = 14.0
            while s < n_len - 14:
                seg = float(rng.uniform(5, 12))
                if rng.random() < 0.5:
                    c = np.array([ax, ay]) + d * (s + seg / 2) + nrm * 6.6
                    yaw = math.atan2(d[1], d[0])
                    if self._free(float(c[0]), float(c[1]), 0.1, margin=0.3) and self._free_along(c, d, seg):
                        self._b.box(
                            float(c[0]),
                            float(c[1]),
                            yaw,
                            seg,
                            0.9,
                            0.0,
                            float(rng.uniform(0.9, 1.3)),
                            VEGETATION,
                            hedge_strip,
                            hedge_cap,
                        )
                        self._occupy(float(c[0]), float(c[1]), yaw, seg, 0.9)
                s += seg + float(rng.uniform(3, 9))

    def _free_along(self, c: np.ndarray, d: np.ndarray, length: float) -> bool:
        return all(
            self._free(float(p[0]), float(p[1]), 0.45, margin=0.2)
            for p in (c + d * f * length / 2 for f in (-1, -0.5, 0.5, 1))
        )

    # ================================================================= moving things
    def _make_dynamic_appearances(self, rng: np.random.Generator) -> None:
        L, W, H = CAR_SIZE
        self.car_strips = [self._atlas.add(object_strips.car_strip(rng, L, W, H, p)) for p in CAR_PAINTS]
        self.car_caps = [self._cap(p) for p in CAR_PAINTS]
        pl, pw, ph = PERSON_SIZE
        self.person_strips = [
            self._atlas.add(
                object_strips.person_strip(
                    rng, pl, pw, ph, s, int(rng.choice([0x1B2631, 0x34495E, 0x5D4037, 0x283747]))
                )
            )
            for s in SHIRTS
        ]
        self.person_cap = self._cap(0x3A2A1E)

    def dynamic_prims(self, objects) -> Prims:
        """Primitives of cars and pedestrians (label Dynamic) at their current positions."""
        b = PrimsBuilder()
        for o in objects:
            if o.kind == "car":
                i = o.appearance % len(self.car_strips)
                b.box(
                    o.x,
                    o.y,
                    o.yaw,
                    CAR_SIZE[0],
                    CAR_SIZE[1],
                    0.0,
                    CAR_SIZE[2],
                    DYNAMIC,
                    self.car_strips[i],
                    self.car_caps[i],
                )
            elif o.kind == "person":
                i = o.appearance % len(self.person_strips)
                b.box(
                    o.x,
                    o.y,
                    o.yaw,
                    PERSON_SIZE[0],
                    PERSON_SIZE[1],
                    0.0,
                    PERSON_SIZE[2],
                    DYNAMIC,
                    self.person_strips[i],
                    self.person_cap,
                )
            else:
                raise ValueError(f"unknown dynamic object kind {o.kind!r} (car, person)")
        return b.build()

    # ================================================================= sky, hills
    def _make_far_field(self, rng: np.random.Generator) -> None:
        n = 720
        theta = np.arange(n) * 2 * math.pi / n
        h = np.zeros(n)
        for k in range(1, 12):
            h += rng.normal() / k**1.2 * np.sin(k * theta + rng.uniform(0, 2 * math.pi))
        h = (h - h.min()) / max(np.ptp(h), 1e-9)
        self.hills = (8.0 + (HILLS_MAX_M - 8.0) * h).astype(np.float32)
        self.hills_rgb = tx.hills_texture(rng, 2048, 64)
        self.clouds = tx.sky_clouds(rng, 2048, 256)
        sk = np.zeros(n)
        for k in range(2, 14):
            sk += rng.normal() / k * np.sin(k * theta + rng.uniform(0, 2 * math.pi))
        self.skyline = (0.12 + 0.1 * (sk - sk.min()) / max(np.ptp(sk), 1e-9)).astype(np.float32)
        self.center = np.array([WIDTH_M / 2, DEPTH_M / 2])

    # ================================================================= lighting
    def sky_panorama(self, lighting: Lighting) -> np.ndarray:
        """Sky colour ``(256, 2048, 3)`` uint8 RGB over elevation (rows, 0 to 90 deg) and azimuth (columns, 0 to 360
        deg)."""

        def make():
            rows, cols = self.clouds.shape
            el = ((np.arange(rows) + 0.5) * (math.pi / 2 / rows)).astype(np.float32)[:, None]
            az = ((np.arange(cols) + 0.5) * (2 * math.pi / cols)).astype(np.float32)[None, :]
            sky = sky_color(lighting, el + 0 * az, az + 0 * el, self.clouds)
            return np.clip(sky * 255.0 + 0.5, 0, 255).astype(np.uint8)

        return self._cached("sky", lighting, make)

    def _cached(self, what: str, lighting: Lighting, make):
        cache = self.__dict__.setdefault("_light_cache", {})
        key = (what, lighting)
        if key not in cache:
            if len(cache) >= 4:
                cache.pop(next(iter(cache)))
            cache[key] = make()
        return cache[key]

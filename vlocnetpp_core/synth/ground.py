"""The ground of the campus: a class-id raster and a colour raster over the plane z = 0.

Raster cell ``(row, col)`` has its centre at world ``x = x0 + (col + 0.5) * RES``,
``y = y0 + (row + 0.5) * RES`` (rows go north). Outside the raster the ground is Background
(fields around the campus). Drawing helpers take world coordinates in metres.
"""

from __future__ import annotations

import cv2
import numpy as np

from vlocnetpp_core.synth.textures import rgb, smooth_noise

RES = 0.1  # metres per cell
SHIFT = 4  # sub-pixel bits for cv2 drawing
MIP_LEVELS = 4
DETAIL_RES = 0.02  # metres per texel of the fine grain added to the ground near the camera
DETAIL_FADE = (0.025, 0.08)  # pixel footprints (m) where the grain is full / gone
OUTSIDE_RGB = (0x8A, 0x86, 0x5E)  # colour of the fields beyond the raster


class GroundMap:
    """Class ids and albedo of the ground, plus world <-> raster conversions."""

    def __init__(self, x0: float, y0: float, width_m: float, height_m: float, fill_label: int):
        self.x0, self.y0 = x0, y0
        self.cols, self.rows = int(round(width_m / RES)), int(round(height_m / RES))
        self.labels = np.full((self.rows, self.cols), fill_label, np.uint8)
        self.albedo: np.ndarray | None = None  # (rows, cols, 3) uint8 RGB, set by the campus
        self.mips: list[np.ndarray] = []
        self.detail: np.ndarray | None = None  # (N, N) float32 tileable grain, unit std
        self.detail_amount = np.zeros(256, np.float32)  # grain strength per class id

    # ----------------------------------------------------------------- coordinates
    def to_raster(self, x, y):
        """World metres -> raster coordinates (column, row), pixel centres at integers."""
        return (np.asarray(x) - self.x0) / RES - 0.5, (np.asarray(y) - self.y0) / RES - 0.5

    def _pts(self, pts) -> np.ndarray:
        p = np.asarray(pts, np.float64).reshape(-1, 2)
        c, r = self.to_raster(p[:, 0], p[:, 1])
        return np.round(np.stack([c, r], -1) * (1 << SHIFT)).astype(np.int32)

    # ----------------------------------------------------------------- drawing
    def polygon(self, img: np.ndarray, pts, value) -> None:
        cv2.fillPoly(img, [self._pts(pts)], value, lineType=cv2.LINE_8, shift=SHIFT)

    def polyline(self, img: np.ndarray, pts, width_m: float, value, closed: bool = False) -> None:
        """A thick line of ``width_m`` metres along world points (round joints)."""
        p = np.asarray(pts, np.float64).reshape(-1, 2)
        if closed:
            p = np.vstack([p, p[:1]])
        t = max(1, int(round(width_m / RES)))
        cv2.polylines(
            img, [self._pts(p).reshape(-1, 1, 2)], False, value, thickness=t, lineType=cv2.LINE_8, shift=SHIFT
        )

    def circle(self, img: np.ndarray, x: float, y: float, radius_m: float, value) -> None:
        c = self._pts([[x, y]])[0]
        cv2.circle(img, (int(c[0]), int(c[1])), int(round(radius_m / RES * (1 << SHIFT))), value, -1, cv2.LINE_8, SHIFT)

    def rect(self, img: np.ndarray, cx: float, cy: float, yaw: float, length: float, width: float, value) -> None:
        c, s = np.cos(yaw), np.sin(yaw)
        ex, ey = np.array([c, s]) * length / 2, np.array([-s, c]) * width / 2
        ctr = np.array([cx, cy])
        self.polygon(img, [ctr - ex - ey, ctr + ex - ey, ctr + ex + ey, ctr - ex + ey], value)

    # ----------------------------------------------------------------- colour
    def world_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """World x ``(1, cols)`` and y ``(rows, 1)`` of the cell centres."""
        x = (self.x0 + (np.arange(self.cols) + 0.5) * RES).astype(np.float32)[None, :]
        y = (self.y0 + (np.arange(self.rows) + 0.5) * RES).astype(np.float32)[:, None]
        return x, y

    def paint_albedo(self, rng: np.random.Generator, base: dict[int, tuple[int, float, float]], patterns) -> None:
        """Albedo from class ids: ``base[label] = (colour, fine grain, blotches)``; ``patterns(albedo)`` adds
        markings."""
        lut = np.zeros((256, 3), np.float32)
        fine = np.zeros(256, np.float32)
        coarse = np.zeros(256, np.float32)
        for lab, (color, f, c) in base.items():
            lut[lab], fine[lab], coarse[lab] = rgb(color), f, c
        n1 = smooth_noise(rng, self.rows, self.cols, 2.5)
        n2 = smooth_noise(rng, self.rows, self.cols, 25)
        n3 = smooth_noise(rng, self.rows, self.cols, 90)
        L = self.labels
        shade = 1.0 + fine[L] * n1 + coarse[L] * (0.7 * n2 + 0.5 * n3)
        albedo = lut[L] * shade[..., None]
        patterns(albedo)
        self.albedo = np.clip(albedo * 255 + 0.5, 0, 255).astype(np.uint8)
        self.mips = [self.albedo]
        for _ in range(1, MIP_LEVELS):
            prev = self.mips[-1]
            self.mips.append(cv2.resize(prev, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA))

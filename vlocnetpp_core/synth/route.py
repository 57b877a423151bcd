"""Closed routes on the ground plane (road centrelines, driving lanes), parameterised by arc length."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Route:
    """A closed polyline ``points (M, 2)`` (metres, world x/y), densely sampled, not repeating its start."""

    name: str
    points: np.ndarray

    @functools.cached_property
    def arclength(self) -> np.ndarray:
        """Cumulative length ``(M + 1,)`` at each vertex, closing back to the start."""
        seg = np.linalg.norm(np.diff(np.vstack([self.points, self.points[:1]]), axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(seg)])

    @property
    def length(self) -> float:
        return float(self.arclength[-1])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``(..., 2)`` and unit tangents ``(..., 2)`` at arc lengths ``s`` (wrapping around)."""
        cum = self.arclength
        pts = np.vstack([self.points, self.points[:1]])
        s = np.mod(np.asarray(s, np.float64), cum[-1])
        i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(cum) - 2)
        seg = pts[i + 1] - pts[i]
        seg_len = np.maximum(cum[i + 1] - cum[i], 1e-12)
        f = ((s - cum[i]) / seg_len)[..., None]
        return pts[i] + f * seg, seg / seg_len[..., None]

    def heading(self, s: np.ndarray) -> np.ndarray:
        """Direction of travel (radians, world frame) at ``s``, smoothed over the vertex spacing."""
        _, t = self.at(s)
        return np.arctan2(t[..., 1], t[..., 0])

    def offset(self, d: float, name: str | None = None) -> Route:
        """The route moved ``d`` metres to the right of the direction of travel."""
        nxt = np.roll(self.points, -1, axis=0)
        prv = np.roll(self.points, 1, axis=0)
        t = nxt - prv
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        right = np.stack([t[:, 1], -t[:, 0]], 1)
        return Route(name or self.name, self.points + d * right)

    def reversed(self) -> Route:
        return Route(self.name, self.points[::-1].copy())


def rounded_rectangle(name: str, x0: float, y0: float, x1: float, y1: float, r: float, step: float = 0.1) -> Route:
    """Counter-clockwise rounded rectangle starting at ``(x0 + r, y0)`` heading east."""
    pieces = []

    def line(ax, ay, bx, by):
        n = max(1, int(math.ceil(math.hypot(bx - ax, by - ay) / step)))
        f = np.arange(n) / n
        pieces.append(np.stack([ax + (bx - ax) * f, ay + (by - ay) * f], 1))

    def arc(cx, cy, a0):
        n = max(2, int(math.ceil(r * math.pi / 2 / step)))
        a = a0 + (math.pi / 2) * np.arange(n) / n
        pieces.append(np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], 1))

    line(x0 + r, y0, x1 - r, y0)
    arc(x1 - r, y0 + r, -math.pi / 2)
    line(x1, y0 + r, x1, y1 - r)
    arc(x1 - r, y1 - r, 0.0)
    line(x1 - r, y1, x0 + r, y1)
    arc(x0 + r, y1 - r, math.pi / 2)
    line(x0, y1 - r, x0, y0 + r)
    arc(x0 + r, y0 + r, math.pi)
    return Route(name, np.vstack(pieces))

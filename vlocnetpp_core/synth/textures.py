"""Procedural textures of the synthetic campus and the atlas that holds them.

Every textured surface owns (or shares) a *strip* in one RGBA atlas, painted in metres at
``PPM`` texels per metre: ``u`` runs along the surface (around a box's perimeter, around a
cylinder), ``v`` runs down from the top of the surface. Channel 3 is the reflectivity
(0 = matte, 255 = mirror-like glass). A separate cut-out mask (fences, racks) marks texels
that are holes. The atlas is kept at ``LEVELS`` resolutions (box-filtered) for distant surfaces.

The painted strips themselves: :mod:`.facades` (buildings) and :mod:`.object_strips` (trees, poles,
fences, signs, shelters, cars, people).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

PPM = 16.0  # texels per metre at level 0
LEVELS = 3
ATLAS_WIDTH = 4096
GUTTER = 2 ** (LEVELS + 1)  # replicated border around each strip so mip levels do not bleed


def smooth_noise(rng: np.random.Generator, height: int, width: int, cell: float) -> np.ndarray:
    """``(height, width)`` float32 noise with unit standard deviation and feature size ``cell`` pixels."""
    cell = max(float(cell), 1.0)
    gh, gw = int(math.ceil(height / cell)) + 3, int(math.ceil(width / cell)) + 3
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    up = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
    off = int(cell)
    out = up[off : off + height, off : off + width]
    return out / max(float(out.std()), 1e-6)


def periodic_noise(rng: np.random.Generator, height: int, width: int, cell: float) -> np.ndarray:
    """Like :func:`smooth_noise` but seamless between the last and the first column (azimuth wraps)."""
    pad = max(int(2 * cell), 2)
    n = smooth_noise(rng, height, width + pad, cell)
    out = n[:, :width].copy()
    r = np.linspace(0, 1, pad, endpoint=False, dtype=np.float32)
    out[:, :pad] = r * n[:, :pad] + (1 - r) * n[:, width : width + pad]
    return out


def tileable_noise(rng: np.random.Generator, n: int, cell: float) -> np.ndarray:
    """``(n, n)`` float32 noise, unit standard deviation, seamless when tiled, features of ``cell`` texels."""
    spec = np.fft.rfft2(rng.standard_normal((n, n)))
    k = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.rfftfreq(n)[None, :])
    out = np.fft.irfft2(spec * np.exp(-((k * cell) ** 2)), s=(n, n))
    return (out / max(float(out.std()), 1e-9)).astype(np.float32)


def rgb(hex_or_tuple) -> np.ndarray:
    """Colour as float32 RGB in [0, 1] from ``0xRRGGBB`` or a 0..255 tuple."""
    if isinstance(hex_or_tuple, int):
        v = hex_or_tuple
        return np.array([(v >> 16) & 255, (v >> 8) & 255, v & 255], np.float32) / 255.0
    return np.asarray(hex_or_tuple, np.float32) / 255.0


class Canvas:
    """A strip being painted: float RGB, reflectivity and cut-out, addressed in metres (v down)."""

    def __init__(self, width_m: float, height_m: float, base, refl: float = 0.0):
        self.w = max(1, int(math.ceil(width_m * PPM)))
        self.h = max(1, int(math.ceil(height_m * PPM)))
        self.width_m, self.height_m = width_m, height_m
        self.rgb = np.empty((self.h, self.w, 3), np.float32)
        self.rgb[:] = rgb(base) if not isinstance(base, np.ndarray) else base
        self.refl = np.full((self.h, self.w), refl, np.float32)
        self.hole = np.zeros((self.h, self.w), bool)

    def _span(self, a: float, b: float, n: int) -> slice:
        return slice(max(0, int(round(a * PPM))), min(n, max(int(round(b * PPM)), int(round(a * PPM)) + 1)))

    def rect(
        self,
        u0: float,
        v0: float,
        u1: float,
        v1: float,
        color=None,
        refl: float | None = None,
        hole: bool | None = None,
    ):
        """Paint the rectangle ``[u0, u1] x [v0, v1]`` (metres from the strip's left and top edges)."""
        if u1 <= u0 or v1 <= v0:
            return
        rs, cs = self._span(v0, v1, self.h), self._span(u0, u1, self.w)
        if color is not None:
            self.rgb[rs, cs] = rgb(color) if not isinstance(color, np.ndarray) else color
        if refl is not None:
            self.refl[rs, cs] = refl
        if hole is not None:
            self.hole[rs, cs] = hole

    def shade_noise(self, rng: np.random.Generator, amount: float, cell_m: float) -> None:
        """Multiply the colour by ``1 + amount * noise`` (dirt, weathering, leaf clusters)."""
        n = smooth_noise(rng, self.h, self.w, cell_m * PPM)
        self.rgb *= (1.0 + amount * n)[..., None]

    def rgba(self) -> np.ndarray:
        out = np.empty((self.h, self.w, 4), np.uint8)
        out[..., :3] = np.clip(self.rgb * 255.0 + 0.5, 0, 255)
        out[..., 3] = np.clip(self.refl * 255.0 + 0.5, 0, 255)
        return out


@dataclass(frozen=True)
class Strip:
    """Where a painted strip lives in the atlas (level-0 texel coordinates of its top-left texel)."""

    x0: float
    y0: float
    width_m: float
    height_m: float


class AtlasBuilder:
    """Shelf-packs canvases into one atlas; ``build()`` returns the mip levels and the cut-out mask."""

    def __init__(self):
        self._items: list[tuple[int, int, Canvas]] = []
        self._x = 0
        self._y = 0
        self._shelf = 0

    def add(self, canvas: Canvas) -> Strip:
        w, h = canvas.w + 2 * GUTTER, canvas.h + 2 * GUTTER
        if w > ATLAS_WIDTH:
            raise ValueError(f"texture strip of {canvas.width_m:.1f} m is wider than the atlas")
        if self._x + w > ATLAS_WIDTH:
            self._x, self._y, self._shelf = 0, self._y + self._shelf, 0
        x, y = self._x, self._y
        self._items.append((x, y, canvas))
        self._x += w
        self._shelf = max(self._shelf, h)
        return Strip(float(x + GUTTER), float(y + GUTTER), canvas.width_m, canvas.height_m)

    def swatch(self, color) -> tuple[float, float]:
        """A small single-colour patch; returns the texel at its centre (used for box tops)."""
        c = Canvas(0.4, 0.4, color)
        s = self.add(c)
        return s.x0 + c.w / 2 - 0.5, s.y0 + c.h / 2 - 0.5

    def build(self) -> tuple[list[np.ndarray], np.ndarray]:
        height = self._y + self._shelf
        height += (-height) % (2**LEVELS)
        atlas = np.zeros((max(height, 2**LEVELS), ATLAS_WIDTH, 4), np.uint8)
        hole = np.zeros(atlas.shape[:2], np.uint8)
        g = GUTTER
        for x, y, c in self._items:
            atlas[y : y + c.h + 2 * g, x : x + c.w + 2 * g] = cv2.copyMakeBorder(
                c.rgba(), g, g, g, g, cv2.BORDER_REPLICATE
            )
            hole[y + g : y + g + c.h, x + g : x + g + c.w] = c.hole
        levels = [atlas]
        for _ in range(1, LEVELS):
            prev = levels[-1]
            levels.append(cv2.resize(prev, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA))
        return levels, hole


def box_faces(length: float, width: float) -> list[tuple[float, float]]:
    """``(u0, face_length)`` of a box's faces in strip order: +x', +y', -x', -y' (see ``Prims``)."""
    lens = [width, length, width, length]
    starts = np.concatenate([[0.0], np.cumsum(lens)[:-1]])
    return [(float(a), float(b)) for a, b in zip(starts, lens, strict=True)]


# --------------------------------------------------------------------------- backgrounds


def hills_texture(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Distant terrain seen at the horizon: ``(height, width, 3)`` uint8 RGB, columns = azimuth."""
    base = rgb(0x55704A) * (1 + 0.12 * periodic_noise(rng, height, width, 6))[..., None]
    base *= (1 + 0.08 * periodic_noise(rng, height, width, 40))[..., None]
    fields = (periodic_noise(rng, height, width, 25) > 0.6)[..., None]
    base = np.where(fields, base * np.array([1.35, 1.2, 0.8], np.float32), base)
    return np.clip(base * 255, 0, 255).astype(np.uint8)


def sky_clouds(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Cloud density ``(height, width)`` float32 in [0, 1] over (elevation rows, azimuth columns)."""
    n = 0.65 * periodic_noise(rng, height, width, 48) + 0.35 * periodic_noise(rng, height, width, 12)
    return np.clip(0.5 + 0.25 * n, 0, 1)

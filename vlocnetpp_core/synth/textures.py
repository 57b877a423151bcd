"""Procedural textures of the synthetic campus and the atlas that holds them.

Every textured surface owns (or shares) a *strip* in one RGBA atlas, painted in metres at
``PPM`` texels per metre: ``u`` runs along the surface (around a box's perimeter, around a
cylinder), ``v`` runs down from the top of the surface. Channel 3 is the reflectivity
(0 = matte, 255 = mirror-like glass). A separate cut-out mask (fences, racks) marks texels
that are holes. The atlas is kept at ``LEVELS`` resolutions (box-filtered) for distant surfaces.
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


# --------------------------------------------------------------------------- facades


@dataclass(frozen=True)
class FacadeStyle:
    """How a building's walls look: colours and the rhythm of its windows (metres)."""

    wall: int
    window: int = 0x2A3440
    frame: int = 0xD8D8D0
    floor_height: float = 3.4
    window_width: float = 1.4
    window_height: float = 1.6
    pitch: float = 3.0  # horizontal window spacing
    sill: float = 0.9
    window_refl: float = 0.35
    band: int | None = None  # horizontal band colour between floors
    ground_floor: str = "doors"  # "doors" | "shop" | "plain"
    curtain: bool = False  # whole facade is glass with mullions
    ribbon: bool = False  # continuous window ribbons instead of single windows
    weathering: float = 0.06


def paint_facade(c: Canvas, rng: np.random.Generator, u0: float, length: float, style: FacadeStyle, main: bool) -> None:
    """Paint one face occupying ``[u0, u0 + length]`` of the strip (the strip spans the wall height)."""
    H = c.height_m
    c.rect(u0, 0, u0 + length, H, style.wall, refl=0.0)
    if style.curtain:
        c.rect(u0 + 0.3, 0.8, u0 + length - 0.3, H - 0.2, style.window, refl=0.75)
        step = style.pitch / 2
        for k in range(1, int(length / step)):
            c.rect(u0 + k * step - 0.06, 0.8, u0 + k * step + 0.06, H - 0.2, style.frame, refl=0.0)
        for f in range(1, int(H / style.floor_height) + 1):
            v = H - f * style.floor_height
            if v > 0.8:
                c.rect(u0 + 0.3, v - 0.12, u0 + length - 0.3, v + 0.12, style.frame, refl=0.0)
    else:
        floors = max(1, int((H - 0.6) / style.floor_height))
        n = max(1, int((length - 1.0) / style.pitch))
        margin = (length - n * style.pitch) / 2
        for f in range(floors):
            top = H - (f + 1) * style.floor_height  # v of this floor's ceiling... floors counted from the ground
            v_floor = H - f * style.floor_height  # v of this floor's floor level
            if f == 0 and style.ground_floor != "plain":
                if style.ground_floor == "shop":
                    c.rect(u0 + 0.4, v_floor - 2.6, u0 + length - 0.4, v_floor - 0.3, style.window, refl=0.55)
                    for k in range(n + 1):
                        x = u0 + margin + k * style.pitch
                        c.rect(x - 0.1, v_floor - 2.6, x + 0.1, v_floor - 0.3, style.frame, refl=0.0)
                else:
                    doors = [n // 2] if not main else [n // 2, max(0, n // 2 - 3)]
                    for k in range(n):
                        x = u0 + margin + (k + 0.5) * style.pitch
                        if k in doors:
                            c.rect(x - 0.9, v_floor - 2.4, x + 0.9, v_floor, 0x4A3B2C, refl=0.1)
                            c.rect(x - 0.75, v_floor - 2.25, x + 0.75, v_floor, 0x6E8A9A, refl=0.4)
                        else:
                            _window(c, rng, x, v_floor - style.sill - style.window_height, style)
                if style.band is not None:
                    c.rect(
                        u0,
                        v_floor - style.floor_height - 0.15,
                        u0 + length,
                        v_floor - style.floor_height + 0.15,
                        style.band,
                    )
                continue
            if style.ribbon:
                y0 = v_floor - style.sill - style.window_height
                c.rect(u0 + 0.5, y0, u0 + length - 0.5, y0 + style.window_height, style.window, refl=style.window_refl)
                for k in range(n + 1):
                    x = u0 + margin + k * style.pitch
                    c.rect(x - 0.07, y0, x + 0.07, y0 + style.window_height, style.frame, refl=0.0)
            else:
                for k in range(n):
                    x = u0 + margin + (k + 0.5) * style.pitch
                    _window(c, rng, x, v_floor - style.sill - style.window_height, style)
            if style.band is not None:
                c.rect(u0, top - 0.15, u0 + length, top + 0.15, style.band)
    c.rect(u0, 0, u0 + length, 0.45, _darker(style.wall, 0.8))  # roof parapet


def _darker(color: int, f: float) -> np.ndarray:
    return rgb(color) * f


def _window(c: Canvas, rng: np.random.Generator, x: float, top: float, s: FacadeStyle) -> None:
    w, h = s.window_width, s.window_height
    c.rect(x - w / 2 - 0.08, top - 0.08, x + w / 2 + 0.08, top + h + 0.08, s.frame, refl=0.0)
    c.rect(x - w / 2, top, x + w / 2, top + h, s.window, refl=s.window_refl)
    blind = rng.random()
    if blind < 0.3:  # some blinds half down: per-window variation on a repetitive rhythm
        c.rect(x - w / 2, top, x + w / 2, top + h * rng.uniform(0.2, 0.7), 0xC8C0A8, refl=0.0)
    c.rect(x - w / 2, top + h * 0.48, x + w / 2, top + h * 0.52, s.frame, refl=0.0)


def box_faces(length: float, width: float) -> list[tuple[float, float]]:
    """``(u0, face_length)`` of a box's faces in strip order: +x', +y', -x', -y' (see ``Prims``)."""
    lens = [width, length, width, length]
    starts = np.concatenate([[0.0], np.cumsum(lens)[:-1]])
    return [(float(a), float(b)) for a, b in zip(starts, lens, strict=True)]


def building_strip(
    rng: np.random.Generator, length: float, width: float, height: float, style: FacadeStyle, mural: int | None = None
) -> Canvas:
    """Facade strip of a ``length x width x height`` box building; ``mural`` paints a unique panel on face ``mural``."""
    per = 2 * (length + width)
    c = Canvas(per, height, style.wall)
    faces = box_faces(length, width)
    for i, (u0, flen) in enumerate(faces):
        paint_facade(c, rng, u0, flen, style, main=(i % 2 == 1))
    c.shade_noise(rng, style.weathering, 1.5)
    if mural is not None:
        u0, flen = faces[mural]
        m0 = u0 + flen * rng.uniform(0.15, 0.4)
        mw = min(flen * 0.35, 9.0)
        v1 = height - 0.5
        v0 = max(0.5, v1 - min(height * 0.6, 8.0))
        palette = [0xE63946, 0xF1C40F, 0x2E86DE, 0x27AE60, 0xFF7F11, 0x8E44AD]
        c.rect(m0, v0, m0 + mw, v1, 0xF4F1DE, refl=0.0)
        for _ in range(14):
            a, b = sorted(rng.uniform(m0, m0 + mw, 2))
            p, q = sorted(rng.uniform(v0, v1, 2))
            c.rect(a, p, max(b, a + 0.6), max(q, p + 0.6), palette[int(rng.integers(len(palette)))], refl=0.0)
    return c


# --------------------------------------------------------------------------- small objects


def foliage_strip(rng: np.random.Generator, radius: float, height: float, base: int) -> Canvas:
    """Around-the-crown strip for a tree crown (u = azimuth * radius, v down from the top)."""
    c = Canvas(2 * math.pi * radius, height, base)
    c.shade_noise(rng, 0.28, 0.35)
    c.shade_noise(rng, 0.15, 1.2)
    v = np.linspace(0, 1, c.h, dtype=np.float32)[:, None, None]
    c.rgb *= 1.1 - 0.35 * v  # darker underneath
    return c


def bark_strip(rng: np.random.Generator, radius: float, height: float) -> Canvas:
    c = Canvas(2 * math.pi * radius, height, 0x5B4636)
    c.shade_noise(rng, 0.25, 0.15)
    return c


def metal_strip(rng: np.random.Generator, radius: float, height: float, color: int, bands: bool = False) -> Canvas:
    c = Canvas(max(2 * math.pi * radius, 0.3), height, color)
    c.shade_noise(rng, 0.05, 0.3)
    if bands:
        for v in np.arange(0.3, height, 0.6):
            c.rect(0, v, c.width_m, v + 0.15, 0xF0F0F0)
    return c


def fence_strip(
    rng: np.random.Generator, length: float, width: float, height: float, color: int, post_spacing: float, mesh: float
) -> Canvas:
    """A see-through fence (posts, rails and a vertical-bar mesh) around a thin box."""
    per = 2 * (length + width)
    c = Canvas(per, height, color)
    c.rect(0, 0, per, height, hole=True)
    for u0, flen in box_faces(length, width):
        if flen < 0.3:
            c.rect(u0, 0, u0 + flen, height, hole=False)
            continue
        for x in np.arange(0.0, flen + 1e-6, post_spacing):
            c.rect(u0 + x - 0.05, 0, u0 + x + 0.05, height, hole=False)
        for v in (0.08, height - 0.12, height * 0.5):
            c.rect(u0, v - 0.05, u0 + flen, v + 0.05, hole=False)
        for x in np.arange(mesh / 2, flen, mesh):
            c.rect(u0 + x - 0.025, 0.08, u0 + x + 0.025, height - 0.12, hole=False)
    c.shade_noise(rng, 0.08, 0.5)
    return c


def panel_strip(
    rng: np.random.Generator, length: float, width: float, height: float, colors: list[int], refl: float = 0.0
) -> Canvas:
    """A box whose faces carry coloured stripes (signs, kiosks, billboards, benches)."""
    per = 2 * (length + width)
    c = Canvas(per, height, colors[0], refl=refl)
    for u0, flen in box_faces(length, width):
        if flen < 0.3:
            continue
        n = len(colors)
        for i in range(1, n):
            c.rect(
                u0 + 0.05 * flen,
                height * (i / n) - 0.5 * height / n + 0.02 * height,
                u0 + 0.95 * flen,
                height * (i / n) + 0.45 * height / n,
                colors[i],
            )
    c.shade_noise(rng, 0.05, 0.4)
    return c


def glass_strip(length: float, width: float, height: float, frame: int = 0x9AA3A8) -> Canvas:
    """Reflective glass panel with a frame (bus shelters, pavilions)."""
    per = 2 * (length + width)
    c = Canvas(per, height, 0x3E5560, refl=0.8)
    for u0, flen in box_faces(length, width):
        c.rect(u0, 0, u0 + 0.08, height, frame, refl=0.0)
        c.rect(u0 + flen - 0.08, 0, u0 + flen, height, frame, refl=0.0)
    c.rect(0, 0, per, 0.1, frame, refl=0.0)
    c.rect(0, height - 0.1, per, height, frame, refl=0.0)
    return c


def car_strip(rng: np.random.Generator, length: float, width: float, height: float, paint: int) -> Canvas:
    """Car body: paint, a window band, wheels and lights, around a box."""
    per = 2 * (length + width)
    c = Canvas(per, height, paint, refl=0.15)
    for i, (u0, flen) in enumerate(box_faces(length, width)):
        if i % 2 == 1:  # sides
            c.rect(u0 + 0.9, 0.1, u0 + flen - 0.6, 0.6, 0x22282E, refl=0.6)
            for x in (0.9, flen - 0.9):
                c.rect(u0 + x - 0.35, height - 0.65, u0 + x + 0.35, height, 0x151515, refl=0.0)
        else:  # front / back
            c.rect(u0 + 0.15, 0.1, u0 + flen - 0.15, 0.55, 0x22282E, refl=0.6)
            lamp = 0xF8F3D0 if i == 0 else 0xC0302A
            c.rect(u0 + 0.1, 0.75, u0 + 0.45, 0.95, lamp, refl=0.0)
            c.rect(u0 + flen - 0.45, 0.75, u0 + flen - 0.1, 0.95, lamp, refl=0.0)
            c.rect(u0 + 0.2, height - 0.35, u0 + flen - 0.2, height - 0.05, 0x202020, refl=0.0)
    c.shade_noise(rng, 0.04, 0.5)
    return c


def person_strip(
    rng: np.random.Generator, length: float, width: float, height: float, shirt: int, trousers: int
) -> Canvas:
    per = 2 * (length + width)
    c = Canvas(per, height, trousers)
    c.rect(0, 0.0, per, 0.25, 0x3A2A1E)  # hair
    c.rect(0, 0.25, per, 0.32, 0xD9A77E)  # face
    c.rect(0, 0.32, per, 0.9, shirt)
    c.rect(0, height - 0.1, per, height, 0x202020)  # shoes
    c.shade_noise(rng, 0.06, 0.2)
    return c


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

"""Building facades of the synthetic campus: a :class:`FacadeStyle` (colours, window rhythm) painted around a box
building's perimeter into one atlas strip (:func:`building_strip`; metres, ``v`` down from the top of the wall)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlocnetpp_core.synth.textures import Canvas, box_faces, rgb


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

"""Atlas strips of the campus's small objects: tree crowns and bark, poles, fences, signs and panels, glass shelters,
cars and people (metres; ``u`` around the object, ``v`` down from its top)."""

from __future__ import annotations

import math

import numpy as np

from vlocnetpp_core.synth.textures import Canvas, box_faces


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

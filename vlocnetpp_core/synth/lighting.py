"""Lighting of one visit: sun, ambient light, sky colours, clouds, haze and a colour cast.

Colours are float RGB in [0, 1]. A surface of albedo ``A`` with unit normal ``n`` is lit as
``A * tint * (ambient + sun * max(0, n . l) * (1 - shadow))`` where ``l`` points to the sun.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class Lighting:
    name: str
    sun_azimuth: float  # radians, world frame (0 = east, counter-clockwise)
    sun_elevation: float  # radians above the horizon
    sun: float  # direct light
    ambient: float  # sky light
    sky_zenith: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]
    tint: tuple[float, float, float]  # colour cast of the light
    clouds: float  # cloud cover 0..1
    haze_m: float  # distance at which 63% of the colour is haze

    def sun_direction(self) -> np.ndarray:
        """Unit vector from the scene to the sun, world frame."""
        ce = math.cos(self.sun_elevation)
        return np.array(
            [ce * math.cos(self.sun_azimuth), ce * math.sin(self.sun_azimuth), math.sin(self.sun_elevation)]
        )

    def to_dict(self) -> dict:
        d = asdict(self)
        return {
            k: (round(v, 4) if isinstance(v, float) else [round(x, 4) for x in v] if isinstance(v, tuple) else v)
            for k, v in d.items()
        }


# name: (sun elevation deg, sun, ambient, zenith, horizon, tint, clouds, haze)
_PRESETS = {
    "noon": (58.0, 0.75, 0.42, (0.25, 0.47, 0.85), (0.70, 0.80, 0.92), (1.0, 1.0, 0.98), 0.25, 900.0),
    "morning": (20.0, 0.70, 0.38, (0.30, 0.50, 0.82), (0.88, 0.82, 0.74), (1.06, 0.97, 0.86), 0.3, 600.0),
    "evening": (9.0, 0.55, 0.33, (0.22, 0.30, 0.58), (0.95, 0.70, 0.50), (1.12, 0.90, 0.72), 0.35, 500.0),
    "overcast": (40.0, 0.12, 0.78, (0.62, 0.65, 0.70), (0.82, 0.83, 0.85), (0.95, 0.97, 1.0), 0.9, 400.0),
    "hazy": (32.0, 0.45, 0.55, (0.45, 0.58, 0.78), (0.85, 0.86, 0.86), (1.0, 0.99, 0.95), 0.55, 300.0),
}

PRESETS = tuple(sorted(_PRESETS))

DEFAULT_LIGHTING = Lighting(
    "noon",
    math.radians(200.0),
    math.radians(58.0),
    0.75,
    0.42,
    (0.25, 0.47, 0.85),
    (0.70, 0.80, 0.92),
    (1.0, 1.0, 0.98),
    0.25,
    900.0,
)


def sample_lighting(rng: np.random.Generator, preset: str | None = None) -> Lighting:
    """A preset (random unless given) with jittered sun position, intensities and colours."""
    name = preset or str(rng.choice(sorted(_PRESETS)))
    if name not in _PRESETS:
        raise ValueError(f"unknown lighting preset {name!r}; choose one of {', '.join(sorted(_PRESETS))}")
    elev, sun, amb, zen, hor, tint, clouds, haze = _PRESETS[name]
    j = lambda s: float(rng.uniform(1 - s, 1 + s))  # noqa: E731
    tint_j = tuple(float(np.clip(t * j(0.03), 0.6, 1.3)) for t in tint)
    return Lighting(
        name=name,
        sun_azimuth=float(rng.uniform(0, 2 * math.pi)),
        sun_elevation=math.radians(float(np.clip(elev + rng.uniform(-6, 6), 5, 80))),
        sun=sun * j(0.15),
        ambient=amb * j(0.1),
        sky_zenith=tuple(float(v) for v in np.clip(np.array(zen) * j(0.06), 0, 1)),
        sky_horizon=tuple(float(v) for v in np.clip(np.array(hor) * j(0.04), 0, 1)),
        tint=tint_j,
        clouds=float(np.clip(clouds + rng.uniform(-0.15, 0.15), 0, 1)),
        haze_m=haze * j(0.2),
    )


def sky_color(lighting: Lighting, elevation: np.ndarray, azimuth: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    """Sky radiance ``(..., 3)`` for view directions given by elevation / azimuth (radians) and cloud density."""
    zen = np.asarray(lighting.sky_zenith, np.float32)
    hor = np.asarray(lighting.sky_horizon, np.float32)
    t = np.clip(elevation / 0.9, 0, 1) ** 0.55
    col = hor + (zen - hor) * t[..., None]
    sd = lighting.sun_direction()
    ce = np.cos(elevation)
    cosang = ce * np.cos(azimuth) * sd[0] + ce * np.sin(azimuth) * sd[1] + np.sin(elevation) * sd[2]
    glow = (
        np.exp((cosang - 1.0) * 18.0) * (0.45 * lighting.sun) + np.exp((cosang - 1.0) * 900.0) * 1.5 * lighting.sun
    ).astype(np.float32)
    thr = 1.0 - lighting.clouds
    cov = np.clip((cloud - thr * 0.75 - 0.2) * 3.0, 0, 1).astype(np.float32) * min(1.0, lighting.clouds * 2.5)
    cloud_col = np.float32(0.55 + 0.4 * lighting.ambient + 0.3 * lighting.sun) * (
        np.float32(0.85) + np.float32(0.15) * cloud[..., None]
    )
    col = col * (1 - cov[..., None]) + cloud_col * cov[..., None]
    return col + glow[..., None] * (1 - 0.8 * cov[..., None])

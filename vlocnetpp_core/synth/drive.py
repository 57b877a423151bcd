"""One visit (a "loop") of the campus: the driving pattern, camera poses, lighting and moving objects.

A visit drives one lap of a circuit (around the south or the north block, clockwise or
counter-clockwise) in a lane (either road lane or either sidewalk), weaving a little, at a
cruise speed of 1-3 m/s that drops in the turns, with the camera 1.2 m up, a small heading
bias and smooth pitch/roll of a few degrees. Frames are taken at a fixed interval: by default
the ``frames`` of a visit are spread over one lap (about 1 m apart, like the published
DeepLoc images, and never more than ``MAX_SPACING_M``); ``frame_interval=0.05`` gives 20 Hz
video with 5-15 cm between frames instead (then a visit covers only part of a lap).

Everything that differs between visits comes from ``(scene, seed, split, loop)``; the campus
does not depend on the seed.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.synth.campus import Campus, DynamicObject, stable_seed
from vlocnetpp_core.synth.layout import CAR_PAINTS, CAR_SIZE, LANES, SHIRTS
from vlocnetpp_core.synth.lighting import PRESETS, Lighting, sample_lighting
from vlocnetpp_core.synth.render import level_rotation
from vlocnetpp_core.synth.route import Route

CAMERA_HEIGHT = 1.2
MAX_SPACING_M = 1.5  # default frame spacing never exceeds this (the DeepLoc reader splits at 2 m)
MAX_LANE_OFFSET_M = 4.5  # the outer edge of the sidewalks' driving line (metres either side of the centreline)
WANDER_WAVELENGTHS_M = (70.0, 160.0)  # a wandering visit drifts across the road over tens of metres
MIN_SPEED, MAX_SPEED = 1.0, 3.0
LATERAL_ACCEL = 0.6  # m/s^2 in turns
_DS = 0.05  # arc-length step of the dense trajectory
SPLIT_CODES = {"train": 1, "test": 2}
# (circuit, clockwise): the four ways around the campus; train loops cycle through all of them
COMBOS = (("south", False), ("north", True), ("south", True), ("north", False))


@dataclass(frozen=True)
class DrivingPattern:
    circuit: str
    clockwise: bool
    lane: str
    cruise_speed: float  # m/s
    weave_amplitude: float  # m
    weave_length: float  # m
    heading_bias_deg: float
    start_fraction: float  # where on the circuit the visit starts
    lane_wander: float = 0.0  # m: slow drift either side of the lane (0: keeps to the lane)


@dataclass
class Mover:
    """A car or pedestrian moving at constant speed along a closed route (or standing still)."""

    kind: str
    appearance: int
    route: Route | None
    s0: float
    speed: float
    x: float = 0.0  # used when route is None
    y: float = 0.0
    yaw: float = 0.0

    def at(self, t: float) -> DynamicObject:
        if self.route is None:
            return DynamicObject(self.kind, self.appearance, self.x, self.y, self.yaw)
        p, d = self.route.at(self.s0 + self.speed * t)
        return DynamicObject(self.kind, self.appearance, float(p[0]), float(p[1]), math.atan2(d[1], d[0]))

    def positions(self, times: np.ndarray) -> np.ndarray:
        if self.route is None:
            return np.tile([self.x, self.y], (len(times), 1))
        return self.route.at(self.s0 + self.speed * times)[0]


@dataclass
class Visit:
    """Poses (``t (N, 3)``, ``q (N, 4)`` w,x,y,z, camera-to-world), times and what moves."""

    split: str
    loop: int
    pattern: DrivingPattern
    lighting: Lighting
    times: np.ndarray
    t: np.ndarray
    q: np.ndarray
    route_length: float
    frame_interval: float
    movers: list[Mover] = field(default_factory=list)

    def objects_at(self, i: int) -> list[DynamicObject]:
        return [m.at(float(self.times[i])) for m in self.movers]

    def info(self) -> dict:
        step = np.linalg.norm(np.diff(self.t[:, :2], axis=0), axis=1) if len(self.t) > 1 else np.zeros(1)
        return {
            "split": self.split,
            "loop": self.loop,
            "pattern": {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self.pattern).items()},
            "lighting": self.lighting.to_dict(),
            "frames": len(self.t),
            "frame_interval_s": round(self.frame_interval, 5),
            "route_length_m": round(self.route_length, 3),
            "mean_spacing_m": round(float(step.mean()), 4),
            "max_spacing_m": round(float(step.max()), 4),
            "moving_objects": sum(m.route is not None for m in self.movers),
            "static_objects": sum(m.route is None for m in self.movers),
        }


def _smooth_noise_1d(rng: np.random.Generator, x: np.ndarray, scales: tuple[float, ...]) -> np.ndarray:
    """Sum of random sinusoids with wavelengths ``scales`` (same units as ``x``), roughly in [-1, 1]."""
    out = np.zeros_like(x, dtype=np.float64)
    for lam in scales:
        out += np.sin(2 * math.pi * x / (lam * rng.uniform(0.8, 1.25)) + rng.uniform(0, 2 * math.pi))
    return out / len(scales)


def choose_pattern(rng: np.random.Generator, split: str, loop: int, combo_offset: int) -> DrivingPattern:
    """Train loops cycle through the four circuit/direction combinations (and the lighting presets); test loops pick at
    random."""
    if split == "train":
        circuit, cw = COMBOS[(loop + combo_offset) % len(COMBOS)]
    else:
        circuit, cw = COMBOS[int(rng.integers(len(COMBOS)))]
    return DrivingPattern(
        circuit=circuit,
        clockwise=cw,
        lane=str(rng.choice(sorted(LANES))),
        cruise_speed=float(rng.uniform(1.4, 2.7)),
        weave_amplitude=float(rng.uniform(0.0, 0.3)),
        weave_length=float(rng.uniform(15.0, 40.0)),
        heading_bias_deg=float(rng.uniform(-4.0, 4.0)),
        start_fraction=float(rng.uniform(0.0, 1.0)),
    )


def plan_visit(
    campus: Campus,
    seed: int,
    split: str,
    loop: int,
    frames: int,
    frame_interval: float | None = None,
    lane_offset: float | None = None,
    lane_wander: float = 0.0,
    lighting_presets: tuple[str, ...] | None = None,
) -> Visit:
    """The ``loop``-th visit of ``split`` for ``seed``: ``frames`` camera poses plus lighting and movers.

    ``lane_offset`` (metres right of the circuit's centreline) replaces the lane the visit drew, e.g.
    to drive between the lanes that training visits use; everything else about the visit is unchanged.
    ``lane_wander`` (metres) lets the visit drift slowly up to that far either side of its lane (over
    :data:`WANDER_WAVELENGTHS_M`, never beyond :data:`MAX_LANE_OFFSET_M`), so that visits cover the
    road between the lanes; 0 leaves the visit exactly as without it. ``lighting_presets``: the presets that train
    visits cycle through and test visits draw from (repeats weigh a preset more); None: every preset once.
    """
    if split not in SPLIT_CODES:
        raise ValueError(f"split must be train or test, got {split!r}")
    if frames < 1:
        raise ValueError("a visit needs at least one frame")
    base_seed = stable_seed("visits", campus.scene, int(seed))
    offset = int(np.random.default_rng(base_seed).integers(len(COMBOS)))
    rng = np.random.default_rng([base_seed, SPLIT_CODES[split], int(loop)])
    pattern = choose_pattern(rng, split, loop, offset)
    lateral = LANES[pattern.lane] if lane_offset is None else float(lane_offset)
    if lane_offset is not None:
        pattern = replace(pattern, lane=f"offset {lateral:+.2f} m")
    choices = PRESETS if lighting_presets is None else tuple(lighting_presets)
    if split == "train":
        preset = choices[(loop + offset) % len(choices)]
    else:  # the default draws inside sample_lighting: visits rendered before this option stay as they were
        preset = None if lighting_presets is None else str(rng.choice(choices))
    lighting = sample_lighting(rng, preset)
    base = campus.circuits[pattern.circuit]
    if pattern.clockwise:
        base = base.reversed()
    path = base.offset(lateral)
    L = path.length
    s_start = pattern.start_fraction * L
    lap = np.arange(0.0, L + _DS, _DS)
    speed = _speed_profile(rng, path, s_start, lap, pattern)
    t_lap = float(np.sum(_DS / speed[:-1]))
    if frame_interval is None:
        frame_interval = min(t_lap / frames, MAX_SPACING_M / float(speed.max()))
    if frame_interval <= 0:
        raise ValueError("frame_interval must be positive")
    laps = max(1, int(math.ceil((frames - 1) * frame_interval / t_lap + 1e-9)))
    s = np.arange(0.0, laps * L + 2 * _DS, _DS)
    v = np.tile(speed[:-1], laps + 1)[: len(s)]
    tcum = np.concatenate([[0.0], np.cumsum(_DS / v[:-1])])
    times = np.arange(frames) * frame_interval
    s_f = np.interp(times, tcum, s)
    # lateral weave and heading of travel from the dense path
    weave = pattern.weave_amplitude * _smooth_noise_1d(rng, s, (pattern.weave_length, pattern.weave_length * 2.3))
    if lane_wander > 0:  # its own random stream: the rest of the visit stays as without wander
        pattern = replace(pattern, lane_wander=float(lane_wander))
        drift = lane_wander * _smooth_noise_1d(
            np.random.default_rng([base_seed, SPLIT_CODES[split], int(loop), 1]), s, WANDER_WAVELENGTHS_M
        )
        weave = np.clip(lateral + weave + drift, -MAX_LANE_OFFSET_M, MAX_LANE_OFFSET_M) - lateral
    p, tang = path.at(s_start + s)
    right = np.stack([tang[:, 1], -tang[:, 0]], 1)
    xy = p + weave[:, None] * right
    d = np.gradient(xy, axis=0)
    travel = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    x_f = np.interp(s_f, s, xy[:, 0])
    y_f = np.interp(s_f, s, xy[:, 1])
    yaw = (
        np.interp(s_f, s, travel)
        + math.radians(pattern.heading_bias_deg)
        + math.radians(1.5) * _smooth_noise_1d(rng, times, (7.0, 3.1))
    )
    pitch = math.radians(3.0) * _smooth_noise_1d(rng, times, (9.0, 4.0, 1.7))
    roll = math.radians(2.6) * _smooth_noise_1d(rng, times, (11.0, 3.3, 1.3))
    height = CAMERA_HEIGHT + 0.02 * _smooth_noise_1d(rng, times, (2.0, 0.7))
    q = camera_quaternions(yaw, pitch, roll)
    t = np.stack([x_f, y_f, height], 1)
    visit = Visit(split, loop, pattern, lighting, times, t, q, L, float(frame_interval))
    visit.movers = _movers(campus, rng, visit)
    return visit


def _speed_profile(rng, path: Route, s_start: float, lap: np.ndarray, pattern: DrivingPattern) -> np.ndarray:
    """Speed (m/s) at each arc length of one lap: cruise with slow variations, slower in turns."""
    heading = np.unwrap(path.heading(s_start + lap))
    k = np.abs(np.gradient(heading, lap))
    k = np.convolve(k, np.ones(41) / 41, mode="same")  # curvature over ~2 m
    v = pattern.cruise_speed * (1.0 + 0.12 * _smooth_noise_1d(rng, lap, (25.0, 60.0)))
    v = np.minimum(v, np.sqrt(LATERAL_ACCEL / np.maximum(k, 1e-6)))
    v = np.convolve(np.pad(v, 60, mode="edge"), np.ones(121) / 121, mode="valid")  # smooth over ~6 m
    return np.clip(v, MIN_SPEED, MAX_SPEED)


def camera_quaternions(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``(N, 4)`` camera-to-world quaternions of a camera with heading ``yaw`` (world, radians)
    and pitch (about the camera x axis) / roll (about the optical axis) relative to level."""
    R_level = np.stack([level_rotation(float(a)) for a in yaw])
    q_level = geometry.matrix_to_quat(R_level)
    z = np.zeros_like(pitch)
    q_pitch = np.stack([np.cos(pitch / 2), np.sin(pitch / 2), z, z], 1)
    q_roll = np.stack([np.cos(roll / 2), z, z, np.sin(roll / 2)], 1)
    return geometry.quat_normalize(geometry.quat_mul(q_level, geometry.quat_mul(q_pitch, q_roll)))


def _movers(campus: Campus, rng: np.random.Generator, visit: Visit) -> list[Mover]:
    """Cars on the roads, pedestrians on the sidewalks and parked cars, none touching the camera or each other."""
    times, cam = visit.times, visit.t[:, :2]
    candidates: list[Mover] = []
    for _ in range(int(rng.integers(5, 9))):
        route = campus.car_routes[int(rng.integers(len(campus.car_routes)))]
        if rng.random() < 0.5:
            route = route.reversed()
        candidates.append(
            Mover(
                "car",
                int(rng.integers(len(CAR_PAINTS))),
                route.offset(1.5),
                float(rng.uniform(0, route.length)),
                float(rng.uniform(3.0, 6.5)),
            )
        )
    for _ in range(int(rng.integers(9, 15))):
        route = campus.walk_routes[int(rng.integers(len(campus.walk_routes)))]
        if rng.random() < 0.5:
            route = route.reversed()
        candidates.append(
            Mover(
                "person",
                int(rng.integers(len(SHIRTS))),
                route,
                float(rng.uniform(0, route.length)),
                float(rng.uniform(0.8, 1.5)),
            )
        )
    px0, py0, px1, py1 = campus.plaza
    for _ in range(int(rng.integers(2, 5))):
        candidates.append(
            Mover(
                "person",
                int(rng.integers(len(SHIRTS))),
                None,
                0.0,
                0.0,
                float(rng.uniform(px0 + 1, px1 - 1)),
                float(rng.uniform(py0 + 1, py1 - 1)),
                float(rng.uniform(-math.pi, math.pi)),
            )
        )
    occupancy = float(rng.uniform(0.35, 0.9))
    for x, y, yaw in campus.parking:
        if rng.random() < occupancy:
            candidates.append(
                Mover(
                    "car",
                    int(rng.integers(len(CAR_PAINTS))),
                    None,
                    0.0,
                    0.0,
                    x,
                    y,
                    yaw + (math.pi if rng.random() < 0.5 else 0.0),
                )
            )
    kept: list[Mover] = []
    kept_pos: list[np.ndarray] = []
    for m in candidates:
        pos = m.positions(times)
        radius = 0.5 * math.hypot(*CAR_SIZE[:2]) if m.kind == "car" else 0.4
        if np.min(np.linalg.norm(pos - cam, axis=1)) < radius + 1.2:
            continue
        if any(np.min(np.linalg.norm(pos - p, axis=1)) < radius + r + 0.2 for p, r in kept_pos):
            continue
        kept.append(m)
        kept_pos.append((pos, radius))
    return kept

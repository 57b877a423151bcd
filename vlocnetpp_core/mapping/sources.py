"""Where the keyframes of a map come from: the frames of a dataset on disk, or rendered from a synthetic scene.

A keyframe sequence (:class:`DatasetKeyframes`, :class:`SceneKeyframes`) is the keyframes of one sequence of
consecutive frames, in order; ``frames()`` decodes or renders them (:class:`~vlocnetpp_core.data.sample.Frame`,
with pose, intrinsics, depth and labels). Both are picklable, so that :func:`.build.build_map_of` can hand
them to worker processes. The keyframes are chosen by :func:`keyframe_positions` on the poses as the dataset
reader gives them.

:func:`scene_keyframes` renders only the keyframes of the visits ``vlocnetpp synth`` would render with the same
arguments (no dataset on disk): frame ``i`` of a visit depends only on the scene, its pose (as written to
``poses.txt``), the visit's lighting and what moves at its time, so each keyframe has the same pixels, depth and
labels as in the rendered dataset, and the map is the map of that dataset's train split.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.data.sample import DatasetIndex, Frame


def keyframe_positions(t: np.ndarray, q: np.ndarray, spacing_m: float, angle_deg: float) -> list[int]:
    """Positions of the keyframes among the poses ``t (N, 3)``, ``q (N, 4)`` of one sequence: the first frame, then
    every frame at least ``spacing_m`` from the last keyframe or turned by at least ``angle_deg`` from it."""
    q = geometry.quat_normalize(np.asarray(q, np.float64))
    keep = [0]
    for i in range(1, len(t)):
        moved = np.linalg.norm(t[i] - t[keep[-1]]) >= spacing_m
        turned = float(geometry.rotation_error_deg(q[i], q[keep[-1]])) >= angle_deg
        if moved or turned:
            keep.append(i)
    return keep


@dataclass(frozen=True)
class DatasetKeyframes:
    """The keyframes ``ids`` (record numbers) of one sequence of ``index``."""

    index: DatasetIndex
    ids: tuple[int, ...]

    def __len__(self) -> int:
        return len(self.ids)

    def frames(self) -> list[Frame]:
        ix = self.index
        return [ix.load(i, depth=ix.has_depth, labels=ix.has_labels) for i in self.ids]


def dataset_keyframes(indexes, spacing_m: float, angle_deg: float) -> list[DatasetKeyframes]:
    """The keyframe sequences of the ``DatasetIndex``es ``indexes``; ``UserError`` naming a dataset without frames."""
    from vlocnetpp_core.errors import UserError

    out = []
    for index in indexes:
        if len(index) == 0:
            raise UserError(f"{index.root}: split {index.split!r} has no frames to build a map from")
        for rng in (r for r in index.sequences if len(r)):
            t = np.array([index.records[i].t for i in rng], np.float64)
            q = np.array([index.records[i].q for i in rng], np.float64)
            out.append(DatasetKeyframes(index, tuple(rng[p] for p in keyframe_positions(t, q, spacing_m, angle_deg))))
    return out


@dataclass(frozen=True)
class SceneKeyframes:
    """Frames ``ids`` (positions in the visit) of train visit ``loop`` of ``vlocnetpp synth --scene scene --seed seed
    --frames-per-loop frames_per_loop --size WxH --lane-wander lane_wander``, rendered on demand."""

    scene: str
    seed: int
    loop: int
    frames_per_loop: int
    size: tuple[int, int]
    lane_wander: float
    ids: tuple[int, ...]

    def __len__(self) -> int:
        return len(self.ids)

    def frames(self) -> list[Frame]:
        from vlocnetpp_core.synth.render import render_frame
        from vlocnetpp_core.synth.writer import default_intrinsics

        campus = _campus(self.scene)
        visit = _visit(self.scene, self.seed, self.loop, self.frames_per_loop, self.lane_wander)
        K = default_intrinsics(*self.size)
        written = _written_values(visit)
        t, q = _reader_poses(written)
        out = []
        for i in self.ids:  # the renderer is given exactly the pose that is written
            rgb, labels, depth = render_frame(
                campus, written[i, :3].tolist(), written[i, 3:].tolist(), K, visit.lighting, visit.objects_at(i)
            )
            # as the dataset reader gives it
            depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
            out.append(
                Frame(rgb, t[i].copy(), q[i].copy(), depth, labels, K, 0.0, self.loop, f"loop {self.loop} frame {i}")
            )
        return out


def scene_keyframes(
    scene: str,
    seed: int,
    loops: int,
    frames_per_loop: int,
    spacing_m: float,
    angle_deg: float,
    size: tuple[int, int] = (320, 180),
    lane_wander: float = 0.0,
) -> list[SceneKeyframes]:
    """The keyframe sequences of the ``loops`` train visits of a synthetic scene (module docstring), split into
    sequences where the dataset reader would split them."""
    from vlocnetpp_core.data.deeploc import MAX_ID_GAP, MAX_JUMP_DEG, MAX_JUMP_M, split_sequences

    out = []
    for loop in range(loops):
        visit = _visit(scene, seed, loop, frames_per_loop, lane_wander)
        t, q = _reader_poses(_written_values(visit))
        for rng in split_sequences(np.arange(len(t)), t, q, MAX_ID_GAP, MAX_JUMP_M, MAX_JUMP_DEG):
            ids = tuple(
                rng[p]
                for p in keyframe_positions(t[rng.start : rng.stop], q[rng.start : rng.stop], spacing_m, angle_deg)
            )
            out.append(SceneKeyframes(scene, seed, loop, frames_per_loop, tuple(size), float(lane_wander), ids))
    return out


def scene_source(
    scene: str,
    seed: int,
    loops: int,
    frames_per_loop: int,
    size: tuple[int, int] = (320, 180),
    lane_wander: float = 0.0,
) -> str:
    """Where :func:`scene_keyframes` of these arguments come from, in words (a map's ``source``)."""
    wander = f", lane wander {lane_wander:g} m" if lane_wander else ""
    return f"scene {scene} seed {seed}, {loops} train visits of {frames_per_loop} frames at {size[0]}x{size[1]}{wander}"


def _written_values(visit) -> np.ndarray:
    """``(N, 7)``: each frame's ``x y z qw qx qy qz`` as ``poses.txt`` holds them (rounded as written)."""
    from vlocnetpp_core.synth.writer import format_pose

    return np.array(
        [[float(v) for v in format_pose("frame", t, q).split()[1:]] for t, q in zip(visit.t, visit.q, strict=True)]
    )


def _reader_poses(written: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``t (N, 3)``, ``q (N, 4)`` as the dataset reader gives the ``written`` poses: the quaternion normalised (one
    line at a time, as it reads them), ``w >= 0``."""
    q = np.stack([row[3:] / float(np.linalg.norm(row[3:])) for row in written])
    return written[:, :3].copy(), geometry.quat_normalize(q)


@lru_cache(maxsize=2)
def _campus(scene: str):
    from vlocnetpp_core.synth.campus import load_campus

    return load_campus(scene)


@lru_cache(maxsize=8)
def _visit(scene: str, seed: int, loop: int, frames_per_loop: int, lane_wander: float):
    from vlocnetpp_core.synth.drive import plan_visit

    return plan_visit(_campus(scene), seed, "train", loop, frames_per_loop, None, None, lane_wander)

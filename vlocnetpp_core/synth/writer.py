"""Write a synthetic campus dataset in the DeepLoc layout, atomically.

Layout (the contract with ``vlocnetpp_core.data.deeploc``)::

    OUT/DeepLoc/{train,test}/LeftImages/Image_<id>.png        RGB (BGR on disk, as cv2 writes)
    OUT/DeepLoc/{train,test}/labels/Image_<id>.png            uint8 class ids 0..9
    OUT/DeepLoc/{train,test}/labels_colorized/Image_<id>.png  colour preview
    OUT/DeepLoc/{train,test}/poses.txt                        '# comment', header, 'Image_<id>.png x y z qw qx qy qz'
    OUT/DeepLoc_stereo/{train,test}/DepthImages/Image_<id>.pfm  float32 metres, sky = 0
    OUT/intrinsics.json  OUT/scene.json  OUT/preview/{mosaic,map}.png

Loop ``k`` of a split has ids ``k * 10000 + 1, k * 10000 + 2, ...``. Everything is written to a
temporary folder next to ``OUT`` and renamed into place at the end
(:func:`~vlocnetpp_core.outputs.atomic_output_dir`), so an interrupted or failed run leaves no ``OUT``
behind. The same ``(scene, seed, sizes)`` give the same bytes.
"""

from __future__ import annotations

import json
import math
import re
import time
from pathlib import Path

import numpy as np

from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.classes import colorize
from vlocnetpp_core.data.imageio import BackgroundWriter, write_image
from vlocnetpp_core.data.pfm import write_pfm
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.outputs import atomic_output_dir
from vlocnetpp_core.synth.campus import load_campus
from vlocnetpp_core.synth.drive import MAX_LANE_OFFSET_M, plan_visit
from vlocnetpp_core.synth.lighting import PRESETS
from vlocnetpp_core.synth.preview import mosaic, top_down_map
from vlocnetpp_core.synth.render import render_frame

GENERATOR_VERSION = 1
DEFAULT_FRAMES_PER_LOOP = 175
ID_STRIDE = 10000
MOSAIC_ROWS_PER_SPLIT = 4


def default_intrinsics(width: int, height: int) -> Intrinsics:
    """The DeepLoc default camera (ZED, f = 700 px at 1280 wide) scaled to ``width``; square pixels."""
    f = 700.0 * width / 1280.0
    return Intrinsics(f, f, width / 2 - 0.5, height / 2 - 0.5, int(width), int(height))


def format_pose(name: str, t: np.ndarray, q: np.ndarray) -> str:
    return f"{name} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}"


def check_render_args(
    scene: str,
    seed: int,
    train_loops: int,
    test_loops: int,
    frames_per_loop: int,
    size,
    frame_interval,
    lane_wander: float = 0.0,
    lighting_presets: tuple[str, ...] | None = None,
) -> tuple[int, int]:
    """``(width, height)`` of ``size``; :class:`UserError` naming the flag of the first bad argument."""
    if not isinstance(scene, str) or not re.fullmatch(r"[A-Za-z0-9_.-]{1,64}", scene):
        raise UserError(f"--scene must be a name of letters, digits, '_', '.', '-' (at most 64), got {scene!r}")
    if int(seed) < 0:
        raise UserError(f"--seed must be >= 0, got {seed}")
    if train_loops < 0 or test_loops < 0 or train_loops + test_loops == 0:
        raise UserError(f"need at least one loop (--loops {train_loops}, --test-loops {test_loops})")
    if max(train_loops, test_loops) > 99:
        raise UserError("at most 99 loops per split")
    if not 1 <= frames_per_loop < ID_STRIDE:
        raise UserError(f"--frames-per-loop must be between 1 and {ID_STRIDE - 1}, got {frames_per_loop}")
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError) as err:
        raise UserError(f"--size must be WIDTHxHEIGHT, got {size!r}") from err
    if not (16 <= w <= 4096 and 16 <= h <= 4096):
        raise UserError(f"--size must be between 16x16 and 4096x4096, got {w}x{h}")
    if frame_interval is not None and not frame_interval > 0:
        raise UserError(f"--frame-interval must be positive, got {frame_interval}")
    if not (math.isfinite(lane_wander) and 0 <= lane_wander <= MAX_LANE_OFFSET_M):
        raise UserError(f"--lane-wander must be within 0 and {MAX_LANE_OFFSET_M:g} m, got {lane_wander}")
    if lighting_presets is not None:
        unknown = [name for name in lighting_presets if name not in PRESETS]
        if unknown or not lighting_presets:
            raise UserError(
                f"--lighting must name presets among {', '.join(PRESETS)}, got {','.join(lighting_presets) or 'none'}"
            )
    return w, h


def render_dataset(
    out: str | Path,
    scene: str = "campus",
    seed: int = 0,
    train_loops: int = 4,
    test_loops: int = 2,
    frames_per_loop: int = DEFAULT_FRAMES_PER_LOOP,
    size: tuple[int, int] = (320, 180),
    force: bool = False,
    progress: bool = True,
    frame_interval: float | None = None,
    test_lane_offset: float | None = None,
    lane_wander: float = 0.0,
    lighting_presets: tuple[str, ...] | None = None,
) -> dict:
    """Render ``train_loops`` + ``test_loops`` visits of campus ``scene`` into ``out``; returns a summary dict.

    ``frame_interval`` (seconds) fixes the time between frames (``0.05`` = 20 Hz video); by
    default each loop's frames are spread over one lap of its circuit. ``test_lane_offset``
    (metres right of the centreline, at most :data:`MAX_LANE_OFFSET_M` either way) drives the test
    loops there instead of in one of the four lanes. ``lane_wander`` (metres) lets every train loop
    drift slowly up to that far either side of its lane (``plan_visit``); ``lighting_presets`` the lighting presets
    of the visits (``plan_visit``; None: all). Raises :class:`UserError` for bad arguments or
    an existing ``out`` without ``force``.
    """
    w, h = check_render_args(
        scene, seed, train_loops, test_loops, frames_per_loop, size, frame_interval, lane_wander, lighting_presets
    )
    if test_lane_offset is not None and not (
        math.isfinite(test_lane_offset) and abs(test_lane_offset) <= MAX_LANE_OFFSET_M
    ):
        raise UserError(
            f"--test-lane-offset must be within +-{MAX_LANE_OFFSET_M:g} m "
            f"of the centreline (the sidewalks), got {test_lane_offset}"
        )
    out = Path(out)
    with atomic_output_dir(out, force) as tmp:
        summary = _render_into(
            tmp,
            scene,
            int(seed),
            train_loops,
            test_loops,
            frames_per_loop,
            (w, h),
            progress,
            frame_interval,
            test_lane_offset,
            lane_wander,
            lighting_presets,
        )
    summary["out"] = str(out)
    return summary


def _render_into(
    root: Path,
    scene: str,
    seed: int,
    train_loops: int,
    test_loops: int,
    frames: int,
    size: tuple[int, int],
    progress: bool,
    frame_interval: float | None,
    test_lane_offset: float | None = None,
    lane_wander: float = 0.0,
    lighting_presets: tuple[str, ...] | None = None,
) -> dict:
    from tqdm import tqdm

    t_start = time.perf_counter()
    campus = load_campus(scene)
    K = default_intrinsics(*size)
    (root / "intrinsics.json").write_text(json.dumps(K.to_dict(), indent=2) + "\n")
    loops = {"train": train_loops, "test": test_loops}
    total = (train_loops + test_loops) * frames
    render_time = 0.0
    loop_info = []
    samples = []
    trajectories = []
    bar = tqdm(total=total, disable=not progress, unit="frame", desc=f"synth {scene}", dynamic_ncols=True)
    writer = BackgroundWriter(name="synth-writer")
    try:
        for split, n_loops in loops.items():
            if n_loops == 0:
                continue
            img_dir = root / "DeepLoc" / split / "LeftImages"
            lab_dir = root / "DeepLoc" / split / "labels"
            col_dir = root / "DeepLoc" / split / "labels_colorized"
            dep_dir = root / "DeepLoc_stereo" / split / "DepthImages"
            for d in (img_dir, lab_dir, col_dir, dep_dir):
                d.mkdir(parents=True, exist_ok=True)
            lines = [f"# synthetic campus {scene} seed {seed}", "ImageName x y z qw qx qy qz"]
            picks = set(np.linspace(0, n_loops * frames - 1, MOSAIC_ROWS_PER_SPLIT).round().astype(int).tolist())
            for loop in range(n_loops):
                train = split == "train"  # wander moves the train loops, the lane offset the test loops
                visit = plan_visit(
                    campus,
                    seed,
                    split,
                    loop,
                    frames,
                    frame_interval,
                    None if train else test_lane_offset,
                    lane_wander if train else 0.0,
                    lighting_presets,
                )
                info = visit.info()
                info["first_id"] = loop * ID_STRIDE + 1
                loop_info.append(info)
                trajectories.append(
                    (
                        split,
                        f"loop {loop}: {visit.pattern.circuit} {'cw' if visit.pattern.clockwise else 'ccw'}, "
                        f"{visit.pattern.lane}, {visit.lighting.name}",
                        visit.t[:, :2],
                    )
                )
                for i in range(frames):
                    name = f"Image_{loop * ID_STRIDE + i + 1}"
                    line = format_pose(name + ".png", visit.t[i], visit.q[i])
                    vals = [float(v) for v in line.split()[1:]]  # render exactly the pose that is written
                    t0 = time.perf_counter()
                    rgb, labels, depth = render_frame(
                        campus, vals[:3], vals[3:], K, visit.lighting, visit.objects_at(i)
                    )
                    render_time += time.perf_counter() - t0
                    files = (
                        (img_dir / f"{name}.png", rgb[..., ::-1]),
                        (lab_dir / f"{name}.png", labels),
                        (col_dir / f"{name}.png", colorize(labels)[..., ::-1]),
                        (dep_dir / f"{name}.pfm", depth),
                    )
                    writer.submit(_write_files, files)
                    lines.append(line)
                    if loop * frames + i in picks:
                        samples.append((f"{split} loop {loop} {name}", rgb, labels, depth))
                    bar.update(1)
            (root / "DeepLoc" / split / "poses.txt").write_text("\n".join(lines) + "\n")
        writer.finish()
    finally:
        writer.close()
        bar.close()
    _write_scene_info(
        root,
        campus,
        samples,
        trajectories,
        {
            "scene": scene,
            "seed": seed,
            "size": list(size),
            "frames_per_loop": frames,
            "loops": loops,
            "frame_interval_s": frame_interval,
            "intrinsics": K.to_dict(),
            "visits": loop_info,
        },
    )
    return {
        "scene": scene,
        "seed": seed,
        "size": list(size),
        "train_frames": train_loops * frames,
        "test_frames": test_loops * frames,
        "frames": total,
        "seconds": time.perf_counter() - t_start,
        "render_seconds": render_time,
        "render_fps": total / render_time if render_time > 0 else float("nan"),
    }


def _write_scene_info(root: Path, campus, samples: list, trajectories: list, info: dict) -> None:
    """``preview/mosaic.png`` (sample frames), ``preview/map.png`` (top-down map with the visits) and
    ``scene.json`` (generator, ``info``, landmarks)."""
    preview = root / "preview"
    preview.mkdir()
    write_image(preview / "mosaic.png", mosaic(samples)[..., ::-1])
    write_image(preview / "map.png", top_down_map(campus, trajectories)[..., ::-1])
    scene_info = {
        "generator": "vlocnetpp synthetic campus",
        "generator_version": GENERATOR_VERSION,
        "id_stride": ID_STRIDE,
        **info,
        "landmarks": [{"name": n, "x": round(x, 3), "y": round(y, 3)} for n, x, y in campus.landmarks],
    }
    (root / "scene.json").write_text(json.dumps(scene_info, indent=2, sort_keys=True) + "\n")


def _write_files(files: tuple[tuple[Path, np.ndarray], ...]) -> None:
    for path, arr in files:
        if path.suffix == ".pfm":
            write_pfm(path, arr)
        else:
            write_image(path, arr)

"""Evaluation plots are written as readable PNGs that show what they claim to show."""

from __future__ import annotations

import cv2
import numpy as np

from vlocnetpp_core.classes import CLASS_COLORS
from vlocnetpp_core.evaluation.metrics import SequenceRecorder
from vlocnetpp_core.evaluation.plots import top_down_axes, write_plots


def read_rgb(path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None, f"{path} is not a readable image"
    return image[..., ::-1]


def has_color(image: np.ndarray, rgb, min_pixels: int = 50) -> bool:
    return int(np.all(image == np.asarray(rgb, np.uint8), axis=-1).sum()) >= min_pixels


def test_top_down_axes_drop_the_flattest_axis():
    t = np.stack([np.linspace(0, 50, 20), np.linspace(0, 0.5, 20), np.sin(np.linspace(0, 3, 20)) * 30], axis=1)
    assert top_down_axes(t) == (0, 2)


def test_write_plots_per_sequence_and_overall(tmp_path):
    rec = SequenceRecorder("seq-03")
    n = 20
    for k in range(n):
        angle = k / n * 2 * np.pi
        t = np.array([10 * np.cos(angle), 0.0, 10 * np.sin(angle)])
        q = np.array([1.0, 0.0, 0.0, 0.0])
        rec.add(k * 0.05, t, q, t + 0.3, q, np.array([0.0, 0.0, 3.0]), q, ms=5.0)
        true = np.full((24, 32), 2, np.uint8)
        true[:8] = 1
        pred = true.copy()
        pred[:, :4] = 6
        rec.add_labels(true, pred)
        if k in (0, 10):
            rec.add_sample(np.full((24, 32, 3), 120, np.uint8), pred, true)
    written = write_plots(tmp_path, [rec.result()])
    names = sorted(str(p.relative_to(tmp_path)) for p in written)
    assert names == [
        "confusion.png",
        "seq-03/confusion.png",
        "seq-03/errors.png",
        "seq-03/segmentation.png",
        "seq-03/trajectory.png",
    ]
    assert (
        sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file()) == names
    )  # no temporaries left
    strip = read_rgb(tmp_path / "seq-03/segmentation.png")
    for class_id in (1, 2, 6):  # sky, road (true and predicted), building (predicted only)
        assert has_color(strip, CLASS_COLORS[class_id]), class_id
    traj = read_rgb(tmp_path / "seq-03/trajectory.png")
    assert traj.shape[0] >= 400 and traj.shape[1] >= 400
    assert has_color(traj, (255, 127, 14), 20)  # the odometry line (matplotlib tab:orange)
    assert has_color(traj, (31, 119, 180), 20)  # the global pose dots (tab:blue)

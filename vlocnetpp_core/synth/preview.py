"""Preview images of a rendered dataset: a frame mosaic and a top-down map with the trajectories."""

from __future__ import annotations

import math

import cv2
import numpy as np

from vlocnetpp_core.classes import colorize
from vlocnetpp_core.synth.campus import Campus
from vlocnetpp_core.synth.ground import RES
from vlocnetpp_core.synth.layout import DEPTH_M, WIDTH_M
from vlocnetpp_core.synth.prims import BOX, ELLIPSOID

TRAIN_COLORS = [(31, 119, 180), (23, 190, 207), (44, 160, 44), (148, 103, 189), (140, 86, 75), (127, 127, 127)]
TEST_COLORS = [(214, 39, 40), (255, 127, 14), (227, 119, 194), (188, 189, 34)]


def depth_color(depth: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB rendering of metres (inverse depth, turbo); invalid (0) is black."""
    inv = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-3), 0.0)
    v = np.clip(inv / 0.8, 0, 1) ** 0.5
    img = cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    return np.where((depth > 0)[..., None], img, 0).astype(np.uint8)


def mosaic(samples: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]], tile_width: int = 320) -> np.ndarray:
    """Rows of (RGB | colourised labels | depth) for ``(caption, rgb, labels, depth)`` samples; RGB out."""
    rows = []
    for caption, rgb, labels, depth in samples:
        h, w = labels.shape
        tw = min(tile_width, w)
        th = max(1, round(h * tw / w))
        tiles = [
            cv2.resize(rgb, (tw, th), interpolation=cv2.INTER_AREA),
            cv2.resize(colorize(labels), (tw, th), interpolation=cv2.INTER_NEAREST),
            cv2.resize(depth_color(depth), (tw, th), interpolation=cv2.INTER_NEAREST),
        ]
        row = np.concatenate(tiles, 1)
        _label(row, caption, (6, 16))
        rows.append(row)
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 2), (0, width - r.shape[1]), (0, 0))) for r in rows]
    return np.concatenate(rows, 0)


def top_down_map(
    campus: Campus, trajectories: list[tuple[str, str, np.ndarray]], scale: float = 0.2, margin: float = 12.0
) -> np.ndarray:
    """North-up map (RGB) of the campus with ``(split, name, xy (N, 2))`` trajectories, 2 pixels per ``scale``
    metres."""
    g = campus.ground
    level = min(max(int(round(math.log2(scale / RES))), 0), len(g.mips) - 1)
    s = RES * 2**level
    x0, y0 = -margin, -margin
    c0, r0 = int((x0 - g.x0) / s), int((y0 - g.y0) / s)
    c1, r1 = int((WIDTH_M + margin - g.x0) / s), int((DEPTH_M + margin - g.y0) / s)
    img = np.ascontiguousarray(g.mips[level][r0:r1, c0:c1][::-1]).copy()
    H = img.shape[0]
    ox, oy = g.x0 + c0 * s, g.y0 + r0 * s

    def px(x, y):
        return np.stack([(np.asarray(x) - ox) / s, H - (np.asarray(y) - oy) / s], -1)

    P = campus.prims
    for i in range(len(P)):
        c = px(P.cx[i], P.cy[i])
        if P.kind[i] == BOX:
            ca, sa = P.cos[i], P.sin[i]
            ex, ey = np.array([ca, sa]) * P.a[i], np.array([-sa, ca]) * P.b[i]
            ctr = np.array([P.cx[i], P.cy[i]])
            pts = px(*np.array([ctr - ex - ey, ctr + ex - ey, ctr + ex + ey, ctr - ex + ey]).T)
            color = (90, 90, 95) if P.label[i] == 6 else (160, 160, 160)
            cv2.fillConvexPoly(img, np.round(pts * 16).astype(np.int32), color, cv2.LINE_AA, 4)
        elif P.kind[i] == ELLIPSOID:
            cv2.circle(
                img, tuple(int(v) for v in np.round(c * 16)), int(P.a[i] / s * 16), (60, 110, 45), -1, cv2.LINE_AA, 4
            )
    counters = {"train": 0, "test": 0}
    legend = []
    for split, name, xy in trajectories:
        palette = TRAIN_COLORS if split == "train" else TEST_COLORS
        color = palette[counters[split] % len(palette)]
        counters[split] += 1
        pts = np.round(px(xy[:, 0], xy[:, 1]) * 16).astype(np.int32)
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, color, 2, cv2.LINE_AA, 4)
        cv2.circle(img, tuple(int(v) for v in pts[0]), 5 * 16, color, -1, cv2.LINE_AA, 4)
        legend.append((f"{split} {name}", color))
    img = cv2.resize(img, (img.shape[1] * 2, img.shape[0] * 2), interpolation=cv2.INTER_LINEAR)
    for k, (text, color) in enumerate(legend):
        y = 22 + 20 * k
        cv2.rectangle(img, (10, y - 12), (26, y + 2), color, -1)
        _label(img, text, (32, y))
    _label(img, f"{campus.scene}: north up, {s / 2:.2f} m per pixel", (10, img.shape[0] - 12))
    return img


def _label(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.45) -> None:
    """White text on a dark box at ``org`` (baseline left)."""
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x, y = org
    cv2.rectangle(img, (x - 3, y - h - 3), (x + w + 3, y + base), (20, 20, 20), -1)
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)

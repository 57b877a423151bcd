"""Decoding of dataset images, label maps and depth maps, with errors that name the file.

All readers use ``cv2.imread(..., IMREAD_UNCHANGED)`` (no PIL) and return numpy arrays:

* colour: ``(H, W, 3) uint8`` RGB; grey is replicated, alpha dropped, 16-bit scaled to 8-bit;
* labels: ``(H, W) uint8`` class ids 0..9, 255 = ignore; anything else is an error;
* depth: ``(H, W) float32`` metres, 0 = invalid. PFM files hold metres (non-finite and
  negative values become 0); 16-bit PNGs hold millimetres with 0 and 65535 invalid.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from vlocnetpp_core.classes import IGNORE_INDEX, NUM_CLASSES
from vlocnetpp_core.data.pfm import read_pfm
from vlocnetpp_core.errors import DataError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".tif", ".tiff")
DEPTH_EXTENSIONS = (".pfm", ".png", ".tif", ".tiff")


def _imread(path: str | Path, what: str) -> np.ndarray:
    p = Path(path)
    if not p.is_file():
        raise DataError(p, f"{what} file not found")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise DataError(p, f"cannot decode {what} (truncated or not an image file)")
    return img


def read_rgb(path: str | Path) -> np.ndarray:
    """``(H, W, 3) uint8`` RGB from a grey, RGB or RGBA file (8 or 16 bit)."""
    img = _imread(path, "image")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise DataError(path, f"expected an 8- or 16-bit image, got {img.dtype}")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    if img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    raise DataError(path, f"expected 1, 3 or 4 channels, got {img.shape[2]}")


def _check_size(path: str | Path, arr: np.ndarray, shape: tuple[int, int] | None, what: str) -> None:
    if shape is not None and arr.shape[:2] != tuple(shape):
        raise DataError(
            path, f"{what} is {arr.shape[1]}x{arr.shape[0]}, expected {shape[1]}x{shape[0]} like its colour image"
        )


def read_labels(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """``(H, W) uint8`` class ids from a one-channel PNG; ``shape (H, W)`` is checked when given."""
    lab = _imread(path, "label image")
    if lab.ndim == 3:
        if lab.shape[2] >= 3 and np.array_equal(lab[..., 0], lab[..., 1]) and np.array_equal(lab[..., 0], lab[..., 2]):
            lab = lab[..., 0]  # a grey image saved as RGB
        else:
            raise DataError(
                path, "expected a one-channel label image of class ids (labels_colorized/ is a preview, not ids)"
            )
    _check_size(path, lab, shape, "label image")
    bad = (lab >= NUM_CLASSES) & (lab != IGNORE_INDEX)
    if bad.any():
        raise DataError(
            path, f"label id {int(lab[bad].max())} outside 0..{NUM_CLASSES - 1} (and not {IGNORE_INDEX} = ignore)"
        )
    return lab.astype(np.uint8)


def read_depth(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """``(H, W) float32`` metres, 0 = invalid, from a PFM (metres) or 16-bit PNG (millimetres)."""
    p = Path(path)
    if p.suffix.lower() == ".pfm":
        if not p.is_file():
            raise DataError(p, "depth file not found")
        depth = read_pfm(p)  # DataError naming the file on a bad header or truncated data
        if depth.ndim == 3 and depth.shape[2] == 1:
            depth = depth[..., 0]
        if depth.ndim != 2:
            raise DataError(p, f"expected a one-channel depth map, got shape {depth.shape}")
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    else:
        raw = _imread(p, "depth image")
        if raw.ndim != 2:
            raise DataError(p, "expected a one-channel depth image")
        if raw.dtype == np.uint16:
            depth = np.where(raw == 65535, 0, raw).astype(np.float32) * np.float32(0.001)
        elif raw.dtype == np.float32:
            depth = np.where(np.isfinite(raw) & (raw > 0), raw, 0.0).astype(np.float32)
        else:
            raise DataError(p, f"expected 16-bit depth in millimetres (or float metres), got {raw.dtype}")
    _check_size(p, depth, shape, "depth map")
    return depth


def write_image(path: str | Path, img: np.ndarray) -> None:
    """Write ``img`` with OpenCV (colour in BGR order; 16-bit PNG for uint16); ``DataError`` naming the file on
    failure."""
    if not cv2.imwrite(str(path), np.ascontiguousarray(img)):
        raise DataError(path, "could not write the image (disk full or no permission?)")


class BackgroundWriter:
    """Runs file writes on ``threads`` worker threads (PNG encoding releases the GIL) while the caller makes the
    next frame, with at most ``max_pending`` writes in flight (``submit`` then waits for the oldest)."""

    def __init__(self, threads: int = 1, max_pending: int = 8, name: str = "writer"):
        self._pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix=name)
        self._pending: deque[Future] = deque()
        self._max = max_pending

    def submit(self, fn: Callable[..., object], *args) -> None:
        """Run ``fn(*args)`` in the background; re-raises the failure of an earlier write."""
        self._pending.append(self._pool.submit(fn, *args))
        while len(self._pending) > self._max:
            self._pending.popleft().result()

    def finish(self) -> None:
        """Wait for every pending write, re-raising the first failure."""
        while self._pending:
            self._pending.popleft().result()

    def close(self) -> None:
        """Cancel what has not started and stop the threads (after :meth:`finish`, or on an error)."""
        for f in self._pending:
            f.cancel()
        self._pool.shutdown(wait=True)

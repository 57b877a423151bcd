"""Pinhole intrinsics that follow every resize and crop of the image they belong to.

Pixel convention: pixel centres at integer coordinates, ``(u, v)`` = (column, row), which is
what OpenCV's ``cv2.resize`` uses. Resizing by a factor ``s`` maps a point ``u`` to
``(u + 0.5) * s - 0.5``, so ``fx' = s fx`` and ``cx' = (cx + 0.5) s - 0.5``; cropping at
``(x0, y0)`` maps ``cx' = cx - x0``. Projecting a 3D point before and after a transform lands
on the same image content (``test/test_geometry.py`` checks it).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera ``fx, fy, cx, cy`` in pixels for an image of ``width x height``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def parse(cls, text: str, width: int, height: int) -> Intrinsics:
        """From ``"fx,fy,cx,cy"`` (the ``--intrinsics`` flag of every tool)."""
        try:
            fx, fy, cx, cy = (float(v) for v in text.split(","))
        except ValueError as err:
            raise ValueError(f"intrinsics must be 'fx,fy,cx,cy' (four numbers), got {text!r}") from err
        if fx <= 0 or fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={fx}, fy={fy}")
        return cls(fx, fy, cx, cy, int(width), int(height))

    @classmethod
    def from_matrix(cls, K, width: int, height: int) -> Intrinsics:
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    def matrix(self) -> np.ndarray:
        """``3 x 3`` float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def resized(self, width: int, height: int) -> Intrinsics:
        """Intrinsics of this image resized (possibly anisotropically) to ``width x height``."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, int(width), int(height)
        )

    def cropped(self, x0: int, y0: int, width: int, height: int) -> Intrinsics:
        """Intrinsics of the ``width x height`` crop whose top-left pixel is ``(x0, y0)``."""
        return Intrinsics(self.fx, self.fy, self.cx - x0, self.cy - y0, int(width), int(height))

    def flipped_horizontally(self) -> Intrinsics:
        """Intrinsics after mirroring the image left-right (``u -> W - 1 - u``)."""
        return Intrinsics(self.fx, self.fy, self.width - 1 - self.cx, self.cy, self.width, self.height)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        return cls(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]), int(d["width"]), int(d["height"]))


# DeepLoc publishes no intrinsics. The ZED left camera at 1280x720 (HD720) has a focal length
# of about 700 px and the principal point near the image centre; these are approximate and
# should be replaced by your calibration (``--intrinsics fx,fy,cx,cy``).
DEEPLOC_DEFAULT = Intrinsics(fx=700.0, fy=700.0, cx=639.5, cy=359.5, width=1280, height=720)

# Microsoft 7-Scenes (Kinect): focal 585 px, principal point (320, 240) at 640x480.
SEVEN_SCENES_DEFAULT = Intrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)

"""The campus geometry: vertical convex prisms and ellipsoids, as a struct of arrays.

World frame: x east, y north, z up, metres. Three kinds of primitive:

* ``BOX``: an oriented box, centre ``(cx, cy)``, yaw, half extents ``a`` (along its local x')
  and ``b`` (local y'), heights ``[z0, z1]``. Its side strip runs around the perimeter
  counter-clockwise starting at corner ``(a, -b)``: faces +x' (length 2b), +y' (2a), -x' (2b),
  -y' (2a) (``textures.box_faces``).
* ``CYLINDER``: vertical, centre, radius ``a``, heights ``[z0, z1]``; ``u`` = azimuth * radius.
* ``ELLIPSOID``: centre ``(cx, cy, (z0 + z1) / 2)``, horizontal radius ``a``, vertical radius
  ``(z1 - z0) / 2``; ``u`` = azimuth * a (tree crowns).

Each primitive has a class id, an atlas strip (origin ``tx, ty`` in level-0 texels, size ``tw, th``
in metres), a texel for
its horizontal faces (``cap_x, cap_y``) and a cut-out flag (fences: holes in the texture are
see-through).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from vlocnetpp_core.synth.textures import Strip

BOX, CYLINDER, ELLIPSOID = 0, 1, 2


@dataclass
class Prims:
    kind: np.ndarray  # (N,) int8
    cx: np.ndarray  # (N,) float64, metres
    cy: np.ndarray
    cos: np.ndarray  # yaw of boxes
    sin: np.ndarray
    a: np.ndarray
    b: np.ndarray
    z0: np.ndarray
    z1: np.ndarray
    label: np.ndarray  # (N,) uint8
    tx: np.ndarray
    ty: np.ndarray
    tw: np.ndarray  # strip size in metres (cylinders and ellipsoids stretch their strip around)
    th: np.ndarray
    cap_x: np.ndarray
    cap_y: np.ndarray
    cutout: np.ndarray  # (N,) bool

    def __len__(self) -> int:
        return len(self.kind)

    @property
    def radius(self) -> np.ndarray:
        """Bounding radius of each footprint."""
        return np.where(self.kind == BOX, np.hypot(self.a, self.b), self.a)

    def take(self, idx: np.ndarray) -> Prims:
        return Prims(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    @staticmethod
    def concat(parts: list[Prims]) -> Prims:
        return Prims(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Prims)})


class PrimsBuilder:
    """Collects primitives one by one; ``build()`` freezes them into :class:`Prims`."""

    def __init__(self):
        self._rows: list[tuple] = []

    def __len__(self) -> int:
        return len(self._rows)

    def box(
        self, cx, cy, yaw, length, width, z0, z1, label, strip: Strip, cap: tuple[float, float], cutout=False
    ) -> None:
        """Box of full ``length`` along its yaw direction and full ``width`` across it."""
        self._rows.append(
            (
                BOX,
                cx,
                cy,
                np.cos(yaw),
                np.sin(yaw),
                length / 2,
                width / 2,
                z0,
                z1,
                label,
                strip.x0,
                strip.y0,
                strip.width_m,
                strip.height_m,
                cap[0],
                cap[1],
                cutout,
            )
        )

    def cylinder(self, cx, cy, radius, z0, z1, label, strip: Strip, cap: tuple[float, float]) -> None:
        self._rows.append(
            (
                CYLINDER,
                cx,
                cy,
                1.0,
                0.0,
                radius,
                radius,
                z0,
                z1,
                label,
                strip.x0,
                strip.y0,
                strip.width_m,
                strip.height_m,
                cap[0],
                cap[1],
                False,
            )
        )

    def ellipsoid(self, cx, cy, zc, radius, half_height, label, strip: Strip) -> None:
        self._rows.append(
            (
                ELLIPSOID,
                cx,
                cy,
                1.0,
                0.0,
                radius,
                half_height,
                zc - half_height,
                zc + half_height,
                label,
                strip.x0,
                strip.y0,
                strip.width_m,
                strip.height_m,
                0.0,
                0.0,
                False,
            )
        )

    def build(self) -> Prims:
        cols = list(zip(*self._rows, strict=True)) if self._rows else [[]] * 17
        dt = [np.int8] + [np.float64] * 8 + [np.uint8] + [np.float64] * 6 + [bool]
        return Prims(*(np.asarray(c, dtype=d) for c, d in zip(cols, dt, strict=True)))

"""The sample contract shared by every dataset reader: :class:`Frame` and :class:`DatasetIndex`.

A reader (DeepLoc, 7-Scenes) builds a :class:`DatasetIndex` once: an ordered list of
:class:`FrameRecord` (file paths plus the ground-truth pose) grouped into sequences of
consecutive frames. Nothing is decoded until :meth:`DatasetIndex.load` is called, so an index
is cheap to build, small, and picklable (DataLoader workers get a copy).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.data import imageio
from vlocnetpp_core.errors import UserError

# Stamps are synthesised from the frame order (neither DeepLoc nor 7-Scenes ships any). They
# increase over a whole split; each sequence starts this many seconds after the previous one
# ends, so a consumer that resets its temporal state on time gaps sees the sequence boundaries.
SEQUENCE_GAP_S = 10.0


@dataclass
class Frame:
    """One decoded frame.

    ``image (H, W, 3) uint8 RGB``; pose ``T_wc``: ``t (3,) float64`` metres, ``q (4,) float64``
    ``(w, x, y, z)`` with ``w >= 0``; ``depth (H, W) float32`` metres (0 = invalid) or None;
    ``labels (H, W) uint8`` class ids 0..9 (255 = ignore) or None; ``intrinsics`` at this image
    size; ``stamp`` seconds; ``sequence`` id; ``frame_id`` a name for humans (file stem); ``mirrored``:
    flipped left-right with its pose in the mirrored world (``transforms.flip_frame``).
    """

    image: np.ndarray
    t: np.ndarray
    q: np.ndarray
    depth: np.ndarray | None
    labels: np.ndarray | None
    intrinsics: Intrinsics
    stamp: float
    sequence: int
    frame_id: str
    mirrored: bool = False


def mirror_pose(t: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A pose conjugated by ``M = diag(-1, 1, 1)`` (the left-right mirror of the optical frame): ``t (..., 3)``
    -> ``(-x, y, z)``, ``q (..., 4)`` ``(w, x, y, z)`` -> ``(w, x, -y, -z)``. The same map for a camera pose in
    a mirrored world and for a relative pose between two mirrored frames (yaw and roll change sign)."""
    return t * np.array([-1.0, 1.0, 1.0]), q * np.array([1.0, 1.0, -1.0, -1.0])


@dataclass(frozen=True)
class FrameRecord:
    """Where one frame's files are and its ground truth; :meth:`DatasetIndex.load` decodes it."""

    image: str
    t: tuple[float, float, float]
    q: tuple[float, float, float, float]
    stamp: float
    sequence: int
    frame_id: str
    depth: str | None = None
    labels: str | None = None


@dataclass
class DatasetIndex:
    """An ordered, lazily loaded dataset split.

    ``records`` are in temporal order; ``sequences`` are the contiguous ranges of ``records``
    that form one recording (a DeepLoc loop, a 7-Scenes ``seq-XX``). ``intrinsics`` are for
    images of ``intrinsics.width x intrinsics.height``; a frame of another size gets them
    rescaled to its size. ``notes`` are things a user should know (skipped files, ...).
    """

    format: str
    root: Path
    split: str
    records: list[FrameRecord]
    sequences: list[range]
    intrinsics: Intrinsics
    intrinsics_source: str = ""
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.records)

    @property
    def has_depth(self) -> bool:
        return any(r.depth is not None for r in self.records)

    @property
    def has_labels(self) -> bool:
        return any(r.labels is not None for r in self.records)

    def load(self, i: int, depth: bool = True, labels: bool = True) -> Frame:
        """Decode record ``i`` (its depth and labels only where asked: training stages that do not use
        them skip their files). Raises ``DataError`` naming the file on unreadable or inconsistent data."""
        r = self.records[i]
        image = imageio.read_rgb(r.image)
        h, w = image.shape[:2]
        K = self.intrinsics
        if (K.width, K.height) != (w, h):
            K = K.resized(w, h)
        return Frame(
            image=image,
            t=np.array(r.t, dtype=np.float64),
            q=np.array(r.q, dtype=np.float64),
            depth=imageio.read_depth(r.depth, (h, w)) if depth and r.depth is not None else None,
            labels=imageio.read_labels(r.labels, (h, w)) if labels and r.labels is not None else None,
            intrinsics=K,
            stamp=r.stamp,
            sequence=r.sequence,
            frame_id=r.frame_id,
        )


def sequence_stamps(lengths: list[int], rate_hz: float) -> list[np.ndarray]:
    """Stamps in seconds for sequences of ``lengths`` frames at ``rate_hz``, laid end to end with
    :data:`SEQUENCE_GAP_S` between sequences (so they increase over the whole split)."""
    out, start = [], 0.0
    for n in lengths:
        s = start + np.arange(n) / rate_hz
        out.append(s)
        start = (s[-1] if n else start) + SEQUENCE_GAP_S
    return out


def resolve_intrinsics(given: Intrinsics | str | None, default: Intrinsics, width: int, height: int) -> Intrinsics:
    """Intrinsics for images of ``width x height``.

    ``given`` may be an :class:`Intrinsics` (rescaled when made for another size), a string
    ``"fx,fy,cx,cy"`` (taken to be for this image size: the ``--intrinsics`` flag) or None
    (``default``, rescaled to this size).
    """
    if isinstance(given, str):
        try:
            return Intrinsics.parse(given, width, height)
        except ValueError as err:
            raise UserError(f"--intrinsics: {err}") from err
    K = default if given is None else given
    return K if (K.width, K.height) == (width, height) else K.resized(width, height)

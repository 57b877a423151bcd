"""Depth images matched to colour frames by stamp: the subscription callback adds, the worker looks up.

The last :data:`DEPTH_MATCH_FRAMES` depth messages are kept (a refused one as its stamp only, so that the colour
frame with that stamp neither waits for it nor counts it missing); nothing else is held, so memory stays bounded
whatever the depth publisher does.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable

import numpy as np
from sensor_msgs.msg import Image

from vlocnetpp_core.inference.preprocess import FrameError
from vlocnetpp_ros import conversions

DEPTH_MATCH_FRAMES = 8  # depth images (or stamps of refused ones) kept for matching colour stamps
DEPTH_WAIT_S = 0.05  # how long a colour frame waits for its depth image (in the worker)


def stamp_key(stamp) -> tuple[int, int]:
    """``builtin_interfaces/Time`` as a hashable value that holds no message."""
    return int(stamp.sec), int(stamp.nanosec)


class DepthMatcher:
    """The last depth images by stamp; ``ignore(err)`` counts and logs a depth image not used."""

    def __init__(self, ignore: Callable[[FrameError], None]):
        self._ignore = ignore
        # (stamp, depth Image or None when it was refused on arrival), newest last
        self._depths: deque[tuple[tuple[int, int], Image | None]] = deque(maxlen=DEPTH_MATCH_FRAMES)
        self._arrived = threading.Condition()

    def __len__(self) -> int:
        """Depth messages (or stamps) kept."""
        return len(self._depths)

    def add(self, msg: Image) -> None:
        """A depth message from the subscription (never blocks for long): kept, or only its stamp when refused."""
        key = stamp_key(msg.header.stamp)
        try:
            conversions.check_depth(msg)
        except FrameError as err:
            self._ignore(err)
            msg = None
        with self._arrived:
            self._depths.append((key, msg))
            self._arrived.notify_all()

    def matching(self, stamp) -> np.ndarray | None:
        """Depth ``(H, W) float32`` metres with exactly this stamp, waiting up to ``DEPTH_WAIT_S`` for it (not once
        the newest depth image is later than ``stamp``: it will not come); None: use the predicted depth (also when
        the depth image with this stamp was refused on arrival: counted then)."""
        key = stamp_key(stamp)

        def find():
            return next((entry for entry in reversed(self._depths) if entry[0] == key), None)

        def settled() -> bool:  # ours is here, or a later one is (a camera sends its depth images in stamp order)
            return bool(self._depths) and (self._depths[-1][0] > key or find() is not None)

        with self._arrived:
            self._arrived.wait_for(settled, DEPTH_WAIT_S)
            entry = find()
        if entry is None:
            self._ignore(
                FrameError("depth_missing", "no depth image with the colour image's stamp; using the predicted depth")
            )
            return None
        if entry[1] is None:
            return None
        try:
            return conversions.depth_to_array(entry[1])
        except FrameError as err:
            self._ignore(err)
            return None

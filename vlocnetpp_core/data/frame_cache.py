"""``FrameCache``: a dataset split decoded once and kept in memory at a fixed size, for training.

Decoding a 320x180 PNG and resizing it costs about as much as the lite network's training step on
one image; training visits every frame hundreds of times. The cache decodes each frame once,
resizes it to ``size`` (the largest size the training transform asks for, so its resize and crop
work on the cached pixels) and serves :meth:`load` from memory. DataLoader workers forked after
the cache is filled share its pages.
"""

from __future__ import annotations

import os
import sys

from vlocnetpp_core.data.sample import DatasetIndex, Frame
from vlocnetpp_core.data.transforms import resize_frame

# The cache may take at most this share of the memory available when it is built.
MAX_MEMORY_SHARE = 0.4


def cache_bytes(n: int, size: tuple[int, int], depth: bool, labels: bool) -> int:
    """Bytes of ``n`` cached frames of ``size (W, H)``: RGB uint8, depth float32 and labels uint8 where kept."""
    w, h = size
    return n * w * h * (3 + 4 * depth + labels)


def available_memory() -> int:
    """Bytes of memory available to new allocations (Linux ``MemAvailable``; total physical memory elsewhere)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


class FrameCache:
    """The frames of ``index`` at ``size (W, H)`` (intrinsics follow), decoded on construction.

    Stands in for the :class:`DatasetIndex` in a ``ClipDataset`` (``records``, ``sequences``,
    ``load``, ``len``). ``depth`` / ``labels``: decode and keep those too (else the frames hold None).
    """

    def __init__(
        self, index: DatasetIndex, size: tuple[int, int], depth: bool = True, labels: bool = True, progress: bool = True
    ):
        from tqdm import tqdm

        self.index, self.size = index, (int(size[0]), int(size[1]))
        self.records, self.sequences = index.records, index.sequences
        self.depth, self.labels = depth and index.has_depth, labels and index.has_labels
        self.frames: list[Frame] = [
            resize_frame(index.load(i, self.depth, self.labels), *self.size)
            for i in tqdm(
                range(len(index)), desc="decode frames", unit="frame", disable=(not progress) or None, file=sys.stderr
            )
        ]

    def __len__(self) -> int:
        return len(self.frames)

    def load(self, i: int, depth: bool = True, labels: bool = True) -> Frame:
        """Cached frame ``i`` (its depth / labels only where asked and cached)."""
        f = self.frames[i]
        if (f.depth is not None and not depth) or (f.labels is not None and not labels):
            from dataclasses import replace

            f = replace(f, depth=f.depth if depth else None, labels=f.labels if labels else None)
        return f

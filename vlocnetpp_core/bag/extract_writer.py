"""Writing the frames ``vlocnetpp extract`` keeps as a DeepLoc-layout dataset, atomically.

Layout (what :mod:`vlocnetpp_core.data.deeploc` reads; no labels)::

    OUT/DeepLoc/{train,test}/LeftImages/Image_<id>.png           RGB (BGR on disk, as cv2 writes), lossless
    OUT/DeepLoc/{train,test}/poses.txt                           '# comment', header, 'Image_<id>.png x y z qw qx qy qz'
                                                                 (T_wc)
    OUT/DeepLoc/{train,test}/stamps.txt                          'Image_<id>.png <header stamp, integer ns>'
                                                                 (not read by the reader)
    OUT/DeepLoc_stereo/{train,test}/DepthImages/Image_<id>.pfm   32FC1 depth: float32 metres (0 = invalid)
    OUT/DeepLoc_stereo/{train,test}/DepthImages/Image_<id>.png   16UC1 depth: uint16 millimetres as in the bag
    OUT/intrinsics.json                                          {"fx", "fy", "cx", "cy", "width", "height"}
    OUT/extract.json                                             where it came from: bag, topics, options, counts

:func:`~vlocnetpp_core.outputs.atomic_output_dir` (the one of ``synth`` too) gives a hidden temporary
folder next to ``OUT`` (``.OUT.partial-<pid>``, the naming of :mod:`vlocnetpp_core.bag.bagfile`, whose
stale-folder cleanup it shares) that is renamed to ``OUT`` only when the block ends without an error; an
error, Ctrl-C or SIGTERM (with :func:`~vlocnetpp_core.interrupts.sigterm_as_interrupt`) deletes it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from vlocnetpp_core.bag.extract_plan import PlannedFrame
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.data.imageio import BackgroundWriter, write_image
from vlocnetpp_core.data.pfm import write_pfm
from vlocnetpp_core.outputs import atomic_output_dir, check_output_dir

check_output = check_output_dir  # the name extract.py checks its output with before reading the bag

__all__ = ["DeepLocWriter", "atomic_output_dir", "check_output"]


class DeepLocWriter:
    """Writes images and depth of :class:`PlannedFrame` s under ``root`` (module doc) on background threads
    (PNG encoding releases the GIL), at most ``max_pending`` files in flight; :meth:`finish` writes the index."""

    def __init__(self, root: Path, threads: int = 2, max_pending: int = 8):
        self.root = Path(root)
        self._files = BackgroundWriter(threads, max_pending, "extract-writer")
        self.images: set[tuple[str, int]] = set()  # (split, id) of the images written
        self.depths: dict[tuple[str, int], Path] = {}  # (split, id) -> depth file written

    def _dir(self, *parts: str) -> Path:
        d = self.root.joinpath(*parts)
        d.mkdir(parents=True, exist_ok=True)
        return d

    def image(self, frame: PlannedFrame, rgb: np.ndarray) -> None:
        """``rgb (H, W, 3) uint8`` as ``LeftImages/Image_<id>.png``."""
        self._files.submit(write_image, self._dir("DeepLoc", frame.split, "LeftImages") / frame.name, rgb[..., ::-1])
        self.images.add((frame.split, frame.id))

    def depth(self, frame: PlannedFrame, depth: np.ndarray) -> None:
        """``depth (H, W)``: float32 metres (written as PFM) or uint16 millimetres (16-bit PNG)."""
        folder = self._dir("DeepLoc_stereo", frame.split, "DepthImages")
        if depth.dtype == np.uint16:
            path = folder / f"Image_{frame.id}.png"
            self._files.submit(write_image, path, depth)
        else:
            path = folder / f"Image_{frame.id}.pfm"
            self._files.submit(write_pfm, path, depth.astype(np.float32))
        self.depths[(frame.split, frame.id)] = path

    def close(self) -> None:
        """Wait for every pending file (re-raising the first failure)."""
        try:
            self._files.finish()
        finally:
            self._files.close()

    def finish(self, frames: list[PlannedFrame], K: Intrinsics, provenance: dict) -> list[PlannedFrame]:
        """Write ``poses.txt`` and ``stamps.txt`` per split for the frames whose image was written,
        ``intrinsics.json`` and ``extract.json``; delete depth files of frames without an image.
        Returns the frames written."""
        self.close()
        written = [f for f in frames if (f.split, f.id) in self.images]
        for key in set(self.depths) - self.images:
            self.depths.pop(key).unlink(missing_ok=True)
        for split in sorted({f.split for f in written}):
            rows = [f for f in written if f.split == split]
            lines = [
                f"# extracted by vlocnetpp extract from {provenance.get('bag', '?')}",
                "ImageName x y z qw qx qy qz",
            ]
            lines += [f"{f.name} " + " ".join(f"{v:.9f}" for v in (*f.t, *f.q)) for f in rows]
            (self.root / "DeepLoc" / split / "poses.txt").write_text("\n".join(lines) + "\n")
            (self.root / "DeepLoc" / split / "stamps.txt").write_text("".join(f"{f.name} {f.stamp_ns}\n" for f in rows))
        (self.root / "intrinsics.json").write_text(json.dumps(K.to_dict(), indent=2) + "\n")
        (self.root / "extract.json").write_text(json.dumps(provenance, indent=2, sort_keys=True) + "\n")
        return written

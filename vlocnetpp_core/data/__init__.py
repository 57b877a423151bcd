"""Datasets: DeepLoc and 7-Scenes readers, the sample contract, clip transforms, ``ClipDataset``.

``open_dataset(path, format=None, split="train", intrinsics=None)`` indexes a split (format
detected from the layout; ``FORMATS`` lists them) into a :class:`DatasetIndex`; ``ClipDataset(index,
clip_len, transform)`` turns it into clips of tensors; ``make_transform(train, size)`` is the standard
resize/crop/jitter pipeline. See docs/architecture.md ("Data"). The names below load their module on
first use, so that the torch-free modules (``formats``, ``imageio``, ``pfm``, ...) import without torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from vlocnetpp_core import lazy_getattr
from vlocnetpp_core.data.formats import FORMATS

_EXPORTS = {
    "ClipDataset": "dataset",
    "clip_to_tensors": "dataset",
    "detect_format": "dataset",
    "open_dataset": "dataset",
    "read_deeploc": "deeploc",
    "DatasetIndex": "sample",
    "Frame": "sample",
    "FrameRecord": "sample",
    "read_sevenscenes": "sevenscenes",
    "make_transform": "transforms",
}
__all__ = ["FORMATS", *_EXPORTS]

if TYPE_CHECKING:
    from vlocnetpp_core.data.dataset import ClipDataset, clip_to_tensors, detect_format, open_dataset  # noqa: F401
    from vlocnetpp_core.data.deeploc import read_deeploc  # noqa: F401
    from vlocnetpp_core.data.sample import DatasetIndex, Frame, FrameRecord  # noqa: F401
    from vlocnetpp_core.data.sevenscenes import read_sevenscenes  # noqa: F401
    from vlocnetpp_core.data.transforms import make_transform  # noqa: F401


__getattr__ = lazy_getattr(__name__, _EXPORTS, globals())

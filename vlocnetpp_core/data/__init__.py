"""Datasets: DeepLoc and 7-Scenes readers, the sample contract, clip transforms, ``ClipDataset``.

``open_dataset(path, format=None, split="train", intrinsics=None)`` indexes a split (format
detected from the layout) into a :class:`DatasetIndex`; ``ClipDataset(index, clip_len,
transform)`` turns it into clips of tensors; ``make_transform(train, size)`` is the standard
resize/crop/jitter pipeline. See docs/architecture.md ("Data").
"""

from vlocnetpp_core.data.dataset import ClipDataset, clip_to_tensors, detect_format, open_dataset
from vlocnetpp_core.data.deeploc import read_deeploc
from vlocnetpp_core.data.sample import DatasetIndex, Frame, FrameRecord
from vlocnetpp_core.data.sevenscenes import read_sevenscenes
from vlocnetpp_core.data.transforms import make_transform

__all__ = [
    "ClipDataset",
    "DatasetIndex",
    "Frame",
    "FrameRecord",
    "clip_to_tensors",
    "detect_format",
    "make_transform",
    "open_dataset",
    "read_deeploc",
    "read_sevenscenes",
]

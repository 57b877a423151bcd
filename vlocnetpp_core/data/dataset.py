"""``ClipDataset``: clips of consecutive frames as tensors, and ``open_dataset`` (format detection)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from vlocnetpp_core import geometry
from vlocnetpp_core.classes import IGNORE_INDEX
from vlocnetpp_core.data.sample import DatasetIndex, Frame
from vlocnetpp_core.errors import DataError, UserError
from vlocnetpp_core.intrinsics import Intrinsics

FORMATS = ("deeploc", "7scenes")


def detect_format(path: str | Path) -> str:
    """``"deeploc"`` or ``"7scenes"`` from the folder layout; ``DataError`` when neither matches."""
    p = Path(path)
    if not p.is_dir():
        raise DataError(p, "dataset folder not found")
    if (p / "DeepLoc").is_dir() or any((p / s / "LeftImages").is_dir() for s in ("train", "test")):
        return "deeploc"
    if (p / "TrainSplit.txt").is_file() or (p / "TestSplit.txt").is_file() or any(p.glob("seq-*/frame-*.color.png")):
        return "7scenes"
    raise DataError(
        p, "unknown dataset layout: expected DeepLoc/{train,test}/LeftImages/ (DeepLoc) or TrainSplit.txt + seq-XX/ (7-Scenes)"
    )


def available_splits(path: str | Path, format: str) -> list[str]:
    """The splits (``train``, ``test``) present in the dataset at ``path`` of ``format``."""
    if format == "deeploc":
        from vlocnetpp_core.data.deeploc import find_deeploc_root

        deeploc_dir, _ = find_deeploc_root(path)
        return [s for s in ("train", "test") if (deeploc_dir / s).is_dir()]
    from vlocnetpp_core.data.sevenscenes import SPLIT_FILES

    return [s for s, f in SPLIT_FILES.items() if (Path(path) / f).is_file()]


def open_dataset(path: str | Path, format: str | None = None, split: str = "train", intrinsics: Intrinsics | str | None = None, **options) -> DatasetIndex:
    """Index ``split`` of the dataset at ``path``; ``format`` ``"deeploc"`` / ``"7scenes"`` or None to detect.

    ``intrinsics``: an :class:`Intrinsics`, ``"fx,fy,cx,cy"`` for the dataset's image size, or None
    for the reader's default. ``options`` go to the reader (e.g. ``quaternion_order`` for DeepLoc).
    """
    fmt = detect_format(path) if format is None else format.lower().replace("-", "")
    if fmt == "deeploc":
        from vlocnetpp_core.data.deeploc import read_deeploc

        return read_deeploc(path, split, intrinsics, **options)
    if fmt == "7scenes":
        from vlocnetpp_core.data.sevenscenes import read_sevenscenes

        return read_sevenscenes(path, split, intrinsics, **options)
    raise UserError(f"unknown dataset format {format!r}; expected one of {', '.join(FORMATS)}")


class ClipDataset(torch.utils.data.Dataset):
    """Clips of ``clip_len`` frames of one sequence, ``stride`` frames apart, as a dict of tensors.

    Every frame of a sequence that has ``clip_len`` frames after it (``stride`` apart) starts a
    clip. ``transform(frames, rng)`` (see ``data/transforms.py``) is applied to the whole clip
    with one random draw; the generator is seeded from torch's RNG, so ``torch.manual_seed`` and
    DataLoader worker seeding make it reproducible. Keys (docs/architecture.md, "Data"):
    ``image (T, 3, H, W)`` float in [0, 1], ``t (T, 3)``, ``q (T, 4)`` (w, x, y, z), ``rel_t (T, 3)``,
    ``rel_q (T, 4)`` (``T_{i-1}^{-1} T_i``, identity for frame 0), ``depth (T, 1, H, W)`` metres
    (zeros when absent), ``labels (T, H, W)`` int64 (255 when absent), ``K (T, 3, 3)``, ``stamp (T,)``
    float64, ``sequence ()``, ``has_depth ()`` / ``has_labels ()`` (every frame has them) and
    ``index (T,)`` (record indices in the ``DatasetIndex``). ``depth=False`` / ``labels=False`` skip
    decoding those files (the clips then hold zeros / 255, as for a dataset without them).
    """

    def __init__(self, index: DatasetIndex, clip_len: int = 1, transform=None, stride: int = 1, depth: bool = True, labels: bool = True):
        if clip_len < 1 or stride < 1:
            raise ValueError(f"clip_len and stride must be >= 1, got {clip_len}, {stride}")
        self.index = index
        self.load_depth, self.load_labels = depth, labels
        self.clip_len = clip_len
        self.stride = stride
        self.transform = transform
        span = (clip_len - 1) * stride
        self.starts = [s for seq in index.sequences for s in range(seq.start, seq.stop - span)]

    def __len__(self) -> int:
        return len(self.starts)

    def clip_indices(self, i: int) -> list[int]:
        """Record indices of clip ``i``."""
        s = self.starts[i]
        return [s + k * self.stride for k in range(self.clip_len)]

    def load_clip(self, i: int, rng: np.random.Generator | None = None) -> list[Frame]:
        """Decoded and transformed frames of clip ``i``."""
        frames = [self.index.load(j, self.load_depth, self.load_labels) for j in self.clip_indices(i)]
        if self.transform is not None:
            frames = self.transform(frames, rng if rng is not None else np.random.default_rng())
        return frames

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng(int(torch.randint(0, 2**62, ()).item()))
        return clip_to_tensors(self.load_clip(i, rng), self.clip_indices(i))


def clip_to_tensors(frames: list[Frame], indices: list[int]) -> dict[str, torch.Tensor]:
    """The tensor dict of :class:`ClipDataset` for already transformed ``frames``."""
    t = np.stack([f.t for f in frames])
    q = np.stack([f.q for f in frames])
    rel_t, rel_q = np.zeros_like(t), np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (len(frames), 1))
    if len(frames) > 1:
        rel_t[1:], rel_q[1:] = geometry.relative_pose(t[:-1], q[:-1], t[1:], q[1:])
    h, w = frames[0].image.shape[:2]
    for f in frames:
        if f.image.shape[:2] != (h, w):
            raise ValueError(f"frames of a clip differ in size ({f.frame_id}: {f.image.shape[:2]} vs {(h, w)}); use a transform with a fixed size")
    depth = np.stack([f.depth if f.depth is not None else np.zeros((h, w), np.float32) for f in frames])
    labels = np.stack([f.labels if f.labels is not None else np.full((h, w), IGNORE_INDEX, np.uint8) for f in frames])
    image = torch.from_numpy(np.ascontiguousarray(np.stack([f.image for f in frames]).transpose(0, 3, 1, 2))).float().div_(255.0)
    return {
        "image": image,
        "t": torch.from_numpy(t).float(),
        "q": torch.from_numpy(q).float(),
        "rel_t": torch.from_numpy(rel_t).float(),
        "rel_q": torch.from_numpy(rel_q).float(),
        "depth": torch.from_numpy(depth)[:, None].float(),
        "labels": torch.from_numpy(labels).long(),
        "K": torch.from_numpy(np.stack([f.intrinsics.matrix() for f in frames])).float(),
        "stamp": torch.tensor([f.stamp for f in frames], dtype=torch.float64),
        "sequence": torch.tensor(frames[0].sequence, dtype=torch.int64),
        "has_depth": torch.tensor(all(f.depth is not None for f in frames)),
        "has_labels": torch.tensor(all(f.labels is not None for f in frames)),
        "index": torch.tensor(indices, dtype=torch.int64),
    }

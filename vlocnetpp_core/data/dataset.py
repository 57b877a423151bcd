"""``ClipDataset``: clips of consecutive frames as tensors, and ``open_dataset`` (format detection)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.classes import IGNORE_INDEX
from vlocnetpp_core.data.formats import FORMATS
from vlocnetpp_core.data.sample import DatasetIndex, Frame, mirror_pose
from vlocnetpp_core.errors import DataError, UserError


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
        p,
        "unknown dataset layout: expected DeepLoc/{train,test}/LeftImages/ "
        "(DeepLoc) or TrainSplit.txt + seq-XX/ (7-Scenes)",
    )


def available_splits(path: str | Path, format: str) -> list[str]:
    """The splits (``train``, ``test``) present in the dataset at ``path`` of ``format``."""
    if format == "deeploc":
        from vlocnetpp_core.data.deeploc import find_deeploc_root

        deeploc_dir, _ = find_deeploc_root(path)
        return [s for s in ("train", "test") if (deeploc_dir / s).is_dir()]
    from vlocnetpp_core.data.sevenscenes import SPLIT_FILES

    return [s for s, f in SPLIT_FILES.items() if (Path(path) / f).is_file()]


def open_dataset(
    path: str | Path,
    format: str | None = None,
    split: str = "train",
    intrinsics: Intrinsics | str | None = None,
    **options,
) -> DatasetIndex:
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
    decoding those files and leave the ``depth`` / ``labels`` keys out (what the pose stages load: a batch
    of 16 clips of two 224x128 frames saves collating 11 MB of zeros).
    """

    def __init__(
        self,
        index: DatasetIndex,
        clip_len: int = 1,
        transform=None,
        stride: int = 1,
        depth: bool = True,
        labels: bool = True,
    ):
        if clip_len < 1 or stride < 1:
            raise ValueError(f"clip_len and stride must be >= 1, got {clip_len}, {stride}")
        self.index = index
        self.load_depth, self.load_labels = depth, labels
        self.clip_len = clip_len
        self.stride = stride
        self.transform = transform
        span = (clip_len - 1) * stride
        self.starts = [s for seq in index.sequences for s in range(seq.start, seq.stop - span)]
        self.rel_t, self.rel_q = self._relative_poses()

    def _relative_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """``rel_t (N, T, 3)``, ``rel_q (N, T, 4)`` of every clip (identity for frame 0) from the records' poses, in
        one vectorised call: computed per clip, in the training loop, they took a third of a pose stage's data time."""
        n, T = len(self.starts), self.clip_len
        rel_t, rel_q = np.zeros((n, T, 3)), np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (n, T, 1))
        if n and T > 1:
            t = np.array([r.t for r in self.index.records], dtype=np.float64)
            q = np.array([r.q for r in self.index.records], dtype=np.float64)
            idx = np.asarray(self.starts)[:, None] + self.stride * np.arange(T)[None, :]
            rel_t[:, 1:], rel_q[:, 1:] = geometry.relative_pose(
                t[idx[:, :-1]], q[idx[:, :-1]], t[idx[:, 1:]], q[idx[:, 1:]]
            )
        return rel_t, rel_q

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
        return clip_to_tensors(
            self.load_clip(i, rng),
            self.clip_indices(i),
            (self.rel_t[i], self.rel_q[i]),
            self.load_depth,
            self.load_labels,
        )


def clip_to_tensors(
    frames: list[Frame], indices: list[int], rel: tuple[np.ndarray, np.ndarray], depth: bool = True, labels: bool = True
) -> dict[str, torch.Tensor]:
    """The tensor dict of :class:`ClipDataset` for already transformed ``frames`` and their relative poses ``rel``
    (``rel_t (T, 3)``, ``rel_q (T, 4)``: :meth:`ClipDataset._relative_poses`, mirrored here with mirrored frames);
    ``depth`` / ``labels``: with those keys."""
    t = np.stack([f.t for f in frames])
    q = np.stack([f.q for f in frames])
    rel_t, rel_q = mirror_pose(*rel) if frames[0].mirrored else rel
    h, w = frames[0].image.shape[:2]
    for f in frames:
        if f.image.shape[:2] != (h, w):
            raise ValueError(
                f"frames of a clip differ in size ({f.frame_id}: "
                f"{f.image.shape[:2]} vs {(h, w)}); use a transform with a fixed size"
            )
    dense = {}
    if depth:
        dense["depth"] = torch.from_numpy(
            np.stack([f.depth if f.depth is not None else np.zeros((h, w), np.float32) for f in frames])
        )[:, None].float()
    if labels:
        dense["labels"] = torch.from_numpy(
            np.stack([f.labels if f.labels is not None else np.full((h, w), IGNORE_INDEX, np.uint8) for f in frames])
        ).long()
    # (T, H, W, 3) uint8 -> (T, 3, H, W) float in [0, 1]: transposed and converted in one copy
    image = (
        torch.empty(len(frames), 3, h, w)
        .copy_(torch.from_numpy(np.stack([f.image for f in frames])).permute(0, 3, 1, 2))
        .div_(255.0)
    )
    return {
        "image": image,
        "t": torch.from_numpy(t).float(),
        "q": torch.from_numpy(q).float(),
        "rel_t": torch.from_numpy(rel_t).float(),
        "rel_q": torch.from_numpy(rel_q).float(),
        **dense,
        "K": torch.from_numpy(np.stack([f.intrinsics.matrix() for f in frames])).float(),
        "stamp": torch.tensor([f.stamp for f in frames], dtype=torch.float64),
        "sequence": torch.tensor(frames[0].sequence, dtype=torch.int64),
        "has_depth": torch.tensor(all(f.depth is not None for f in frames)),
        "has_labels": torch.tensor(all(f.labels is not None for f in frames)),
        "index": torch.tensor(indices, dtype=torch.int64),
    }

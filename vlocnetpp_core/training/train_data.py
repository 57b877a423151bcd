"""Training data: the clips of a dataset at several frame strides, and a resumable, rank-aware sample order."""

from __future__ import annotations

import hashlib
import math

import torch


class EpochSampler(torch.utils.data.Sampler):
    """Yields ``(clip index, sample seed)`` in a per-epoch permutation, this rank's share only.

    The order and the augmentation seed of every sample are a pure function of
    ``(seed, epoch, position)``, so a run resumed at any step sees exactly the samples (and the
    augmentations) an uninterrupted run would, whatever the number of loader workers.
    """

    def __init__(self, n: int, batch_size: int, seed: int, rank: int = 0, world: int = 1):
        self.n, self.batch_size, self.seed, self.rank, self.world = n, batch_size, seed, rank, world
        self.per_rank = batch_size // world
        self.batches_per_epoch = max(1, n // batch_size)
        self.epoch = 0
        self.skip_batches = 0

    def set_position(self, epoch: int, skip_batches: int) -> None:
        self.epoch, self.skip_batches = epoch, skip_batches

    def __iter__(self):
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        perm = torch.randperm(self.n, generator=g).tolist()
        if len(perm) < self.batch_size:  # tiny datasets: repeat to fill one batch
            perm = (perm * math.ceil(self.batch_size / max(1, len(perm))))[: self.batch_size]
        for b in range(self.skip_batches, self.batches_per_epoch):
            batch = perm[b * self.batch_size : (b + 1) * self.batch_size]
            for k in range(self.rank * self.per_rank, (self.rank + 1) * self.per_rank):
                yield batch[k], _sample_seed(self.seed, self.epoch, b * self.batch_size + k)

    def __len__(self) -> int:
        return (self.batches_per_epoch - self.skip_batches) * self.per_rank


def _sample_seed(*parts: int) -> int:
    return int.from_bytes(hashlib.blake2b(repr(parts).encode(), digest_size=8).digest(), "little") >> 2


def training_clips(
    index,
    clip_len: int,
    transform,
    strides: tuple[int, ...] = (1,),
    seg: bool = True,
    cache_size: tuple[int, int] | None = None,
    log=print,
) -> torch.utils.data.ConcatDataset:
    """The ``ClipDataset`` of ``index`` at each frame stride, pooled (item ``i`` as in ``ClipDataset``);
    depth and labels are decoded only when the run trains segmentation (``seg``).

    Stride ``s`` shows the network every ``s``-th frame: ``s`` times the motion between the frames
    it fuses, as from a faster robot or a slower camera. Odometry trained at one stride learns the
    training speed rather than the motion (docs/training.md).

    ``cache_size (W, H)``: decode every frame once into a :class:`FrameCache` at that size (the
    largest the transform resizes to) when it takes at most ``MAX_MEMORY_SHARE`` of the available
    memory; otherwise (or with None) frames are decoded per clip.
    """
    from vlocnetpp_core.data import ClipDataset
    from vlocnetpp_core.data.frame_cache import MAX_MEMORY_SHARE, FrameCache, available_memory, cache_bytes

    if cache_size is not None:
        need, free = (
            cache_bytes(len(index), cache_size, seg and index.has_depth, seg and index.has_labels),
            available_memory(),
        )
        if need <= MAX_MEMORY_SHARE * free:
            log(
                f"decoding {len(index)} training frames into memory at "
                f"{cache_size[0]}x{cache_size[1]} ({need / 2**20:.0f} MiB)"
            )
            index = FrameCache(index, cache_size, depth=seg, labels=seg)
        else:
            log(
                "training frames decoded per clip: "
                f"caching them would take {need / 2**30:.1f} GiB of {free / 2**30:.1f} GiB available"
            )
    return torch.utils.data.ConcatDataset(
        [ClipDataset(index, clip_len, transform, stride=s, depth=seg, labels=seg) for s in strides]
    )


class SeededClips(torch.utils.data.Dataset):
    """``ClipDataset`` indexed by ``(i, seed)``: the augmentation of a sample depends on its seed only."""

    def __init__(self, clips):
        self.clips = clips

    def __len__(self) -> int:
        return len(self.clips)

    def __getitem__(self, item):
        i, seed = item
        # the CPU generator, which the augmentation draws from: torch.manual_seed would also reseed every CUDA generator
        torch.random.default_generator.manual_seed(seed)
        return self.clips[i]


def split_validation(index):
    """Hold out the last sequence of a training split for validation (when it has at least 3)."""
    from dataclasses import replace

    if len(index.sequences) < 3:
        return index, None
    last = index.sequences[-1]
    train = replace(index, records=index.records[: last.start], sequences=index.sequences[:-1])
    val = replace(index, records=index.records[last.start :], sequences=[range(0, len(last))])
    return train, val

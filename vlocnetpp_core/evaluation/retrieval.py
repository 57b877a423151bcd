"""Nearest-neighbour image retrieval: the baseline every pose regressor must beat.

For each query image the pose of the most similar reference (training) image is returned. An
image is described by its gradient thumbnail: the grey image resized to ``64 x 36`` (area
filter), Sobel x and y, averaged over ``4 x 4`` pixel cells (``16 x 9`` cells, two channels:
288 numbers), L2-normalised. The mean descriptor of the reference set is removed (what every
image of the place shares says nothing about where it was taken) and both sides are
normalised again; similarity is the cosine. No learning, no ROS: a few milliseconds per image.

A regressor that is not better than this, on the same frames, has learned less than a lookup
table of its training images (docs/conventions.md, Metrics: Retrieval baseline).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

THUMBNAIL_SIZE = (64, 36)  # width, height
CELL = 4  # pixels per cell side: 16 x 9 cells


def describe(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3) uint8`` RGB (or ``(H, W)`` grey) -> ``(288,) float32`` unit gradient-thumbnail descriptor."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    grey = cv2.resize(image, THUMBNAIL_SIZE, interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    w, h = THUMBNAIL_SIZE
    cells = []
    for dx, dy in ((1, 0), (0, 1)):
        g = cv2.Sobel(grey, cv2.CV_32F, dx, dy, ksize=3)
        cells.append(g.reshape(h // CELL, CELL, w // CELL, CELL).mean(axis=(1, 3)))
    d = np.stack(cells).ravel()
    return d / max(float(np.linalg.norm(d)), 1e-12)


def _normalise_rows(d: np.ndarray) -> np.ndarray:
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


@dataclass
class ReferenceSet:
    """Reference images as descriptors with their poses: ``descriptors (N, D)`` (raw, unit rows),
    ``t (N, 3)`` metres and ``q (N, 4)`` ``(w, x, y, z)`` camera-to-world."""

    descriptors: np.ndarray
    t: np.ndarray
    q: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        if len(self.descriptors) == 0:
            raise ValueError(f"reference set {self.source!r} has no images")
        self._mean = self.descriptors.mean(axis=0)
        self._centred = _normalise_rows(self.descriptors - self._mean).astype(np.float32)

    def __len__(self) -> int:
        return len(self.descriptors)

    def nearest(self, queries: np.ndarray) -> np.ndarray:
        """``queries (M, D)`` raw descriptors -> ``(M,)`` index of the most similar reference image."""
        q = _normalise_rows(np.atleast_2d(queries) - self._mean).astype(np.float32)
        return np.argmax(q @ self._centred.T, axis=1)

    def ranked(self, query: np.ndarray, count: int) -> np.ndarray:
        """``query (D,)`` raw descriptor -> the indices ``(count,)`` of the most similar reference images, most similar
        first."""
        q = _normalise_rows(np.atleast_2d(query) - self._mean).astype(np.float32)[0]
        similarity = self._centred @ q
        top = np.argpartition(-similarity, count - 1)[:count] if count < len(similarity) else np.arange(len(similarity))
        return top[np.argsort(-similarity[top], kind="stable")]

    def poses(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The poses ``(M, 3)``, ``(M, 4)`` of the nearest reference images of ``queries (M, D)``."""
        k = self.nearest(queries)
        return self.t[k], self.q[k]

    def save(self, path: str | Path) -> Path:
        """Write ``descriptors`` (float16), ``t``, ``q`` and ``source`` to an ``.npz``, atomically."""
        import os

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp.npz")
        np.savez_compressed(
            tmp, descriptors=self.descriptors.astype(np.float16), t=self.t, q=self.q, source=np.array(self.source)
        )
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> ReferenceSet:
        """Read what :meth:`save` wrote (no pickle); ``DataError`` naming the file when it is not such a file."""
        from vlocnetpp_core.errors import DataError

        try:
            with np.load(path, allow_pickle=False) as f:
                d, t, q, source = f["descriptors"].astype(np.float32), f["t"], f["q"], str(f["source"])
        except (OSError, ValueError, KeyError) as err:
            raise DataError(path, f"not a retrieval reference file ({err})") from None
        if d.ndim != 2 or t.shape != (len(d), 3) or q.shape != (len(d), 4) or len(d) == 0:
            raise DataError(path, f"inconsistent retrieval reference: descriptors {d.shape}, t {t.shape}, q {q.shape}")
        return cls(d, t, q, source)

    @classmethod
    def from_images(cls, images: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], source: str = "") -> ReferenceSet:
        """From ``(image, t, q)`` triples."""
        d, t, q = [], [], []
        for image, ti, qi in images:
            d.append(describe(image))
            t.append(ti)
            q.append(qi)
        if not d:
            raise ValueError(f"reference set {source!r} has no images")
        return cls(np.stack(d), np.asarray(t, np.float64), np.asarray(q, np.float64), source)

    @classmethod
    def concat(cls, sets: Sequence[ReferenceSet], source: str = "") -> ReferenceSet:
        """One reference holding every image of ``sets`` (e.g. the training splits of several datasets)."""
        if not sets:
            raise ValueError(f"reference set {source!r} has no images")
        return cls(
            np.concatenate([r.descriptors for r in sets]),
            np.concatenate([r.t for r in sets]),
            np.concatenate([r.q for r in sets]),
            source or "; ".join(r.source for r in sets),
        )

    @classmethod
    def from_dataset(cls, index, progress: bool = False) -> ReferenceSet:
        """Every frame of a ``DatasetIndex`` (e.g. the training split the network learned from)."""
        from tqdm import tqdm

        frames = tqdm(
            range(len(index)), desc="retrieval reference", unit="frame", disable=not progress, dynamic_ncols=True
        )
        source = f"{index.root} ({index.split})"
        loaded = (index.load(i, depth=False, labels=False) for i in frames)  # the images alone
        return cls.from_images(((f.image, f.t, f.q) for f in loaded), source)


def reference_of(checkpoint: str | Path) -> Path:
    """Where the reference set of a checkpoint's training images lives: ``NAME.reference.npz`` beside
    ``NAME.safetensors``."""
    p = Path(checkpoint)
    return p.with_name(p.name.removesuffix(".safetensors") + ".reference.npz")


def open_reference(
    path: str | Path, format: str | None = None, split: str = "train", progress: bool = False
) -> ReferenceSet:
    """The reference set at ``path``: a file written by :meth:`ReferenceSet.save` (``.npz``), or a dataset
    folder, whose ``split`` (default the training images) is described."""
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.errors import UserError

    if Path(path).is_file():
        return ReferenceSet.load(path)
    index = open_dataset(path, format, split)
    if len(index) == 0:
        raise UserError(f"{path}: split {split!r} has no frames to use as the retrieval reference")
    return ReferenceSet.from_dataset(index, progress)


def retrieval_results(reference: ReferenceSet, results: Sequence, descriptors: Sequence[np.ndarray]) -> list:
    """The baseline on the frames of ``results`` (``SequenceResult``s of a localizer): the same
    sequences, stamps and ground truth, with the retrieved poses as the prediction and no odometry,
    segmentation or timing. ``descriptors[k] (N_k, D)`` describe the frames of ``results[k]``."""
    from dataclasses import replace

    out = []
    for r, d in zip(results, descriptors, strict=True):
        if len(d) != len(r.stamps):
            raise ValueError(f"{r.name}: {len(d)} descriptors for {len(r.stamps)} frames")
        t, q = reference.poses(d)
        out.append(replace(r, pred_t=t, pred_q=q, rel_t=None, rel_q=None, confusion=None, ms=None, samples=()))
    return out

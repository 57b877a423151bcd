"""Clip transforms: resize, crops, photometric jitter and (segmentation-only) horizontal flip.

A transform maps a clip (a list of :class:`Frame`) and a ``numpy.random.Generator`` to a new
clip. Random parameters are drawn once per clip, so every frame of a clip gets the same crop,
scale, jitter and flip (temporal fusion and warping need consistent frames). Every geometric
transform updates the intrinsics, so projecting a 3D point with the new ``Frame.intrinsics``
lands on the same image content. Resizing follows the localizer's rules (``preprocess.resize_image``:
area when shrinking, else linear; depth and labels with exact pixel-centre nearest neighbour, so
valid and invalid depth are never blended), so evaluation and the node see the same pixels.

Horizontal flip: a mirrored image has no rigid camera pose in the real world. :class:`HorizontalFlip`
mirrors the world too (poses conjugated by ``M = diag(-1, 1, 1)``), which keeps relative poses,
depth and intrinsics consistent (warping stays exact) but places the camera in a mirrored map, so
global-pose targets become wrong. Only use it for training that reads no global pose (``make_transform(...,
flip=True)``): the trainer mirrors the clips of ``stl-vo`` (relative poses, mirrored with the frames, stay exact).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import cv2
import numpy as np

from vlocnetpp_core.data.sample import Frame, mirror_pose
from vlocnetpp_core.inference.preprocess import resize_image, resize_nearest

Clip = list[Frame]

GREY_WEIGHTS = np.array([0.299, 0.587, 0.114])  # RGB -> grey (ITU-R BT.601 luma)


def resize_frame(frame: Frame, width: int, height: int) -> Frame:
    """Resize to ``width x height`` (aspect may change; intrinsics follow) with the localizer's rules
    (:func:`vlocnetpp_core.inference.preprocess.resize_image`,
    :func:`~vlocnetpp_core.inference.preprocess.resize_nearest`)."""
    h, w = frame.image.shape[:2]
    if (w, h) == (width, height):
        return frame
    size = (width, height)
    return dataclasses.replace(
        frame,
        image=resize_image(frame.image, size),
        depth=None if frame.depth is None else resize_nearest(frame.depth, size),
        labels=None if frame.labels is None else resize_nearest(frame.labels, size),
        intrinsics=frame.intrinsics.resized(width, height),
    )


def crop_frame(frame: Frame, x0: int, y0: int, width: int, height: int) -> Frame:
    """The ``width x height`` window whose top-left pixel is ``(x0, y0)``."""
    h, w = frame.image.shape[:2]
    if x0 < 0 or y0 < 0 or x0 + width > w or y0 + height > h:
        raise ValueError(f"crop {width}x{height} at ({x0}, {y0}) does not fit a {w}x{h} image")
    win = (slice(y0, y0 + height), slice(x0, x0 + width))
    return dataclasses.replace(
        frame,
        image=np.ascontiguousarray(frame.image[win]),
        depth=None if frame.depth is None else np.ascontiguousarray(frame.depth[win]),
        labels=None if frame.labels is None else np.ascontiguousarray(frame.labels[win]),
        intrinsics=frame.intrinsics.cropped(x0, y0, width, height),
    )


def flip_frame(frame: Frame) -> Frame:
    """Mirror left-right; the pose is conjugated by ``diag(-1, 1, 1)`` (a mirrored world, see module doc)."""
    t, q = mirror_pose(frame.t, frame.q)
    return dataclasses.replace(
        frame,
        image=np.ascontiguousarray(frame.image[:, ::-1]),
        depth=None if frame.depth is None else np.ascontiguousarray(frame.depth[:, ::-1]),
        labels=None if frame.labels is None else np.ascontiguousarray(frame.labels[:, ::-1]),
        intrinsics=frame.intrinsics.flipped_horizontally(),
        t=t,
        q=q,
        mirrored=not frame.mirrored,
    )


class Compose:
    """Apply transforms in order."""

    def __init__(self, transforms: Sequence):
        self.transforms = list(transforms)

    def __call__(self, clip: Clip, rng: np.random.Generator) -> Clip:
        for t in self.transforms:
            clip = t(clip, rng)
        return clip

    def __repr__(self) -> str:
        return f"Compose({self.transforms})"


def draw_scale(scale: tuple[float, float], rng: np.random.Generator) -> float:
    """A factor drawn uniformly from ``scale = (lo, hi)``; ``lo`` without a draw when the range is empty."""
    return float(rng.uniform(*scale)) if scale[1] > scale[0] else scale[0]


@dataclasses.dataclass
class Resize:
    """Resize to exactly ``size (W, H)`` (the aspect follows ``size``), times a random factor in ``scale``."""

    size: tuple[int, int]
    scale: tuple[float, float] = (1.0, 1.0)

    def __call__(self, clip: Clip, rng: np.random.Generator) -> Clip:
        s = draw_scale(self.scale, rng)
        w, h = (max(self.size[0], round(self.size[0] * s)), max(self.size[1], round(self.size[1] * s)))
        return [resize_frame(f, w, h) for f in clip]


@dataclasses.dataclass
class RandomCrop:
    """A ``size (W, H)`` window at a random position, the same for every frame of the clip (training)."""

    size: tuple[int, int]

    def __call__(self, clip: Clip, rng: np.random.Generator) -> Clip:
        h, w = clip[0].image.shape[:2]
        if w < self.size[0] or h < self.size[1]:
            raise ValueError(f"cannot crop {self.size[0]}x{self.size[1]} from a {w}x{h} image")
        x0 = int(rng.integers(0, w - self.size[0] + 1))
        y0 = int(rng.integers(0, h - self.size[1] + 1))
        return [crop_frame(f, x0, y0, *self.size) for f in clip]


@dataclasses.dataclass
class ColorJitter:
    """Random brightness, contrast and saturation factors in ``[1 - a, 1 + a]`` (one draw per clip)."""

    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2

    def __call__(self, clip: Clip, rng: np.random.Generator) -> Clip:
        b, c, s = (float(rng.uniform(1 - a, 1 + a)) for a in (self.brightness, self.contrast, self.saturation))
        return [dataclasses.replace(f, image=jitter_image(f.image, b, c, s)) for f in clip]


def jitter_image(image: np.ndarray, brightness: float, contrast: float, saturation: float) -> np.ndarray:
    """``(H, W, 3) uint8`` RGB scaled in brightness, then contrast about the mean grey, then saturation
    about each pixel's grey (rounded, saturated to 0..255).

    The three steps compose to one affine colour map (the grey weights sum to 1), applied in one pass:
    ``out = c b S img + (1 - c) b mean_grey``, with ``S = s I + (1 - s) 1 w^T`` and ``w`` the grey weights.
    """
    mean_grey = brightness * float(GREY_WEIGHTS @ np.asarray(cv2.mean(image)[:3]))
    colour = saturation * np.eye(3) + (1.0 - saturation) * np.outer(np.ones(3), GREY_WEIGHTS)
    affine = np.hstack([contrast * brightness * colour, np.full((3, 1), (1.0 - contrast) * mean_grey)])
    return cv2.transform(image, affine)


@dataclasses.dataclass
class HorizontalFlip:
    """Mirror the whole clip with probability ``p``. Segmentation-only training (see module doc)."""

    p: float = 0.5

    def __call__(self, clip: Clip, rng: np.random.Generator) -> Clip:
        return [flip_frame(f) for f in clip] if rng.random() < self.p else clip


def make_transform(
    train: bool,
    size: tuple[int, int],
    scale: tuple[float, float] = (1.0, 1.15),
    brightness: float = 0.2,
    contrast: float = 0.2,
    saturation: float = 0.2,
    flip: bool = False,
) -> Compose:
    """The standard pipeline to network input ``size (W, H)``.

    Test: resize the whole image to ``size`` (what the ``Localizer`` does with camera frames, so
    evaluation, bag replay and the node see the same pixels; the aspect follows ``size``, which
    for 16:9 cameras and the 16:9-ish input sizes of the configs is a distortion of a few percent
    that the intrinsics absorb). Train: resize to ``size`` times a random factor in ``scale``,
    random crop (the paper's random-crop training; ``scale=(1, 1)``: none, the whole image as at
    test time), photometric jitter, and a horizontal flip of half the clips when ``flip`` (training
    that reads no global pose: it breaks global poses).
    """
    size = (int(size[0]), int(size[1]))
    if not train:
        return Compose([Resize(size)])
    if not (1.0 <= scale[0] <= scale[1]) or not math.isfinite(scale[1]):
        raise ValueError(f"scale must be a range (lo, hi) with 1 <= lo <= hi, got {scale}")
    geometric = [Resize(size, scale), RandomCrop(size)] if scale[1] > 1.0 else [Resize(size)]
    ts = [*geometric, ColorJitter(brightness, contrast, saturation)]
    if flip:
        ts.append(HorizontalFlip(0.5))
    return Compose(ts)

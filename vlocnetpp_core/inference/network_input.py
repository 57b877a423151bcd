"""The network's input tensors of a camera frame (:func:`network_input`), from :mod:`.preprocess`'s arrays.

The image is resized to the network input size ``(W, H)`` of the checkpoint, anisotropically when the
aspect ratios differ (no crop, so every pixel of the camera image has a class id after the mask is brought
back), with the intrinsics following through :meth:`Intrinsics.resized`. Depth is resized with exact
nearest neighbour so that invalid (0) pixels never blend into valid ones.
"""

from __future__ import annotations

import numpy as np
import torch

from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.inference.preprocess import FrameError, resize_image, resize_nearest


def image_tensor(rgb: np.ndarray) -> torch.Tensor:
    """``(H, W, 3) uint8`` -> ``(1, 3, H, W) float32`` in ``[0, 1]`` (the model's input format)."""
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float().div_(255.0)


def network_input(
    rgb: np.ndarray, size: tuple[int, int], intrinsics: Intrinsics, depth: np.ndarray | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Everything one model step needs, at the network input ``size = (W, H)``.

    Args:
        rgb: ``(H0, W0, 3) uint8`` camera image.
        intrinsics: of the camera image (any resolution with the same field of view: it is scaled).
        depth: ``(H0, W0) float32`` metres aligned with ``rgb`` (0 = invalid), or None.

    Returns:
        ``image (1, 3, H, W)`` in ``[0, 1]``, ``K (1, 3, 3)`` float32 at ``W x H``,
        ``depth (1, 1, H, W)`` metres or None.
    """
    if depth is not None and depth.shape[:2] != rgb.shape[:2]:
        raise FrameError(
            "depth_size",
            f"depth image is {depth.shape[1]}x{depth.shape[0]} but the colour image is {rgb.shape[1]}x{rgb.shape[0]}",
        )
    image = image_tensor(resize_image(rgb, size))
    K = torch.from_numpy(intrinsics.resized(*size).matrix()).float()[None]
    d = None if depth is None else torch.from_numpy(np.ascontiguousarray(resize_nearest(depth, size)))[None, None]
    return image, K, d

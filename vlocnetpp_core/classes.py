"""The ten DeepLoc semantic classes, their ids and preview colours (RGB)."""

from __future__ import annotations

import numpy as np

CLASS_NAMES: tuple[str, ...] = (
    "Background",
    "Sky",
    "Road",
    "Sidewalk",
    "Grass",
    "Vegetation",
    "Building",
    "Poles & Fences",
    "Dynamic",
    "Other",
)
NUM_CLASSES = len(CLASS_NAMES)

# Label value meaning "no label here"; losses and metrics skip it.
IGNORE_INDEX = 255

CLASS_COLORS: np.ndarray = np.array(
    [
        (0, 0, 0),  # Background
        (70, 130, 180),  # Sky
        (128, 64, 128),  # Road
        (244, 35, 232),  # Sidewalk
        (152, 251, 152),  # Grass
        (107, 142, 35),  # Vegetation
        (70, 70, 70),  # Building
        (153, 153, 153),  # Poles & Fences
        (220, 20, 60),  # Dynamic
        (250, 170, 30),  # Other
    ],
    dtype=np.uint8,
)


def colorize(labels: np.ndarray) -> np.ndarray:
    """``(H, W)`` class ids -> ``(H, W, 3)`` uint8 RGB preview; ids outside 0..9 are white."""
    lut = np.full((256, 3), 255, dtype=np.uint8)
    lut[:NUM_CLASSES] = CLASS_COLORS
    return lut[labels.astype(np.uint8)]

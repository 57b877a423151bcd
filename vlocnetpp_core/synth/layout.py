"""The campus's fixed dimensions, the class ids of the synthetic scene and the sizes and colours of its moving
things."""

from __future__ import annotations

from vlocnetpp_core.classes import CLASS_NAMES

# class ids, in the order of vlocnetpp_core.classes.CLASS_NAMES
BACKGROUND, SKY, ROAD, SIDEWALK, GRASS, VEGETATION, BUILDING, POLE, DYNAMIC, OTHER = range(10)
assert CLASS_NAMES[BUILDING] == "Building" and CLASS_NAMES[OTHER] == "Other" and len(CLASS_NAMES) == 10

WIDTH_M, DEPTH_M = 100.0, 120.0  # campus extent (x, y)
ROAD_HALF = 3.0  # road half-width
SIDEWALK_EDGE = 5.5  # outer edge of a sidewalk from the road centreline
LANES = {"right lane": 1.5, "left lane": -1.5, "right sidewalk": 4.25, "left sidewalk": -4.25}
HILLS_RADIUS = 320.0
HILLS_MAX_M = 38.0

CAR_SIZE = (4.4, 1.8, 1.5)  # length, width, height
PERSON_SIZE = (0.5, 0.34, 1.75)
CAR_PAINTS = (0xB03A2E, 0x1F4E79, 0xD5D8DC, 0x1C1C1C, 0x7D8C2F, 0xE3B23C, 0x6C3483, 0x5D6D7E)
SHIRTS = (0xC0392B, 0x2471A3, 0x27AE60, 0xF4D03F, 0x6E2C00, 0xECF0F1, 0x17202A, 0xAF7AC5)

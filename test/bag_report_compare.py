"""Comparing two metric reports of ``evaluate_sequences`` (the bag tests' oracle), leaf by leaf."""

from __future__ import annotations

import pytest

SCORED_PARTS = ("pose", "odometry", "segmentation")  # a bag holds no step times, so "timing" is left out


def assert_same_metrics(want: dict, got: dict, rel: float = 1e-9) -> None:
    """``got`` equals ``want`` in every pose, odometry and segmentation number, per sequence and overall."""
    assert got["per_sequence"].keys() == want["per_sequence"].keys()
    pairs = [("overall", want["overall"], got["overall"])]
    pairs += [(name, part, got["per_sequence"][name]) for name, part in want["per_sequence"].items()]
    for name, w, g in pairs:
        for key in SCORED_PARTS:
            _leaf_equal(w[key], g[key], f"{name}/{key}", rel)


def _leaf_equal(w, g, path: str, rel: float) -> None:
    if isinstance(w, dict):
        assert isinstance(g, dict) and w.keys() == g.keys(), path
        for k in w:
            _leaf_equal(w[k], g[k], f"{path}/{k}", rel)
    elif isinstance(w, list):
        assert isinstance(g, list) and len(w) == len(g), path
        for i, (u, v) in enumerate(zip(w, g, strict=True)):
            _leaf_equal(u, v, f"{path}[{i}]", rel)
    elif isinstance(w, float):
        assert g == pytest.approx(w, rel=rel, abs=1e-12), path
    else:
        assert g == w, path

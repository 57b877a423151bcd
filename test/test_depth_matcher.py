"""The depth images matched to colour frames by stamp (vlocnetpp_ros/depth_matcher.py), with real sensor_msgs."""

from __future__ import annotations

import threading
import time

import numpy as np
from std_msgs.msg import Header

from vlocnetpp_ros import conversions, depth_matcher
from vlocnetpp_ros.depth_matcher import DepthMatcher


def _depth(stamp_s: float, metres: float = 4.0):
    header = Header(stamp=conversions.seconds_to_stamp(stamp_s), frame_id="camera")
    return conversions.array_to_image(np.full((6, 8), metres, np.float32), "32FC1", header)


def test_a_depth_image_arriving_while_the_frame_waits_is_used(monkeypatch):
    monkeypatch.setattr(depth_matcher, "DEPTH_WAIT_S", 10.0)
    ignored = []
    matcher = DepthMatcher(ignored.append)
    later = threading.Timer(0.05, matcher.add, (_depth(1.0, 2.5),))
    later.start()
    depth = matcher.matching(conversions.seconds_to_stamp(1.0))
    later.join()
    assert depth is not None and depth.shape == (6, 8) and np.all(depth == 2.5) and ignored == []


def test_a_frame_stops_waiting_once_a_later_depth_image_is_there(monkeypatch):
    """Depth images come in stamp order: once a later one arrived, the frame's own will not; it takes the predicted
    depth at once instead of waiting DEPTH_WAIT_S (set to 30 s here: a wait would show as a slow test)."""
    monkeypatch.setattr(depth_matcher, "DEPTH_WAIT_S", 30.0)
    ignored = []
    matcher = DepthMatcher(ignored.append)
    matcher.add(_depth(1.0))
    matcher.add(_depth(1.2))
    start = time.monotonic()
    assert matcher.matching(conversions.seconds_to_stamp(1.1)) is None
    assert time.monotonic() - start < 20.0
    assert [err.reason for err in ignored] == ["depth_missing"]
    assert matcher.matching(conversions.seconds_to_stamp(1.0)) is not None  # an earlier one kept is still found


def test_without_a_later_depth_image_the_frame_waits_then_uses_the_predicted_depth(monkeypatch):
    wait_s = 0.05
    monkeypatch.setattr(depth_matcher, "DEPTH_WAIT_S", wait_s)
    ignored = []
    matcher = DepthMatcher(ignored.append)
    matcher.add(_depth(1.0))
    start = time.monotonic()
    assert matcher.matching(conversions.seconds_to_stamp(1.1)) is None
    assert time.monotonic() - start >= wait_s * 0.9 and [err.reason for err in ignored] == ["depth_missing"]

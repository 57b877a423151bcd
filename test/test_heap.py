"""The node's heap figures (vlocnetpp_ros.heap) follow what this process allocates and frees."""

import numpy as np
import pytest

from vlocnetpp_ros.heap import Heap


def test_heap_in_use_follows_an_allocation_and_its_release():
    heap = Heap()
    if heap.in_use_mb() is None:
        pytest.skip("no glibc mallinfo2 here")
    before = heap.in_use_mb()
    block = np.ones(64 * 1024 * 1024, np.uint8)  # 64 MiB through malloc (numpy's data buffer), every page touched
    held = heap.in_use_mb()
    del block
    heap.trim()
    after = heap.in_use_mb()
    assert 63.0 < held - before < 66.0, (before, held)
    assert abs(after - before) < 2.0, (before, after)

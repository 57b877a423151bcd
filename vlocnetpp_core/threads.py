"""One meaning of a CPU thread count everywhere: the node's ``num_threads``, ``--threads`` of train, bench
and the benchmarks, and the ONNX Runtime session.

``N >= 1``: N threads for the network. ``0``: all cores but one (at least 1), leaving a core to DDS and
the ROS executor (the node) or to data loading and the OS; on a loaded CPU, OpenMP threads that wait on
a descheduled sibling make every step several times slower (docs/performance.md). Torch's thread
count is process-wide, so it is set once, by the program's entry point (:func:`use_threads`), never
inside a library constructor. The same call puts OpenBLAS (numpy's and OpenCV's) on one thread
(:func:`single_threaded_blas`).
"""

from __future__ import annotations

import os


def resolve_threads(requested: int) -> int:
    """The thread count ``requested`` stands for: itself, or with 0 all cores but one (at least 1)."""
    if requested < 0:
        raise ValueError(f"threads must be >= 0 (0: all cores but one), got {requested}")
    return int(requested) or max(1, (os.cpu_count() or 1) - 1)


def use_threads(requested: int) -> int:
    """Set torch's (process-wide) CPU thread count to :func:`resolve_threads` of ``requested``; returns it."""
    import torch

    n = resolve_threads(requested)
    torch.set_num_threads(n)
    single_threaded_blas()
    return n


def single_threaded_blas() -> None:
    """Put the OpenBLAS libraries loaded in this process (numpy's, OpenCV's; torch uses MKL) on one thread.

    Their products here are small (PnP, keyframe search, retrieval), and OpenBLAS's worker threads spin-wait after
    each call: beside the network's thread they took a core from it (measured: docs/performance.md,
    ``node_refined_hz``)."""
    from threadpoolctl import ThreadpoolController

    ThreadpoolController().select(internal_api="openblas").limit(limits=1)

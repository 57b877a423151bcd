"""Interleaved wall-clock timing: every case once per round, so machine noise hits each side of a ratio alike."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch


def synchronizer(device: str | torch.device) -> Callable[[], None]:
    """What must run before reading the clock: ``torch.cuda.synchronize`` on a CUDA device (kernels are
    asynchronous), nothing on the CPU."""
    device = torch.device(device)
    if device.type == "cuda":
        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def interleaved(
    cases: dict[str, Callable[[], object]],
    repetitions: int,
    warmup: int = 1,
    sync: Callable[[], None] = lambda: None,
    after: Callable[[str], None] | None = None,
) -> dict[str, list[float]]:
    """Seconds of each call of each case.

    ``warmup`` untimed rounds first (allocations, lazy initialisation, caches), then
    ``repetitions`` rounds; each round calls every case once, starting with a different case
    each round (rotation), so no case always runs first or after the same neighbour.
    ``after(name)``, if given, runs untimed after every call (clean-up such as deleting an output).
    """
    names = list(cases)
    for _ in range(warmup):
        for name in names:
            cases[name]()
            if after is not None:
                after(name)
    sync()
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(repetitions):
        k = r % len(names)
        for name in names[k:] + names[:k]:
            start = time.perf_counter()
            cases[name]()
            sync()
            times[name].append(time.perf_counter() - start)
            if after is not None:
                after(name)
    return times


def median(values: list[float]) -> float:
    return float(statistics.median(values))

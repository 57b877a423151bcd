"""The refinement's figures of ``vlocnetpp bench``: what SIFT + PnP against the shipped keyframe map costs per frame,
and the node's rate with it.

Unlike the other figures these need trained weights (the network's pose selects the keyframes; an untrained one
selects none and refines nothing): the shipped model, and a keyframe map of the campus (setting ``refinement_map``:
a map file, or ``auto`` for ``NAME.map.npz`` beside the shipped model, which ``vlocnetpp map build`` makes:
docs/refinement.md). Without them the figures are None and a note says why.

* :func:`refined_steps`: ``Localizer.step`` of the shipped model without a map, refining every frame and every second
  frame, interleaved over the same consecutive camera frames (each on its own stream): ``refine_step_{none,every1,
  every2}`` seconds and the share of frames each refined.
* the node figures: :func:`vlocnetpp_core.bench.figures.node_latency` with the map, refining every frame and every
  second one: lockstep (one frame sent, its pose awaited) ``node_refined_latency_every{1,2}``, then fed at
  :data:`STREAM_HZ` as a camera feeds it, faster than it answers: ``node_refined_stream_every{1,2}``, seconds per pose
  published (the node's rate: its network runs on the next frame while the last one is refined).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vlocnetpp_core.bench.timing import interleaved, median
from vlocnetpp_core.errors import UserError

FRAME_INTERVAL_S = 0.05
EVERY = (1, 2)
STREAM_HZ = 30.0  # the camera rate of the node's rate figure: above what it answers


def shipped_model_and_map(map_setting: str = "auto") -> tuple[Path, Path]:
    """The shipped checkpoint and the keyframe map of ``map_setting``
    (:func:`~vlocnetpp_core.inference.checkpoint.resolve_map_path`); ``UserError`` saying which is missing."""
    from vlocnetpp_core.inference.checkpoint import resolve_map_path, shipped_checkpoint

    try:
        checkpoint = shipped_checkpoint()
    except FileNotFoundError as err:
        raise UserError(str(err)) from None
    missing: list[str] = []
    path = resolve_map_path(checkpoint, map_setting, "refinement_map", warn=missing.append)
    if path is None:
        raise UserError(missing[0] if missing else f"no keyframe map beside {checkpoint}")
    return checkpoint, path


def refined_steps(
    frames: list[np.ndarray], device: str, threads: int, repetitions: int, warmup: int, map_setting: str = "auto"
) -> dict:
    """Seconds per ``Localizer.step`` of the shipped model on consecutive ``frames`` (cycled) without refinement and
    refining every k-th frame (k in :data:`EVERY`), interleaved; and the share of frames each published refined."""
    from vlocnetpp_core.inference.localizer import Localizer

    checkpoint, map_path = shipped_model_and_map(map_setting)
    localizers = {"none": Localizer.from_checkpoint(checkpoint, device=device, num_threads=threads)}
    for k in EVERY:
        localizers[f"every{k}"] = Localizer.from_checkpoint(
            checkpoint, device=device, num_threads=threads, map_path=map_path, refine_every=k
        )
    counters = {name: 0 for name in localizers}
    sources: dict[str, list[str]] = {name: [] for name in localizers}

    def stepper(name: str):
        def step() -> None:
            k = counters[name]
            counters[name] += 1
            sources[name].append(localizers[name].step(frames[k % len(frames)], "rgb8", FRAME_INTERVAL_S * k).source)

        return step

    times = interleaved({name: stepper(name) for name in localizers}, repetitions, warmup)
    out = {f"refine_step_{name}": median(values) for name, values in times.items()}
    out.update(
        {
            f"refine_share_{name}": float(np.mean([s != "network" for s in sources[name]]))
            for name in localizers
            if name != "none"
        }
    )
    return out


def node_rates(
    frames: list[np.ndarray],
    workdir: Path,
    device: str,
    threads: int,
    backend: str,
    transport: str,
    repetitions: int,
    warmup: int,
    map_setting: str = "auto",
    stream_frames: int = 240,
) -> dict:
    """Seconds per frame through the node over DDS with the shipped model and map, refining every k-th frame: lockstep,
    and fed ``stream_frames`` at :data:`STREAM_HZ`."""
    from vlocnetpp_core.bench.figures import node_latency

    checkpoint, map_path = shipped_model_and_map(map_setting)
    out = {}
    for k in EVERY:
        node = node_latency(
            checkpoint,
            frames,
            workdir,
            device,
            threads,
            backend,
            transport,
            repetitions,
            warmup,
            map_path=map_path,
            refine_every=k,
            stream_hz=STREAM_HZ,
            stream_s=stream_frames / STREAM_HZ,
        )
        out[f"node_refined_latency_every{k}"] = node["node_latency"]
        out[f"node_refined_stream_every{k}"] = 1.0 / node["node_stream_hz"]
        out[f"node_refine_share_every{k}"] = node.get("node_refined_share")
    return out

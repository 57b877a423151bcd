"""The measurements behind ``vlocnetpp bench``; each returns absolute times (seconds, medians) and sizes.

Every function times its cases interleaved (:func:`~vlocnetpp_core.bench.timing.interleaved`) so
that the two sides of a ratio see the same machine noise.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from vlocnetpp_core.bench.timing import interleaved, median, synchronizer
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.programs import program_command


def synth_frames(
    count: int, size: tuple[int, int], scene: str = "campus", seed: int = 0
) -> tuple[list[np.ndarray], dict]:
    """``count`` consecutive frames (RGB uint8) of a 20 Hz test visit of the synthetic campus at ``size = (W, H)``.

    Returns the frames and ``{"synth_frame": s, "campus_build": s}``: the median render time of
    one frame (:func:`render_frame` only; building the campus is timed separately, once).
    """
    from vlocnetpp_core.synth import default_intrinsics, plan_visit, render_frame
    from vlocnetpp_core.synth.campus import load_campus

    start = time.perf_counter()
    campus = load_campus(scene)
    build = time.perf_counter() - start
    visit = plan_visit(campus, seed, "test", 0, count, frame_interval=0.05)
    K = default_intrinsics(*size)
    frames, times = [], []
    for i in range(count):
        start = time.perf_counter()
        rgb, _, _ = render_frame(campus, visit.t[i], visit.q[i], K, visit.lighting, visit.objects_at(i))
        times.append(time.perf_counter() - start)
        frames.append(rgb)
    return frames, {"synth_frame": median(times), "campus_build": build}


def lite_step(
    checkpoint: Path, frames: list[np.ndarray], device: str, threads: int, repetitions: int, warmup: int
) -> dict:
    """``Localizer.step`` (decode, resize, model step, mask) of the lite checkpoint on camera frames,
    torch and ONNX Runtime backends interleaved, each on its own stream of the same frames.

    The ONNX graph is exported next to the checkpoint first (``NAME.onnx``), so the onnx backend
    finds it. Where the onnx backend cannot run (no ``onnx`` / ``onnxruntime`` package, CUDA
    without onnxruntime-gpu), its entry is None and ``onnx_error`` says why.
    """
    from vlocnetpp_core.inference.localizer import Localizer
    from vlocnetpp_core.inference.onnx_export import export_checkpoint

    localizers = {"torch": Localizer.from_checkpoint(checkpoint, device=device, num_threads=threads)}
    result: dict = {"lite_step_onnx": None}
    try:
        start = time.perf_counter()
        export_checkpoint(checkpoint, checkpoint.with_suffix(".onnx"))
        result["onnx_export"] = time.perf_counter() - start
        localizers["onnx"] = Localizer.from_checkpoint(checkpoint, device=device, num_threads=threads, backend="onnx")
    except UserError as err:
        result["onnx_error"] = str(err)
    counters = {name: 0 for name in localizers}

    def stepper(name: str):
        def step() -> None:
            k = counters[name]
            counters[name] += 1
            localizers[name].step(frames[k % len(frames)], "rgb8", 0.05 * k)

        return step

    times = interleaved({name: stepper(name) for name in localizers}, repetitions, warmup, synchronizer(device))
    for name, values in times.items():
        result[f"lite_step_{name}"] = median(values)
    result["camera_size"] = [int(frames[0].shape[1]), int(frames[0].shape[0])]
    result["input_size"] = list(localizers["torch"].input_size)
    return result


def train_step(config: str, device: str, repetitions: int, warmup: int, batch: int = 16, clip_len: int = 2) -> dict:
    """One ``stl-loc`` training step of ``config`` (the recipe's longest stage: trunk frozen, ``batch`` clips of
    ``clip_len`` random frames at the input size, forward, loss and backward) with the network channels-last,
    as built, and the same network in NCHW, interleaved: ``train_step_nhwc`` / ``train_step_nchw``."""
    from vlocnetpp_core.model import VLocNetPP, load_model_config, train_only
    from vlocnetpp_core.model.stages import stage_tasks
    from vlocnetpp_core.training.losses import VLocNetLoss
    from vlocnetpp_core.training.validation import forward_stage

    cfg = load_model_config(config)
    (w, h), gen = cfg.input_size, torch.Generator().manual_seed(0)
    quats = torch.nn.functional.normalize(torch.randn(batch, clip_len, 4, generator=gen), dim=-1)
    clips = {
        "image": torch.rand(batch, clip_len, 3, h, w, generator=gen),
        "t": torch.randn(batch, clip_len, 3, generator=gen),
        "q": quats,
        "rel_t": torch.randn(batch, clip_len, 3, generator=gen),
        "rel_q": quats,
        "K": torch.tensor([[w / 2, 0.0, w / 2], [0.0, w / 2, h / 2], [0.0, 0.0, 1.0]]).expand(batch, clip_len, 3, 3),
    }
    clips = {k: v.to(device) for k, v in clips.items()}
    criterion = VLocNetLoss(stage_tasks("stl-loc", cfg.tasks), depth=cfg.warping).to(device)
    cases = {}
    for name, layout in (("nhwc", torch.channels_last), ("nchw", torch.contiguous_format)):
        model = VLocNetPP(cfg).to(device, memory_format=layout).train()
        train_only(model, "stl-loc", frozen=("trunk",))
        model.trunk.eval()

        def step(model=model) -> None:
            loss, _ = criterion(forward_stage(model, clips, "stl-loc"), clips)
            loss.backward()

        cases[name] = step
    times = interleaved(cases, repetitions, warmup, synchronizer(device))
    return {f"train_step_{name}": median(values) for name, values in times.items()}


def node_latency(
    checkpoint: Path,
    frames: list[np.ndarray],
    workdir: Path,
    device: str,
    threads: int,
    backend: str,
    transport: str,
    repetitions: int,
    warmup: int,
    timeout_s: float = 300.0,
    map_path: Path | None = None,
    refine_every: int = 1,
    stream_hz: float = 0.0,
    stream_s: float = 8.0,
) -> dict:
    """Run the ``latency-bench`` ROS program (the real node over DDS vs the bare Localizer,
    interleaved); medians of its per-frame seconds, and the node's memory. ``map_path``: both refine against it;
    ``stream_hz`` > 0: then the node fed at that camera rate for ``stream_s`` (``node_stream_hz``: poses it published
    per second)."""
    path = workdir / "camera_frames.npy"
    np.save(path, np.stack(frames))
    argv = [
        *program_command("latency-bench"),
        "--checkpoint",
        str(checkpoint),
        "--frames",
        str(path),
        "--repetitions",
        str(repetitions),
        "--warmup",
        str(warmup),
        "--device",
        device,
        "--backend",
        backend,
        "--num-threads",
        str(threads),
        "--transport",
        transport,
        *(["--map", str(map_path), "--refine-every", str(refine_every)] if map_path is not None else []),
        *(["--stream-hz", str(stream_hz), "--stream-s", str(stream_s)] if stream_hz > 0 else []),
    ]
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise UserError(f"the node latency measurement did not finish within {timeout_s:.0f} s") from None
    if proc.returncode != 0:
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-8:])
        raise UserError(f"the node latency measurement failed (exit code {proc.returncode}):\n{tail}")
    raw = json.loads(proc.stdout.strip().splitlines()[-1])
    return {
        "node_latency": median(raw["latency_s"]),
        "node_bare_step": median(raw["step_s"]),
        "node_peak_rss_mb": raw["node_peak_rss_mb"],
        "node_rss_mb": raw["node_rss_mb"],
        "node_startup": raw["startup_s"],
        **({"node_stream_hz": raw["stream_answered_hz"]} if "stream_answered_hz" in raw else {}),
        **({"node_refined_share": raw["refined_share"]} if raw.get("refined_share") is not None else {}),
    }


def soak(minutes: float, out: Path, threads: int) -> dict:
    """Run the ``soak`` ROS program (the shipped lite model through the real node at 15 Hz, 640x480 colour + depth,
    20 % malformed messages; docs/node.md, "Soak benchmark") for ``minutes``; its files go to ``out``. Returns the share
    of good frames answered, latency p50 / p99 (ms), the node's RSS after the first minute and its growth after it
    (MiB: highest later sample minus that), and the counts."""
    argv = [*program_command("soak"), "--minutes", str(minutes), "--num-threads", str(threads), "--out", str(out)]
    try:
        proc = subprocess.run(
            argv, capture_output=True, text=True, timeout=60 * minutes + 300, stdin=subprocess.DEVNULL
        )
    except subprocess.TimeoutExpired:
        raise UserError(f"the soak did not finish within {minutes:g} min + 5 min") from None
    if proc.returncode != 0:
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-8:])
        raise UserError(f"the soak failed (exit code {proc.returncode}):\n{tail}")
    raw = json.loads((out / "soak.json").read_text())
    warm = [s["rss_mb"] for s in raw["samples"] if s["t_s"] >= raw["settings"]["warmup_s"]] or [raw["rss_mb_end"]]
    return {
        "answered_share": raw["answered"] / max(raw["good_frames_sent"], 1),
        "good_frames_sent": raw["good_frames_sent"],
        "answered": raw["answered"],
        "bad_messages_sent": raw["bad_messages_sent"],
        "latency_ms_p50": raw["latency_ms_p50"],
        "latency_ms_p99": raw["latency_ms_p99"],
        "rss_mb_start": raw["rss_mb_start"],
        "rss_mb_growth": max(warm) - raw["rss_mb_start"],
        "minutes": minutes,
        "plot": str(out / "soak.png"),
    }


def converter(workdir: Path, frames: int, size: tuple[int, int], repetitions: int, warmup: int) -> dict:
    """``vlocnetpp convert`` (raw ``rgb8``) of a rendered DeepLoc-layout test loop vs decoding the same PNG
    files alone (``cv2.imread`` of every colour and label image the converter reads, one thread).
    The converter's fixed costs (opening, closing and renaming the bag) are included; deleting the
    previous round's bag is not (on a filesystem mounted with ``discard`` that alone can take tens of ms).

    CPU times per frame are reported too (the converter's decoding threads, the rest of the process, and
    the plain decode): on a loaded machine they vary much less than wall times, and they bound the
    converter's wall time on an otherwise idle machine with two cores (see ``run_bench``)."""
    from vlocnetpp_core.bag.convert import convert
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.synth import render_dataset

    root = workdir / "converter_dataset"
    render_dataset(
        root, train_loops=0, test_loops=1, frames_per_loop=frames, size=size, progress=False, frame_interval=0.05
    )
    index = open_dataset(root, split="test")
    pngs = [p for r in index.records for p in (r.image, r.labels) if p is not None and p.endswith(".png")]
    out = workdir / "converter.mcap"

    def remove_output(_name: str) -> None:  # untimed: deleting the last bag is not part of converting
        out.unlink(missing_ok=True)

    size_mb, cpu = [], {"decode_threads": [], "main_thread": [], "png_decode": []}
    load, decode_cpu = index.load, []

    def timed_load(i: int):  # runs in the converter's decoding threads: collect their CPU time (list.append is atomic)
        start = time.thread_time()
        frame = load(i)
        decode_cpu.append(time.thread_time() - start)
        return frame

    index.load = timed_load

    def convert_once() -> None:
        decode_cpu.clear()
        start = time.process_time()
        convert([index], out, progress=False)
        total = time.process_time() - start
        cpu["decode_threads"].append(sum(decode_cpu))
        cpu["main_thread"].append(total - sum(decode_cpu))
        size_mb.append(out.stat().st_size / 2**20)

    def decode() -> None:
        start = time.thread_time()
        for p in pngs:
            cv2.imread(p, cv2.IMREAD_UNCHANGED)
        cpu["png_decode"].append(time.thread_time() - start)

    times = interleaved({"convert": convert_once, "decode": decode}, repetitions, warmup, after=remove_output)
    n = len(index)
    cpu_ms = {k: median(v) / n for k, v in cpu.items()}
    return {
        "converter_frame": median(times["convert"]) / n,
        "png_decode_frame": median(times["decode"]) / n,
        "converter_cpu_decode_threads": cpu_ms["decode_threads"],
        "converter_cpu_main_thread": cpu_ms["main_thread"],
        "png_decode_cpu": cpu_ms["png_decode"],
        "converter_frames": n,
        "converter_bag_mb": size_mb[-1],
    }


def cpu_load() -> list[float] | None:
    """1, 5 and 15 minute load averages (None where the OS has none)."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def resize_all(frames: list[np.ndarray], size: tuple[int, int]) -> list[np.ndarray]:
    return [cv2.resize(f, tuple(size), interpolation=cv2.INTER_LINEAR) for f in frames]

"""``vlocnetpp bench``: speed and memory against the performance targets (docs/performance.md), in one run.

Figures (each with its target; ratios are measured interleaved, see :mod:`.timing`):

=================================== ======== =========================================================
``cached_vs_recompute_speedup``     >= 1.4   paper config: step recomputing frame t-1 / step with the cached state
``mtl_step_over_resnet50``          <= 3.0   paper config: full multitask step (fastest backend; each reported) / one
                                             plain ResNet-50 forward, same input
``node_latency_over_step``          <= 1.10  lite: image-in -> pose-out through the real node over DDS / bare
                                             ``Localizer.step``
``lite_hz``                         >= 15    lite: ``Localizer.step`` per second at its input size (faster backend; both
                                             reported)
``converter_speed_over_png_decode`` >= 0.8   frames/s of ``vlocnetpp convert`` / frames/s of decoding the same PNGs
                                             alone
``synth_fps``                       >= 30    synthetic campus frames rendered per second at 320x180
``peak_rss_mb``                     (none)   peak resident memory of the node process while streaming (MiB)
``paper_step_ms``                   <= 5     paper step in ms (fastest backend); target on CUDA only (H100-class GPU
                                             goal, docs/performance.md)
``node_refined_hz``                 >= 15    shipped lite model + its keyframe map, refining every frame: poses/s
                                             the node publishes when the camera sends 30 frames/s
``soak_answered_share``             >= 0.99  with ``soak_minutes`` > 0: good frames answered by the node fed at 15 Hz
                                             (640x480 + depth, 20 % malformed messages) for that long
``soak_latency_p99_ms``             <= 100   the same soak: publish -> pose latency, 99th percentile (ms)
``soak_rss_growth_mb``              <= 20    the same soak: node RSS growth after the first minute (MiB)
=================================== ======== =========================================================

The refinement's cost per frame (``Localizer.step`` with and without the map, every frame and every second frame,
interleaved), the node's lockstep rate and its rate refining every second frame are reported beside
``node_refined_hz``
(:mod:`.refinement`; these need the shipped model and map).

Also reported: ``mtl_gmac_over_resnet50``, the step's multiply-accumulates over the ResNet-50's
(the time ratio of a backend exactly as efficient as the yardstick), and on CUDA the step replayed
from a CUDA graph (:mod:`.cuda_graph`) and the step compiled by ``torch.compile`` as further backends. Figures whose
parts are not installed (ROS 2, ``rosbags``, ``onnx`` / ``onnxruntime``) are None with a note saying why.

Untrained checkpoints (``init_checkpoint``) are used: speed does not depend on the weights.
``--quick`` (under a minute) runs the paper config at 224x128 instead of 448x256 and fewer
repetitions, and says so in the output; ``--config FILE`` (YAML) overrides any field of
:class:`BenchSettings`. Results on a machine running other jobs are noisy; the report gives the
load average before and after.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import tempfile
from pathlib import Path

from vlocnetpp_core.bench.settings import BenchSettings
from vlocnetpp_core.bench.table import format_table
from vlocnetpp_core.errors import DataError, UserError, require
from vlocnetpp_core.threads import use_threads

# name -> (comparison, target, what it is)
TARGETS: dict[str, tuple[str, float | None, str]] = {
    "cached_vs_recompute_speedup": (">=", 1.4, "paper step recomputing frame t-1 / step with cached state"),
    "mtl_step_over_resnet50": (
        "<=",
        3.0,
        "paper multitask step (fastest backend) / plain ResNet-50 forward, same input",
    ),
    "node_latency_over_step": ("<=", 1.10, "lite: image-in -> pose-out via the node over DDS / bare Localizer.step"),
    "lite_hz": (">=", 15.0, "lite Localizer.step per second (faster backend)"),
    "converter_speed_over_png_decode": (">=", 0.8, "convert frames/s / PNG decode frames/s"),
    "synth_fps": (">=", 30.0, "synthetic campus frames/s at 320x180"),
    "train_nchw_over_nhwc": (">=", 1.0, "lite stl-loc training step: NCHW network / channels-last network (as built)"),
    "peak_rss_mb": ("", None, "node peak resident memory while streaming (MiB)"),
    "paper_step_ms": ("<=", None, "paper multitask step with cached state (ms, fastest backend); 5 ms goal on CUDA"),
    "node_refined_hz": (
        ">=",
        15.0,
        "shipped lite + keyframe map, refining every frame: poses/s through the node, camera at 30 frames/s",
    ),
    "soak_answered_share": (">=", 0.99, "soak (15 Hz, 640x480 + depth, 20 % bad): good frames answered"),
    "soak_latency_p99_ms": ("<=", 100.0, "soak: publish -> pose latency p99 (ms)"),
    "soak_rss_growth_mb": ("<=", 20.0, "soak: node RSS growth after the first minute (MiB)"),
}
SOAK_FIGURES = {
    "soak_answered_share": "answered_share",
    "soak_latency_p99_ms": "latency_ms_p99",
    "soak_rss_growth_mb": "rss_mb_growth",
}  # figure -> key of figures.soak's result
GPU_PAPER_STEP_MS = 5.0
NOT_TIMES = (
    "node_peak_rss_mb",
    "node_rss_mb",
    "converter_frames",
    "converter_bag_mb",
    "paper_step_gmac",
    "resnet50_gmac",
    "cuda_graph_max_abs_diff",
    "compiled_max_abs_diff",
    "refine_share_every1",
    "refine_share_every2",
    "node_refine_share_every1",
    "node_refine_share_every2",
)  # measured values that are not seconds


def run_bench(settings: BenchSettings, device: str = "cpu", quick: bool = False, progress=None) -> dict:
    """Measure everything; returns the report (see :func:`format_table` and the module doc).

    Figures whose parts are not installed (ROS 2 for the node, ``rosbags`` for the converter,
    ``onnx`` / ``onnxruntime`` for the onnx backend, as on a GPU machine with PyTorch only) are
    reported as not measured (None) with a note saying why; the rest is measured as usual.
    """
    import torch

    from vlocnetpp_core.bench import figures, paper_step
    from vlocnetpp_core.inference.checkpoint import init_checkpoint

    say = progress or (lambda _msg: None)
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"--device {device}: CUDA is not available here")
    use_threads(settings.threads)
    report: dict = {
        "machine": {
            "device": device,
            "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "onnxruntime": _version("onnxruntime"),
            "load_average_start": figures.cpu_load(),
        },
        "settings": {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(settings).items()},
        "quick": quick,
        "notes": [],
        "times_ms": {},
    }
    times: dict = {}
    with tempfile.TemporaryDirectory(prefix="vlocnetpp-bench-") as tmp:
        work = Path(tmp)
        say(f"synthetic campus: {settings.synth_frames} frames at {settings.synth_size[0]}x{settings.synth_size[1]}")
        frames, synth = figures.synth_frames(max(settings.synth_frames, 2), settings.synth_size, settings.scene)
        times.update(synth)
        camera = figures.resize_all(frames, settings.camera_size)
        say("paper config: cached vs recompute vs ResNet-50")
        paper = paper_step.paper_step(
            settings.paper_config,
            settings.paper_input_size,
            frames,
            device,
            settings.repetitions,
            settings.warmup,
            work,
            settings.threads,
        )
        if "onnx_error" in paper:
            report["notes"].append(f"onnx paper step not measured: {paper.pop('onnx_error')}")
        for name in ("cuda_graph", "compiled"):
            if f"{name}_error" in paper:
                report["notes"].append(f"{name} paper step not measured: {paper.pop(f'{name}_error')}")
        times.update({k: v for k, v in paper.items() if k != "input_size"})
        report["paper_input_size"] = paper["input_size"]
        if quick:
            report["notes"].append(
                f"quick: paper config at {paper['input_size'][0]}x{paper['input_size'][1]} (not its 448x256), "
                f"{settings.repetitions} repetitions, {settings.converter_frames} converter frames: indicative only"
            )
        lite_ckpt = init_checkpoint(settings.lite_config, work / "lite", seed=0)
        say("lite config: Localizer.step, torch and onnx backends")
        lite = figures.lite_step(lite_ckpt, camera, device, settings.threads, settings.repetitions * 3, settings.warmup)
        if "onnx_error" in lite:
            report["notes"].append(f"onnx backend not measured: {lite.pop('onnx_error')}")
        report["lite_input_size"], report["camera_size"] = lite.pop("input_size"), lite.pop("camera_size")
        times.update(lite)
        say("lite config: stl-loc training step, channels-last vs NCHW")
        times.update(figures.train_step(settings.lite_config, device, settings.repetitions, settings.warmup))
        if settings.node:
            say("node: latency over DDS vs bare Localizer.step")
            try:
                require("rclpy", "the node figure (ROS 2 Jazzy)")
                node = figures.node_latency(
                    lite_ckpt,
                    camera,
                    work,
                    device,
                    settings.threads,
                    settings.node_backend,
                    settings.node_transport,
                    settings.node_repetitions,
                    settings.node_warmup,
                )
            except UserError as err:
                report["notes"].append(f"node not measured: {err}")
                node = {}
            times.update(node)
        if settings.refinement:
            say("refinement: the shipped model and map, every frame and every 2nd, bare and through the node")
            times.update(_refinement(settings, camera, work, device, report["notes"]))
        say(f"converter: {settings.converter_frames} frames vs PNG decode")
        try:
            require("rosbags", "the converter figure")
        except UserError as err:
            report["notes"].append(f"converter not measured: {err}")
        else:
            times.update(
                figures.converter(
                    work, settings.converter_frames, settings.synth_size, settings.repetitions, settings.warmup
                )
            )
    if settings.soak_minutes > 0:
        say(f"soak: the node at 15 Hz with depth for {settings.soak_minutes:g} min -> {settings.soak_out}")
        try:
            require("rclpy", "the soak (ROS 2 Jazzy)")
            report["soak"] = figures.soak(settings.soak_minutes, Path(settings.soak_out), settings.threads)
        except UserError as err:
            report["notes"].append(f"soak not measured: {err}")
    report["machine"]["load_average_end"] = figures.cpu_load()
    _add_figures(report, times, device)
    return report


def _refinement(settings: BenchSettings, camera: list, work: Path, device: str, notes: list[str]) -> dict:
    """The refinement's times (:mod:`.refinement`); a note instead of each part that cannot run here."""
    from vlocnetpp_core.bench import refinement

    times: dict = {}
    try:
        times.update(
            refinement.refined_steps(
                camera, device, settings.threads, settings.repetitions * 3, settings.warmup, settings.refinement_map
            )
        )
        if settings.node:
            require("rclpy", "the node figure (ROS 2 Jazzy)")
            times.update(
                refinement.node_rates(
                    camera,
                    work,
                    device,
                    settings.threads,
                    settings.node_backend,
                    settings.node_transport,
                    settings.node_repetitions,
                    settings.node_warmup,
                    settings.refinement_map,
                    settings.node_stream_frames,
                )
            )
    except UserError as err:
        notes.append(f"refinement {'through the node ' if times else ''}not measured: {err}")
    return times


def _add_figures(report: dict, times: dict, device: str) -> None:
    """The figures, their targets and the absolute times (ms) from the measured ``times`` (seconds)."""
    lite_steps = {name: times.get(f"lite_step_{name}") for name in ("torch", "onnx")}
    paper_steps = {
        "torch": times["paper_step_cached"],
        "onnx": times.get("paper_step_onnx"),
        "cuda_graph": times.get("paper_step_cuda_graph"),
        "compiled": times.get("paper_step_compiled"),
    }
    best, paper_best = _fastest(lite_steps), _fastest(paper_steps)
    converter = "converter_frame" in times
    values = {
        "cached_vs_recompute_speedup": times["paper_step_recompute"] / times["paper_step_cached"],
        "mtl_step_over_resnet50": paper_steps[paper_best] / times["resnet50_forward"],
        "node_latency_over_step": times["node_latency"] / times["node_bare_step"] if "node_latency" in times else None,
        "lite_hz": 1.0 / lite_steps[best],
        "converter_speed_over_png_decode": times["png_decode_frame"] / times["converter_frame"] if converter else None,
        "synth_fps": 1.0 / times["synth_frame"],
        "train_nchw_over_nhwc": times["train_step_nchw"] / times["train_step_nhwc"],
        "peak_rss_mb": times.get("node_peak_rss_mb"),
        "paper_step_ms": 1000.0 * paper_steps[paper_best],
        "node_refined_hz": 1.0 / times["node_refined_stream_every1"] if "node_refined_stream_every1" in times else None,
        **{name: report.get("soak", {}).get(key) for name, key in SOAK_FIGURES.items()},
    }
    report.update(values)
    if converter:
        # wall time per frame on an idle 2-core machine is at least half the CPU time and at least the main thread's
        cpu_bound = max(
            (times["converter_cpu_decode_threads"] + times["converter_cpu_main_thread"]) / 2,
            times["converter_cpu_main_thread"],
        )
        report["converter_speed_over_png_decode_idle_estimate"] = times["png_decode_cpu"] / cpu_bound
    report["lite_backend"] = best
    for name, value in lite_steps.items():
        report[f"lite_hz_{name}"] = None if value is None else 1.0 / value
    report["paper_backend"] = paper_best
    for name, value in paper_steps.items():
        if name in ("torch", "onnx") or value is not None:  # the CUDA-only variants when measured
            report[f"mtl_step_over_resnet50_{name}"] = None if value is None else value / times["resnet50_forward"]
    report["mtl_gmac_over_resnet50"] = times["paper_step_gmac"] / times["resnet50_gmac"]
    report["times_ms"] = {k: round(1000.0 * v, 3) for k, v in times.items() if k not in NOT_TIMES and v is not None}
    report.update({k: times[k] for k in NOT_TIMES if k in times})
    targets = {}
    for name, (op, target, what) in TARGETS.items():
        if name == "paper_step_ms" and device.startswith("cuda"):
            target, op = GPU_PAPER_STEP_MS, "<="
        value = values[name]
        met = None if target is None or value is None else (value >= target if op == ">=" else value <= target)
        targets[name] = {
            "value": value,
            "target": target,
            "compare": op if target is not None else None,
            "met": met,
            "what": what,
        }
    report["targets"] = targets
    report["notes"].append(
        f"lite_hz uses the {best} backend ("
        + ", ".join(f"{n} {report[f'lite_hz_{n}']:.1f} Hz" for n in lite_steps if report[f"lite_hz_{n}"] is not None)
        + ")"
    )
    report["notes"].append(
        f"mtl_step_over_resnet50 and paper_step_ms use the {paper_best} paper step ("
        + ", ".join(
            f"{n} {report[f'mtl_step_over_resnet50_{n}']:.2f}"
            for n in paper_steps
            if report.get(f"mtl_step_over_resnet50_{n}") is not None
        )
        + f"); the ResNet-50 yardstick is always one plain eager torch forward; in compute the step is "
        f"{report['mtl_gmac_over_resnet50']:.2f}x the ResNet-50 ({times['paper_step_gmac']:.2f} vs "
        f"{times['resnet50_gmac']:.2f} GMAC)"
    )


def _fastest(steps: dict[str, float | None]) -> str:
    """The name of the fastest measured step (None: not measured); the first on a tie."""
    measured = {name: t for name, t in steps.items() if t is not None}
    return min(measured, key=measured.get)


def _version(package: str) -> str | None:
    """The installed version of ``package`` (None: not installed)."""
    import importlib.metadata

    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def _jsonable(obj):
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.add_argument(
        "--config",
        metavar="FILE",
        default=None,
        help="YAML of bench settings overriding the defaults (see BenchSettings)",
    )
    p.add_argument("--device", default="cpu", help="cpu or cuda (cuda:N) for the network figures (default cpu)")
    p.add_argument(
        "--quick",
        action="store_true",
        help="under a minute: paper config at 224x128, few repetitions (indicative only)",
    )


def run(args: argparse.Namespace) -> int:
    import yaml

    dev = str(args.device)
    if not (dev == "cpu" or dev == "cuda" or (dev.startswith("cuda:") and dev[5:].isdigit())):
        raise UserError(f"--device must be cpu, cuda or cuda:N, got {dev!r}")
    settings = BenchSettings.quick() if args.quick else BenchSettings()
    if args.config:
        path = Path(args.config)
        if not path.is_file():
            raise DataError(path, "no such bench settings file")
        try:
            values = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as err:
            raise DataError(path, f"not valid YAML: {err}") from None
        if not isinstance(values, dict):
            raise DataError(path, "expected a mapping of bench settings")
        settings = settings.updated(values, str(path))
    report = run_bench(settings, dev, args.quick, progress=lambda msg: print(f"bench: {msg}", file=sys.stderr))
    print(json.dumps(_jsonable(report), indent=2) if args.json else format_table(report))
    return 0

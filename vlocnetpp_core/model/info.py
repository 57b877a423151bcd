"""``vlocnetpp model-info``: parameter counts per stream and per training stage of a model config."""

from __future__ import annotations

import argparse
import json
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        default="lite",
        help="model config: 'paper', 'lite', 'lite_pose' (no semantic stream) or a YAML file (default: lite)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def model_info(config_name: str) -> dict[str, Any]:
    """Summary of the network a config builds: input size, switches, tasks, parameter counts (per stage: the
    stages the network can train; a pose-only network has no ``stl-seg``)."""
    from vlocnetpp_core.model import STAGES, VLocNetPP, load_model_config, params_per_stream, trainable_parameters

    config = load_model_config(config_name)
    model = VLocNetPP(config)
    per_stream = params_per_stream(model)
    return {
        "config": config.name,
        "input_size": list(config.input_size),
        "params_total": sum(per_stream.values()),
        "params_per_stream": per_stream,
        "params_trained_per_stage": {
            stage: sum(p.numel() for p in trainable_parameters(model, stage))
            for stage in STAGES
            if _trains(stage, config.tasks)
        },
        "switches": {
            k: getattr(config, k) for k in ("semantic_stream", "temporal_fusion", "semantic_fusion", "warping")
        },
        "global_stream": {
            "downsample": config.global_downsample,
            "pooling": config.global_pose_pooling,
            "anchors": config.global_pose_anchors,
            "rotation_anchors": config.global_rotation_anchors,
            "res5_size": list(config.global_res5_size),
        },
        "odometry_stream": {"pooling": config.odometry_pose_pooling, "res5_size": list(config.odometry_res5_size)},
        "tasks": list(config.tasks),
        "num_classes": config.num_classes if config.semantic_stream else 0,
    }


def _trains(stage: str, tasks: tuple[str, ...]) -> bool:
    """Whether a network with ``tasks`` can train ``stage`` (a pose-only one cannot train ``stl-seg``)."""
    from vlocnetpp_core.model.stages import stage_tasks

    try:
        stage_tasks(stage, tasks)
    except ValueError:
        return False
    return True


def format_table(info: dict[str, Any]) -> str:
    w, h = info["input_size"]
    classes = f"{info['num_classes']} classes" if info["num_classes"] else "pose only (no semantic stream)"
    lines = [
        f"model config {info['config']!r}: input {w}x{h} (width x height), {classes}",
        "switches: " + ", ".join(f"{k}={'on' if v else 'off'}" for k, v in info["switches"].items()),
        _global_stream_line(info["global_stream"]),
        _odometry_stream_line(info["odometry_stream"]),
        "",
        f"{'stream':<12}{'parameters':>14}",
    ]
    lines += [f"{name:<12}{n:>14,}" for name, n in info["params_per_stream"].items()]
    lines += [f"{'total':<12}{info['params_total']:>14,}", "", f"{'stage':<12}{'trained':>14}"]
    lines += [f"{name:<12}{n:>14,}" for name, n in info["params_trained_per_stage"].items()]
    return "\n".join(lines)


POOLING_WORDS = {"average": "averaged (the paper)", "flatten": "flattened (a departure from the paper)"}


def _global_stream_line(g: dict[str, Any]) -> str:
    """One line on the global stream's resolution and head, naming the departures from the paper."""
    h, w = g["res5_size"]
    res3 = "as is (the paper)" if g["downsample"] == 1 else f"pooled by {g['downsample']} (a departure from the paper)"
    head = POOLING_WORDS[g["pooling"]]
    xyz = (
        "fc2 regresses the position (the paper)"
        if not g["anchors"]
        else f"the position is {g['anchors']} scored anchors plus offsets (a departure from the paper)"
    )
    quat = (
        "fc3 regresses the rotation (the paper)"
        if not g["rotation_anchors"]
        else f"the rotation is {g['rotation_anchors']} scored anchor "
        "rotations each turned by a residual (a departure from the paper)"
    )
    return f"global stream: reads the trunk's Res3 map {res3}; its {w}x{h} Res5c map is {head} into fc1; {xyz}; {quat}"


def _odometry_stream_line(o: dict[str, Any]) -> str:
    """One line on the odometry head, naming the departure from the paper."""
    h, w = o["res5_size"]
    return f"odometry stream: its {w}x{h} Res5 map of the two frames is {POOLING_WORDS[o['pooling']]} into fc1"


def run(args: argparse.Namespace) -> int:
    info = model_info(args.config)
    print(json.dumps(info, indent=2) if args.json else format_table(info))
    return 0

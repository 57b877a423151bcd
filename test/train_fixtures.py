"""Helpers of the `vlocnetpp train` tests (``test_train*.py``): one short run through the command line and its log.
Their dataset, the ``tiny`` fixture, is in ``conftest.py``."""

from __future__ import annotations

import json
from pathlib import Path

from vlocnetpp_core.cli import main as cli


def train_args(data: Path, config: Path, out: Path, stage: str, steps: int, *extra: str) -> list[str]:
    return [
        "train",
        "--config",
        str(config),
        "--data",
        str(data),
        "--stage",
        stage,
        "--out",
        str(out),
        "--steps",
        str(steps),
        "--batch-size",
        "2",
        "--clip-len",
        "2",
        "--workers",
        "0",
        "--no-progress",
        "--val-every",
        str(steps),
        *extra,
    ]


def train(data: Path, config: Path, out: Path, stage: str, steps: int, *extra: str) -> list[dict]:
    assert cli(train_args(data, config, out, stage, steps, *extra)) == 0
    return read_log(out)


def read_log(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]


def steps_of(log: list[dict]) -> list[dict]:
    return [r for r in log if "validation" not in r]

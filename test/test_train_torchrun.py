"""`vlocnetpp train` under torchrun: two processes with gloo on the CPU."""

from __future__ import annotations

import os
import subprocess
import sys

from conftest import REPO
from train_fixtures import read_log, steps_of

from vlocnetpp_core.inference.checkpoint import load_checkpoint


def test_torchrun_two_processes_gloo(tiny, tmp_path):
    data, config = tiny
    out = tmp_path / "ddp"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        "2",
        "-m",
        "vlocnetpp_core.training.train",
        "--config",
        str(config),
        "--data",
        str(data),
        "--stage",
        "stl-seg",
        "--out",
        str(out),
        "--steps",
        "3",
        "--batch-size",
        "2",
        "--clip-len",
        "2",
        "--workers",
        "0",
        "--no-progress",
        "--device",
        "cpu",
    ]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    model, meta = load_checkpoint(out / "last.safetensors")
    assert meta["training"]["world_size"] == 2 and meta["training"]["step"] == 3
    assert len([r for r in steps_of(read_log(out))]) == 3  # rank 0 alone writes the log

"""`vlocnetpp train`: continuing a run: --resume (the learning-rate curve, a killed run resumed exactly) and
--restart (the weights kept, the optimiser and loss weights anew)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import REPO
from learning_probe import train_config
from train_fixtures import read_log, steps_of, train


def test_a_cosine_run_anneals_each_step_and_a_resume_continues_its_curve(tiny, tmp_path):
    """--lr-end: the rate of every logged step follows the half cosine; resuming the finished run with the same
    flags keeps the saved phase, with more --steps it starts a new one at the resumed step."""
    from vlocnetpp_core.training.lr_schedule import LearningRatePhase
    from vlocnetpp_core.training.trainer import Trainer

    data, config = tiny
    out = tmp_path / "cosine"
    log = train(data, config, out, "stl-loc", 6, "--lr", "1e-3", "--lr-end", "1e-5", "--threads", "1")
    curve = LearningRatePhase(0, 1e-3, 1e-5, 6)
    assert [r["lr"] for r in steps_of(log)] == pytest.approx([curve.at(s) for s in range(6)], rel=1e-9)
    base = [
        "train",
        "--config",
        str(config),
        "--data",
        str(data),
        "--stage",
        "stl-loc",
        "--out",
        str(out),
        "--batch-size",
        "2",
        "--clip-len",
        "2",
        "--workers",
        "0",
        "--no-progress",
        "--threads",
        "1",
        "--resume",
        "--lr",
        "1e-3",
        "--lr-end",
        "1e-5",
    ]
    assert Trainer(train_config([*base, "--steps", "6"])).phase == curve
    assert Trainer(train_config([*base, "--steps", "10"])).phase == LearningRatePhase(6, 1e-3, 1e-5, 10)


def test_restart_keeps_weights_and_step_with_a_fresh_optimiser_and_loss_weights(tiny, tmp_path):
    """--restart (a warm restart): the run's weights, step and best score come back, Adam's moments and the learned
    loss weights start anew; --resume restores both. Adam's first step moves every weight by the rate exactly."""
    from safetensors.torch import load_file

    from vlocnetpp_core.cli import build_parser
    from vlocnetpp_core.inference.checkpoint import read_checkpoint_tensors
    from vlocnetpp_core.training.lr_schedule import LearningRatePhase
    from vlocnetpp_core.training.trainer import Trainer

    data, config = tiny
    out = tmp_path / "warm"
    train(data, config, out, "stl-loc", 3, "--lr", "1e-3", "--threads", "1")
    saved = load_file(str(out / "train_state.safetensors"))
    assert float(saved["criterion.s_x"]) != 0.0 and float(saved["criterion.s_q"]) != -3.0  # learned over 3 steps
    base = [
        "train",
        "--config",
        str(config),
        "--data",
        str(data),
        "--stage",
        "stl-loc",
        "--out",
        str(out),
        "--batch-size",
        "2",
        "--clip-len",
        "2",
        "--workers",
        "0",
        "--no-progress",
        "--threads",
        "1",
        "--val-every",
        "4",
        "--steps",
        "4",
    ]
    parse = build_parser("train").parse_args
    resumed = Trainer(train_config([*base, "--resume"]))
    assert resumed.optimizer.state and float(resumed.criterion.s_x.detach()) == float(saved["criterion.s_x"])
    restarted = Trainer(train_config([*base, "--restart", "--lr", "3e-4", "--lr-end", "1e-5"]))
    assert restarted.step == 3 and not restarted.optimizer.state
    assert (float(restarted.criterion.s_x.detach()), float(restarted.criterion.s_q.detach())) == (0.0, -3.0)
    weights, _ = read_checkpoint_tensors(out / "last.safetensors")
    assert all(torch.equal(restarted.model.state_dict()[k], v) for k, v in weights.items())
    assert restarted.phase == LearningRatePhase(3, 3e-4, 1e-5, 4)
    restarted.run()
    assert steps_of(read_log(out))[-1]["lr"] == pytest.approx(3e-4)
    after = load_file(str(out / "train_state.safetensors"))
    assert abs(float(after["criterion.s_x"])) == pytest.approx(3e-4, rel=1e-4)
    assert abs(float(after["criterion.s_q"]) + 3.0) == pytest.approx(
        3e-4, abs=5e-7
    )  # a float32 step near -3 (ulp 2.4e-7)
    with pytest.raises(SystemExit):  # one or the other
        parse([*base, "--resume", "--restart"])


def _train_cmd(data: Path, config: Path, out: Path, steps: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "vlocnetpp_core.training.train",
        "--config",
        str(config),
        "--data",
        str(data),
        "--stage",
        "mtl",
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
        "3",
        "--seed",
        "3",
        "--threads",
        "1",
    ]


def test_killed_run_resumes_exactly(tiny, tmp_path):
    data, config = tiny
    steps = 8
    straight = tmp_path / "straight"
    subprocess.run(_train_cmd(data, config, straight, steps), check=True, capture_output=True, cwd=REPO, timeout=600)
    reference = {r["step"]: r for r in steps_of(read_log(straight))}

    killed = tmp_path / "killed"
    proc = subprocess.Popen(
        _train_cmd(data, config, killed, 40), cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        log = killed / "log.jsonl"
        if log.exists() and any(r.get("step", 0) >= 4 and "validation" not in r for r in read_log(killed)):
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    saved = json.loads((killed / "train_state.json").read_text())["step"]
    assert saved in (3, 6)
    subprocess.run(
        [*_train_cmd(data, config, killed, steps), "--resume"], check=True, capture_output=True, cwd=REPO, timeout=600
    )
    resumed = [r for r in steps_of(read_log(killed))]
    after = {r["step"]: r for r in resumed[len(resumed) - (steps - saved) :]}
    assert sorted(after) == list(range(saved + 1, steps + 1))
    for step, rec in after.items():
        for key in ("loss", "x", "x_vo", "seg"):
            assert rec[key] == pytest.approx(reference[step][key], rel=1e-6, abs=1e-7), (step, key)

    # Other frame strides would index another clip list from the saved position: refused.
    other = subprocess.run(
        [*_train_cmd(data, config, killed, steps + 2), "--resume", "--frame-strides", "1,2"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=600,
    )
    assert other.returncode != 0 and "resume it with the same" in other.stderr
    # A step-down for the last part of the run: --resume --lr applies from the resumed step on.
    subprocess.run(
        [*_train_cmd(data, config, killed, steps + 2), "--resume", "--lr", "3e-5"],
        check=True,
        capture_output=True,
        cwd=REPO,
        timeout=600,
    )
    lrs = {r["step"]: r["lr"] for r in steps_of(read_log(killed))}
    assert lrs[steps] == pytest.approx(1e-4)  # the mtl default the run started with
    assert lrs[steps + 1] == lrs[steps + 2] == pytest.approx(3e-5)

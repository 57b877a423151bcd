"""`vlocnetpp train`: the flags it refuses and the clips each stage trains on (frame strides, mirroring).

The stages' learning and the mtl assembly: ``test_train_stages.py``; resume and restart: ``test_train_resume.py``;
torchrun: ``test_train_torchrun.py``; pose-only networks: ``test_train_pose_only.py``."""

from __future__ import annotations

import numpy as np
import pytest
from learning_probe import train_config

from vlocnetpp_core.cli import main as cli


def test_training_clips_pool_frame_strides(tiny):
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.training.train_data import training_clips

    index = open_dataset(tiny[0], None, "train")  # 3 loops of 10 frames
    single, pooled = training_clips(index, 2, None), training_clips(index, 2, None, (1, 2))
    assert (len(single), len(pooled)) == (3 * 9, 3 * 9 + 3 * 8)
    step = np.median([np.linalg.norm(pooled[i]["rel_t"][1].numpy()) for i in range(len(single))])
    double = np.median([np.linalg.norm(pooled[i]["rel_t"][1].numpy()) for i in range(len(single), len(pooled))])
    assert double == pytest.approx(2 * step, rel=0.15)  # the clips of stride 2 span two frames' motion
    with pytest.raises(SystemExit):
        cli(
            [
                "train",
                "--config",
                "lite",
                "--data",
                str(tiny[0]),
                "--stage",
                "stl-vo",
                "--out",
                "x",
                "--frame-strides",
                "0,1",
            ]
        )


def test_crop_scale_below_one_is_refused(tiny, tmp_path, capsys):
    out = tmp_path / "run"
    assert (
        cli(
            [
                "train",
                "--config",
                "lite",
                "--data",
                str(tiny[0]),
                "--stage",
                "stl-loc",
                "--out",
                str(out),
                "--crop-scale",
                "0.5",
            ]
        )
        == 2
    )
    assert "--crop-scale must be >= 1, got 0.5" in capsys.readouterr().err


def test_zero_epochs_is_refused_not_thirty(tiny, tmp_path, capsys):
    out = tmp_path / "run"
    assert (
        cli(["train", "--config", "lite", "--data", str(tiny[0]), "--stage", "mtl", "--out", str(out), "--epochs", "0"])
        != 0
    )
    assert "--epochs must be > 0" in capsys.readouterr().err and not out.exists()


def test_freeze_refuses_unknown_parts_and_freezing_everything(tiny, tmp_path, capsys):
    data, config = tiny
    base = [
        "train",
        "--config",
        str(config),
        "--data",
        str(data),
        "--out",
        str(tmp_path / "run"),
        "--steps",
        "2",
        "--workers",
        "0",
        "--batch-size",
        "2",
        "--clip-len",
        "2",
        "--no-progress",
    ]
    with pytest.raises(SystemExit):
        cli([*base, "--stage", "stl-loc", "--freeze", "trunk,backbone"])
    assert "backbone" in capsys.readouterr().err
    assert cli([*base, "--stage", "stl-vo", "--freeze", "odometry,trunk"]) != 0  # stl-vo trains both
    assert "nothing of what stl-vo trains" in capsys.readouterr().err


def test_only_the_odometry_stage_mirrors_its_training_clips(tiny, tmp_path):
    # stl-vo's clips are flipped left-right half the time (relative poses mirrored with them); the stages that learn
    # a global pose never see a mirrored world, and stl-seg stays as measured
    from vlocnetpp_core.data.transforms import HorizontalFlip
    from vlocnetpp_core.training.trainer import Trainer

    data, config = tiny
    flips = {}
    for stage in ("stl-loc", "stl-vo", "stl-seg", "mtl"):
        args = [
            "train",
            "--config",
            str(config),
            "--data",
            str(data),
            "--stage",
            stage,
            "--out",
            str(tmp_path / stage),
            "--steps",
            "1",
            "--batch-size",
            "2",
            "--clip-len",
            "2",
            "--workers",
            "0",
            "--no-progress",
            "--threads",
            "1",
        ]
        trainer = Trainer(train_config(args))
        flips[stage] = [
            any(isinstance(t, HorizontalFlip) for t in clips.transform.transforms)
            for clips in trainer.train_clips.datasets
        ]
    assert flips == {"stl-loc": [False], "stl-vo": [True], "stl-seg": [False], "mtl": [False]}

"""``TrainConfig``: built from the command line, a file or directly, checked once; a ``Trainer`` runs a step from
one."""

from __future__ import annotations

import math
import sys

import pytest
import torch
import yaml

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.model import STAGE_SPECS, load_model_config
from vlocnetpp_core.training.config import ConfigError, TrainConfig

BASE = {"config": "lite", "data": "DATA", "stage": "stl-loc", "out": "OUT"}


def test_the_command_line_gives_one_field_per_flag():
    from vlocnetpp_core.cli import build_parser
    from vlocnetpp_core.training.train import train_config

    args = build_parser("train").parse_args(
        [
            "train",
            "--config",
            "lite",
            "--data",
            "D",
            "--stage",
            "stl-vo",
            "--out",
            "O",
            "--frame-strides",
            "2,1,2",
            "--freeze",
            "trunk",
            "--init",
            "a",
            "--init",
            "b",
        ]
    )
    config = train_config(args)
    assert config == TrainConfig(
        config="lite", data="D", stage="stl-vo", out="O", frame_strides=(1, 2), freeze=("trunk",), init=("a", "b")
    )
    flags = set(vars(args)) - {"command", "_module", "recipe", "train_config"}  # the command line's own
    assert flags == set(TrainConfig.keys())  # every train flag is a field, and no more


def test_a_config_written_reads_back_equal(tmp_path):
    config = TrainConfig(**BASE, frame_strides=[2, 1], init=[tmp_path / "a.safetensors"], lr=1, s_q_init=0)
    assert config.frame_strides == (1, 2) and config.lr == 1.0 and isinstance(config.s_q_init, float)
    assert config.init == (str(tmp_path / "a.safetensors"),)  # a path as its string
    assert TrainConfig.read(config.write(tmp_path / "c.json")) == config


@pytest.mark.parametrize(
    "change, key, message",
    [
        ({"batch_size": "8"}, "batch_size", "--batch-size must be an integer, got '8'"),
        ({"bf16": 1}, "bf16", "--bf16 must be true or false"),
        ({"steps": True}, "steps", "--steps must be an integer"),
        ({"frame_strides": 2}, "frame_strides", "--frame-strides must be a list of int values"),
        ({"stage": "stl-depth"}, "stage", "--stage must be one of stl-loc, stl-vo, stl-seg, mtl"),
        ({"format": "kitti"}, "format", "--format must be one of deeploc, 7scenes"),
        ({"crop_scale": 0.5}, "crop_scale", "--crop-scale must be >= 1, got 0.5"),
        ({"epochs": 0}, "epochs", "--epochs must be > 0, got 0 (--steps 0 assembles mtl"),
        ({"steps": 3, "epochs": 1.0}, "epochs", "--steps and --epochs exclude each other"),
        ({"resume": True, "restart": True}, "restart", "--resume and --restart exclude each other"),
        ({"freeze": ["trunk", "head"]}, "freeze", "--freeze: head is not a part of the network"),
        (
            {"stage": "stl-seg", "config": "lite_pose"},
            "config",
            "--config lite_pose: stage stl-seg trains the segmentation stream",
        ),
    ],
)
def test_a_bad_value_is_named_by_its_key(change, key, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")) as err:
        TrainConfig(**{**BASE, **change})
    assert err.value.key == key


def test_a_file_with_an_unknown_or_missing_key_is_named(tmp_path):
    (tmp_path / "typo.json").write_text('{"config": "lite", "data": "D", "stage": "mtl", "out": "O", "batchsize": 2}')
    with pytest.raises(UserError, match="typo.json: unknown key 'batchsize'"):
        TrainConfig.read(tmp_path / "typo.json")
    (tmp_path / "short.json").write_text('{"config": "lite", "stage": "mtl", "out": "O"}')
    with pytest.raises(UserError, match="short.json: --data required"):
        TrainConfig.read(tmp_path / "short.json")


def test_the_stage_defaults_come_from_the_stage_table():
    for name, spec in STAGE_SPECS.items():
        config = TrainConfig(**{**BASE, "stage": name})
        assert (config.learning_rate, config.crop) == (spec.lr, spec.crop_scale)
    assert (STAGE_SPECS["mtl"].lr, STAGE_SPECS["stl-seg"].crop_scale) == (1e-4, 1.15)
    assert TrainConfig(**BASE, lr=3e-4, crop_scale=1.1).learning_rate == 3e-4


def test_the_train_config_imports_no_torch():
    import subprocess

    code = "import sys, vlocnetpp_core.training.config, vlocnetpp_core.training.recipe; print('torch' in sys.modules)"
    assert (
        subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
        == "False"
    )


def test_a_trainer_built_from_a_train_config_takes_a_step(tmp_path):
    """No command line: a TrainConfig made in code runs an optimiser step that moves what the stage trains, and only
    that."""
    from vlocnetpp_core.synth import render_dataset
    from vlocnetpp_core.training.train_data import SeededClips
    from vlocnetpp_core.training.trainer import Trainer

    render_dataset(
        tmp_path / "data", seed=0, train_loops=2, test_loops=0, frames_per_loop=6, size=(64, 48), progress=False
    )
    cfg = load_model_config("lite").to_dict() | {"input_size": [64, 48]}
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    config = TrainConfig(
        config=str(tmp_path / "tiny.yaml"),
        data=str(tmp_path / "data"),
        stage="stl-vo",
        out=str(tmp_path / "run"),
        steps=1,
        batch_size=2,
        clip_len=2,
        workers=0,
        threads=1,
        no_progress=True,
    )
    trainer = Trainer(config)
    assert (trainer.lr, trainer.crop_scale, trainer.tasks, trainer.total) == (1e-3, 1.0, ("vo",), 1)
    before = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    loader = torch.utils.data.DataLoader(SeededClips(trainer.train_clips), batch_size=2, sampler=trainer.sampler)
    record = trainer.train_step(next(iter(loader)), 0)
    assert record["step"] == 1 and record["lr"] == 1e-3 and math.isfinite(record["loss"]) and "q_vo" in record
    after = trainer.model.state_dict()
    moved = {k.split(".")[0] for k, v in after.items() if v.is_floating_point() and not torch.equal(v, before[k])}
    assert moved == {"trunk", "odometry"}  # stl-vo trains the odometry stream and the shared trunk

"""``TrainConfig``: the configuration of one ``vlocnetpp train`` run of one stage, checked once, when it is made.

One field per ``train`` flag (the flag's name with ``_`` for ``-``; ``--recipe`` and ``--train-config`` are the
command line's, not a run's). It is built from the command line (``training/train.py``, the only place that sees
an ``argparse.Namespace``), from a recipe stage (``training/recipe.py``), from a JSON file (``train
--train-config FILE``, what a recipe hands its stage processes: :meth:`TrainConfig.from_dict`), or directly (tests).
This module imports no torch, so that a recipe is checked in well under a second.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vlocnetpp_core.data.formats import FORMATS
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.model.config import load_model_config
from vlocnetpp_core.model.stages import PARTS, STAGES, stage_spec, stage_tasks

S_Q_INIT = -3.0  # the paper's initial rotation loss weight (VLocNetLoss)
_TYPE_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


class ConfigError(UserError):
    """A bad ``TrainConfig`` value; ``key`` is the field (the recipe key) it is about."""

    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key = key


def flag(key: str) -> str:
    """The ``vlocnetpp train`` flag of a field (``batch_size`` -> ``--batch-size``)."""
    return "--" + key.replace("_", "-")


@dataclass(frozen=True)
class TrainConfig:
    """One training run (docs/training.md has every flag). ``steps``/``epochs`` None: 30 epochs; ``lr`` None: the
    stage's default rate (with ``resume``: the run's); ``crop_scale`` None: the stage's default; ``val_every`` 0: at the
    last step only; ``device`` None: cuda if present."""

    config: str
    data: str
    stage: str
    out: str
    format: str | None = None
    steps: int | None = None
    epochs: float | None = None
    init: tuple[str, ...] = ()
    init_backbone: str | None = None
    freeze: tuple[str, ...] = ()
    resume: bool = False
    restart: bool = False
    batch_size: int = 32
    clip_len: int = 3
    frame_strides: tuple[int, ...] = (1,)
    lr: float | None = None
    lr_end: float | None = None
    crop_scale: float | None = None
    s_q_init: float = S_Q_INIT
    intrinsics: str | None = None
    val_data: str | None = None
    val_split: str = "train"
    val_every: int = 500
    save_every_s: float = 300.0
    workers: int = 2
    threads: int = field(default_factory=lambda: os.cpu_count() or 1)
    device: str | None = None
    bf16: bool = False
    seed: int = 0
    no_progress: bool = False

    def __post_init__(self) -> None:
        for key, hint in _hints().items():
            object.__setattr__(self, key, _typed(key, getattr(self, key), hint))
        object.__setattr__(self, "frame_strides", tuple(sorted(set(self.frame_strides))))
        object.__setattr__(self, "freeze", tuple(sorted(set(self.freeze))))
        _check(self)

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        """A config from a mapping of field names (a JSON file, a recipe stage); ``ConfigError`` naming an unknown
        key."""
        unknown = sorted(set(values) - set(cls.keys()))
        if unknown:
            raise ConfigError(
                unknown[0],
                f"unknown key {', '.join(map(repr, unknown))} (a train flag with _ for -: {', '.join(cls.keys())})",
            )
        missing = [key for key in ("config", "data", "stage", "out") if values.get(key) is None]
        if missing:
            raise ConfigError(missing[0], f"{', '.join(map(flag, missing))} required")
        return cls(**values)

    @classmethod
    def read(cls, path: str | Path) -> TrainConfig:
        """The config a :meth:`write` left in ``path``; ``UserError`` naming the file on any mistake."""
        try:
            values = json.loads(Path(path).read_text())
        except (OSError, ValueError) as err:
            raise UserError(f"{path}: cannot read the train config ({err})") from None
        if not isinstance(values, dict):
            raise UserError(f"{path}: a train config is a JSON object of train flags")
        try:
            return cls.from_dict(values)
        except ConfigError as err:
            raise UserError(f"{path}: {err}") from None

    def to_dict(self) -> dict[str, Any]:
        return {key: list(v) if isinstance(v := getattr(self, key), tuple) else v for key in self.keys()}

    def write(self, path: str | Path) -> Path:
        """Write the config as JSON (atomically) for ``vlocnetpp train --train-config FILE``."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=1) + "\n")
        tmp.replace(path)
        return path

    @property
    def learning_rate(self) -> float:
        """``lr``, else the stage's default rate."""
        return self.lr if self.lr is not None else stage_spec(self.stage).lr

    @property
    def crop(self) -> float:
        """``crop_scale``, else the stage's default."""
        return self.crop_scale if self.crop_scale is not None else stage_spec(self.stage).crop_scale


@functools.cache
def _hints() -> dict[str, Any]:
    return typing.get_type_hints(TrainConfig)


def _typed(key: str, value: Any, hint: Any) -> Any:
    """``value`` as the field's type (an int where a float is due, a list or tuple where a tuple is, a path where a
    string is); ``ConfigError`` for anything else."""
    args = typing.get_args(hint)
    if type(None) in args:
        if value is None:
            return None
        hint = next(a for a in args if a is not type(None))
    if typing.get_origin(hint) is tuple:
        (item,) = {a for a in typing.get_args(hint) if a is not Ellipsis}
        if not isinstance(value, (list, tuple)):
            raise ConfigError(key, f"{flag(key)} must be a list of {item.__name__} values, got {value!r}")
        return tuple(_typed(key, v, item) for v in value)
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint is str and isinstance(value, os.PathLike):
        return os.fspath(value)
    if not isinstance(value, hint) or (hint is not bool and isinstance(value, bool)):
        raise ConfigError(key, f"{flag(key)} must be {_TYPE_NAMES[hint]}, got {value!r}")
    return value


def _check(c: TrainConfig) -> None:
    """The value rules of every field, and that the model config has the stage's streams."""
    if c.stage not in STAGES:
        raise ConfigError("stage", f"--stage must be one of {', '.join(STAGES)}, got {c.stage!r}")
    if c.format is not None and c.format not in FORMATS:
        raise ConfigError("format", f"--format must be one of {', '.join(FORMATS)}, got {c.format!r}")
    for key, low, allow_equal in (
        ("steps", 0, True),
        ("epochs", 0, False),
        ("batch_size", 1, True),
        ("clip_len", 1, True),
        ("val_every", 0, True),
        ("save_every_s", 0, False),
        ("workers", 0, True),
        ("threads", 0, True),
        ("lr", 0, False),
        ("lr_end", 0, True),
        ("crop_scale", 1, True),
    ):
        value = getattr(c, key)
        if value is not None and not (math.isfinite(value) and (value >= low if allow_equal else value > low)):
            hint = " (--steps 0 assembles mtl from its stages without training)" if key == "epochs" else ""
            raise ConfigError(key, f"{flag(key)} must be {'>=' if allow_equal else '>'} {low}, got {value:g}{hint}")
    if c.steps is not None and c.epochs is not None:
        raise ConfigError("epochs", "--steps and --epochs exclude each other")
    if c.resume and c.restart:
        raise ConfigError("restart", "--resume and --restart exclude each other")
    if not c.frame_strides or min(c.frame_strides) < 1:
        raise ConfigError("frame_strides", f"--frame-strides must be strides >= 1, got {list(c.frame_strides)}")
    unknown = [part for part in c.freeze if part not in PARTS]
    if unknown:
        raise ConfigError("freeze", f"--freeze: {', '.join(unknown)} is not a part of the network ({', '.join(PARTS)})")
    try:
        stage_tasks(c.stage, load_model_config(c.config).tasks)
    except ValueError as err:
        raise ConfigError("config", f"--config {c.config}: {err}") from None

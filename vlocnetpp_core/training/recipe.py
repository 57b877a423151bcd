"""``vlocnetpp train --recipe FILE --out DIR``: a whole training schedule from one declarative YAML file.

A recipe names its datasets (rendered by ``synth`` when missing, or existing folders), the train
flags every stage shares, the stages in order (each a ``vlocnetpp train`` run in ``DIR/<name>``
with its own flags, ``--init`` sources and learning-rate schedule) and the export of the final
weights. Example (``config/recipes/shipped.yaml`` is the shipped model's)::

    config: lite
    datasets:
      campus: {synth: {scene: campus, seed: 0, loops: 8, test_loops: 1, frames_per_loop: 250}}
    defaults: {data: campus, batch_size: 8, clip_len: 3}
    stages:
      - {name: stl-vo, stage: stl-vo, schedule: [{steps: 1500, lr: 1.0e-3}]}
      - {name: stl-loc, stage: stl-loc, init: [stl-vo], schedule: [{steps: 6000, lr: 1.0e-3}, {steps: 8000, lr: 1.0e-4}]}
    export: {stage: stl-loc, to: models/my_model, dtype: float16, reference: campus}

Stage keys: ``name`` (run folder), ``stage``, ``schedule`` (list of ``{steps, lr}``: train to
``steps`` in total at ``lr``, resuming from the previous entry; with ``lr_end: R`` the rate falls
from ``lr`` to ``R`` along a half cosine over the entry, ``vlocnetpp train --lr-end``; with
``restart: true`` the entry starts from the previous one's weights with a fresh optimiser state and
the learned loss weights at their initial values, ``vlocnetpp train --restart``), ``init`` (stage names: their
weights, in order), ``weights`` (which of a stage's checkpoints later stages' ``init`` and the export
calibration take: ``best``, default, the lowest validation error, or ``last``, e.g. for a schedule whose
last entry restarts the rate, where validation errors of different phases trade position against rotation), ``continue`` (a stage name: start as a copy of that stage's run
folder and resume it, e.g. to use a stage's early weights as another's init and train it on),
``data`` / ``val_data`` (dataset names), ``config`` (this stage's model config instead of the
recipe's: a built-in name or a YAML file relative to the recipe; e.g. a stage that learns a
shared trunk with another head), and any other ``vlocnetpp train`` flag (``threads``, ``frame_strides``,
``s_q_init``, ``val_split``, ...; lists become comma-separated). Running it (:mod:`vlocnetpp_core.training.recipe_run`):
every dataset render and every stage is its own process (a stage's thread count its own); a stage starts as
soon as its datasets are rendered, the stages it takes weights from have finished and its ``threads`` fit
in the free cores, logs to ``DIR/<name>.log``, and is
resumable: running the recipe again skips finished schedule entries and resumes an interrupted one
exactly. The time of each stage is added to ``DIR/timings.json`` and printed.

``export``: the ``weights`` (``best``, default, or ``last``) of ``stage`` written to ``to``
(``NAME``: ``NAME.safetensors`` + ``NAME.json``) in ``dtype``, with the covariance calibration
of its validation (or, when it did not validate, of the stages named in ``calibration``:
``{pose: STAGE, odometry: STAGE}``), and the retrieval reference of the ``reference`` dataset's
training images as ``NAME.reference.npz`` (the baseline ``evaluate`` and the demo compare with;
a list of datasets: all their training images, e.g. every image whose pose the network learnt).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from vlocnetpp_core.errors import UserError

STAGE_KEYS = {"name", "stage", "schedule", "init", "data", "val_data", "continue", "config", "weights"}
WEIGHTS = ("best", "last")


@dataclass(frozen=True)
class Entry:
    """One schedule entry: train to ``steps`` (in total) at ``lr``, annealed to ``lr_end`` along a half cosine when set;
    ``restart``: start it with a fresh optimiser state and the initial loss weights (a warm restart)."""

    steps: int
    lr: float
    lr_end: float | None = None
    restart: bool = False


@dataclass
class Stage:
    """One ``vlocnetpp train`` run of a recipe: its flags (argparse names, ``_`` separated) and schedule."""

    name: str
    stage: str
    schedule: list[Entry]
    init: list[str] = field(default_factory=list)
    flags: dict = field(default_factory=dict)
    continues: str | None = None
    config: str | None = None  # model config of this stage (default: the recipe's)
    weights: str = "best"  # the checkpoint later stages take from this one (best or last)

    @property
    def steps(self) -> int:
        return self.schedule[-1].steps


@dataclass
class Recipe:
    path: Path
    config: str
    datasets: dict[str, dict]
    stages: list[Stage]
    export: dict | None


def load_recipe(path: str | Path) -> Recipe:
    """Parse and check a recipe file; ``UserError`` naming the file and the key on any mistake."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise UserError(f"{path}: cannot read the recipe ({err})") from None
    if not isinstance(raw, dict) or "stages" not in raw or "config" not in raw:
        raise UserError(f"{path}: a recipe is a mapping with at least 'config' and 'stages'")
    datasets = raw.get("datasets") or {}
    defaults = {k.replace("-", "_"): v for k, v in (raw.get("defaults") or {}).items()}
    stages, names = [], set()
    for k, entry in enumerate(raw["stages"]):
        entry = {**defaults, **{key.replace("-", "_"): v for key, v in entry.items()}}
        where = f"{path}: stage {k} ({entry.get('name', 'unnamed')})"
        for key in ("name", "stage", "schedule"):
            if key not in entry:
                raise UserError(f"{where}: missing '{key}'")
        if "parallel" in entry:
            raise UserError(f"{where}: 'parallel' is gone: stages now start as soon as their inits are done and their "
                            "threads fit in the free cores (give each stage's threads instead)")
        schedule = _schedule(entry["schedule"], where)
        for ref in [*(entry.get("init") or []), *([entry["continue"]] if "continue" in entry else [])]:
            if ref not in names:
                raise UserError(f"{where}: '{ref}' (init or continue) is not an earlier stage")
        for key in ("data", "val_data"):
            if key in entry and entry[key] not in datasets:
                raise UserError(f"{where}: {key} '{entry[key]}' is not one of the recipe's datasets ({', '.join(datasets) or 'none'})")
        weights = entry.get("weights", "best")
        if weights not in WEIGHTS:
            raise UserError(f"{where}: weights must be one of {', '.join(WEIGHTS)}, got {weights!r}")
        names.add(entry["name"])
        config = None if entry.get("config") is None else _stage_config(str(entry["config"]), path, where)
        flags = {key: v for key, v in entry.items() if key not in STAGE_KEYS - {"data", "val_data"}}
        stages.append(Stage(entry["name"], entry["stage"], schedule, list(entry.get("init") or []), flags, entry.get("continue"),
                            config, weights))
    export = raw.get("export")
    if export is not None and export.get("stage") not in names:
        raise UserError(f"{path}: export stage '{export.get('stage')}' is not one of the stages")
    if export is not None and export.get("reference"):
        references = [export["reference"]] if isinstance(export["reference"], str) else list(export["reference"])
        unknown = [name for name in references if name not in datasets]
        if unknown:
            raise UserError(f"{path}: export reference {', '.join(map(repr, unknown))} is not one of the recipe's datasets "
                            f"({', '.join(datasets) or 'none'})")
        export = {**export, "reference": references}
    return Recipe(path, str(raw["config"]), datasets, stages, export)


def _schedule(raw, where: str) -> list[Entry]:
    """A stage's ``schedule`` list as entries; ``UserError`` for a malformed entry or steps out of order."""
    try:
        schedule = [Entry(int(s["steps"]), float(s["lr"]), None if s.get("lr_end") is None else float(s["lr_end"]), _flag(s.get("restart", False)))
                    for s in raw]
    except (TypeError, KeyError, ValueError, AttributeError):
        raise UserError(f"{where}: 'schedule' must be a list of {{steps: N, lr: R}} (optionally lr_end: R, a cosine to R, "
                        "and restart: true, a fresh optimiser state)") from None
    if not schedule or any(b.steps < a.steps for a, b in zip(schedule[:-1], schedule[1:], strict=True)):
        raise UserError(f"{where}: 'schedule' steps must be given in increasing order")
    if schedule[0].restart:
        raise UserError(f"{where}: the first schedule entry cannot restart (there is nothing before it to restart from)")
    return schedule


def _flag(value) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"expected true or false, got {value!r}")
    return value


def _stage_config(value: str, recipe_path: Path, where: str) -> str:
    """A stage's ``config``: a built-in name, or a YAML path relative to the recipe file (made absolute)."""
    from vlocnetpp_core.model.config import BUILTIN_CONFIGS

    if value in BUILTIN_CONFIGS:
        return value
    resolved = (recipe_path.parent / value).resolve()
    if not resolved.is_file():
        raise UserError(f"{where}: config '{value}' is neither a built-in model config ({', '.join(BUILTIN_CONFIGS)}) "
                        f"nor a file next to the recipe ({resolved})")
    return str(resolved)


# --------------------------------------------------------------------------- running


def dataset_path(recipe: Recipe, name: str, out: Path) -> Path:
    spec = recipe.datasets[name]
    return Path(spec["path"]) if "path" in spec else out / "data" / name


def _flag_args(flags: dict, recipe: Recipe, out: Path) -> list[str]:
    args = []
    for key, value in flags.items():
        if key in ("data", "val_data"):
            value = dataset_path(recipe, value, out)
        if isinstance(value, bool):
            if value:
                args.append("--" + key.replace("_", "-"))
            continue
        if isinstance(value, (list, tuple)):
            value = ",".join(str(v) for v in value)
        args += ["--" + key.replace("_", "-"), str(value)]
    return args


def stage_step(run_dir: Path) -> int:
    """The step a stage's run folder has reached (-1 when it has not started; a 0-step run, e.g. ``mtl``
    assembled from its single-task stages, has reached 0)."""
    state = run_dir / "train_state.json"
    return int(json.loads(state.read_text())["step"]) if state.is_file() else -1


def stage_weights(recipe: Recipe, name: str, out: Path) -> Path:
    """``OUT/NAME/best`` or ``OUT/NAME/last`` (the stage's ``weights``): the checkpoint (without suffix) that later stages take."""
    stage = next((s for s in recipe.stages if s.name == name), None)
    if stage is None:
        raise UserError(f"{recipe.path}: '{name}' is not one of the stages")
    return out / name / stage.weights


def stage_commands(stage: Stage, recipe: Recipe, out: Path, python: str = sys.executable) -> list[list[str]]:
    """The ``vlocnetpp train`` commands still to run for ``stage`` (one per unfinished schedule entry)."""
    run_dir = out / stage.name
    done = stage_step(run_dir)
    base = [python, "-m", "vlocnetpp_core.cli", "train", "--config", stage.config or recipe.config, "--stage", stage.stage, "--out", str(run_dir),
            "--no-progress", *_flag_args(stage.flags, recipe, out)]
    for ref in stage.init:
        base += ["--init", str(stage_weights(recipe, ref, out).with_suffix(".safetensors"))]
    commands, start = [], 0
    for entry in stage.schedule:
        if done < entry.steps:
            if entry.restart and done <= start:  # not begun yet (an interrupted restart resumes as any entry)
                again = ["--restart"]
            else:
                again = ["--resume"] if done > 0 or commands else []
            anneal = [] if entry.lr_end is None else ["--lr-end", f"{entry.lr_end:g}"]
            commands.append([*base, "--steps", str(entry.steps), "--lr", f"{entry.lr:g}", *anneal, *again])
            done = entry.steps
        start = entry.steps
    return commands

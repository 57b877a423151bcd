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
      - {name: stl-loc, stage: stl-loc, init: [stl-vo],
         schedule: [{steps: 6000, lr: 1.0e-3}, {steps: 8000, lr: 1.0e-4}]}
    export: {stage: stl-loc, to: models/my_model, dtype: float16, reference: campus}

Stage keys: ``name`` (run folder), ``stage``, ``schedule`` (list of ``{steps, lr}``: train to
``steps`` in total at ``lr``, resuming from the previous entry; with ``lr_end: R`` the rate falls
from ``lr`` to ``R`` along a half cosine over the entry, ``vlocnetpp train --lr-end``; with
``restart: true`` the entry starts from the previous one's weights with a fresh optimiser state and
the learned loss weights at their initial values, ``vlocnetpp train --restart``), ``init`` (names of earlier
stages: their weights, in order), ``weights`` (which of a stage's checkpoints later stages' ``init`` and the export
calibration take: ``best``, default, the lowest validation error, or ``last``, e.g. for a schedule whose
last entry restarts the rate, where validation errors of different phases trade position against rotation),
``continue`` (an earlier stage's name: start as a copy of that stage's run folder and resume it, e.g. to use a
stage's early weights as another's init and train it on), ``data`` / ``val_data`` (dataset names), ``config`` (this
stage's model config instead of the recipe's: a built-in name or a YAML file relative to the recipe; e.g. a stage
that learns a shared trunk with another head), and any other key of
:class:`~vlocnetpp_core.training.config.TrainConfig` (a ``vlocnetpp train`` flag with ``_`` for ``-``: ``threads``,
``frame_strides``, ``s_q_init``, ``val_split``, ...; lists as YAML lists) except those the recipe sets itself
(:data:`SET_BY_RECIPE`). ``defaults`` gives keys every stage shares.

``base: FILE`` (a recipe next to this one): this recipe is that one's datasets, defaults and stages, exactly as the
base runs them (their model config included), then its own stages (which may take weights from the base's), with
its datasets and defaults over the base's and its ``config`` for its own stages; the base's export is not taken.
Run into the base's run folder it trains only its own stages, e.g. ablation arms beside a finished recipe
(``config/recipes/multitask_arms.yaml``).

:func:`load_recipe` checks the whole file before anything runs: every key (unknown ones are named with their
stage), every value (each schedule entry becomes a ``TrainConfig``, checked as ``vlocnetpp train`` checks its
flags, the model config included), the stage order (``init`` and ``continue`` name earlier stages, so there is no
cycle) and the export. Running it (:mod:`vlocnetpp_core.training.recipe_run`): every dataset render and every
stage is its own process (a stage's thread count its own); a stage starts as soon as its datasets are rendered,
the stages it takes weights from have finished and its ``threads`` fit in the free cores. Each schedule entry
still to run is written as ``DIR/<name>.<k>.json`` (its ``TrainConfig``) and run as ``vlocnetpp train
--train-config DIR/<name>.<k>.json``, logging to ``DIR/<name>.log``; it is resumable: running the recipe again
skips finished schedule entries and resumes an interrupted one exactly. The time of each stage is added to
``DIR/timings.json`` and printed.

``export`` (keys :data:`EXPORT_KEYS`): the ``weights`` (``best``, default, or ``last``) of ``stage`` written to ``to``
(``NAME``: ``NAME.safetensors`` + ``NAME.json``) in ``dtype`` (:data:`EXPORT_DTYPES`; default float16), with the
covariance calibration of its validation (or, when it did not validate, of the stages named in ``calibration``:
``{pose: STAGE, odometry: STAGE}``), and the retrieval reference of the ``reference`` dataset's
training images as ``NAME.reference.npz`` (the baseline ``evaluate`` and the demo compare with;
a list of datasets: all their training images, e.g. every image whose pose the network learnt), and, with
``class_offsets: DATASET``, the segmentation's per-class offsets fitted on that dataset's test split (validation
visits; :mod:`vlocnetpp_core.inference.class_offsets`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.training.config import ConfigError, TrainConfig

RECIPE_KEYS = ("base", "config", "datasets", "defaults", "stages", "export")
STAGE_KEYS = ("name", "stage", "schedule", "init", "data", "val_data", "continue", "config", "weights")
SET_BY_RECIPE = ("out", "steps", "epochs", "lr", "lr_end", "resume", "restart", "no_progress")
WEIGHTS = ("best", "last")
EXPORT_KEYS = ("stage", "weights", "to", "dtype", "reference", "calibration", "class_offsets")
EXPORT_DTYPES = ("float16", "float32")
CALIBRATION_KINDS = ("pose", "odometry")


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
    """One ``vlocnetpp train`` run of a recipe: its ``TrainConfig`` keys (``train``), datasets and schedule."""

    name: str
    stage: str
    schedule: list[Entry]
    init: list[str] = field(default_factory=list)
    train: dict[str, Any] = field(default_factory=dict)  # TrainConfig keys other than those the recipe sets
    continues: str | None = None
    config: str | None = None  # model config of this stage (default: the recipe's)
    weights: str = "best"  # the checkpoint later stages take from this one (best or last)
    data: str | None = None  # dataset names
    val_data: str | None = None

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
    defaults: dict[str, Any] = field(default_factory=dict)  # the keys this file's stages share (over its base's)


def load_recipe(path: str | Path, _chain: tuple[Path, ...] = ()) -> Recipe:
    """Parse and check a whole recipe file (module doc); ``UserError`` naming the file, the stage and the key."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise UserError(f"{path}: cannot read the recipe ({err})") from None
    if not isinstance(raw, dict) or "stages" not in raw or not ({"config", "base"} & set(raw)):
        raise UserError(f"{path}: a recipe is a mapping with at least 'config' (or 'base') and 'stages'")
    _known(raw, RECIPE_KEYS, f"{path}")
    base = _base_recipe(raw, path, _chain)
    if not isinstance(raw.get("datasets") or {}, dict) or not isinstance(raw["stages"], list):
        raise UserError(f"{path}: 'datasets' is a mapping of names and 'stages' a list")
    datasets = {**base.datasets, **(raw.get("datasets") or {})}
    defaults = _keys(raw.get("defaults") or {}, f"{path}: defaults")
    _known(defaults, (*STAGE_KEYS, *TrainConfig.keys()), f"{path}: defaults", SET_BY_RECIPE)
    defaults = {**base.defaults, **defaults}
    names = [s.name for s in base.stages] + [e.get("name") if isinstance(e, dict) else None for e in raw["stages"]]
    first = len(base.stages)
    stages = base.stages + [
        _stage(entry, first + k, names, defaults, datasets, path) for k, entry in enumerate(raw["stages"])
    ]
    recipe = Recipe(path, str(raw.get("config", base.config)), datasets, stages, None, defaults)
    # every schedule entry of this file's stages as the TrainConfig it runs (the base's: checked by its own load)
    for k, stage in enumerate(stages[first:], first):
        try:
            stage_configs(stage, recipe, Path("OUT"), done=-1)
        except ConfigError as err:
            raise UserError(f"{path}: stage {k} ({stage.name}): '{err.key}': {err}") from None
        except UserError as err:
            raise UserError(f"{path}: stage {k} ({stage.name}): {err}") from None
    recipe.export = _export(raw.get("export"), names, datasets, path)
    return recipe


def _base_recipe(raw: dict, path: Path, chain: tuple[Path, ...]) -> Recipe:
    """The recipe ``raw['base']`` names (a file relative to ``path``), checked, without its export; an empty one
    when there is no ``base``."""
    if "base" not in raw:
        return Recipe(path, "", {}, [], None)
    base = (path.parent / str(raw["base"])).resolve()
    if base in chain or base == path.resolve():
        raise UserError(f"{path}: base '{raw['base']}' is this recipe or one of its own bases (a cycle)")
    if not base.is_file():
        raise UserError(f"{path}: base '{raw['base']}' is not a recipe file next to this one ({base})")
    recipe = load_recipe(base, (*chain, path.resolve()))
    recipe.stages = [replace(stage, config=stage.config or recipe.config) for stage in recipe.stages]
    return recipe


def _keys(raw, where: str) -> dict:
    if not isinstance(raw, dict):
        raise UserError(f"{where}: expected a mapping of keys, got {raw!r}")
    return {str(key).replace("-", "_"): value for key, value in raw.items()}


def _known(entry: dict, known, where: str, refused=()) -> None:
    """``UserError`` naming the first key of ``entry`` that is refused or not ``known``."""
    for key in entry:
        if key in refused:
            raise UserError(
                f"{where}: '{key}' is set by the recipe (the schedule, the run folder, init), not by a stage"
            )
        if key not in known:
            raise UserError(
                f"{where}: unknown key '{key}' (known: "
                f"{', '.join(dict.fromkeys(k for k in known if k not in refused))})"
            )


def _stage(raw, k: int, names: list, defaults: dict, datasets: dict, path: Path) -> Stage:
    """Stage ``k`` of the file with the ``defaults`` filled in; ``UserError`` for a bad key, reference or schedule."""
    entry = {**defaults, **_keys(raw, f"{path}: stage {k}")}
    where = f"{path}: stage {k} ({entry.get('name', 'unnamed')})"
    if "parallel" in entry:
        raise UserError(
            f"{where}: 'parallel' is gone: stages now start as soon as their inits are done and their "
            "threads fit in the free cores (give each stage's threads instead)"
        )
    _known(entry, (*STAGE_KEYS, *TrainConfig.keys()), where, SET_BY_RECIPE)
    for key in ("name", "stage", "schedule"):
        if key not in entry:
            raise UserError(f"{where}: missing '{key}'")
    if entry["name"] in names and names.index(entry["name"]) != k:
        raise UserError(f"{where}: the name '{entry['name']}' is also stage {names.index(entry['name'])}'s")
    refs = [*(entry.get("init") or []), *([entry["continue"]] if "continue" in entry else [])]
    for ref in refs:
        if ref not in names[:k]:
            why = (
                " (a later stage or itself: stages run in file order, so that would be a cycle)" if ref in names else ""
            )
            raise UserError(f"{where}: '{ref}' (init or continue) is not an earlier stage{why}")
    for key in ("data", "val_data"):
        if key in entry and entry[key] not in datasets:
            raise UserError(
                f"{where}: {key} '{entry[key]}' is not one of the recipe's datasets ({', '.join(datasets) or 'none'})"
            )
    weights = entry.get("weights", "best")
    if weights not in WEIGHTS:
        raise UserError(f"{where}: weights must be one of {', '.join(WEIGHTS)}, got {weights!r}")
    config = None if entry.get("config") is None else _stage_config(str(entry["config"]), path, where)
    train = {key: v for key, v in entry.items() if key not in STAGE_KEYS}
    return Stage(
        entry["name"],
        entry["stage"],
        _schedule(entry["schedule"], where),
        list(entry.get("init") or []),
        train,
        entry.get("continue"),
        config,
        weights,
        entry.get("data"),
        entry.get("val_data"),
    )


def _export(export, names: list, datasets: dict, path: Path) -> dict | None:
    """The checked ``export`` mapping (``reference`` as a list of dataset names), or None."""
    if export is None:
        return None
    where = f"{path}: export"
    if not isinstance(export, dict):
        raise UserError(f"{where}: expected a mapping ({', '.join(EXPORT_KEYS)})")
    for key in export:
        if key not in EXPORT_KEYS:
            raise UserError(f"{where}: unknown key '{key}' (known: {', '.join(EXPORT_KEYS)})")
    if export.get("stage") not in names:
        raise UserError(f"{path}: export stage '{export.get('stage')}' is not one of the stages")
    if export.get("weights", "best") not in WEIGHTS:
        raise UserError(f"{where}: 'weights' must be one of {', '.join(WEIGHTS)}, got {export['weights']!r}")
    if str(export.get("dtype", "float16")) not in EXPORT_DTYPES:
        raise UserError(f"{where}: 'dtype' must be one of {', '.join(EXPORT_DTYPES)}, got {export['dtype']!r}")
    calibration = export.get("calibration")
    if calibration is not None:
        if not isinstance(calibration, dict) or set(calibration) != set(CALIBRATION_KINDS):
            raise UserError(f"{where}: 'calibration' is {{pose: STAGE, odometry: STAGE}}, got {calibration!r}")
        unknown = [stage for stage in calibration.values() if stage not in names]
        if unknown:
            raise UserError(f"{where}: calibration stage {', '.join(map(repr, unknown))} is not one of the stages")
    if export.get("reference"):
        references = [export["reference"]] if isinstance(export["reference"], str) else list(export["reference"])
        unknown = [name for name in references if name not in datasets]
        if unknown:
            raise UserError(
                f"{path}: export reference {', '.join(map(repr, unknown))} is not one of the recipe's datasets "
                f"({', '.join(datasets) or 'none'})"
            )
        export = {**export, "reference": references}
    offsets = export.get("class_offsets")
    if offsets is not None and (not isinstance(offsets, str) or offsets not in datasets):
        raise UserError(
            f"{where}: 'class_offsets' {offsets!r} is not one of the recipe's datasets "
            f"({', '.join(datasets) or 'none'})"
        )
    if not isinstance(export.get("to"), str):
        raise UserError(f"{where}: 'to' (the path of the exported weights, NAME) is required")
    return export


def _schedule(raw, where: str) -> list[Entry]:
    """A stage's ``schedule`` list as entries; ``UserError`` for a malformed entry or steps out of order."""
    try:
        schedule = [
            Entry(
                int(s["steps"]),
                float(s["lr"]),
                None if s.get("lr_end") is None else float(s["lr_end"]),
                _flag(s.get("restart", False)),
            )
            for s in raw
        ]
    except (TypeError, KeyError, ValueError, AttributeError):
        raise UserError(
            f"{where}: 'schedule' must be a list of {{steps: N, lr: R}} (optionally lr_end: R, a cosine to R, "
            "and restart: true, a fresh optimiser state)"
        ) from None
    if not schedule or any(b.steps < a.steps for a, b in zip(schedule[:-1], schedule[1:], strict=True)):
        raise UserError(f"{where}: 'schedule' steps must be given in increasing order")
    if schedule[0].restart:
        raise UserError(
            f"{where}: the first schedule entry cannot restart (there is nothing before it to restart from)"
        )
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
        raise UserError(
            f"{where}: config '{value}' is neither a built-in model config ({', '.join(BUILTIN_CONFIGS)}) "
            f"nor a file next to the recipe ({resolved})"
        )
    return str(resolved)


# --------------------------------------------------------------------------- running


def dataset_path(recipe: Recipe, name: str, out: Path) -> Path:
    spec = recipe.datasets[name]
    return Path(spec["path"]) if "path" in spec else out / "data" / name


def stage_step(run_dir: Path) -> int:
    """The step a stage's run folder has reached (-1 when it has not started; a 0-step run, e.g. ``mtl``
    assembled from its single-task stages, has reached 0)."""
    state = run_dir / "train_state.json"
    return int(json.loads(state.read_text())["step"]) if state.is_file() else -1


def stage_weights(recipe: Recipe, name: str, out: Path) -> Path:
    """``OUT/NAME/best`` or ``OUT/NAME/last`` (the stage's ``weights``): the checkpoint (without suffix) that later
    stages take."""
    stage = next((s for s in recipe.stages if s.name == name), None)
    if stage is None:
        raise UserError(f"{recipe.path}: '{name}' is not one of the stages")
    return out / name / stage.weights


def stage_configs(stage: Stage, recipe: Recipe, out: Path, done: int | None = None) -> list[TrainConfig]:
    """The ``TrainConfig`` of every schedule entry of ``stage`` still to run from step ``done`` (default: the step its
    run folder in ``out`` has reached; -1: from the start), each resuming (or restarting) from the one before."""
    done = stage_step(out / stage.name) if done is None else done
    base = {
        **stage.train,
        "config": stage.config or recipe.config,
        "stage": stage.stage,
        "out": str(out / stage.name),
        "no_progress": True,
        "init": [str(stage_weights(recipe, ref, out).with_suffix(".safetensors")) for ref in stage.init],
    }
    for key in ("data", "val_data"):
        if getattr(stage, key) is not None:
            base[key] = str(dataset_path(recipe, getattr(stage, key), out))
    configs, start = [], 0
    for entry in stage.schedule:
        if done < entry.steps:
            restart = entry.restart and done <= start  # not begun yet (an interrupted restart resumes as any entry)
            resume = not restart and (done > 0 or bool(configs))
            configs.append(
                TrainConfig.from_dict(
                    {
                        **base,
                        "steps": entry.steps,
                        "lr": entry.lr,
                        "lr_end": entry.lr_end,
                        "resume": resume,
                        "restart": restart,
                    }
                )
            )
            done = entry.steps
        start = entry.steps
    return configs


def stage_commands(stage: Stage, recipe: Recipe, out: Path, python: str) -> list[list[str]]:
    """The commands still to run for ``stage``: each entry's ``TrainConfig`` written to ``OUT/NAME.K.json`` (K: the
    entry's number, from 1), run by ``vlocnetpp train --train-config``."""
    configs = stage_configs(stage, recipe, out)
    first = len(stage.schedule) - len(configs) + 1
    commands = []
    for k, config in enumerate(configs, first):
        path = config.write(out / f"{stage.name}.{k}.json")
        commands.append([python, "-m", "vlocnetpp_core.cli", "train", "--train-config", str(path)])
    return commands

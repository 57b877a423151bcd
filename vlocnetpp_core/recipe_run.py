"""Running a recipe (``vlocnetpp train --recipe FILE --out DIR``): its datasets, its stages as soon as they can
start, then its export. The file format and each stage's commands: :mod:`vlocnetpp_core.recipe`.

Datasets that are not there yet are rendered side by side, one process per core. Stages run as their own
processes, scheduled on the machine's cores: a stage starts (in file order) once every stage it takes weights
from (``init``, ``continue``) has finished and its ``threads`` fit in the cores the running stages leave
free (one that asks for more than there are starts alone), so a later stage may start beside an earlier one
that still runs, e.g. ``stl-vo`` beside ``stl-seg`` once ``stl-loc-trunk`` is done. When a stage fails no
other starts; the running ones finish, then the run stops with the failed stages' logs named. Every
stage's wall time, the datasets' and the whole run's are added to ``DIR/timings.json`` and printed.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import IO

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.recipe import Recipe, Stage, dataset_path, load_recipe, stage_commands
from vlocnetpp_core.threads import resolve_threads

POLL_S = 1.0  # how often the scheduler looks at its running stages


def run_recipe(path: str | Path, out: str | Path, cores: int | None = None) -> int:
    """Datasets, stages and export of the recipe at ``path`` into ``out``, on ``cores`` (default: the machine's)."""
    recipe = load_recipe(path)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cores = cores or os.cpu_count() or 1

    def log(msg: str) -> None:
        print(f"[recipe {time.strftime('%H:%M:%S')}] {msg}", flush=True)

    t0 = time.monotonic()
    prepare_datasets(recipe, out, log, cores)
    run_stages(recipe, out, log, cores)
    if recipe.export:
        from vlocnetpp_core.recipe_export import export_weights

        log(f"export: {export_weights(recipe, out)}")
    record_time(out, "recipe (end to end)", time.monotonic() - t0, log)
    return 0


def prepare_datasets(recipe: Recipe, out: Path, log, cores: int = 1) -> None:
    """Render every ``synth`` dataset that is not there yet (``OUT/data/NAME``), up to ``cores`` at a time."""
    todo = []
    for name, spec in recipe.datasets.items():
        target = dataset_path(recipe, name, out)
        if "path" in spec:
            if not target.is_dir():
                raise UserError(f"{recipe.path}: dataset '{name}': {target} not found")
        elif not target.is_dir():
            todo.append((name, target, _synth_args(spec["synth"])))
    if not todo:
        return
    t0 = time.monotonic()
    todo.sort(key=lambda item: -(item[2]["train_loops"] + item[2]["test_loops"]) * item[2]["frames_per_loop"])  # longest first
    with ProcessPoolExecutor(min(cores, len(todo)), mp_context=get_context("spawn")) as pool:
        started = {pool.submit(_render, target, args): (name, time.monotonic()) for name, target, args in todo}
        for done in as_completed(started):
            done.result()  # a UserError (bad synth keys) surfaces here, with its message
            name, start = started[done]
            log(f"dataset {name}: rendered in {time.monotonic() - start:.0f} s")
    record_time(out, "datasets", time.monotonic() - t0, log)


def _synth_args(synth: dict) -> dict:
    """A dataset's ``synth`` keys as ``render_dataset`` arguments (the recipe's defaults filled in)."""
    return {"scene": synth.get("scene", "campus"), "seed": int(synth.get("seed", 0)), "train_loops": int(synth.get("loops", 4)),
            "test_loops": int(synth.get("test_loops", 2)), "frames_per_loop": int(synth.get("frames_per_loop", 175)),
            "size": tuple(synth.get("size", (320, 180))), "lane_wander": float(synth.get("lane_wander", 0.0))}


def _render(target: Path, args: dict) -> None:
    from vlocnetpp_core.synth import render_dataset

    render_dataset(target, **args, progress=False)


@dataclass
class _Running:
    stage: Stage
    threads: int
    proc: subprocess.Popen
    logf: IO
    start: float


def run_stages(recipe: Recipe, out: Path, log, cores: int) -> None:
    """Every stage, each as soon as its inputs are finished and its threads fit (module docstring); raises
    :class:`UserError` naming the logs of the stages that failed, once the running ones have ended."""
    waiting, running, finished, failed = list(recipe.stages), [], set(), []
    while waiting or running:
        free = cores - sum(r.threads for r in running)
        for stage in list(waiting) if not failed else []:
            threads = stage_threads(stage)
            if _inputs(stage) <= finished and (threads <= free or not running):
                waiting.remove(stage)
                started = _start(stage, threads, recipe, out, log)
                if started is None:
                    finished.add(stage.name)  # nothing left to train
                else:
                    running.append(started)
                    free -= threads
        if failed and not running:
            break
        time.sleep(POLL_S if running else 0)
        for run in [r for r in running if r.proc.poll() is not None]:
            running.remove(run)
            run.logf.close()
            if run.proc.returncode == 0:
                finished.add(run.stage.name)
                record_time(out, run.stage.name, time.monotonic() - run.start, log)
            else:
                failed.append(run.stage.name)
                log(f"stage {run.stage.name} failed (exit {run.proc.returncode}); no other stage starts"
                    + (f", waiting for {', '.join(r.stage.name for r in running)}" if running else ""))
    if failed:
        raise UserError(f"stage {', '.join(failed)} failed; see {', '.join(str(out / f'{n}.log') for n in failed)} "
                        "(run the recipe again to resume)")


def stage_threads(stage: Stage) -> int:
    """The CPU threads a stage's ``vlocnetpp train`` uses (its ``threads``; train's default: every core)."""
    return resolve_threads(int(stage.flags.get("threads", os.cpu_count() or 1)))


def _inputs(stage: Stage) -> set[str]:
    return set(stage.init) | ({stage.continues} if stage.continues else set())


def _start(stage: Stage, threads: int, recipe: Recipe, out: Path, log) -> _Running | None:
    """Launch the commands still to run for ``stage`` (one shell, in order); None when there are none."""
    continue_run(stage, out)
    commands = stage_commands(stage, recipe, out)
    if not commands:
        return None
    logf = open(out / f"{stage.name}.log", "a")
    log(f"stage {stage.name}: {stage.stage} to step {stage.steps} on {threads} thread{'s' * (threads > 1)} "
        f"(log {out / f'{stage.name}.log'})")
    script = " && ".join(shlex.join(c) for c in commands)
    proc = subprocess.Popen(["bash", "-c", script], stdout=logf, stderr=subprocess.STDOUT)
    return _Running(stage, threads, proc, logf, time.monotonic())


def continue_run(stage: Stage, out: Path) -> None:
    """A stage that ``continue``s another starts as a copy of that stage's run folder (then resumes it)."""
    if stage.continues and not (out / stage.name).exists():
        tmp = out / f".{stage.name}.copy"
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(out / stage.continues, tmp)
        tmp.rename(out / stage.name)


def record_time(out: Path, name: str, seconds: float, log) -> None:
    """Add ``seconds`` to ``name`` in ``OUT/timings.json`` (so a resumed run sums its parts) and print both."""
    path = out / "timings.json"
    timings = json.loads(path.read_text()) if path.is_file() else {}
    timings[name] = timings.get(name, 0.0) + seconds
    tmp = path.with_name(".timings.json.tmp")
    tmp.write_text(json.dumps(timings, indent=2) + "\n")
    tmp.replace(path)
    log(f"{name}: {seconds / 60:.1f} min (in total {timings[name] / 60:.1f} min)")

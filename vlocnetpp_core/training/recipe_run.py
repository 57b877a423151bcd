"""Running a recipe (``vlocnetpp train --recipe FILE --out DIR``): its datasets and stages as soon as they can start,
then its export. The file format and each stage's commands: :mod:`vlocnetpp_core.training.recipe`.

Every dataset still to render (``vlocnetpp synth``, one core each) and every stage (``vlocnetpp train``, on its
``threads``) is a job: its own process, scheduled on the machine's cores. Each dataset comes just before the first
stage that takes it (longest first among equals; those no stage takes, last), so that no render delays an earlier
stage; a job starts (in that order) once its datasets are rendered, every stage it takes weights from (``init``,
``continue``) has finished and its ``threads`` fit in the cores the running jobs leave free (one that asks for more
than there are starts alone). So a stage may start while a later stage's dataset still renders, and a later stage
beside an earlier one that still runs, e.g. ``stl-vo`` beside ``stl-seg`` once ``stl-loc-trunk`` is done. When a job
fails no other starts; the running ones finish, then the run stops naming the failed jobs' logs and their last
lines. Ctrl-C or SIGTERM interrupts every running job too. Every job's wall time (an interrupted one's up to the
interruption) and the whole run's are added to ``DIR/timings.json`` and printed, so a resumed run sums its parts.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.interrupts import sigterm_as_interrupt
from vlocnetpp_core.threads import resolve_threads
from vlocnetpp_core.training.recipe import Recipe, Stage, dataset_path, load_recipe, stage_commands

POLL_S = 1.0  # how often the scheduler looks at its running jobs


def run_recipe(path: str | Path, out: str | Path, cores: int | None = None) -> int:
    """Datasets, stages and export of the recipe at ``path`` into ``out``, on ``cores`` (default: the machine's)."""
    recipe = load_recipe(path)
    out = Path(out)
    jobs = recipe_jobs(recipe, out)  # checks the datasets too, before anything is written
    out.mkdir(parents=True, exist_ok=True)
    cores = cores or os.cpu_count() or 1

    def log(msg: str) -> None:
        print(f"[recipe {time.strftime('%H:%M:%S')}] {msg}", flush=True)

    t0 = time.monotonic()
    try:
        with sigterm_as_interrupt():
            run_jobs(jobs, out, log, cores)
            if recipe.export:
                from vlocnetpp_core.training.recipe_export import export_weights

                log(f"export: {export_weights(recipe, out)}")
    finally:
        record_time(out, "recipe (end to end)", time.monotonic() - t0, log)
    return 0


@dataclass
class Job:
    """One process of a recipe run: ``commands()`` gives the command lines still to run (in one shell, in
    order; none: the job is done), called when it starts; ``inputs`` are the jobs that must finish first."""

    name: str  # a stage's name, or "dataset NAME"
    threads: int
    commands: Callable[[], list[list[str]]]
    log_path: Path
    inputs: set[str] = field(default_factory=set)
    what: str = ""  # printed when it starts


def recipe_jobs(recipe: Recipe, out: Path, python: str = sys.executable) -> list[Job]:
    """The recipe's jobs in the order they are considered: the stages in file order, each after the datasets it
    is the first to take (the longest first); last, the datasets no stage takes (the export's)."""
    first_use = {}
    for k, stage in enumerate(recipe.stages):
        for name in stage_datasets(stage):
            first_use.setdefault(name, k)
    renders = []
    for name, spec in recipe.datasets.items():
        target = dataset_path(recipe, name, out)
        if "path" in spec:
            if not target.is_dir():
                raise UserError(f"{recipe.path}: dataset '{name}': {target} not found")
            continue
        args = synth_args(spec.get("synth"), f"{recipe.path}: dataset '{name}'")
        frames = (args["loops"] + args["test_loops"]) * args["frames_per_loop"]
        renders.append(
            (
                first_use.get(name, len(recipe.stages)),
                -frames,
                Job(
                    f"dataset {name}",
                    1,
                    lambda target=target, args=args: [] if target.is_dir() else [synth_command(target, args, python)],
                    out / "data" / f"{name}.log",
                    what=f"rendering {frames} frames into {target}",
                ),
            )
        )
    renders.sort(key=lambda r: r[:2])  # by the stage that first takes them, the longest first

    def first_taken_by(k: int) -> list[Job]:
        return [job for first, _, job in renders if first == k]

    rendered = {job.name for *_, job in renders}
    jobs = []
    for k, stage in enumerate(recipe.stages):
        jobs += first_taken_by(k)
        inputs = set(stage.init) | ({stage.continues} if stage.continues else set())
        inputs |= {f"dataset {name}" for name in stage_datasets(stage)} & rendered
        threads = stage_threads(stage)
        jobs.append(
            Job(
                stage.name,
                threads,
                lambda stage=stage: _stage_commands(stage, recipe, out, python),
                out / f"{stage.name}.log",
                inputs,
                f"{stage.stage} to step {stage.steps} on {threads} thread{'s' * (threads > 1)}",
            )
        )
    return jobs + first_taken_by(len(recipe.stages))


def stage_datasets(stage: Stage) -> list[str]:
    """The datasets a stage trains and validates on (its ``data`` and ``val_data``)."""
    return [name for name in (stage.data, stage.val_data) if name is not None]


SYNTH_KEYS = ("scene", "seed", "loops", "test_loops", "frames_per_loop", "size", "lane_wander", "lighting")


def synth_args(synth: dict | None, where: str) -> dict:
    """A dataset's ``synth`` keys with ``vlocnetpp synth``'s defaults filled in; ``UserError`` naming ``where`` for a
    missing ``synth``, an unknown key or a bad value."""
    if not isinstance(synth, dict):
        raise UserError(f"{where}: a dataset is {{synth: {{...}}}} (rendered) or {{path: DIR}} (an existing folder)")
    unknown = sorted(set(synth) - set(SYNTH_KEYS))
    if unknown:
        raise UserError(f"{where}: unknown synth key {', '.join(map(repr, unknown))} (known: {', '.join(SYNTH_KEYS)})")
    from vlocnetpp_core.synth.cli import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = {}
    try:
        for key in SYNTH_KEYS:
            default = parser.get_default(key)
            value = synth.get(key, default)
            if key == "size":
                args[key] = "x".join(str(int(v)) for v in value)
            elif key == "lighting" and isinstance(value, list):  # a YAML list of presets
                args[key] = ",".join(map(str, value))
            else:
                args[key] = type(default)(value)
    except (TypeError, ValueError) as err:
        raise UserError(f"{where}: bad synth value ({err})") from None
    return args


def synth_command(target: Path, args: dict, python: str = sys.executable) -> list[str]:
    """The ``vlocnetpp synth`` command line that renders a dataset of ``synth_args`` into ``target``."""
    flags = [f"--{key.replace('_', '-')}={value}" for key, value in args.items()]
    return [python, "-m", "vlocnetpp_core.cli", "synth", str(target), *flags, "--no-progress"]


def _stage_commands(stage: Stage, recipe: Recipe, out: Path, python: str) -> list[list[str]]:
    continue_run(stage, out)
    return stage_commands(stage, recipe, out, python)


@dataclass
class _Running:
    job: Job
    proc: subprocess.Popen
    logf: IO
    start: float


def run_jobs(jobs: list[Job], out: Path, log, cores: int) -> None:
    """Every job, each as soon as its inputs are finished and its threads fit (module docstring); raises
    :class:`UserError` naming the logs of the jobs that failed, once the running ones have ended."""
    waiting, running, finished, failed = list(jobs), [], set(), []
    try:
        while waiting or running:
            free = cores - sum(r.job.threads for r in running)
            for job in list(waiting) if not failed else []:
                if job.inputs <= finished and (job.threads <= free or not running):
                    waiting.remove(job)
                    started = _start(job, log)
                    if started is None:
                        finished.add(job.name)  # nothing left to do
                    else:
                        running.append(started)
                        free -= job.threads
            if failed and not running:
                break
            time.sleep(POLL_S if running else 0)
            for run in [r for r in running if r.proc.poll() is not None]:
                running.remove(run)
                run.logf.close()
                if run.proc.returncode == 0:
                    finished.add(run.job.name)
                    record_time(out, run.job.name, time.monotonic() - run.start, log)
                else:
                    failed.append(run.job)
                    log(
                        f"{run.job.name} failed (exit {run.proc.returncode}); nothing else starts"
                        + (f", waiting for {', '.join(r.job.name for r in running)}" if running else "")
                    )
    except BaseException:  # Ctrl-C or SIGTERM (sigterm_as_interrupt): no job outlives the recipe
        _interrupt(running, out, log)
        raise
    if failed:
        raise UserError(
            "; ".join(f"{job.name} failed: {_last_line(job.log_path)} (log {job.log_path})" for job in failed)
            + " (run the recipe again to resume)"
        )


def _interrupt(running: list[_Running], out: Path, log, grace_s: float = 60.0) -> None:
    """SIGTERM every running job (its whole process group; not SIGINT, which a recipe started in the background
    with ``&`` passes on ignored), SIGKILL those still there after ``grace_s``, and add the time they ran to
    ``timings.json`` (a stage resumes from its last checkpoint when the recipe runs again)."""
    for run in running:
        with suppress(ProcessLookupError):
            os.killpg(run.proc.pid, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for run in running:
        try:
            run.proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            with suppress(ProcessLookupError):
                os.killpg(run.proc.pid, signal.SIGKILL)
            run.proc.wait()
        run.logf.close()
        log(f"{run.job.name} interrupted")
        record_time(out, run.job.name, time.monotonic() - run.start, log)


def _last_line(path: Path) -> str:
    lines = (
        [line.strip() for line in path.read_text(errors="replace").splitlines() if line.strip()]
        if path.is_file()
        else []
    )
    return lines[-1] if lines else "no output"


def stage_threads(stage: Stage) -> int:
    """The CPU threads a stage's ``vlocnetpp train`` uses (its ``threads``; train's default: every core)."""
    return resolve_threads(int(stage.train.get("threads", os.cpu_count() or 1)))


def _start(job: Job, log) -> _Running | None:
    """Launch the commands still to run for ``job`` (one shell, in order); None when there are none."""
    commands = job.commands()
    if not commands:
        return None
    job.log_path.parent.mkdir(parents=True, exist_ok=True)
    logf = open(job.log_path, "a")
    log(f"start {job.name}: {job.what} (log {job.log_path})")
    script = " && ".join(shlex.join(c) for c in commands)
    # its own process group, so that an interrupted recipe stops the job's shell and the command it runs alike
    proc = subprocess.Popen(["bash", "-c", script], stdout=logf, stderr=subprocess.STDOUT, start_new_session=True)
    return _Running(job, proc, logf, time.monotonic())


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

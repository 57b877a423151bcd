"""`vlocnetpp train --recipe`: datasets, stages (with inits, schedules, side by side), export, resume, errors."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from vlocnetpp_core.cli import main as cli
from vlocnetpp_core.data import open_dataset
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.evaluation.retrieval import ReferenceSet
from vlocnetpp_core.inference.checkpoint import read_checkpoint_meta
from vlocnetpp_core.model import load_model_config
from vlocnetpp_core.training.config import TrainConfig
from vlocnetpp_core.training.recipe import load_recipe, stage_commands, stage_configs, stage_weights
from vlocnetpp_core.training.recipe_run import recipe_jobs, run_recipe

VO = {"name": "vo", "stage": "stl-vo", "schedule": [{"steps": 2, "lr": 1e-3}]}
WANDER = {
    "synth": {
        "seed": 0,
        "loops": 3,
        "test_loops": 0,
        "frames_per_loop": 8,
        "size": [64, 48],
        "lane_wander": 1.0,
        "lighting": ["overcast", "noon"],
    }
}


def _recipe(tmp_path, **changes) -> dict:
    cfg = load_model_config("lite").to_dict()
    cfg["input_size"] = [64, 48]
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    (tmp_path / "tiny_direct.yaml").write_text(yaml.safe_dump(cfg | {"global_pose_anchors": 0}))
    recipe = {
        "config": str(tmp_path / "tiny.yaml"),
        "datasets": {
            "campus": {"synth": {"seed": 0, "loops": 3, "test_loops": 1, "frames_per_loop": 8, "size": [64, 48]}},
            "wander": WANDER,
        },
        "defaults": {"data": "campus", "batch_size": 2, "clip_len": 2, "workers": 0, "val_every": 2},
        "stages": [
            {
                "name": "vo",
                "stage": "stl-vo",
                "schedule": [{"steps": 2, "lr": 1e-3}],
                "threads": 1,
                "config": "tiny_direct.yaml",
            },  # another model config (its global head without anchors), next to the recipe
            {"name": "seg", "stage": "stl-seg", "schedule": [{"steps": 2, "lr": 1e-3}], "threads": 1},
            {
                "name": "loc",
                "stage": "stl-loc",
                "init": ["vo"],
                "s_q_init": 0,
                "data": "wander",
                "schedule": [{"steps": 2, "lr": 1e-3}, {"steps": 4, "lr": 1e-4, "lr_end": 1e-6}],
            },
            {"name": "seg-more", "stage": "stl-seg", "continue": "seg", "schedule": [{"steps": 3, "lr": 1e-3}]},
        ],
        "export": {
            "stage": "loc",
            "to": str(tmp_path / "models" / "tiny"),
            "dtype": "float16",
            "reference": ["campus", "wander"],
            "class_offsets": "campus",
        },
    }
    recipe.update(changes)
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(recipe))
    return path


def _train_positions(root) -> list:
    index = open_dataset(root, "deeploc", "train")
    return [index.load(i, depth=False, labels=False).t for i in range(len(index))]


def test_recipe_runs_every_stage_exports_and_resumes(tmp_path, capsys):
    path, out = _recipe(tmp_path), tmp_path / "run"
    assert run_recipe(path, out, cores=2) == 0
    printed = capsys.readouterr().out.splitlines()

    def line(text: str) -> int:
        return next(i for i, msg in enumerate(printed) if text in msg)

    # both datasets render side by side on the two cores, campus (vo's and seg's data) first; vo and seg start once it
    # is rendered, loc once vo (its init) and wander (its data) are done, seg-more once seg is
    assert (
        line("start dataset campus:")
        < line("start dataset wander:")
        < min(line("] dataset campus: "), line("] dataset wander: "))
    )
    assert line("] dataset campus: ") < min(line("start vo:"), line("start seg:"))
    assert line("start loc:") > max(line("] vo: "), line("] dataset wander: "))
    assert line("start seg-more:") > line("] seg: ") and line("export:") > line("] loc: ")
    timings = json.loads((out / "timings.json").read_text())
    assert set(timings) == {"dataset campus", "dataset wander", "vo", "seg", "loc", "seg-more", "recipe (end to end)"}
    assert all(v > 0 for v in timings.values())
    more = [
        json.loads(line)
        for line in (out / "seg-more" / "log.jsonl").read_text().splitlines()
        if "validation" not in line
    ]
    assert [r["step"] for r in more] == [1, 2, 3]  # seg's two steps (its copied run), then one more, resumed
    log = [
        json.loads(line) for line in (out / "loc" / "log.jsonl").read_text().splitlines() if "validation" not in line
    ]
    # the schedule, resumed at the step-down; the second entry a cosine from 1e-4 at step 2 to 1e-6 at step 4
    assert [r["step"] for r in log] == [1, 2, 3, 4]
    assert [r["lr"] for r in log] == pytest.approx([1e-3, 1e-3, 1e-4, (1e-4 + 1e-6) / 2], rel=1e-9)
    assert read_checkpoint_meta(out / "vo" / "last")["model_config"]["global_pose_anchors"] == 0  # the stage's config
    meta = read_checkpoint_meta(tmp_path / "models" / "tiny")
    assert meta["model_config"]["global_pose_anchors"] == 256  # the recipe's, on the trunk of a stage of another config
    assert meta["training"]["stage"] == "stl-loc" and meta["training"]["init"][0]["path"].endswith(
        "vo/best.safetensors"
    )
    reference = ReferenceSet.load(tmp_path / "models" / "tiny.reference.npz")
    # the training images of both datasets, 3 loops of 8 frames each
    assert len(reference) == 48 and "dataset 'campus'" in reference.source and "dataset 'wander'" in reference.source
    assert {tuple(t) for t in reference.t} == {
        tuple(t) for name in ("campus", "wander") for t in _train_positions(out / "data" / name)
    }
    # the segmentation's class offsets, fitted on the campus test loop, in the export's calibration
    calibration = meta["calibration"]
    assert len(calibration["class_logit_offsets"]) == meta["model_config"]["num_classes"]
    assert calibration["class_logit_offsets_source"].startswith("mean IoU on campus (test)")
    visits = json.loads((out / "data" / "wander" / "scene.json").read_text())["visits"]
    assert [v["pattern"]["lane_wander"] for v in visits] == [1.0] * 3  # the recipe's synth keys reach the renderer
    assert {v["lighting"]["name"] for v in visits} == {"overcast", "noon"}
    assert meta["training"]["data"].endswith("wander")  # the stage's own data

    recipe = load_recipe(path)
    assert all(stage_configs(s, recipe, out) == [] for s in recipe.stages)  # finished: nothing left to run
    assert cli(["train", "--recipe", str(path), "--out", str(out)]) == 0
    assert "start " not in capsys.readouterr().out  # no dataset rendered again, no stage ran again
    again = json.loads((out / "timings.json").read_text())
    assert (
        again.pop("recipe (end to end)") >= timings.pop("recipe (end to end)") and again == timings
    )  # only the export again

    # a recipe on this one (its base) run into the same folder trains only its own stage and exports nothing
    arm = tmp_path / "arm.yaml"
    own = {"name": "loc-arm", "stage": "stl-loc", "init": ["vo"], "config": "tiny_direct.yaml", "s_q_init": 0}
    arm.write_text(yaml.safe_dump({"base": path.name, "stages": [{**own, "schedule": [{"steps": 2, "lr": 1e-3}]}]}))
    exported = (tmp_path / "models" / "tiny.safetensors").stat().st_mtime_ns
    assert cli(["train", "--recipe", str(arm), "--out", str(out)]) == 0
    assert [m.split("] ")[1].split(":")[0] for m in capsys.readouterr().out.splitlines() if "start " in m] == [
        "start loc-arm"
    ]
    assert (tmp_path / "models" / "tiny.safetensors").stat().st_mtime_ns == exported
    assert read_checkpoint_meta(out / "loc-arm" / "last")["model_config"]["global_pose_anchors"] == 0


def test_recipe_resumes_an_unfinished_schedule(tmp_path):
    path, out = _recipe(tmp_path), tmp_path / "run"
    recipe = load_recipe(path)
    loc = recipe.stages[2]
    (out / "loc").mkdir(parents=True)
    (out / "loc" / "train_state.json").write_text(json.dumps({"step": 2}))
    (config,) = stage_configs(loc, recipe, out)
    assert (config.steps, config.lr, config.lr_end, config.resume, config.restart) == (4, 1e-4, 1e-6, True, False)
    assert config.init == (str(out / "vo" / "best.safetensors"),) and config.data == str(out / "data" / "wander")
    assert (config.s_q_init, config.batch_size, config.val_every) == (0.0, 2, 2)  # the stage's keys and the defaults'
    (command,) = stage_commands(loc, recipe, out, sys.executable)  # the stage process gets its config as a file
    assert (
        command[-2:] == ["--train-config", str(out / "loc.2.json")] and TrainConfig.read(out / "loc.2.json") == config
    )


def test_a_restart_entry_restarts_once_then_resumes(tmp_path):
    """`restart: true`: the entry's command restarts the run (fresh optimiser) until the entry has begun; an
    interrupted restart resumes as any entry; the first entry has nothing to restart from."""
    stages = yaml.safe_load(_recipe(tmp_path).read_text())["stages"]
    stages[2]["schedule"][1]["restart"] = True
    path, out = _recipe(tmp_path, stages=stages), tmp_path / "run"
    loc = load_recipe(path).stages[2]
    first, second = stage_configs(loc, load_recipe(path), out)
    assert (first.restart, first.resume, second.restart, second.resume) == (False, False, True, False)
    (out / "loc").mkdir(parents=True)
    for step, restart in ((2, True), (3, False)):
        (out / "loc" / "train_state.json").write_text(json.dumps({"step": step}))
        (config,) = stage_configs(loc, load_recipe(path), out)
        assert (config.restart, config.resume) == (restart, not restart)
    stages[2]["schedule"][0]["restart"] = True
    with pytest.raises(UserError, match="the first schedule entry cannot restart"):
        load_recipe(_recipe(tmp_path, stages=stages))
    stages[2]["schedule"][0]["restart"] = "yes"
    with pytest.raises(UserError, match="restart: true"):
        load_recipe(_recipe(tmp_path, stages=stages))


def test_a_recipe_on_a_base_runs_the_bases_stages_as_the_base_does_then_its_own(tmp_path):
    """`base: FILE`: the base's datasets, defaults and stages (each stage's train configs exactly the base's, its
    model config included), then the file's own stages with its defaults over the base's; not the base's export."""
    base = load_recipe(_recipe(tmp_path))
    arm = tmp_path / "arm.yaml"
    arm.write_text(
        yaml.safe_dump(
            {
                "base": "recipe.yaml",
                "config": "lite",
                "datasets": {"more": WANDER},
                "defaults": {"batch_size": 4},
                "stages": [{**VO, "name": "vo-more", "init": ["vo"], "data": "more"}],
            }
        )
    )
    recipe, out = load_recipe(arm), tmp_path / "run"
    assert [s.name for s in recipe.stages] == ["vo", "seg", "loc", "seg-more", "vo-more"]
    assert set(recipe.datasets) == {"campus", "wander", "more"} and recipe.export is None
    for ours, theirs in zip(recipe.stages, base.stages, strict=False):
        assert stage_configs(ours, recipe, out) == stage_configs(theirs, base, out)
    (more,) = stage_configs(recipe.stages[-1], recipe, out)
    assert (more.batch_size, more.val_every, more.config) == (4, 2, "lite")  # its defaults over the base's
    assert more.init == (str(out / "vo" / "best.safetensors"),) and more.data == str(out / "data" / "more")


def test_a_stage_whose_weights_are_last_gives_its_last_checkpoint(tmp_path):
    recipe = load_recipe(_recipe(tmp_path))
    recipe.stages[0].weights = "last"  # vo: as `weights: last` in the file
    (config, _) = stage_configs(recipe.stages[2], recipe, tmp_path / "run")
    assert config.init == (str(tmp_path / "run" / "vo" / "last.safetensors"),)
    stages = [
        {**s, "weights": "last"} if s["name"] == "vo" else s
        for s in yaml.safe_load(_recipe(tmp_path).read_text())["stages"]
    ]
    assert load_recipe(_recipe(tmp_path, stages=stages)).stages[0].weights == "last"


@pytest.mark.parametrize(
    "change, message",
    [
        (
            {"stages": [{"name": "loc", "stage": "stl-loc", "init": ["vo"], "schedule": [{"steps": 2, "lr": 1e-3}]}]},
            "'vo' (init or continue) is not an earlier stage",
        ),
        ({"stages": [{"name": "vo", "stage": "stl-vo", "schedule": [{"steps": 2}]}]}, "'schedule' must be a list"),
        (
            {"stages": [{"name": "vo", "stage": "stl-vo", "data": "nope", "schedule": [{"steps": 2, "lr": 1e-3}]}]},
            "data 'nope' is not one of",
        ),
        (
            {
                "stages": [
                    {"name": "vo", "stage": "stl-vo", "config": "nope.yaml", "schedule": [{"steps": 2, "lr": 1e-3}]}
                ]
            },
            "config 'nope.yaml' is neither a built-in model config",
        ),
        (
            {"stages": [{"name": "vo", "stage": "stl-vo", "weights": "final", "schedule": [{"steps": 2, "lr": 1e-3}]}]},
            "weights must be one of best, last",
        ),
        (
            {"stages": [{"name": "vo", "stage": "stl-vo", "parallel": "a", "schedule": [{"steps": 2, "lr": 1e-3}]}]},
            "'parallel' is gone",
        ),
        (
            {"datasets": {"campus": {"synth": {"loops": 2, "lane_wonder": 1.0}}, "wander": WANDER}},
            "unknown synth key 'lane_wonder'",
        ),
        ({"datasets": {"campus": {"synth": {"loops": "many"}}, "wander": WANDER}}, "dataset 'campus': bad synth value"),
        (
            {"datasets": {"campus": {"render": {"loops": 2}}, "wander": WANDER}},
            "a dataset is {synth: {...}} (rendered) or {path: DIR}",
        ),
        ({"export": {"stage": "mtl"}}, "export stage 'mtl'"),
        ({"base": "recipe.yaml"}, "base 'recipe.yaml' is this recipe or one of its own bases (a cycle)"),
        ({"base": "nope.yaml"}, "base 'nope.yaml' is not a recipe file next to this one"),
        (
            {"export": {"stage": "loc", "reference": ["campus", "nope"]}},
            "export reference 'nope' is not one of the recipe's datasets",
        ),
        # every key of every stage, of the defaults and of the export is known, and every value a train flag takes
        ({"stages": [{**VO, "bach_size": 2}]}, "stage 0 (vo): unknown key 'bach_size'"),
        ({"defaults": {"data": "campus", "workerz": 0}}, "defaults: unknown key 'workerz'"),
        (
            {"stages": [{**VO, "batch_size": "eight"}]},
            "stage 0 (vo): 'batch_size': --batch-size must be an integer, got 'eight'",
        ),
        (
            {"stages": [{**VO, "frame_strides": [0, 1]}]},
            "stage 0 (vo): 'frame_strides': --frame-strides must be strides >= 1",
        ),
        (
            {"stages": [{**VO, "freeze": ["trunk", "odometri"]}]},
            "stage 0 (vo): 'freeze': --freeze: odometri is not a part",
        ),
        ({"stages": [{**VO, "lr": 1e-3}]}, "stage 0 (vo): 'lr' is set by the recipe"),
        (
            {"stages": [{**VO, "stage": "stl-seg", "config": "lite_pose"}]},
            "stage 0 (vo): 'config': --config lite_pose: stage stl-seg",
        ),
        ({"stages": [{**VO}, {**VO}]}, "stage 1 (vo): the name 'vo' is also stage 0's"),
        # an init cycle: a stage can only take weights from an earlier one
        (
            {"stages": [{**VO, "init": ["loc"]}, {**VO, "name": "loc", "stage": "stl-loc", "init": ["vo"]}]},
            "stage 0 (vo): 'loc' (init or continue) is not an earlier stage (a later stage or itself",
        ),
        (
            {"stages": [{**VO, "continue": "vo"}]},
            "'vo' (init or continue) is not an earlier stage (a later stage or itself",
        ),
        (
            {"export": {"stage": "loc", "to": "m", "dtype": "bfloat16"}},
            "export: 'dtype' must be one of float16, float32, got 'bfloat16'",
        ),
        ({"export": {"stage": "loc", "to": "m", "wieghts": "last"}}, "export: unknown key 'wieghts'"),
        (
            {"export": {"stage": "loc", "to": "m", "class_offsets": "val"}},
            "export: 'class_offsets' 'val' is not one of the recipe's datasets",
        ),
        (
            {"export": {"stage": "loc", "to": "m", "class_offsets": ["campus"]}},
            "export: 'class_offsets' ['campus'] is not one of the recipe's datasets",
        ),
        ({"export": {"stage": "loc", "to": "m", "weights": "final"}}, "export: 'weights' must be one of best, last"),
        (
            {"export": {"stage": "loc", "to": "m", "calibration": {"pose": "loc", "odometry": "vo-x"}}},
            "calibration stage 'vo-x'",
        ),
    ],
)
def test_recipe_mistakes_are_one_line_naming_the_file(tmp_path, capsys, change, message):
    path = _recipe(tmp_path, **change)
    assert cli(["train", "--recipe", str(path), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert message in err and "recipe.yaml" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()  # refused before anything ran


def test_a_recipe_mistake_fails_in_under_a_second_before_torch_loads(tmp_path):
    """The whole recipe is checked (every schedule entry a TrainConfig) without importing torch."""
    from conftest import REPO

    stages = yaml.safe_load(_recipe(tmp_path).read_text())["stages"]
    stages[-1]["clip_len"] = 0  # the last stage's: every stage before it is checked too
    path = _recipe(tmp_path, stages=stages)
    code = (
        "import sys, time; from vlocnetpp_core.cli import main; t = time.monotonic(); "
        f"rc = main(['train', '--recipe', {str(path)!r}, '--out', {str(tmp_path / 'run')!r}]); "
        "print(rc, time.monotonic() - t, 'torch' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    rc, seconds, torch_loaded = done.stdout.split()
    assert rc == "2" and "stage 3 (seg-more): 'clip_len': --clip-len must be >= 1, got 0" in done.stderr
    assert float(seconds) < 1.0 and torch_loaded == "False"


def test_export_weights_that_were_not_written_are_an_error_not_the_last(tmp_path):
    """`weights: best` of a run that wrote no best (no validation scored) is named, not exported from `last` instead."""
    from vlocnetpp_core.training.recipe_export import export_weights

    out = tmp_path / "run"
    (out / "loc").mkdir(parents=True)
    (out / "loc" / "last.safetensors").write_bytes(b"")
    with pytest.raises(UserError, match="export weights 'best': .*best.safetensors was not written by stage loc"):
        export_weights(load_recipe(_recipe(tmp_path)), out)


def test_a_failing_stage_names_its_log(tmp_path, capsys):
    path = _recipe(tmp_path, stages=[{**VO, "freeze": ["trunk", "odometry"]}], export=None)  # nothing left to train
    assert cli(["train", "--recipe", str(path), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert (
        "vo failed: " in err and str(tmp_path / "run" / "vo.log") in err and "is left to train" in err
    )  # the log's last line


def test_train_without_recipe_needs_config_data_and_stage(tmp_path, capsys):
    assert cli(["train", "--out", str(tmp_path / "run"), "--config", "lite"]) == 2
    assert "--data, --stage required (or --recipe FILE)" in capsys.readouterr().err


def test_each_dataset_is_considered_just_before_the_first_stage_that_takes_it(tmp_path):
    """A render never takes a core before an earlier stage: `wander` (first taken by `loc`) comes after `vo` and
    `seg`, and a dataset only the export takes (`classes`) comes last."""
    datasets = {"campus": WANDER, "wander": WANDER, "classes": WANDER}
    export = {"stage": "loc", "to": str(tmp_path / "m"), "class_offsets": "classes"}
    recipe = load_recipe(_recipe(tmp_path, datasets=datasets, export=export))
    names = [job.name for job in recipe_jobs(recipe, tmp_path / "run")]
    assert names == ["dataset campus", "vo", "seg", "dataset wander", "loc", "seg-more", "dataset classes"]


@pytest.mark.parametrize("name", ["shipped", "own_robot", "multitask_arms"])
def test_the_shipped_recipes_give_valid_train_commands(name, tmp_path):
    """Every stage of config/recipes/NAME.yaml is a `vlocnetpp train --train-config FILE` command, with its inits."""
    from conftest import REPO

    from vlocnetpp_core.cli import build_parser

    recipe = load_recipe(REPO / "config" / "recipes" / f"{name}.yaml")
    parser = build_parser("train")
    for stage in recipe.stages:
        commands = stage_commands(stage, recipe, tmp_path, sys.executable)
        assert len(commands) == len(stage.schedule)
        for command in commands:
            config = TrainConfig.read(parser.parse_args(command[command.index("train") :]).train_config)
            assert config.stage == stage.stage and config.config == (stage.config or recipe.config)
            load_model_config(config.config)
            assert [str(stage_weights(recipe, ref, tmp_path)) + ".safetensors" for ref in stage.init] == list(
                config.init
            )
    if name == "multitask_arms":  # the shipped recipe's stages and run folder, its arms after them; no export
        assert recipe.export is None and [s.name for s in recipe.stages[:7]] == [
            s.name for s in load_recipe(REPO / "config" / "recipes" / "shipped.yaml").stages
        ]
    else:
        assert recipe.export["stage"] == recipe.stages[-1].name


@pytest.mark.parametrize("config", ["lite", "lite_pose"])
def test_the_recipes_trunk_configs_are_their_model_with_the_direct_pose_head(config):
    """config/recipes/CONFIG_trunk.yaml (the trunk stage of shipped.yaml and own_robot.yaml) differs from CONFIG only in
    its name and position and rotation anchors, so the trunk it learns fits the network the recipe exports."""
    from conftest import REPO

    model = load_model_config(config).to_dict()
    trunk = load_model_config(str(REPO / "config" / "recipes" / f"{config}_trunk.yaml")).to_dict()
    assert {k for k in model if model[k] != trunk[k]} == {"name", "global_pose_anchors", "global_rotation_anchors"}
    assert trunk["global_pose_anchors"] == trunk["global_rotation_anchors"] == 0


def test_sigterm_stops_every_job_and_keeps_their_steps_and_time(tmp_path):
    """SIGTERM to a recipe started as ``nohup ... &`` starts it (SIGINT ignored) stops its stage gracefully: the
    training process saves the steps it took, the recipe exits 130, no process of it is left, and the time the stage ran
    is added to timings.json, so that a resumed run sums its parts."""
    from conftest import REPO

    stages = [{"name": "vo", "stage": "stl-vo", "schedule": [{"steps": 100000, "lr": 1e-3}], "threads": 1}]
    path, out = _recipe(tmp_path, stages=stages, export=None), tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "vlocnetpp_core.cli", "train", "--recipe", str(path), "--out", str(out)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )  # what a shell's & does
    steps_log = out / "vo" / "log.jsonl"
    try:
        while not (steps_log.is_file() and steps_log.read_text().count("clips_per_s") >= 3):
            assert proc.poll() is None, proc.stdout.read()
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130 and "vo interrupted" in rest and "Traceback" not in rest
    still = [p for p in Path("/proc").iterdir() if p.name.isdigit() and str(out) in _cmdline(p)]
    assert not still, [_cmdline(p) for p in still]
    saved = read_checkpoint_meta(out / "vo" / "last.safetensors")["training"]["step"]
    assert f"interrupted at step {saved}: saved" in (out / "vo.log").read_text()  # SIGTERMed, not SIGKILLed
    logged = sum("clips_per_s" in line for line in steps_log.read_text().splitlines())
    assert logged >= 3 and saved in (
        logged,
        logged + 1,
    )  # every logged step kept (+1: stopped between a step and its record)
    timings = json.loads((out / "timings.json").read_text())
    assert timings["vo"] > 0 and timings["recipe (end to end)"] >= timings["vo"]


def _cmdline(proc_dir: Path) -> str:
    try:
        return (proc_dir / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:  # the process ended meanwhile
        return ""

"""``vlocnetpp demo``: the whole system on fresh data, end to end, with real computations.

1. render fresh test loops of the synthetic campus the shipped model was trained on (scene
   ``campus``; a visit seed never used for training: training used seed 0),
2. convert them to a ROS 2 MCAP bag (``vlocnetpp convert``),
3. replay the bag through the real ``localizer`` node over DDS with the shipped model
   (``vlocnetpp replay --through-node --rate max``: every frame is processed), refining its pose
   against the keyframe map beside the model (``models/vlocnetpp_lite.map.npz``, ``--map auto``). On the first run
   the demo builds that map (step 0: the keyframes of the model's training visits, rendered, :data:`SHIPPED_MAP`;
   about half a minute on 2 cores), beside the model where that folder is writable, else in the output folder;
4. score the output bag (``vlocnetpp evaluate-bag``) and print the results table, the plots
   and the output bag. Rows: the network's pose, the refined pose (with the map), the retrieval
   baseline (pose of the nearest training image, from the descriptors shipped beside the model:
   ``models/vlocnetpp_lite.reference.npz``) and the structure-based baseline (retrieval + SIFT + PnP
   against the map, no network), all on the same frames.

Nothing is cached: every number comes from this run.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import time
from pathlib import Path

from vlocnetpp_core.bag import topics
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.checkpoint import MAP_AUTO
from vlocnetpp_core.programs import program_command

TRAINING_SEED = 0  # the visits the shipped model was trained on (config/recipes/shipped.yaml)
# the shipped model's keyframe map: the train visits of the recipe's `campus` dataset, at the map's default spacing
SHIPPED_MAP = {"scene": "campus", "seed": TRAINING_SEED, "loops": 32, "frames_per_loop": 250}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_output", help="output folder (default ./demo_output; replaced if it exists)")
    p.add_argument(
        "--seed",
        type=int,
        default=101,
        help="visit seed of the fresh test loops (default 101; 0 was used for training)",
    )
    p.add_argument("--loops", type=int, default=2, help="test loops to render (default 2)")
    p.add_argument("--frames-per-loop", type=int, default=175, help="frames per loop (default 175, one lap)")
    p.add_argument("--checkpoint", default=None, help="checkpoint to run (default: the shipped model)")
    p.add_argument(
        "--map",
        default="auto",
        metavar="MAP.npz|auto",
        help="keyframe map to refine against (default auto: "
        "NAME.map.npz beside the checkpoint, none when missing; '' for none)",
    )


def _step(n: int, text: str) -> float:
    print(f"\n[demo {n}/4] {text}", flush=True)
    return time.perf_counter()


def _done(t0: float) -> None:
    print(f"          done in {time.perf_counter() - t0:.1f} s", flush=True)


def run(args: argparse.Namespace) -> int:
    from vlocnetpp_core.bag.convert import convert
    from vlocnetpp_core.bag.evaluate_bag import bag_report, refined_share_line
    from vlocnetpp_core.classes import CLASS_NAMES
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.evaluation.report import format_report, write_outputs
    from vlocnetpp_core.evaluation.retrieval import ReferenceSet, reference_of
    from vlocnetpp_core.inference.checkpoint import resolve_map_path, shipped_checkpoint
    from vlocnetpp_core.mapping.refiner import Refiner
    from vlocnetpp_core.synth import render_dataset

    if args.seed == TRAINING_SEED:
        raise UserError(
            f"--seed {TRAINING_SEED} is the seed the shipped model was trained on; pick another for a fair test"
        )
    try:
        checkpoint = Path(args.checkpoint) if args.checkpoint else shipped_checkpoint()
    except FileNotFoundError as err:
        raise UserError(str(err)) from None
    notes: list[str] = []
    build_shipped_map = args.checkpoint is None and args.map == MAP_AUTO
    map_path = resolve_map_path(checkpoint, args.map, "--map", None if build_shipped_map else notes.append)
    out = Path(args.out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    start = time.perf_counter()
    to_build = map_path is None and build_shipped_map
    if to_build:
        map_path = _shipped_map_path(checkpoint, out)
    print(f"VLocNet++ demo: model {checkpoint}, map {map_path or 'none (the network pose only)'}, output {out}/")
    for line in notes:
        print(f"note: {line}")
    if to_build:
        _build_shipped_map(map_path)

    t0 = _step(
        1, f"rendering {args.loops} fresh test loops of the synthetic campus (scene 'campus', visit seed {args.seed})"
    )
    data = out / "campus"
    render_dataset(
        data,
        scene="campus",
        seed=args.seed,
        train_loops=0,
        test_loops=args.loops,
        frames_per_loop=args.frames_per_loop,
        progress=True,
    )
    _done(t0)

    t0 = _step(2, "converting them to a ROS 2 MCAP bag (camera, depth, camera info, labels, ground truth)")
    bag = out / "test_loops.mcap"
    print("          " + convert([open_dataset(data, "deeploc", "test")], bag).format().replace("\n", "\n          "))
    _done(t0)

    refining = ", refining against the keyframe map" if map_path else ""
    t0 = _step(
        3,
        "replaying the bag through the real 'localizer' node over DDS "
        f"(one frame at a time, every frame processed{refining})",
    )
    result_bag = out / "localized.mcap"
    summary = _replay_through_node(bag, checkpoint, map_path, result_bag)
    print("          " + summary.replace("\n", "\n          "))
    _done(t0)

    t0 = _step(4, "evaluating the output bag (global pose, odometry, segmentation; baselines on the same frames)")
    reference_file = reference_of(checkpoint)
    reference = ReferenceSet.load(reference_file) if reference_file.is_file() else None
    refiner = Refiner.from_file(map_path) if map_path else None
    report, results = bag_report(result_bag, samples=3, reference=reference, refiner=refiner)
    report["meta"] = {
        "checkpoint": str(checkpoint),
        "bag": str(result_bag),
        "seed": args.seed,
        "map": str(map_path) if map_path else None,
    }
    frames = {r.name: len(r.stamps) for r in results}
    n = sum(frames.values())
    wall = _seconds_per_frame(summary, n)
    if wall is not None:
        report["overall"]["timing"]["through_node_ms"] = 1000 * wall
    _done(t0)

    print("\nResults on the fresh test loops (ms/frame: see below)\n")
    print(format_report(report, frames))
    if refined_share_line(report):
        print(refined_share_line(report))
    if reference is None:
        print(
            f"note: no retrieval baseline: {reference_file} (the descriptors of the model's training images) not found"
        )
    if map_path is None:
        print("note: no refined and no structure-based rows: " + (notes[0] if notes else "no keyframe map (--map '')"))
    if wall is not None:
        print(
            f"through the node: {1000 * wall:.1f} ms per frame "
            "(image published -> pose received, lockstep, including DDS)"
        )
    print()
    write_outputs(report, results, CLASS_NAMES, out / "metrics.json", None, out / "plots")
    outputs = [t for t in topics.OUTPUT_TOPICS if map_path or t != topics.NETWORK_POSE_TOPIC]
    print(f"output bag: {result_bag} (input topics + {', '.join(outputs)})")
    print(f"demo finished in {time.perf_counter() - start:.0f} s")
    return 0


def _shipped_map_path(checkpoint: Path, out: Path) -> Path:
    """Where the first run builds the shipped model's map: beside ``checkpoint`` (where ``map: auto`` finds it), or in
    ``out`` where that folder is not writable."""
    path = checkpoint.with_name(checkpoint.name.removesuffix(".safetensors") + ".map.npz")
    return path if os.access(path.parent, os.W_OK) else out / path.name


def _build_shipped_map(path: Path) -> None:
    """Step 0 of the first run: build the shipped model's map (:data:`SHIPPED_MAP`) into ``path``."""
    from vlocnetpp_core.mapping.build import build_scene_map

    spec = SHIPPED_MAP
    t0 = _step(
        0,
        f"building the shipped model's keyframe map (first run only): the keyframes of its {spec['loops']} training "
        f"visits (scene '{spec['scene']}', seed {spec['seed']}), rendered, into {path}",
    )
    build_scene_map(**spec, workers=os.cpu_count() or 1).save(path)
    _done(t0)


def _replay_through_node(bag: Path, checkpoint: Path, map_path: Path | None, out: Path) -> str:
    """``vlocnetpp replay --through-node --rate max`` of ``bag`` into ``out`` (with ``--map`` when there is a map);
    its summary."""
    cmd = [
        *program_command("replay-node"),
        str(bag),
        "--checkpoint",
        str(checkpoint),
        "--out",
        str(out),
        "--through-node",
        "--rate",
        "max",
        *(["--map", str(map_path)] if map_path else []),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise UserError(f"replay through the node failed:\n{proc.stderr[-3000:]}")
    return proc.stdout.strip()


def _seconds_per_frame(summary: str, frames: int) -> float | None:
    """Wall seconds per frame from the replay summary line ('... N frames localized in S s ...')."""
    import re

    m = re.search(r"(\d+) frames localized in ([0-9.]+) s", summary)
    if not m or int(m.group(1)) == 0:
        return None
    return float(m.group(2)) / int(m.group(1))

#!/usr/bin/env python3
"""Accuracy on visits nothing has seen: draw fresh visit seeds, render their test loops, score checkpoints.

    .venv/bin/python scripts/fresh_visits.py                       # 8 seeds drawn at random, the shipped model + map
    .venv/bin/python scripts/fresh_visits.py --seed 4242 --seed 77 # given seeds (e.g. to re-run a verdict)
    .venv/bin/python scripts/fresh_visits.py --checkpoint new=runs/x/export/vlocnetpp_lite.safetensors --map ''

Per seed: ``--test-loops`` loops of ``--frames-per-loop`` frames of the synthetic campus (``vlocnetpp synth --seed S
--loops 0``), then ``vlocnetpp evaluate`` of every checkpoint (with ``--map``: its refinement and the structure-based
baseline; ``--reference``: the retrieval baseline) on the same frames, with its per-frame trajectories
(``LABEL.seedS.trajectories/``, TUM files). Prints one markdown table (each seed's rows,
then the mean and the worst seed of every row) and writes it with the reports to ``--out``. Seeds drawn are printed
first; seeds that trained, validated or ranked anything (:data:`SPENT`, docs/results.md) are never drawn. Choices
between variants belong on validation seeds (seed 11); a seed that ranked variants is spent: add it to SPENT.
"""

from __future__ import annotations

import argparse
import json
import random
import subprocess
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# 0 and 2 train, 11 validates the shipped model; 101, 7, 23, 42 ranked the recipe (docs/results.md); 5, 202 the tests'
# visits; 791569, 835667, 943975, 479491 chose the odometry fusion's constants with 11; the verdicts (docs/results.md):
# never drawn again, so the next verdict is on other visits
# fmt: off
SPENT = {0, 1, 2, 5, 7, 11, 23, 42, 101, 202,  # 1: an experiment's visits (2026-12-07, fourth); 2: campus-more's
         307008, 445811, 936886, 733135, 107868, 370004, 177925, 600629,  # refinement, EPnP (2026-12-20)
         740804, 762581, 939547, 526530, 342913, 570627, 193802, 711590,  # refinement, AP3P (2026-12-06)
         684805, 794529, 695689, 164404, 978398, 877148, 728843, 306382,  # AP3P, inliers again (2026-12-06)
         791569, 835667, 943975, 479491,  # validation of the odometry fusion's constants (2026-12-07)
         419167, 913411, 340430, 244380, 161928, 817369, 153345, 526595,  # the fusion's verdict (2026-12-07)
         165582, 241377, 62239, 506526, 568621, 838749, 157573, 928725,  # the bias filter's verdict (2026-12-07)
         272040, 910218, 51986, 173264, 300494, 856423, 110790, 28160,  # the class offsets' verdict (2026-12-08)
         815376, 541657, 463874, 194182, 18706, 190116, 765370, 825119}  # stl-vo-more's verdict (2026-12-08)
# fmt: on
COLUMNS = [
    ("t [m]", "pose", "median_translation_m", 1, "{:.3f}"),
    ("R [deg]", "pose", "median_rotation_deg", 1, "{:.2f}"),
    ("< 0.1 m, 1 deg [%]", "pose", "accuracy_0.1m_1deg", 100, "{:.1f}"),
    ("> 0.5 m or 5 deg [%]", "pose", "accuracy_0.5m_5deg", -100, "{:.2f}"),
    ("VO t [%]", "odometry", "translation_error_percent", 1, "{:.2f}"),
    ("VO R [deg/m]", "odometry", "rotation_error_deg_per_m", 1, "{:.3f}"),
    ("mIoU [%]", "segmentation", "miou", 100, "{:.1f}"),
]
WORSE_IS_LOWER = {"accuracy_0.1m_1deg", "miou"}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=8, metavar="N", help="visit seeds to draw at random (default 8)")
    p.add_argument("--seed", type=int, action="append", default=[], help="a given visit seed instead (repeatable)")
    p.add_argument(
        "--checkpoint",
        action="append",
        default=[],
        metavar="[LABEL=]CKPT",
        help="checkpoint to score (repeatable; default shipped=models/vlocnetpp_lite.safetensors)",
    )
    p.add_argument(
        "--map", default="models/vlocnetpp_lite.map.npz", help="keyframe map for every checkpoint ('' for none)"
    )
    p.add_argument("--refine-every", type=int, default=1, metavar="K", help="evaluate --refine-every (default 1)")
    p.add_argument(
        "--reference", default="models/vlocnetpp_lite.reference.npz", help="retrieval reference (.npz or dataset)"
    )
    p.add_argument("--test-loops", type=int, default=3, help="test loops per seed (default 3)")
    p.add_argument("--frames-per-loop", type=int, default=175, help="frames per loop (default 175)")
    p.add_argument("--out", default="runs/fresh-visits", help="folder of the rendered loops, reports and table")
    p.add_argument("--jobs", type=int, default=1, metavar="N", help="seeds rendered and scored at once (default 1)")
    args = p.parse_args(argv)
    spent = sorted(SPENT & set(args.seed))
    if spent:
        print(
            f"note: seeds {spent} were used before (SPENT): not fresh; "
            "fine to re-run a recorded verdict, not for a new one",
            file=sys.stderr,
        )
    return args


def draw_seeds(count: int) -> list[int]:
    """``count`` distinct visit seeds from the operating system's randomness, none of them :data:`SPENT`."""
    rng = random.SystemRandom()
    seeds: list[int] = []
    while len(seeds) < count:
        s = rng.randrange(1000, 1_000_000)
        if s not in SPENT and s not in seeds:
            seeds.append(s)
    return seeds


def vlocnetpp(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "vlocnetpp_core.cli", *args], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)


def score(args: argparse.Namespace, seed: int, label: str, checkpoint: str) -> dict:
    """The ``evaluate`` report of ``checkpoint`` on the loops of ``seed`` (rendered and scored once per out folder)."""
    out = Path(args.out)
    data = out / f"seed{seed}"
    if not data.is_dir():
        print(f"rendering visit seed {seed}", file=sys.stderr)
        vlocnetpp(
            "synth",
            str(data),
            "--seed",
            str(seed),
            "--loops",
            "0",
            "--test-loops",
            str(args.test_loops),
            "--frames-per-loop",
            str(args.frames_per_loop),
            "--no-progress",
        )
    report = out / f"{label}.seed{seed}.json"
    if not report.is_file():
        print(f"scoring {label} on visit seed {seed}", file=sys.stderr)
        extra = ["--map", args.map, "--refine-every", str(args.refine_every)] if args.map else []
        vlocnetpp(
            "evaluate",
            "--checkpoint",
            checkpoint,
            "--data",
            str(data),
            "--reference",
            args.reference,
            *extra,
            "--threshold-m",
            "0.1",
            "--threshold-deg",
            "1",
            "--json",
            str(report),
            "--no-progress",
            "--trajectories",
            str(out / f"{label}.seed{seed}.trajectories"),
        )
    return json.loads(report.read_text())


def rows_of(label: str, report: dict, first: bool) -> dict[str, dict]:
    """Row name -> its ``overall``-shaped metrics: the network, refined, and (for the first checkpoint) the
    baselines."""
    o = report["overall"]
    rows = {f"{label} (network)": o}
    if "frame_network" in report:
        rows[f"{label} (network, each frame alone)"] = report["frame_network"]["overall"]
    if "pose_refined" in o:
        rows[f"{label} refined"] = {"pose": o["pose_refined"]}
    if first:
        for key, name in (("baseline", "retrieval"), ("structure_baseline", "structure-based")):
            if key in report:
                rows[name] = report[key]["overall"]
    return rows


def value(metrics: dict, group: str, key: str, factor: int) -> float:
    v = metrics.get(group, {}).get(key)
    if v is None:
        return float("nan")
    return (1 - v) * -factor if factor < 0 else v * factor


def table(per_seed: dict[int, dict[str, dict]]) -> str:
    """The markdown table: per seed its rows, then every row's mean and worst seed."""
    names = list(next(iter(per_seed.values())))
    lines = ["| seed | row | " + " | ".join(c[0] for c in COLUMNS) + " |", "|---|---|" + "---|" * len(COLUMNS)]
    cell = lambda v, fmt: "-" if np.isnan(v) else fmt.format(v)  # noqa: E731
    for seed, rows in per_seed.items():
        for name in names:
            lines.append(
                f"| {seed} | {name} | "
                + " | ".join(cell(value(rows[name], g, k, f), fmt) for _, g, k, f, fmt in COLUMNS)
                + " |"
            )
    for name in names:
        vals = np.array([[value(rows[name], g, k, f) for _, g, k, f, _ in COLUMNS] for rows in per_seed.values()])
        with warnings.catch_warnings():  # a column without numbers (a baseline's odometry) stays "-"
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(vals, axis=0)
            worst = [
                np.nanmin(c) if k in WORSE_IS_LOWER else np.nanmax(c)
                for c, (_, _, k, _, _) in zip(vals.T, COLUMNS, strict=True)
            ]
        lines.append(
            f"| mean | {name} | " + " | ".join(cell(v, c[4]) for v, c in zip(mean, COLUMNS, strict=True)) + " |"
        )
        lines.append(
            f"| worst | {name} | " + " | ".join(cell(v, c[4]) for v, c in zip(worst, COLUMNS, strict=True)) + " |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    seeds = args.seed or draw_seeds(args.seeds)
    checkpoints = [c.split("=", 1) if "=" in c else (Path(c).stem, c) for c in args.checkpoint] or [
        ("shipped", "models/vlocnetpp_lite.safetensors")
    ]
    missing = [
        path for path in (*(c for _, c in checkpoints), args.map, args.reference) if path and not (ROOT / path).exists()
    ]
    if missing:
        hint = " (the map: 'vlocnetpp map build', README)" if args.map in missing else ""
        sys.exit(f"fresh_visits: no such file: {', '.join(missing)}{hint}")
    print(
        f"visit seeds: {' '.join(map(str, seeds))} "
        f"({args.test_loops} test loops of {args.frames_per_loop} frames each)",
        flush=True,
    )
    Path(args.out).mkdir(parents=True, exist_ok=True)

    def rows_of_seed(seed: int) -> dict[str, dict]:
        rows: dict[str, dict] = {}
        for k, (label, ckpt) in enumerate(checkpoints):
            rows.update(rows_of(label, score(args, seed, label, ckpt), first=k == 0))
        return rows

    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        per_seed = dict(zip(seeds, pool.map(rows_of_seed, seeds), strict=True))
    text = (
        f"visit seeds {' '.join(map(str, seeds))}; map {args.map or 'none'}, "
        f"refine every {args.refine_every}\n\n{table(per_seed)}\n"
    )
    (Path(args.out) / "table.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

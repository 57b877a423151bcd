#!/usr/bin/env python3
"""Where and when the network is wrong on fresh visits: its errors per visit condition and along the circuit.

    .venv/bin/python scripts/visit_errors.py runs/fresh-visits            # a scripts/fresh_visits.py --out folder
    .venv/bin/python scripts/visit_errors.py runs/fresh-visits --label shipped --plot runs/visit_errors.png

Reads, for every ``seedS/`` of the folder, the visits' conditions (``seedS/scene.json``: lighting preset, circuit,
direction, lane, moving objects) and the per-frame trajectories ``LABEL.seedS.trajectories/seq-XX/`` that
``fresh_visits.py`` wrote (ground truth, the network's pose and, where the localizer fused it with its odometry,
``frame_pose.tum``: each frame alone). Prints one markdown table per condition: frames, the median position and
rotation error of the network and of each frame alone; and with ``--plot`` a figure: the error per lighting preset
and per lane (boxes), and along the circuit for every visit.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.evaluation.trajectory import read_tum

CONDITIONS = ("lighting", "lane", "circuit", "moving objects")
POSES = {"network": "global_pose.tum", "each frame alone": "frame_pose.tum"}


def visits(folder: Path, label: str) -> list[dict]:
    """Every scored visit loop: its conditions, ``where (N,)`` the fraction of the loop, and per pose of
    :data:`POSES` found ``(t_err (N,) m, r_err (N,) deg)``."""
    out = []
    for data in sorted(folder.glob("seed*/")):
        scene = json.loads((data / "scene.json").read_text())
        tests = [v for v in scene["visits"] if v["split"] == "test"]
        seqs = sorted((folder / f"{label}.{data.name}.trajectories").glob("seq-*"))
        if len(seqs) != len(tests):
            note = f"{len(seqs)} scored sequences for {len(tests)} test loops"
            print(f"note: {data.name}: {note}, skipped", file=sys.stderr)
            continue
        for visit, seq in zip(tests, seqs, strict=True):
            truth = read_tum(seq / "ground_truth.tum")
            errors = {}
            for name, file in POSES.items():
                if (seq / file).is_file():
                    est = read_tum(seq / file)
                    errors[name] = (
                        np.linalg.norm(est.t - truth.t, axis=1),
                        np.asarray(geometry.rotation_error_deg(est.q, truth.q)),
                    )
            p = visit["pattern"]
            out.append(
                {
                    "name": f"{data.name} loop {visit['loop']}",
                    "lighting": visit["lighting"]["name"],
                    "lane": p["lane"],
                    "circuit": f"{p['circuit']} {'cw' if p['clockwise'] else 'ccw'}",
                    "moving objects": str(visit["moving_objects"]),
                    "where": np.linspace(0.0, 1.0, len(truth.t), endpoint=False),
                    "errors": errors,
                }
            )
    return out


def tables(loops: list[dict]) -> str:
    """One markdown table per condition: frames and median errors of every pose."""
    names = [n for n in POSES if any(n in v["errors"] for v in loops)]
    lines = []
    for cond in CONDITIONS:
        groups = defaultdict(list)
        for v in loops:
            groups[v[cond]].append(v)
        lines += [f"\n| {cond} | visits | frames | " + " | ".join(f"{n}: t / R" for n in names) + " |"]
        lines += ["|---|---|---|" + "---|" * len(names)]
        for key in sorted(groups):
            vs = groups[key]
            cells = []
            for n in names:
                t = np.concatenate([v["errors"][n][0] for v in vs if n in v["errors"]])
                r = np.concatenate([v["errors"][n][1] for v in vs if n in v["errors"]])
                cells.append(f"{np.median(t):.3f} m / {np.median(r):.2f} deg")
            frames = sum(len(v["where"]) for v in vs)
            lines.append(f"| {key} | {len(vs)} | {frames} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(loops: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5), gridspec_kw={"width_ratios": [1, 1, 2]})
    for ax, cond in zip(axes[:2], ("lighting", "lane"), strict=True):
        keys = sorted({v[cond] for v in loops})
        data = [np.concatenate([v["errors"]["network"][0] for v in loops if v[cond] == k]) for k in keys]
        ax.boxplot(data, showfliers=False)
        ax.set_xticks(range(1, len(keys) + 1), keys, rotation=20)
        ax.set_ylabel("network position error [m]")
        ax.set_title(f"per {cond}")
    presets = sorted({v["lighting"] for v in loops})
    colours = dict(zip(presets, plt.cm.tab10.colors, strict=False))
    for v in loops:
        t = v["errors"]["network"][0]
        smooth = np.convolve(t, np.ones(9) / 9, mode="same")
        axes[2].plot(v["where"], smooth, color=colours[v["lighting"]], lw=1, alpha=0.8)
    for preset in presets:
        axes[2].plot([], [], color=colours[preset], label=preset)
    axes[2].legend(fontsize=8)
    axes[2].set_xlabel("fraction of the loop")
    axes[2].set_ylabel("position error [m], 9 frames' mean")
    axes[2].set_title("along the circuit, every visit")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"plot: {path}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder", type=Path, help="a scripts/fresh_visits.py --out folder")
    p.add_argument("--label", default="shipped", help="the checkpoint's label there (default shipped)")
    p.add_argument("--plot", type=Path, default=None, metavar="PNG", help="write the figure here")
    args = p.parse_args(argv)
    loops = visits(args.folder, args.label)
    if not loops:
        print(f"error: no scored visits of label {args.label!r} in {args.folder}", file=sys.stderr)
        return 2
    print(f"{len(loops)} visits of {args.folder}, label {args.label}")
    print(tables(loops))
    if args.plot:
        plot(loops, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())

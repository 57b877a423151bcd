"""scripts/fresh_visits.py and scripts/visit_errors.py end to end on two short loops of a tests' visit seed: the
table's rows (the network fused with its odometry, each frame alone, retrieval), and the error per visit condition
read back from the trajectories and the scene's conditions; a missing input refused before any rendering."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _script(name: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / name), *args], capture_output=True, text=True, cwd=ROOT, timeout=600
    )


def test_fresh_visits_table_and_the_errors_per_visit_condition(tmp_path):
    out = tmp_path / "visits"
    run = _script(
        "fresh_visits.py", "--seed", "5", "--test-loops", "2", "--frames-per-loop", "12", "--map", "", "--out", str(out)
    )
    assert run.returncode == 0, run.stderr
    assert "note: seeds [5] were used before" in run.stderr  # a spent seed is said to be one
    rows = {line.split("|")[2].strip() for line in run.stdout.splitlines() if line.startswith("| 5 |")}
    assert rows == {"shipped (network)", "shipped (network, each frame alone)", "retrieval"}, rows
    assert (out / "table.md").read_text().count("| worst |") == 3

    plot = tmp_path / "errors.png"
    run = _script("visit_errors.py", str(out), "--plot", str(plot))
    assert run.returncode == 0, run.stderr
    visits = json.loads((out / "seed5" / "scene.json").read_text())["visits"]
    assert run.stdout.startswith(f"{len(visits)} visits of {out}")
    for v in visits:  # every visit's lighting preset and lane is a row of its table
        assert f"| {v['lighting']['name']} |" in run.stdout and f"| {v['pattern']['lane']} |" in run.stdout
    assert "network: t / R | each frame alone: t / R" in run.stdout
    assert plot.stat().st_size > 10_000

    missing = _script("visit_errors.py", str(out), "--label", "other")
    assert missing.returncode == 2 and "no scored visits of label 'other'" in missing.stderr

    no_map = _script(
        "fresh_visits.py", "--seed", "5", "--map", str(tmp_path / "none.npz"), "--out", str(tmp_path / "x")
    )
    assert no_map.returncode == 1 and "no such file" in no_map.stderr and "map build" in no_map.stderr
    assert not (tmp_path / "x").exists()  # refused before rendering anything

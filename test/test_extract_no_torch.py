"""`vlocnetpp extract` loads no torch, localizer, checkpoint or network: its module, its `--help` and a whole run, each
in a fresh interpreter."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from bag_fixtures import write_sqlite_bag

HEAVY = ("torch", "vlocnetpp_core.inference.localizer", "vlocnetpp_core.inference.checkpoint", "vlocnetpp_core.model")


def _heavy_modules_after(code: str) -> list[str]:
    """Which of :data:`HEAVY` a fresh interpreter has loaded after running ``code`` (the last stdout line)."""
    code += f"\nimport json, sys; print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_extract_loads_neither_torch_nor_the_localizer_nor_the_model():
    """`vlocnetpp extract` reads bags and writes files: its module and its `--help` import no torch, localizer,
    checkpoint or network (vlocnetpp_core.geometry runs numpy inputs in numpy; extrinsics names the localizer's result
    type for annotations only)."""
    assert _heavy_modules_after("import vlocnetpp_core.bag.extract_cli") == []
    help_code = (
        "from vlocnetpp_core.cli import main\n"
        "try:\n    main(['extract', '--help'])\nexcept SystemExit as e:\n    assert e.code == 0, e.code"
    )
    assert _heavy_modules_after(help_code) == []


def test_an_extract_run_loads_no_torch(tmp_path):
    """The whole command on a small bag (poses from Odometry composed with camera extrinsics, depth matched), the
    read-back of the written dataset included."""
    write_sqlite_bag(tmp_path / "bag", np.round(1.0 + 0.1 * np.arange(6), 6), 0.9 + 0.1 * np.arange(8))
    argv = [str(tmp_path / "bag"), str(tmp_path / "ds"), "--pose-topic", "/odom", "--no-progress"]
    argv += ["--camera-extrinsics", "0.3,-0.1,0.8,0.5,-0.5,0.5,-0.5", "--depth-tolerance", "0.01"]
    assert _heavy_modules_after(f"from vlocnetpp_core.cli import main; assert main(['extract', *{argv!r}]) == 0") == []
    assert (tmp_path / "ds" / "DeepLoc" / "train" / "stamps.txt").read_text().count("\n") == 6

"""`vlocnetpp synth`: help, one-line errors, summary, and no half-written output after an interruption."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ctrl_c_interrupts

from vlocnetpp_core import cli

REPO = Path(__file__).resolve().parents[1]


def test_help_lists_the_options(capsys):
    with pytest.raises(SystemExit) as done:
        cli.main(["synth", "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    for flag in (
        "--scene",
        "--seed",
        "--loops",
        "--test-loops",
        "--frames-per-loop",
        "--size",
        "--force",
        "--frame-interval",
        "--lighting",
    ):
        assert flag in text


def test_renders_and_prints_one_summary_line(tmp_path, capsys):
    out = tmp_path / "ds"
    rc = cli.main(
        [
            "synth",
            str(out),
            "--loops",
            "1",
            "--test-loops",
            "1",
            "--frames-per-loop",
            "3",
            "--size",
            "64x36",
            "--lighting",
            "overcast",
            "--no-progress",
        ]
    )
    assert rc == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"wrote {out}: 1 train + 1 test loops, 6 frames at 64x36")
    assert len(list(out.glob("DeepLoc/*/LeftImages/*.png"))) == 6
    visits = json.loads((out / "scene.json").read_text())["visits"]
    assert [v["lighting"]["name"] for v in visits] == ["overcast", "overcast"]
    assert (
        cli.main(["synth", str(out), "--loops", "1", "--frames-per-loop", "3", "--size", "64x36", "--no-progress"]) == 2
    )
    assert "exists already (use --force" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args, words",
    [
        (["--size", "64by36"], "WIDTHxHEIGHT"),
        (["--size", "4x4"], "--size"),
        (["--frames-per-loop", "0"], "--frames-per-loop"),
        (["--lighting", "noon,dusk"], "--lighting must name presets among"),
    ],
)
def test_bad_flags_give_one_line(tmp_path, capsys, args, words):
    try:
        rc = cli.main(["synth", str(tmp_path / "ds"), "--no-progress", *args])
    except SystemExit as e:  # argparse type errors
        rc = e.code
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert words in err[-1] and "Traceback" not in "".join(err)
    assert not (tmp_path / "ds").exists()


def test_interrupted_render_leaves_nothing_behind(tmp_path):
    """Ctrl-C in the middle of rendering: no OUT, no temporary folder, and a replaced OUT stays intact."""
    out = tmp_path / "ds"
    out.mkdir()
    (out / "old.txt").write_text("previous dataset")
    cmd = [
        sys.executable,
        "-m",
        "vlocnetpp_core.cli",
        "synth",
        str(out),
        "--force",
        "--loops",
        "1",
        "--test-loops",
        "0",
        "--frames-per-loop",
        "2000",
        "--size",
        "48x32",
        "--no-progress",
    ]
    proc = subprocess.Popen(
        cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=ctrl_c_interrupts
    )
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob(".ds.partial-*/DeepLoc/train/LeftImages/Image_5.png")):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "rendering never started"
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130 and "interrupted" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]
    assert sorted(p.name for p in out.iterdir()) == ["old.txt"]

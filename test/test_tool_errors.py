"""Bad output paths and inits, tried as a careless user would: one line naming the path or the mismatch, exit 2,
nothing left behind (``vlocnetpp_core.outputs``, ``train_init``)."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import REPO

from vlocnetpp_core.cli import main as cli
from vlocnetpp_core.model import load_model_config
from vlocnetpp_core.synth import render_dataset

SYNTH = ["--loops", "1", "--test-loops", "0", "--frames-per-loop", "2", "--size", "32x24", "--no-progress"]
PR_CAPBSET_DROP = 24


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, Path]:
    """Two train loops of 4 frames at 64x48 and lite_pose at that size."""
    root = tmp_path_factory.mktemp("errors")
    data = root / "campus"
    render_dataset(data, seed=0, train_loops=2, test_loops=0, frames_per_loop=4, size=(64, 48), progress=False)
    config = root / "tiny_pose.yaml"
    config.write_text(yaml.safe_dump({**load_model_config("lite_pose").to_dict(), "input_size": [64, 48]}))
    return data, config


def train_argv(tiny, out: Path | str, *extra: str) -> list[str]:
    data, config = tiny
    return [
        "train",
        "--config",
        str(config),
        "--data",
        str(data),
        "--stage",
        "stl-loc",
        "--out",
        str(out),
        "--steps",
        "1",
        "--batch-size",
        "2",
        "--clip-len",
        "2",
        "--workers",
        "0",
        "--threads",
        "1",
        "--no-progress",
        *extra,
    ]


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert err and "Traceback" not in "\n".join(err)
    return err[-1]


# --------------------------------------------------------------------------- a read-only folder


@pytest.fixture
def readonly(tmp_path) -> Path:
    """A read-only (0o555) folder."""
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    yield ro
    ro.chmod(0o755)


def _without_dac_override() -> None:
    """``preexec_fn``: drop CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH from the bounding set, so that the program the
    child execs runs as root that honours permission bits (``os.access`` included) as any owner does."""
    libc = ctypes.CDLL(None, use_errno=True)
    for cap in (1, 2):
        if libc.prctl(PR_CAPBSET_DROP, cap, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def run_without_root_powers(argv: list[str]) -> subprocess.CompletedProcess:
    """``vlocnetpp ARGV`` in a child process; as root, one without the capability to write where permissions forbid
    it (root writes in a 0o555 folder)."""
    drop = {"preexec_fn": _without_dac_override} if os.geteuid() == 0 else {}
    try:
        return subprocess.run(
            [sys.executable, "-m", "vlocnetpp_core.cli", *argv],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=300,
            **drop,
        )
    except subprocess.SubprocessError as err:  # no CAP_SETPCAP in this container
        pytest.skip(f"cannot start a child without CAP_DAC_OVERRIDE: {err}")


@pytest.mark.parametrize("tool", ["synth", "train"])
def test_a_read_only_folder_is_one_line_naming_it(tiny, readonly, tool):
    # as root the child runs without CAP_DAC_OVERRIDE (with it root writes in a 0o555 folder and os.access says so)
    out = readonly / ("ds" if tool == "synth" else "run")
    argv = ["synth", str(out), *SYNTH] if tool == "synth" else train_argv(tiny, out)
    proc = run_without_root_powers(argv)
    assert proc.returncode == 2, proc.stderr[-2000:]
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert err[0] == f"vlocnetpp {tool}: error: {out}: cannot write in {readonly} (permission denied)"
    assert list(readonly.iterdir()) == []


# --------------------------------------------------------------------------- a file where a folder must be


@pytest.mark.parametrize("tool", ["synth", "train"])
def test_a_path_under_a_file_is_one_line_naming_the_file(tiny, tmp_path, capsys, tool):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    out = afile / "sub" / "ds"
    assert cli(["synth", str(out), *SYNTH] if tool == "synth" else train_argv(tiny, out)) == 2
    assert one_line_error(capsys) == f"vlocnetpp {tool}: error: {out}: {afile} is not a folder"
    assert afile.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_train_out_on_a_file_is_refused(tiny, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    assert cli(train_argv(tiny, afile)) == 2
    assert one_line_error(capsys) == f"vlocnetpp train: error: {afile}: exists and is not a folder"
    assert afile.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_synth_out_on_a_file_is_refused_even_with_force(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    assert cli(["synth", str(afile), "--force", *SYNTH]) == 2
    assert one_line_error(capsys) == f"vlocnetpp synth: error: {afile}: exists and is not a folder; not replacing it"
    assert afile.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


# --------------------------------------------------------------------------- --force from inside the target


@pytest.mark.parametrize("target, cwd", [(".", "ds"), ("..", "ds/sub")])
def test_synth_force_from_inside_the_target_is_refused_up_front(tmp_path, monkeypatch, capsys, target, cwd):
    ds = tmp_path / "ds"
    (ds / "sub").mkdir(parents=True)
    (ds / "keep.txt").write_text("previous dataset")
    monkeypatch.chdir(tmp_path / cwd)
    assert cli(["synth", target, "--force", *SYNTH]) == 2
    line = one_line_error(capsys)
    assert line.startswith(f"vlocnetpp synth: error: {target}: is the current folder or one above it ("), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]  # no ..old-* or .partial-* folder
    assert (
        sorted(p.name for p in ds.iterdir()) == ["keep.txt", "sub"]
        and (ds / "keep.txt").read_text() == "previous dataset"
    )


def test_synth_force_from_beside_the_target_still_replaces_it(tmp_path, monkeypatch, capsys):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "keep.txt").write_text("previous dataset")
    monkeypatch.chdir(tmp_path)
    assert cli(["synth", "ds", "--force", *SYNTH]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"] and not (tmp_path / "ds" / "keep.txt").exists()
    assert (tmp_path / "ds" / "DeepLoc" / "train" / "poses.txt").is_file()


def test_synth_leaves_no_parent_folders_it_made_when_it_fails(tmp_path, monkeypatch, capsys):
    from vlocnetpp_core.synth import writer

    def fail(root, *args, **kwargs):
        (root / "half.txt").write_text("half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(writer, "_render_into", fail)
    with pytest.raises(OSError, match="No space"):
        writer.render_dataset(
            tmp_path / "a" / "b" / "ds", train_loops=1, test_loops=0, frames_per_loop=2, size=(32, 24), progress=False
        )
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- --init sharing no tensor


def test_init_from_a_checkpoint_sharing_no_tensor_is_refused(tiny, tmp_path, capsys):
    from safetensors.torch import load_file, save_file

    from vlocnetpp_core.inference.checkpoint import save_checkpoint
    from vlocnetpp_core.model import VLocNetPP

    other = tmp_path / "OTHER.safetensors"
    save_checkpoint(other, VLocNetPP(load_model_config(tiny[1])))
    save_file({"other_net." + k: v for k, v in load_file(str(other)).items()}, str(other))  # another network's names
    out = tmp_path / "run"
    assert cli(train_argv(tiny, out, "--init", str(other))) == 2
    line = one_line_error(capsys)
    assert (
        line.startswith(f"vlocnetpp train: error: --init {other}: none of its ")
        and "matches a tensor of this stl-loc network" in line
    )
    assert not out.exists()

"""Shared pytest fixtures."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def ctrl_c_interrupts() -> None:
    """``preexec_fn`` for a child the test stops with SIGINT: the default disposition, so Python's Ctrl-C handler is
    installed even when the suite runs as a shell's background job (``&`` starts it with SIGINT ignored, and an ignored
    signal stays ignored across exec)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def pytest_addoption(parser) -> None:
    parser.addoption(
        "--threads",
        type=int,
        default=None,
        metavar="N",
        help="torch and OpenMP threads for the tests and the programs they start (default: the libraries' own), "
        "e.g. 1 to check that nothing depends on a thread count",
    )


def pytest_configure(config) -> None:
    threads = config.getoption("--threads")
    if threads is None:
        return
    if threads < 1:
        raise pytest.UsageError(f"--threads must be >= 1, got {threads}")
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(threads)  # the programs the tests start
    import torch

    torch.set_num_threads(threads)


def _colcon() -> str:
    exe = Path(sys.executable).parent / "colcon"
    return str(exe) if exe.exists() else (shutil.which("colcon") or "colcon")


@pytest.fixture(scope="session", autouse=True)
def camera_publisher_profile() -> None:
    """The tests' rclpy nodes publish camera frames as the project's tools do: with the localizer's Fast DDS
    profile (:class:`vlocnetpp_ros.dds_client.DdsClient`), whose 8 MiB shared-memory segment sends a 640x480 frame
    whole. With Fast DDS's default 512 KiB segment a best-effort publisher's frames over 512 KiB reach another
    process only now and then (docs/node.md, "Camera transport"). Fast DDS reads a profile once per process, at
    its first participant: made here, before any test's."""
    from vlocnetpp_ros.dds_client import DdsClient

    DdsClient("test_profile", "").close()


@pytest.fixture(scope="session")
def colcon_install(tmp_path_factory) -> Path:
    """Build this repository with colcon (from PyPI) once per session; returns the install prefix.

    The build runs in a temporary copy of the tracked sources so that it never touches the
    working tree (no build/, install/, log/ left behind).
    """
    root = tmp_path_factory.mktemp("colcon")
    src = root / "src" / "vlocnetpp_ros"
    files = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True, text=True, check=True
    )
    for rel in files.stdout.splitlines():
        p = REPO / rel
        if p.is_file():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(p, src / rel)
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}:{env.get('PATH', '')}"
    proc = subprocess.run(
        [
            _colcon(),
            "--log-base",
            str(root / "log"),
            "build",
            "--base-paths",
            str(root / "src"),
            "--build-base",
            str(root / "build"),
            "--install-base",
            str(root / "install"),
        ],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, f"colcon build failed:\n{proc.stdout}\n{proc.stderr}"
    return root / "install"


def install_env(install: Path) -> dict[str, str]:
    """Environment for running programs from a colcon install tree (what `source setup.bash` does for us)."""
    env = dict(os.environ)
    prefix = install / "vlocnetpp_ros"
    site = next((prefix / "lib").glob("python3*/site-packages"))
    env["PYTHONPATH"] = f"{site}:{env.get('PYTHONPATH', '')}".rstrip(":")
    env["AMENT_PREFIX_PATH"] = f"{prefix}:{env.get('AMENT_PREFIX_PATH', '')}".rstrip(":")
    return env


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> tuple[Path, Path]:
    """A 3-loop synthetic campus at 64x48 and a lite config at that input size: the data of the `vlocnetpp train`
    tests (``test_train*.py``; rendered once per session, read only: training writes nothing into it).
    ``test_tool_errors.py`` has a smaller one of its own."""
    import yaml

    from vlocnetpp_core.model import load_model_config
    from vlocnetpp_core.synth import render_dataset

    root = tmp_path_factory.mktemp("train")
    data = root / "campus"
    render_dataset(data, seed=0, train_loops=3, test_loops=1, frames_per_loop=10, size=(64, 48), progress=False)
    cfg = load_model_config("lite").to_dict()
    cfg["input_size"] = [64, 48]
    config = root / "tiny.yaml"
    config.write_text(yaml.safe_dump(cfg))
    return data, config

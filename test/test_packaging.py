"""The package builds with colcon, installs what `ros2 run` needs, and keeps core free of ROS."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, install_env

from vlocnetpp_core.cli import COMMANDS


def test_colcon_install_tree_has_what_ros2_run_needs(colcon_install: Path):
    prefix = colcon_install / "vlocnetpp_ros"
    exe = prefix / "lib" / "vlocnetpp_ros" / "localizer"
    assert exe.is_file() and os.access(exe, os.X_OK)
    assert (prefix / "lib" / "vlocnetpp_ros" / "vlocnetpp").is_file()
    share = prefix / "share" / "vlocnetpp_ros"
    assert (share / "package.xml").is_file()
    for name in ("paper.yaml", "lite.yaml", "lite_pose.yaml", "localizer.yaml"):
        assert (share / "config" / name).is_file(), name
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "vlocnetpp_ros").is_file()
    # ament_index_python finds the package once the install tree is on AMENT_PREFIX_PATH
    code = (
        "from ament_index_python.packages import get_package_prefix, get_package_share_directory as s;"
        "print(get_package_prefix('vlocnetpp_ros')); print(s('vlocnetpp_ros'))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=install_env(colcon_install), capture_output=True, text=True, check=True
    )
    lines = out.stdout.split()
    assert Path(lines[0]) == prefix and Path(lines[1]) == share


def test_installed_cli_runs_from_install_tree(colcon_install: Path):
    exe = colcon_install / "vlocnetpp_ros" / "lib" / "vlocnetpp_ros" / "vlocnetpp"
    env = install_env(colcon_install)
    out = subprocess.run([str(exe), "--help"], env=env, cwd="/", capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "synth" in out.stdout and "train" in out.stdout
    for name in ("vlocnetpp-replay-node", "vlocnetpp-latency-bench", "vlocnetpp-soak"):
        assert (exe.parent / name).is_file(), name
    # the ROS programs the core starts are found from the install tree's metadata, by name
    code = (
        "from vlocnetpp_core.programs import program_command as p; print(p('replay-node')[-1], p('latency-bench')[-1])"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd="/", capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["vlocnetpp_ros.replay_bridge", "vlocnetpp_ros.latency_bench"]


def test_package_xml_is_format_3_ament_python():
    import xml.etree.ElementTree as ET

    root = ET.parse(REPO / "package.xml").getroot()
    assert root.get("format") == "3"
    assert root.findtext("name") == "vlocnetpp_ros"
    assert root.find("export/build_type").text == "ament_python"
    deps = {e.text for e in root.findall("exec_depend")}
    assert {"rclpy", "sensor_msgs", "geometry_msgs", "nav_msgs", "std_msgs", "diagnostic_msgs"} <= deps


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_core_never_imports_ros():
    ros = {
        "rclpy",
        "sensor_msgs",
        "geometry_msgs",
        "nav_msgs",
        "std_msgs",
        "diagnostic_msgs",
        "builtin_interfaces",
        "vlocnetpp_ros",
    }
    offenders = {str(p.relative_to(REPO)): sorted(_imports(p) & ros) for p in (REPO / "vlocnetpp_core").rglob("*.py")}
    assert not {k: v for k, v in offenders.items() if v}
    # nor starts a module of the ROS package by name (it asks for a registered program: vlocnetpp_core/programs.py)
    named = [
        str(p.relative_to(REPO)) for p in (REPO / "vlocnetpp_core").rglob("*.py") if "vlocnetpp_ros." in p.read_text()
    ]
    assert not named
    # and importing every core module at runtime does not pull rclpy in
    code = (
        "import importlib, pkgutil, sys, vlocnetpp_core\n"
        "for m in pkgutil.walk_packages(vlocnetpp_core.__path__, 'vlocnetpp_core.'):\n"
        "    importlib.import_module(m.name)\n"
        "print(sorted(k for k in sys.modules if k.split('.')[0] in ('rclpy', 'sensor_msgs')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_cli_lists_subcommands():
    out = subprocess.run(
        [sys.executable, "-m", "vlocnetpp_core.cli", "--help"], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0
    for name in COMMANDS:
        assert name in out.stdout


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_subcommand_has_help(name: str):
    out = subprocess.run(
        [sys.executable, "-m", "vlocnetpp_core.cli", name, "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage: vlocnetpp " + name)


def test_ci_runs_the_readme_test_command():
    readme = (REPO / "README.md").read_text()
    ci = (REPO / ".ci" / "run").read_text()
    assert "bash scripts/dev test" in readme and "bash scripts/dev demo" in readme
    assert "bash scripts/dev test" in ci

"""``vlocnetpp model-info``: JSON and table output through the real CLI entry point."""

from __future__ import annotations

import json

import yaml

from vlocnetpp_core.cli import main
from vlocnetpp_core.model import STREAMS, VLocNetPP, load_model_config


def test_model_info_json_counts_every_stream(capsys):
    assert main(["model-info", "--config", "lite", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    model = VLocNetPP(load_model_config("lite"))
    assert info["params_total"] == sum(p.numel() for p in model.parameters())
    assert set(info["params_per_stream"]) == set(STREAMS)
    assert sum(info["params_per_stream"].values()) == info["params_total"]
    assert info["input_size"] == list(load_model_config("lite").input_size)
    assert info["params_trained_per_stage"]["mtl"] == info["params_total"]
    assert info["params_trained_per_stage"]["stl-loc"] == info["params_per_stream"]["global"]
    assert info["global_stream"] == {
        "downsample": 2,
        "pooling": "flatten",
        "anchors": 256,
        "rotation_anchors": 32,
        "res5_size": [2, 4],
    }
    assert info["odometry_stream"] == {"pooling": "flatten", "res5_size": [4, 7]}


def test_model_info_table_and_yaml_path(tmp_path, capsys):
    cfg = load_model_config("lite").to_dict() | {"name": "no-fusion", "semantic_fusion": False, "input_size": [160, 96]}
    path = tmp_path / "no_fusion.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["model-info", "--config", str(path)]) == 0
    out = capsys.readouterr().out
    assert "'no-fusion'" in out and "160x96" in out and "semantic_fusion=off" in out
    assert "Res3 map pooled by 2" in out and "3x2 Res5c map is flattened" in out
    assert "256 scored anchors plus offsets" in out and "32 scored anchor rotations" in out
    assert "odometry stream: its 5x3 Res5 map of the two frames is flattened" in out
    assert any(line.split() == ["fusion", "0"] for line in out.splitlines())


def test_model_info_bad_config_is_one_line_error(tmp_path, capsys):
    assert main(["model-info", "--config", str(tmp_path / "missing.yaml")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "missing.yaml" in err


def test_model_info_from_the_install_tree_finds_the_shipped_configs(colcon_install):
    """Outside the repository the named configs resolve to share/vlocnetpp_ros/config of the install."""
    import subprocess

    from conftest import install_env

    exe = colcon_install / "vlocnetpp_ros" / "lib" / "vlocnetpp_ros" / "vlocnetpp"
    out = subprocess.run(
        [str(exe), "model-info", "--config", "lite", "--json"],
        env=install_env(colcon_install),
        cwd="/",
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["params_total"] == sum(
        p.numel() for p in VLocNetPP(load_model_config("lite")).parameters()
    )

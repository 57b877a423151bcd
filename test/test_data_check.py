"""``vlocnetpp data-info``: summary contents and the warp-consistency check on exactly rendered data."""

from __future__ import annotations

import json

import numpy as np
import pytest
from data_fixtures import K_SMALL, trajectory, write_deeploc_split, write_sevenscenes

from vlocnetpp_core.cli import main as cli_main
from vlocnetpp_core.data.check import dataset_info


@pytest.fixture(scope="module")
def plane_deeploc(tmp_path_factory):
    root = tmp_path_factory.mktemp("check")
    t, q = trajectory(10, yaw_deg=4.0)
    write_deeploc_split(root, "train", list(range(1, 11)), t, q)
    t, q = trajectory(5, start=0.5, yaw_deg=4.0)
    write_deeploc_split(root, "test", [1, 2, 3, 4, 5], t, q, labels=False)
    (root / "intrinsics.json").write_text(json.dumps(K_SMALL.to_dict()))
    return root


def _cli_json(capsys, *argv) -> dict:
    assert cli_main(["data-info", *map(str, argv), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_json_summary(plane_deeploc, capsys):
    r = _cli_json(capsys, plane_deeploc)
    assert r["format"] == "deeploc" and r["intrinsics"] == K_SMALL.to_dict()
    train, test = r["splits"]["train"], r["splits"]["test"]
    assert (train["frames"], train["sequences"], test["frames"], test["sequences"]) == (10, 1, 5, 1)
    assert train["has_depth"] and train["has_labels"] and test["has_depth"] and not test["has_labels"]
    assert "class_histogram" not in test
    hist = train["class_histogram"]
    assert (
        sum(hist.values()) == pytest.approx(1.0, abs=1e-4)
        and hist["ignore"] == 0
        and min(hist[c] for c in ("Background", "Other")) > 0.05
    )
    assert train["warp_pairs"] == 9 and test["warp_pairs"] == 4
    assert r["warp_consistency"] < 0.1  # rendered exactly: warping explains the motion


def test_warp_consistency_detects_wrong_quaternion_order_and_intrinsics(plane_deeploc):
    good = dataset_info(plane_deeploc, splits=("train",))["warp_consistency"]
    swapped = dataset_info(plane_deeploc, splits=("train",), quaternion_order="xyzw")["warp_consistency"]
    wrong_k = dataset_info(plane_deeploc, splits=("train",), intrinsics="120,120,47.5,35.5")["warp_consistency"]
    assert good < 0.1 and swapped > 3 * good and wrong_k > 3 * good


def test_text_report_warns_when_warping_does_not_help(plane_deeploc, tmp_path, capsys):
    assert cli_main(["data-info", str(plane_deeploc), "--split", "train"]) == 0
    out = capsys.readouterr().out
    assert "train: 10 frames in 1 sequences" in out and "warp consistency: 0.0" in out and "warning" not in out
    # Translations written in decimetres instead of metres: the ground truth no longer explains the motion.
    t, q = trajectory(6, yaw_deg=4.0)
    write_deeploc_split(tmp_path, "train", list(range(1, 7)), t, q)
    poses = tmp_path / "DeepLoc/train/poses.txt"
    lines = poses.read_text().splitlines()
    lines[2:] = [
        " ".join([f[0], *(str(8 * float(v)) for v in f[1:4]), *f[4:]]) for f in (ln.split() for ln in lines[2:])
    ]
    poses.write_text("\n".join(lines))
    assert cli_main(["data-info", str(tmp_path), "--intrinsics", "80,80,47.5,35.5"]) == 0
    out = capsys.readouterr().out
    assert "warning: train:" in out and "quaternion order" in out


def test_sevenscenes_info_and_missing_split(tmp_path, capsys):
    write_sevenscenes(tmp_path, {1: 4, 2: 3}, train=[1], test=[2], K=K_SMALL)
    r = _cli_json(capsys, tmp_path, "--intrinsics", "80,80,47.5,35.5", "--pairs", "2")
    assert r["format"] == "7scenes" and r["splits"]["train"]["frames"] == 4 and r["splits"]["train"]["warp_pairs"] == 2
    assert not r["splits"]["train"]["has_labels"] and r["warp_consistency"] < 0.1
    (tmp_path / "TestSplit.txt").unlink()
    r = _cli_json(capsys, tmp_path, "--format", "7scenes")
    assert list(r["splits"]) == ["train"]
    assert cli_main(["data-info", str(tmp_path), "--split", "test"]) == 2
    assert "no test split found" in capsys.readouterr().err


def test_bad_intrinsics_flag(plane_deeploc, capsys):
    assert cli_main(["data-info", str(plane_deeploc), "--intrinsics", "80,80"]) == 2
    assert "--intrinsics" in capsys.readouterr().err


def test_pairs_are_spread_over_the_split():
    from vlocnetpp_core.data.check import evenly_spread

    assert evenly_spread(list(range(100)), 5) == [0, 25, 50, 74, 99]
    assert evenly_spread([1, 2], 5) == [1, 2]
    assert np.all(np.diff(evenly_spread(list(range(1000)), 50)) > 0)

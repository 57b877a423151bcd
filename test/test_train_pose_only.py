"""`vlocnetpp train` of a pose-only network (no semantic stream) on a dataset without labels or depth."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from learning_probe import deterministic, ratios, train_probed
from train_fixtures import read_log, steps_of, train, train_args

from vlocnetpp_core.cli import main as cli
from vlocnetpp_core.inference.checkpoint import load_checkpoint
from vlocnetpp_core.model import load_model_config


@pytest.fixture(scope="module")
def unlabelled(tiny, tmp_path_factory) -> tuple[Path, Path]:
    """The tiny campus without its labels and depth files (poses and images only), and lite_pose at 64x48."""
    root = tmp_path_factory.mktemp("pose_only")
    data = root / "campus"
    shutil.copytree(tiny[0], data, ignore=shutil.ignore_patterns("labels", "labels_colorized", "DeepLoc_stereo"))
    cfg = load_model_config("lite_pose").to_dict()
    cfg["input_size"] = [64, 48]
    config = root / "tiny_pose.yaml"
    config.write_text(yaml.safe_dump(cfg))
    return data, config


def test_pose_only_refuses_stl_seg(unlabelled, tmp_path, capsys):
    data, config = unlabelled
    out = tmp_path / "seg"
    assert cli(["train", "--config", str(config), "--data", str(data), "--stage", "stl-seg", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert (
        "stage stl-seg trains the segmentation stream" in err
        and "semantic_stream: false" in err
        and "stl-loc, stl-vo, mtl" in err
    )
    assert not out.exists()


def test_pose_only_trains_without_labels_or_depth(unlabelled, tmp_path, capsys):
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.inference.checkpoint import read_checkpoint_tensors

    data, config = unlabelled
    index = open_dataset(data, None, "train")
    assert not index.has_labels and not index.has_depth
    one = ("--threads", "1")  # tiny tensors: a second thread only slows them down on a busy machine
    # Learning on the probe batch (every training clip, learning_probe), after / before, measured over --seed 0-3 x
    # --threads 1, 2: stl-loc (60 steps) x 0.16-0.33, q 0.22-0.45; mtl from scratch (60 steps at its 1e-4) q_vo
    # 0.050-0.135, q 0.66-0.72 (the position terms barely move: x 0.90-0.94, x_vo 0.45-0.82, not checked). --lr 0: 1.0.
    with deterministic():
        loc = train_probed(train_args(data, config, tmp_path / "stl-loc", "stl-loc", 60, *one))
        train(
            data,
            config,
            tmp_path / "stl-vo",
            "stl-vo",
            6,
            *one,
            "--init",
            str(tmp_path / "stl-loc" / "last.safetensors"),
        )
        mtl = train_probed(
            train_args(data, config, tmp_path / "mtl", "mtl", 60, *one)
        )  # loc + vo, Eq. 6 weighting of the pose tasks
    for name, (before, after), checks in (
        ("stl-loc", loc, (("x", 0.6), ("q", 0.8))),
        ("mtl", mtl, (("q_vo", 0.35), ("q", 0.9))),
    ):
        got = ratios(before, after, [key for key, _ in checks])
        for key, factor in checks:
            assert got[key] < factor, (
                f"{name}: {key} on the probe batch went {before[key]:.4g} -> {after[key]:.4g} ({got[key]:.3f}x)"
            )
    assert all(
        {"x", "q", "x_vo", "q_vo"} <= set(r) and not {"seg", "depth"} & set(r)
        for r in steps_of(read_log(tmp_path / "mtl"))
    )
    model, meta = load_checkpoint(tmp_path / "mtl" / "best")
    assert model.semantic is None and meta["model_config"]["semantic_stream"] is False
    # mtl assembled from the two pose stages (the "streams" rule): each stream is exactly its stage's
    inits = [a for stage in ("stl-loc", "stl-vo") for a in ("--init", str(tmp_path / stage / "last.safetensors"))]
    train(data, config, tmp_path / "assembled", "mtl", 0, *one, *inits)
    got = read_checkpoint_tensors(tmp_path / "assembled" / "last")[0]
    for stage, prefix in (("stl-loc", "global_stream."), ("stl-vo", "odometry.")):
        want = read_checkpoint_tensors(tmp_path / stage / "last")[0]
        assert all(torch.equal(got[k], want[k]) for k in want if k.startswith(prefix))
    # evaluate: pose, odometry and the retrieval baseline; no segmentation, and vo/loc both trained
    capsys.readouterr()
    assert (
        cli(
            [
                "evaluate",
                "--checkpoint",
                str(tmp_path / "assembled" / "last"),
                "--data",
                str(data),
                "--json",
                str(tmp_path / "m.json"),
                "--no-progress",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    report = json.loads((tmp_path / "m.json").read_text())
    assert report["meta"]["tasks"] == ["loc", "vo"] and report["meta"]["untrained_tasks"] == []
    assert report["overall"]["pose"]["median_translation_m"] is not None
    assert report["overall"]["odometry"]["translation_error_percent"] is not None and "baseline" in report
    assert "segmentation" not in report["overall"] and "mIoU" not in printed and "retrieval" in printed
    assert "segmentation: none: the model has no semantic stream" in printed and "not trained for" not in printed

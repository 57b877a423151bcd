"""`vlocnetpp evaluate` end to end: a lite checkpoint over a rendered test loop, through the Localizer."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from vlocnetpp_core import cli
from vlocnetpp_core.classes import CLASS_NAMES
from vlocnetpp_core.evaluation.metrics import kitti_segment_errors, pose_errors
from vlocnetpp_core.evaluation.trajectory import read_tum
from vlocnetpp_core.geometry import pose_to_matrix

FRAMES = 12


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    from vlocnetpp_core.inference.checkpoint import save_checkpoint
    from vlocnetpp_core.model import VLocNetPP, load_model_config
    from vlocnetpp_core.synth import render_dataset

    tmp = tmp_path_factory.mktemp("evaluate")
    render_dataset(tmp / "data", train_loops=1, test_loops=1, frames_per_loop=FRAMES, size=(160, 96), progress=False)
    torch.manual_seed(0)
    save_checkpoint(tmp / "ckpt" / "lite", VLocNetPP(load_model_config("lite")))
    out = tmp / "out"
    argv = [
        "evaluate",
        "--checkpoint",
        str(tmp / "ckpt" / "lite"),
        "--data",
        str(tmp / "data"),
        "--no-progress",
        "--json",
        str(out / "metrics.json"),
        "--trajectories",
        str(out / "traj"),
        "--plots",
        str(out / "plots"),
    ]
    return tmp, argv, out


def test_evaluate_writes_report_trajectories_and_plots(evaluated, capsys):
    tmp, argv, out = evaluated
    assert cli.main(argv) == 0
    stdout = capsys.readouterr().out
    assert stdout.splitlines()[0].split()[:2] == ["sequence", "frames"]
    assert any(line.split()[:2] == ["seq-00", str(FRAMES)] for line in stdout.splitlines())
    assert any(line.startswith("overall") for line in stdout.splitlines())

    report = json.loads((out / "metrics.json").read_text())
    assert list(report) == ["overall", "per_sequence", "frame_network", "baseline", "meta"]
    assert list(report["frame_network"]["per_sequence"]) == ["seq-00"]  # each frame alone, beside the fused pose
    assert report["meta"] == {
        "checkpoint": str(tmp / "ckpt" / "lite"),
        "data": str(tmp / "data"),
        "split": "test",
        "tasks": ["loc", "vo", "seg"],
        "untrained_tasks": None,
    }  # the sidecar does not say how it was trained
    assert "note:" not in stdout
    assert any(line.split()[:2] == ["retrieval", str(FRAMES)] for line in stdout.splitlines())
    assert any(line.startswith("network, each frame alone") for line in stdout.splitlines())
    assert list(report["per_sequence"]) == ["seq-00"]
    for part in (report["overall"], report["per_sequence"]["seq-00"]):
        assert list(part) == ["pose", "odometry", "segmentation", "timing"]
        assert list(part["pose"]) == [
            "median_translation_m",
            "median_rotation_deg",
            "accuracy_5cm_5deg",
            "accuracy_0.5m_5deg",
        ]
        assert list(part["odometry"]) == [
            "translation_error_percent",
            "rotation_error_deg_per_m",
            "lengths_m",
            "step_scale",
        ]
        assert list(part["segmentation"]) == ["miou", "iou", "pixel_accuracy"]
        assert list(part["segmentation"]["iou"]) == list(CLASS_NAMES)
        assert 0.0 <= part["segmentation"]["miou"] <= 1.0 and 0.0 <= part["segmentation"]["pixel_accuracy"] <= 1.0
        assert list(part["timing"]) == ["mean_ms", "median_ms"] and part["timing"]["median_ms"] > 0

    # the JSON agrees with the TUM files it came with
    seq = out / "traj" / "seq-00"
    truth, glob, odo = (read_tum(seq / f"{n}.tum") for n in ("ground_truth", "global_pose", "odometry"))
    assert len(truth) == len(glob) == len(odo) == FRAMES
    trans, rot = pose_errors(glob.t, glob.q, truth.t, truth.q)
    pose = report["overall"]["pose"]
    assert pose["median_translation_m"] == pytest.approx(np.median(trans), abs=1e-9)
    assert pose["median_rotation_deg"] == pytest.approx(np.median(rot), abs=1e-6)
    np.testing.assert_allclose(odo.t[0], truth.t[0], atol=1e-12)  # odometry starts at the true first pose
    odometry = report["overall"]["odometry"]
    assert len(odometry["lengths_m"]) == 8 and odometry["lengths_m"][0] > 0
    t_err, _ = kitti_segment_errors(
        pose_to_matrix(truth.t, truth.q), pose_to_matrix(odo.t, odo.q), odometry["lengths_m"]
    )
    assert odometry["translation_error_percent"] == pytest.approx(100 * np.mean(t_err), rel=1e-6)

    # the baseline: the pose of the nearest training image of --data, on the same frames
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.evaluation.retrieval import describe, open_reference

    test = open_dataset(tmp / "data", None, "test")
    frames = [test.load(i) for i in range(len(test))]
    base_t, base_q = open_reference(tmp / "data").poses(np.stack([describe(f.image) for f in frames]))
    base_trans, base_rot = pose_errors(base_t, base_q, truth.t, truth.q)
    baseline = report["baseline"]
    assert baseline["reference_frames"] == FRAMES and baseline["reference"].endswith("(train)")
    assert baseline["overall"]["pose"]["median_translation_m"] == pytest.approx(np.median(base_trans), abs=1e-9)
    assert baseline["overall"]["pose"]["median_rotation_deg"] == pytest.approx(np.median(base_rot), abs=1e-6)
    assert baseline["network_beats_baseline"]["translation"] == bool(
        pose["median_translation_m"] < np.median(base_trans)
    )

    for name in (
        "confusion.png",
        "seq-00/trajectory.png",
        "seq-00/errors.png",
        "seq-00/confusion.png",
        "seq-00/segmentation.png",
    ):
        image = cv2.imread(str(out / "plots" / name))
        assert image is not None and image.shape[0] > 100, name


def test_evaluate_streams_through_the_localizer(evaluated):
    """The global poses written are those of the Localizer stepping over the frames in order."""
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.inference.localizer import Localizer

    tmp, _, out = evaluated
    written = read_tum(out / "traj" / "seq-00" / "global_pose.tum")
    index = open_dataset(tmp / "data", split="test")
    localizer = Localizer.from_checkpoint(tmp / "ckpt" / "lite")
    for i in range(4):
        frame = index.load(index.sequences[0][i])
        result = localizer.step(frame.image, "rgb8", frame.stamp, intrinsics=frame.intrinsics)
        np.testing.assert_allclose(result.t, written.t[i], atol=1e-5)
        assert written.stamps[i] == frame.stamp


def test_evaluate_threshold_and_length_flags(evaluated, tmp_path):
    tmp, argv, _ = evaluated
    argv = argv[:6] + [
        "--no-progress",
        "--max-frames",
        "5",
        "--threshold-m",
        "2",
        "--threshold-deg",
        "90",
        "--odometry-lengths",
        "0.5,1",
        "--json",
        str(tmp_path / "m.json"),
    ]
    assert cli.main(argv) == 0
    report = json.loads((tmp_path / "m.json").read_text())
    assert list(report["overall"]["pose"])[2:] == ["accuracy_5cm_5deg", "accuracy_0.5m_5deg", "accuracy_2m_90deg"]
    assert report["overall"]["odometry"]["lengths_m"] == [0.5, 1.0]
    assert not (tmp_path / "traj").exists()


def test_evaluate_baseline_needs_another_split_or_a_reference(evaluated, tmp_path, capsys):
    tmp, argv, _ = evaluated
    argv = argv[:6] + ["--no-progress", "--max-frames", "4", "--split", "train", "--json", str(tmp_path / "m.json")]
    assert cli.main(argv) == 0  # the training images looked up in themselves would be a zero-error baseline: none
    assert "note: no retrieval baseline" in capsys.readouterr().out
    assert "baseline" not in json.loads((tmp_path / "m.json").read_text())
    assert cli.main(argv + ["--reference", str(tmp / "data")]) == 0  # asked for: the baseline is scored as given
    assert json.loads((tmp_path / "m.json").read_text())["baseline"]["overall"]["pose"]["median_translation_m"] == 0.0
    assert cli.main(argv + ["--reference", str(tmp_path / "missing.npz")]) == 2
    err = capsys.readouterr().err
    assert "--reference" in err and "missing.npz" in err


def test_evaluate_missing_checkpoint_is_one_line(evaluated, capsys):
    tmp, argv, _ = evaluated
    argv = ["evaluate", "--checkpoint", str(tmp / "nope"), "--data", str(tmp / "data"), "--no-progress"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "nope.safetensors" in err and "Traceback" not in err


def test_evaluate_names_the_tasks_a_checkpoint_was_not_trained_for(evaluated, tmp_path, capsys):
    """A single-task checkpoint's other columns come from untrained streams: evaluate says which."""
    from vlocnetpp_core.inference.checkpoint import save_checkpoint
    from vlocnetpp_core.model import VLocNetPP, load_model_config

    tmp, _, _ = evaluated
    torch.manual_seed(0)
    ckpt = save_checkpoint(
        tmp_path / "stl-vo", VLocNetPP(load_model_config("lite")), {"training": {"stage": "stl-vo", "init": []}}
    )
    argv = [
        "evaluate",
        "--checkpoint",
        str(ckpt),
        "--data",
        str(tmp / "data"),
        "--no-progress",
        "--max-frames",
        "3",
        "--json",
        str(tmp_path / "m.json"),
    ]
    assert cli.main(argv) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and "not trained for global pose, segmentation (stage stl-vo" in notes[0]
    assert json.loads((tmp_path / "m.json").read_text())["meta"]["untrained_tasks"] == ["loc", "seg"]


@pytest.mark.parametrize(
    "training, untrained",
    [
        ({"stage": "init"}, ["loc", "vo", "seg"]),
        ({"stage": "stl-seg", "init": []}, ["loc", "vo"]),
        # stl-loc takes only the trunk of an stl-vo init and the encoder of an stl-seg one (as its global stream)
        ({"stage": "stl-loc", "init": [{"stage": "stl-seg"}, {"stage": "stl-vo"}]}, ["vo", "seg"]),
        ({"stage": "stl-vo", "init": [{"stage": "stl-loc"}]}, ["loc", "seg"]),  # only the trunk, as the other way round
        ({"stage": "mtl", "init": []}, []),
        (
            {"stage": "mtl", "step": 0, "init": [{"stage": "stl-loc"}, {"stage": "stl-seg"}]},
            ["vo"],
        ),  # assembled, no odometry stage
        ({}, None),
    ],
)
def test_untrained_tasks_from_the_sidecar(training, untrained):
    from vlocnetpp_core.evaluation.evaluate import untrained_tasks

    assert untrained_tasks({"training": training}) == untrained

"""`vlocnetpp evaluate` outputs that need no model: the printed table, JSON, TUM files (read by evo), flag errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vlocnetpp_core import cli
from vlocnetpp_core.evaluation.metrics import SequenceRecorder, evaluate_sequences
from vlocnetpp_core.evaluation.report import format_report, write_json, write_trajectories

IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])


def make_result(name: str, n: int, offset_m: float, with_odometry: bool, with_labels: bool):
    rec = SequenceRecorder(name)
    for k in range(n):
        t = np.array([0.0, 0.0, float(k)])
        rel = (np.array([0.0, 0.0, 1.0]), IDENTITY_Q) if with_odometry else (None, None)
        rec.add(10.0 + 0.05 * k, t, IDENTITY_Q, t + [offset_m, 0.0, 0.0], IDENTITY_Q, *rel, ms=12.0)
        if with_labels:
            rec.add_labels(np.full((2, 2), 2, np.uint8), np.full((2, 2), 2, np.uint8))
    return rec.result()


@pytest.fixture
def results():
    return [make_result("seq-01", 12, 0.02, True, True), make_result("seq-02", 8, 0.7, False, False)]


def test_format_report_table(results):
    report = evaluate_sequences(results)
    text = format_report(report, {r.name: len(r.stamps) for r in results})
    lines = text.splitlines()
    assert lines[0].split()[:2] == ["sequence", "frames"]
    assert "5cm/5deg [%]" in lines[0] and "0.5m/5deg [%]" in lines[0] and "mIoU [%]" in lines[0]
    seq1 = next(line for line in lines if line.startswith("seq-01")).split()
    seq2 = next(line for line in lines if line.startswith("seq-02")).split()
    overall = next(line for line in lines if line.startswith("overall")).split()
    assert seq1[:7] == ["seq-01", "12", "0.020", "0.00", "100.0", "100.0", "0.00"]
    assert seq1[-3:] == ["100.0", "100.0", "12.0"]  # mIoU, pixel accuracy, ms/frame
    assert seq2[:6] == ["seq-02", "8", "0.700", "0.00", "0.0", "0.0"] and seq2[6:8] == ["-", "-"]  # no odometry
    assert seq2[8:10] == ["-", "-"]  # no labels
    assert overall[:2] == ["overall", "20"]
    assert any(line.startswith("odometry segment lengths [m]: 0.7, 1.4") for line in lines)  # 10%, 20% of 7 m
    assert "IoU [%] (overall): Road 100.0" in text


def test_json_and_tum_files_read_back(tmp_path, results):
    from evo.core import metrics as evo_metrics
    from evo.tools import file_interface

    report = evaluate_sequences(results)
    write_json(tmp_path / "out" / "metrics.json", report)
    back = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert back == report  # None -> null round-trips, no NaN
    assert back["per_sequence"]["seq-02"]["segmentation"]["miou"] is None

    written = write_trajectories(tmp_path / "traj", results)
    names = sorted(str(p.relative_to(tmp_path / "traj")) for p in written)
    assert names == [
        "seq-01/global_pose.tum",
        "seq-01/ground_truth.tum",
        "seq-01/odometry.tum",
        "seq-02/global_pose.tum",
        "seq-02/ground_truth.tum",
    ]
    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "traj/seq-02/ground_truth.tum"))
    est = file_interface.read_tum_trajectory_file(str(tmp_path / "traj/seq-02/global_pose.tum"))
    ape = evo_metrics.APE()
    ape.process_data((ref, est))
    np.testing.assert_allclose(ape.error, 0.7, atol=1e-12)
    np.testing.assert_allclose(ref.timestamps, 10.0 + 0.05 * np.arange(8), atol=1e-12)


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--odometry-lengths", "5,abc"], "--odometry-lengths must be comma-separated metres"),
        (["--odometry-lengths", "5,-1"], "--odometry-lengths must be a positive number"),
        (["--threshold-m", "0"], "--threshold-m must be a positive number"),
        (["--threshold-deg", "nan"], "--threshold-deg must be a positive number"),
        (["--max-frames", "0"], "--max-frames must be >= 1"),
        (["--json", "."], "--json .: is a folder"),
        (["--plots", "file.txt"], "--plots file.txt: exists and is not a folder"),
    ],
)
def test_bad_flags_give_one_line_errors(tmp_path, capsys, monkeypatch, flags, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file.txt").write_text("x")
    rc = cli.main(["evaluate", "--checkpoint", str(tmp_path / "none"), "--data", str(tmp_path), *flags])
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err and "Traceback" not in err

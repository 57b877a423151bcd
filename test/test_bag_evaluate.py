"""`vlocnetpp evaluate-bag` on a bag written here with known localizer outputs (no model): matching by stamp,
sequence splitting on gaps, odometry from accumulated poses, segmentation, against `metrics.evaluate_sequences`."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from bag_report_compare import assert_same_metrics
from data_fixtures import trajectory

from vlocnetpp_core import geometry
from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagWriter
from vlocnetpp_core.cli import main
from vlocnetpp_core.evaluation.metrics import SequenceRecorder, evaluate_sequences

SEQ_LENGTHS = (9, 7)
DROPPED = {3, 12}  # frames the "node" did not answer (record indices over both sequences)
LATE_NS = 150_000_000  # outputs logged 150 ms after the frame, as `ros2 bag record` would


def _noisy(rng, t, q, sigma_t, sigma_deg):
    dq = geometry.quat_normalize(np.concatenate(([1.0], rng.normal(0, np.deg2rad(sigma_deg) / 2, 3))))
    return t + rng.normal(0, sigma_t, 3), geometry.quat_normalize(geometry.quat_mul(q, dq))


def _write_bag(path, rng):
    """Ground truth, labels and /vlocnet/* outputs for two sequences; returns the expected per-sequence results."""
    writer = BagWriter(path)
    expected = []
    with writer:
        writer.add_topic("/ground_truth/pose", messages.POSE_STAMPED)
        writer.add_topic("/camera/semantic", messages.IMAGE)
        writer.add_topic("/vlocnet/pose", messages.POSE_STAMPED)
        writer.add_topic("/vlocnet/odometry", messages.ODOMETRY)
        writer.add_topic("/vlocnet/segmentation", messages.IMAGE)
        index, start_s = 0, 100.0
        odom_t, odom_q = np.zeros(3), np.array([1.0, 0, 0, 0])
        for k, n in enumerate(SEQ_LENGTHS):
            t, q = trajectory(n, start=5 * k)
            rec = SequenceRecorder(f"seq-{k:02d}")
            last_odom = None
            for i in range(n):
                stamp = start_s + i * 0.05
                ns = messages.seconds_to_ns(stamp)
                labels = rng.integers(0, 10, (6, 8)).astype(np.uint8)
                labels[0, 0] = 255
                mask = np.where(rng.random((6, 8)) < 0.7, labels, rng.integers(0, 10, (6, 8))).astype(np.uint8)
                mask[0, 0] = 4
                pred_t, pred_q = _noisy(rng, t[i], q[i], 0.3, 3.0)
                if i > 0:  # the odometry stream: the true motion with noise, accumulated in odom
                    rel_t, rel_q = geometry.relative_pose(t[i - 1], q[i - 1], t[i], q[i])
                    odom_t, odom_q = geometry.pose_compose(odom_t, odom_q, *_noisy(rng, rel_t, rel_q, 0.01, 0.5))
                writer.write("/ground_truth/pose", ns, messages.pose_stamped(ns, "map", t[i], q[i]))
                writer.write("/camera/semantic", ns, messages.image(ns, "camera", labels, "mono8"))
                if index not in DROPPED:
                    late = ns + LATE_NS
                    writer.write("/vlocnet/pose", late, messages.pose_stamped(ns, "map", pred_t, pred_q))
                    writer.write(
                        "/vlocnet/odometry",
                        late,
                        messages.odometry(
                            ns, "odom", "camera", odom_t, odom_q, np.zeros(3), np.zeros(3), np.eye(6), np.eye(6)
                        ),
                    )
                    writer.write("/vlocnet/segmentation", late, messages.image(ns, "camera", mask, "mono8"))
                    rel = None if last_odom is None else geometry.relative_pose(*last_odom, odom_t, odom_q)
                    rec.add(stamp, t[i], q[i], pred_t, pred_q, *(rel if rel is not None else (None, None)))
                    rec.add_labels(labels, mask)
                    last_odom = (odom_t, odom_q)
                index += 1
            expected.append(rec.result())
            start_s += (n - 1) * 0.05 + 10.0
    return expected


def test_evaluate_bag_matches_metrics_of_the_known_outputs(tmp_path, capsys):
    expected = _write_bag(tmp_path / "scored.mcap", np.random.default_rng(0))
    assert (
        main(
            ["evaluate-bag", str(tmp_path / "scored.mcap"), "--json", str(tmp_path / "m.json"), "--threshold-m", "0.3"]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "seq-00" in out and "seq-01" in out
    got = json.loads((tmp_path / "m.json").read_text())
    want = evaluate_sequences(expected, thresholds=[(0.05, 5.0), (0.5, 5.0), (0.3, 5.0)])
    assert set(got["per_sequence"]) == {"seq-00", "seq-01"}
    assert_same_metrics(want, got)
    assert (
        got["overall"]["segmentation"]["pixel_accuracy"] < 1.0
        and got["overall"]["odometry"]["translation_error_percent"] > 0
    )
    assert got["overall"]["timing"]["mean_ms"] is None


def test_evaluate_bag_splits_sequences_on_the_gap_flag(tmp_path, capsys):
    _write_bag(tmp_path / "scored.mcap", np.random.default_rng(1))
    assert (
        main(["evaluate-bag", str(tmp_path / "scored.mcap"), "--json", str(tmp_path / "m.json"), "--max-gap-s", "20"])
        == 0
    )
    got = json.loads((tmp_path / "m.json").read_text())
    assert list(got["per_sequence"]) == ["seq-00"]  # the 10 s gap is no longer a boundary
    assert main(["evaluate-bag", str(tmp_path / "scored.mcap"), "--max-gap-s", "0"]) == 2
    assert "--max-gap-s" in capsys.readouterr().err


def test_evaluate_bag_without_matching_stamps(tmp_path, capsys):
    with BagWriter(tmp_path / "b.mcap") as w:
        w.add_topic("/ground_truth/pose", messages.POSE_STAMPED)
        w.add_topic("/vlocnet/pose", messages.POSE_STAMPED)
        w.write("/ground_truth/pose", 1, messages.pose_stamped(1, "map", np.zeros(3), np.array([1.0, 0, 0, 0])))
        w.write("/vlocnet/pose", 2, messages.pose_stamped(2, "map", np.zeros(3), np.array([1.0, 0, 0, 0])))
    assert main(["evaluate-bag", str(tmp_path / "b.mcap")]) == 2
    err = capsys.readouterr().err
    assert "b.mcap" in err and "stamp" in err


def _write_bag_with_images(path, rng, compressed: bool, skip_image: int | None = None):
    """Ground truth, camera images (distinct random textures) and a /vlocnet/pose 1 m off; returns images and poses."""
    t, q = trajectory(10)
    images = [cv2.GaussianBlur(rng.integers(0, 255, (36, 64, 3)).astype(np.uint8), (3, 3), 0) for _ in t]
    topic = "/camera/image_raw/compressed" if compressed else "/camera/image_raw"
    with BagWriter(path) as w:
        w.add_topic("/ground_truth/pose", messages.POSE_STAMPED)
        w.add_topic("/vlocnet/pose", messages.POSE_STAMPED)
        w.add_topic(topic, messages.COMPRESSED_IMAGE if compressed else messages.IMAGE)
        for i in range(len(t)):
            ns = messages.seconds_to_ns(50.0 + 0.05 * i)
            w.write("/ground_truth/pose", ns, messages.pose_stamped(ns, "map", t[i], q[i]))
            w.write("/vlocnet/pose", ns + LATE_NS, messages.pose_stamped(ns, "map", t[i] + [1.0, 0, 0], q[i]))
            if i != skip_image:
                msg = (
                    messages.compressed_image(ns, "camera", images[i])
                    if compressed
                    else messages.image(ns, "camera", images[i], "rgb8")
                )
                w.write(topic, ns, msg)
    return images, t, q


def test_evaluate_bag_scores_the_retrieval_baseline_on_the_bag_images(tmp_path, capsys):
    from vlocnetpp_core.evaluation.retrieval import ReferenceSet

    rng = np.random.default_rng(3)
    for compressed in (False, True):
        images, t, q = _write_bag_with_images(tmp_path / "b.mcap", rng, compressed)
        order = rng.permutation(len(images))  # the reference holds the same views, shuffled, with their true poses
        ReferenceSet.from_images((images[k], t[k], q[k]) for k in order).save(tmp_path / "ref.npz")
        argv = [
            "evaluate-bag",
            str(tmp_path / "b.mcap"),
            "--reference",
            str(tmp_path / "ref.npz"),
            "--json",
            str(tmp_path / "m.json"),
        ]
        assert main(argv) == 0
        got = json.loads((tmp_path / "m.json").read_text())
        assert got["overall"]["pose"]["median_translation_m"] == pytest.approx(1.0, abs=1e-6)
        assert got["baseline"]["overall"]["pose"]["median_translation_m"] == pytest.approx(
            0.0, abs=1e-9
        )  # each frame found itself
        assert got["baseline"]["network_beats_baseline"]["translation"] is False
        assert "the network does NOT beat retrieval" in capsys.readouterr().out
        (tmp_path / "b.mcap").unlink()
    _write_bag_with_images(tmp_path / "b.mcap", rng, False, skip_image=4)
    assert main(["evaluate-bag", str(tmp_path / "b.mcap"), "--reference", str(tmp_path / "ref.npz")]) == 2
    err = capsys.readouterr().err
    assert "/camera/image_raw has no image for 1 scored frames" in err and "b.mcap" in err

"""The nearest-neighbour retrieval baseline: descriptors, the reference set, its file, and the report row."""

from __future__ import annotations

import numpy as np
import pytest

from vlocnetpp_core.data import open_dataset
from vlocnetpp_core.errors import DataError
from vlocnetpp_core.evaluation.metrics import SequenceRecorder, evaluate_sequences, pose_errors
from vlocnetpp_core.evaluation.report import add_baseline, format_report
from vlocnetpp_core.evaluation.retrieval import ReferenceSet, describe, open_reference, reference_of


@pytest.fixture(scope="module")
def campus(tmp_path_factory):
    """Eight training visits (one lap each, every circuit and direction twice) and one fresh visit (another seed) of the
    synthetic campus."""
    from vlocnetpp_core.synth import render_dataset

    tmp = tmp_path_factory.mktemp("retrieval")
    render_dataset(
        tmp / "train", seed=0, train_loops=8, test_loops=0, frames_per_loop=120, size=(160, 90), progress=False
    )
    render_dataset(
        tmp / "fresh", seed=5, train_loops=0, test_loops=1, frames_per_loop=120, size=(160, 90), progress=False
    )
    return tmp


def _frames(path, split):
    index = open_dataset(path, None, split)
    return [index.load(i) for i in range(len(index))]


def test_descriptor_is_a_unit_vector_that_ignores_contrast():
    rng = np.random.default_rng(0)
    image = rng.integers(40, 200, (90, 160, 3)).astype(np.uint8)
    d = describe(image)
    assert d.shape == (288,) and d.dtype == np.float32
    assert np.linalg.norm(d) == pytest.approx(1.0, abs=1e-5)
    darker = (image.astype(np.float32) * 0.6).round().astype(np.uint8)  # a gain: gradients scale, the unit vector stays
    assert float(describe(darker) @ d) > 0.99
    assert float(describe(rng.integers(0, 255, (90, 160, 3)).astype(np.uint8)) @ d) < 0.5


def test_each_reference_image_retrieves_itself(campus):
    frames = _frames(campus / "train", "train")
    reference = ReferenceSet.from_images((f.image, f.t, f.q) for f in frames)
    queries = np.stack([describe(f.image) for f in frames])
    np.testing.assert_array_equal(reference.nearest(queries), np.arange(len(frames)))


def test_retrieval_localizes_fresh_visits_far_better_than_the_mean_pose(campus):
    reference = open_reference(campus / "train")
    fresh = _frames(campus / "fresh", "test")
    t, q = reference.poses(np.stack([describe(f.image) for f in fresh]))
    true_t, true_q = np.array([f.t for f in fresh]), np.array([f.q for f in fresh])
    trans, _ = pose_errors(t, q, true_t, true_q)
    mean_trans, _ = pose_errors(np.broadcast_to(reference.t.mean(0), true_t.shape), true_q, true_t, true_q)
    assert np.median(trans) < 0.25 * np.median(mean_trans), (np.median(trans), np.median(mean_trans))


def test_reference_file_round_trip_and_bad_files(campus, tmp_path):
    reference = open_reference(campus / "train")
    path = reference.save(tmp_path / "model.reference.npz")
    assert path == reference_of(tmp_path / "model.safetensors")
    back = open_reference(path)
    assert back.source == reference.source and len(back) == len(reference)
    np.testing.assert_array_equal(back.t, reference.t)
    np.testing.assert_allclose(back.descriptors, reference.descriptors, atol=1e-3)  # stored as float16
    queries = reference.descriptors[::7]
    np.testing.assert_array_equal(back.nearest(queries), reference.nearest(queries))
    (tmp_path / "bad.npz").write_bytes(b"not a zip file")
    with pytest.raises(DataError, match="bad.npz"):
        open_reference(tmp_path / "bad.npz")
    assert not list(tmp_path.glob(".*tmp*"))  # written atomically, nothing left behind


def test_report_shows_the_baseline_row_and_verdict():
    rng = np.random.default_rng(1)
    rec = SequenceRecorder("seq-00")
    true_t = np.cumsum(np.ones((30, 3)), axis=0)
    q = np.array([1.0, 0, 0, 0])
    for k, t in enumerate(true_t):
        rec.add(float(k), t, q, t + [2.0, 0, 0], q)  # the network: 2 m off, rotation exact
    results = [rec.result()]
    reference = ReferenceSet(
        rng.normal(size=(30, 8)), true_t + [0.5, 0, 0], np.tile([np.cos(0.05), 0, 0, np.sin(0.05)], (30, 1)), "ref"
    )
    report = add_baseline(evaluate_sequences(results), results, [reference.descriptors.copy()], reference)
    base = report["baseline"]
    assert base["overall"]["pose"]["median_translation_m"] == pytest.approx(0.5)
    assert base["overall"]["pose"]["median_rotation_deg"] == pytest.approx(np.degrees(0.1))
    assert base["network_beats_baseline"] == {"translation": False, "rotation": True}
    text = format_report(report, {"seq-00": 30})
    row = next(line for line in text.splitlines() if line.startswith("retrieval")).split()
    assert row[:4] == ["retrieval", "30", "0.500", "5.73"]
    assert "the network beats retrieval in rotation only" in text

"""Metrics from arrays: known pose / odometry / segmentation numbers, TUM files and ATE/RPE against evo."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vlocnetpp_core import geometry
from vlocnetpp_core.errors import DataError
from vlocnetpp_core.evaluation import metrics
from vlocnetpp_core.evaluation.trajectory import (
    Trajectory,
    accumulate_odometry,
    align_trajectory,
    read_tum,
    umeyama_alignment,
    write_tum,
)

IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])


def yaw_quat(deg: float) -> np.ndarray:
    """Rotation about the camera y axis (down), the vertical axis of a driving camera."""
    return Rotation.from_euler("y", deg, degrees=True).as_quat()[[3, 0, 1, 2]]


def random_trajectory(n: int, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.normal(0.0, 0.5, (n, 3)), axis=0)
    q = Rotation.random(n, random_state=seed).as_quat()[:, [3, 0, 1, 2]]
    return Trajectory(np.arange(n) * 0.05 + 100.0, t, q)


def straight_line(n: int, step_m: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    t = np.zeros((n, 3))
    t[:, 2] = np.arange(n) * step_m  # driving forward along the optical axis
    return t, np.tile(IDENTITY_Q, (n, 1))


# --------------------------------------------------------------------------- global pose


def test_pose_metrics_known_medians_and_accuracies():
    n = 5
    t_true = np.zeros((n, 3))
    q_true = np.tile(IDENTITY_Q, (n, 1))
    offsets = np.array([0.01, 0.04, 0.2, 0.6, 2.0])  # metres, along x
    degrees = np.array([1.0, 6.0, 2.0, 3.0, 0.5])
    t_pred = t_true + offsets[:, None] * np.array([1.0, 0.0, 0.0])
    q_pred = np.stack([yaw_quat(d) for d in degrees])
    trans, rot = metrics.pose_errors(t_pred, q_pred, t_true, q_true)
    np.testing.assert_allclose(trans, offsets, atol=1e-12)
    np.testing.assert_allclose(rot, degrees, atol=1e-6)
    out = metrics.pose_metrics(trans, rot, [(0.05, 5.0), (0.5, 5.0), (1.0, 2.5)])
    assert out["median_translation_m"] == pytest.approx(0.2)
    assert out["median_rotation_deg"] == pytest.approx(2.0)
    assert out["accuracy_5cm_5deg"] == pytest.approx(1 / 5)  # frame 1 is under 5 cm but at 6 deg
    assert out["accuracy_0.5m_5deg"] == pytest.approx(2 / 5)
    assert out["accuracy_1m_2.5deg"] == pytest.approx(2 / 5)  # frames 0 and 2; frame 3 is at 3 deg
    assert list(out) == [
        "median_translation_m",
        "median_rotation_deg",
        "accuracy_5cm_5deg",
        "accuracy_0.5m_5deg",
        "accuracy_1m_2.5deg",
    ]


def test_pose_errors_match_geometry_and_ignore_quaternion_sign():
    traj_a, traj_b = random_trajectory(20, 1), random_trajectory(20, 2)
    trans, rot = metrics.pose_errors(traj_a.t, -traj_a.q, traj_b.t, traj_b.q)
    np.testing.assert_allclose(trans, geometry.translation_error(traj_a.t, traj_b.t), atol=1e-9)
    np.testing.assert_allclose(rot, geometry.rotation_error_deg(traj_a.q, traj_b.q), atol=1e-5)


def test_accuracy_key_names():
    assert metrics.accuracy_key(0.05, 5) == "accuracy_5cm_5deg"
    assert metrics.accuracy_key(0.02, 2) == "accuracy_2cm_2deg"
    assert metrics.accuracy_key(0.5, 5) == "accuracy_0.5m_5deg"
    assert metrics.accuracy_key(2.0, 10) == "accuracy_2m_10deg"


# --------------------------------------------------------------------------- odometry


def test_kitti_translation_error_of_a_scale_drift():
    """Predicted steps 10% too long on a straight 1 m-step line: every segment's error is 0.1 m per
    true metre covered; the devkit divides by the nominal length, which the expectation mirrors."""
    t_true, q_true = straight_line(21)
    T_true = geometry.pose_to_matrix(t_true, q_true)
    T_pred = geometry.pose_to_matrix(t_true * 1.1, q_true)
    lengths = [2.5, 5.5]
    t_err, r_err = metrics.kitti_segment_errors(T_true, T_pred, lengths)
    # a segment of nominal length L ends at the first frame beyond L: ceil(L) frames (3 and 6) later
    expected = [0.1 * 3 / 2.5] * (21 - 3) + [0.1 * 6 / 5.5] * (21 - 6)
    np.testing.assert_allclose(t_err, expected, atol=1e-12)
    np.testing.assert_allclose(r_err, 0.0, atol=1e-6)
    out = metrics.odometry_metrics(t_err, r_err, lengths)
    assert out["translation_error_percent"] == pytest.approx(100 * np.mean(expected))
    assert out["lengths_m"] == lengths


def test_kitti_rotation_error_of_a_heading_drift_from_chained_relative_poses():
    """Each predicted relative pose turns 1 deg too much: a segment of k steps is k deg off."""
    n = 16
    t_true, q_true = straight_line(n)
    rel_t, rel_q = geometry.relative_pose(t_true[:-1], q_true[:-1], t_true[1:], q_true[1:])
    rel_t = np.vstack((np.zeros(3), rel_t))
    rel_q = np.vstack((IDENTITY_Q, [geometry.quat_mul(q, yaw_quat(1.0)) for q in rel_q]))
    t_odo, q_odo = accumulate_odometry(t_true[0], q_true[0], rel_t, rel_q)
    _, rot = metrics.pose_errors(t_odo, q_odo, t_true, q_true)
    np.testing.assert_allclose(rot, np.arange(n), atol=1e-6)  # drift grows 1 deg per frame
    lengths = [3.5]
    t_err, r_err = metrics.kitti_segment_errors(
        geometry.pose_to_matrix(t_true, q_true), geometry.pose_to_matrix(t_odo, q_odo), lengths
    )
    np.testing.assert_allclose(r_err, np.full(n - 4, 4.0 / 3.5), atol=1e-6)
    assert np.all(t_err > 0)


def test_accumulate_odometry_of_true_relative_poses_gives_the_trajectory():
    traj = random_trajectory(30, 3)
    rel_t, rel_q = geometry.relative_pose(traj.t[:-1], traj.q[:-1], traj.t[1:], traj.q[1:])
    garbage_row0 = (np.array([[5.0, 5.0, 5.0]]), np.array([[0.0, 1.0, 0.0, 0.0]]))
    t, q = accumulate_odometry(
        traj.t[0], traj.q[0], np.vstack((garbage_row0[0], rel_t)), np.vstack((garbage_row0[1], rel_q))
    )
    np.testing.assert_allclose(t, traj.t, atol=1e-9)
    np.testing.assert_allclose(q, traj.q, atol=1e-9)


def test_default_odometry_lengths_are_fractions_of_the_shortest_path():
    assert metrics.default_odometry_lengths([40.0, 123.0]) == [4.0, 8.0, 12.0, 16.0, 20.0, 24.0, 28.0, 32.0]
    assert metrics.default_odometry_lengths([0.0]) == []
    assert metrics.default_odometry_lengths([3.0], (0.5,)) == [1.5]


# --------------------------------------------------------------------------- segmentation


def test_confusion_matrix_and_ious_from_known_counts():
    true = np.array([[0, 0, 1], [1, 2, 255]], dtype=np.uint8)
    pred = np.array([[0, 1, 1], [1, 0, 3]], dtype=np.uint8)  # the 3 sits on an ignored pixel
    conf = metrics.confusion_matrix(true, pred, 10)
    expected = np.zeros((10, 10), dtype=np.int64)
    expected[0, 0], expected[0, 1], expected[1, 1], expected[2, 0] = 1, 1, 2, 1
    np.testing.assert_array_equal(conf, expected)
    out = metrics.segmentation_metrics(conf)
    assert out["iou"]["Background"] == pytest.approx(1 / 3)  # tp 1 / (row 2 + column 2 - 1)
    assert out["iou"]["Sky"] == pytest.approx(2 / 3)
    assert out["iou"]["Road"] == 0.0  # in the ground truth, never predicted: counts as 0
    assert all(out["iou"][name] is None for name in ("Sidewalk", "Grass", "Dynamic", "Other"))
    assert out["miou"] == pytest.approx((1 / 3 + 2 / 3 + 0) / 3)
    assert out["pixel_accuracy"] == pytest.approx(3 / 5)


def test_confusion_matrix_rejects_bad_labels():
    with pytest.raises(ValueError, match="predicted labels outside 0..9"):
        metrics.confusion_matrix(np.zeros((2, 2)), np.full((2, 2), 12), 10)
    with pytest.raises(ValueError, match="differ in shape"):
        metrics.confusion_matrix(np.zeros((2, 2)), np.zeros((2, 3)), 10)


def test_segmentation_metrics_without_labels_are_null():
    out = metrics.segmentation_metrics(None)
    assert out["miou"] is None and out["pixel_accuracy"] is None and set(out["iou"].values()) == {None}


# --------------------------------------------------------------------------- report from sequences


def make_sequence(name: str, n: int, pose_offset_m: float, step_scale: float, ms: float) -> metrics.SequenceResult:
    t_true, q_true = straight_line(n)
    rec = metrics.SequenceRecorder(name)
    for k in range(n):
        rel = (None, None) if k == 0 else (np.array([0.0, 0.0, step_scale]), IDENTITY_Q)
        rec.add(k * 0.05, t_true[k], q_true[k], t_true[k] + [pose_offset_m, 0, 0], q_true[k], *rel, ms=ms)
        labels = np.full((4, 4), k % 2, dtype=np.uint8)
        rec.add_labels(labels, np.zeros((4, 4), dtype=np.uint8))
    return rec.result()


def test_evaluate_sequences_per_sequence_and_pooled():
    a = make_sequence("seq-01", 11, 0.01, 1.0, 10.0)  # perfect odometry, 1 cm off
    b = make_sequence("seq-02", 21, 1.0, 1.2, 30.0)  # 20% scale drift, 1 m off
    report = metrics.evaluate_sequences([a, b], thresholds=[(0.05, 5.0), (0.5, 5.0)])
    assert list(report) == ["overall", "per_sequence"]
    assert list(report["per_sequence"]) == ["seq-01", "seq-02"]
    for part in [report["overall"], *report["per_sequence"].values()]:
        assert list(part) == ["pose", "odometry", "segmentation", "timing"]
        assert set(part["odometry"]) == {
            "translation_error_percent",
            "rotation_error_deg_per_m",
            "lengths_m",
            "step_scale",
        }
        assert set(part["timing"]) == {"mean_ms", "median_ms"}
    pa, pb = report["per_sequence"]["seq-01"], report["per_sequence"]["seq-02"]
    assert pa["pose"]["accuracy_5cm_5deg"] == 1.0 and pb["pose"]["accuracy_5cm_5deg"] == 0.0
    assert report["overall"]["pose"]["accuracy_0.5m_5deg"] == pytest.approx(11 / 32)
    assert report["overall"]["pose"]["median_translation_m"] == pytest.approx(1.0)
    # lengths: 10..80% of the shortest path (10 m); the whole lengths end one frame late (devkit rule)
    lengths = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    assert pa["odometry"]["lengths_m"] == lengths
    assert pa["odometry"]["translation_error_percent"] == pytest.approx(0.0, abs=1e-9)
    per_length = {L: (0.2 * (L + 1) / L, 21 - (L + 1)) for L in lengths}  # error ratio, number of segments
    expected_b = sum(e * c for e, c in per_length.values()) / sum(c for _, c in per_length.values())
    assert pb["odometry"]["translation_error_percent"] == pytest.approx(100 * expected_b)
    count_a = sum(11 - (L + 1) for L in lengths)
    count_b = sum(c for _, c in per_length.values())
    assert report["overall"]["odometry"]["translation_error_percent"] == pytest.approx(
        100 * expected_b * count_b / (count_a + count_b)
    )
    assert pb["timing"] == {"mean_ms": 30.0, "median_ms": 30.0}
    # the scale bias: every step of b 1.2 times too long; pooled, b's 20 pairs outnumber a's 10
    assert pa["odometry"]["step_scale"] == pytest.approx(1.0) and pb["odometry"]["step_scale"] == pytest.approx(1.2)
    assert report["overall"]["odometry"]["step_scale"] == pytest.approx(1.2)

    assert report["overall"]["timing"]["mean_ms"] == pytest.approx((11 * 10 + 21 * 30) / 32)
    # labels alternate 0/1 per frame, prediction always 0: IoU(0) = frames with 0 / all frames
    assert pa["segmentation"]["iou"]["Background"] == pytest.approx(6 / 11)
    assert pa["segmentation"]["iou"]["Sky"] == 0.0
    assert report["overall"]["segmentation"]["pixel_accuracy"] == pytest.approx((6 + 11) / 32)


def test_step_ratios_skip_pairs_that_did_not_move():
    """A standing camera has no step to compare with: only the pairs that moved count."""
    true_t = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]])
    rel_t = np.array([[0.0, 0, 0], [0, 0, 1.5], [0, 0, 0.2], [0, 0, 1.0]])
    np.testing.assert_allclose(metrics.step_ratios(true_t, rel_t), [1.5, 0.5])


# --------------------------------------------------------------------------- trajectories, TUM, evo


def test_geometry_quaternions_agree_with_scipy_on_numpy_arrays():
    q = random_trajectory(50, 4).q
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(geometry.quat_to_matrix(q), R, atol=1e-12)
    back = geometry.matrix_to_quat(R)
    np.testing.assert_allclose(back, np.where(q[:, :1] < 0, -q, q), atol=1e-9)
    assert isinstance(back, np.ndarray) and np.all(back[:, 0] >= 0)


def test_tum_round_trip(tmp_path):
    traj = random_trajectory(25, 5)
    write_tum(tmp_path / "sub" / "a.tum", traj)
    back = read_tum(tmp_path / "sub" / "a.tum")
    np.testing.assert_array_equal(back.stamps, traj.stamps)
    np.testing.assert_allclose(back.t, traj.t, atol=1e-15)
    np.testing.assert_allclose(back.q, traj.q, atol=1e-15)
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["a.tum"]  # no temporary left behind


def test_read_tum_names_file_and_line(tmp_path):
    path = tmp_path / "bad.tum"
    path.write_text("# header\n0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 nan 1\n")
    with pytest.raises(DataError, match=r"bad.tum:3: expected 8 numbers"):
        read_tum(path)
    path.write_text("0 1 2 3 0 0 0 0\n")
    with pytest.raises(DataError, match=r"bad.tum:1: zero quaternion"):
        read_tum(path)
    with pytest.raises(DataError, match="missing.tum"):
        read_tum(tmp_path / "missing.tum")


def test_umeyama_recovers_a_similarity():
    src = random_trajectory(40, 6).t
    R = Rotation.random(random_state=7).as_matrix()
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 3.0])
    R_est, t_est, s_est = umeyama_alignment(src, dst, with_scale=True)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t_est, [1.0, -2.0, 3.0], atol=1e-9)
    assert s_est == pytest.approx(2.5)


@pytest.fixture
def tum_pair(tmp_path):
    """A reference trajectory and a noisy, shifted and rotated estimate, written as TUM files."""
    ref = random_trajectory(60, 8)
    rng = np.random.default_rng(9)
    R = Rotation.from_euler("xyz", [3, -5, 20], degrees=True)
    noise = Rotation.from_rotvec(rng.normal(0, 0.05, (60, 3)))
    est_rot = R * noise * Rotation.from_quat(ref.q[:, [1, 2, 3, 0]])
    est = Trajectory(
        ref.stamps,
        1.3 * R.apply(ref.t) + [2.0, 0.5, -1.0] + rng.normal(0, 0.1, (60, 3)),
        est_rot.as_quat()[:, [3, 0, 1, 2]],
    )
    write_tum(tmp_path / "ref.tum", ref)
    write_tum(tmp_path / "est.tum", est)
    return tmp_path / "ref.tum", tmp_path / "est.tum"


def test_ate_and_rpe_agree_with_evo(tum_pair):
    from evo.core import metrics as evo_metrics
    from evo.core import sync
    from evo.tools import file_interface

    ref_path, est_path = tum_pair
    evo_ref, evo_est = sync.associate_trajectories(
        file_interface.read_tum_trajectory_file(str(ref_path)), file_interface.read_tum_trajectory_file(str(est_path))
    )
    ref, est = read_tum(ref_path), read_tum(est_path)
    assert len(ref) == evo_ref.num_poses == 60

    def evo_error(metric, traj_est):
        metric.process_data((evo_ref, traj_est))
        return metric.error

    # ATE: evo's default (no alignment), SE(3) and Sim(3) Umeyama alignment
    np.testing.assert_allclose(metrics.ate(ref, est), evo_error(evo_metrics.APE(), evo_est), atol=1e-6)
    for with_scale in (False, True):
        aligned = copy.deepcopy(evo_est)
        aligned.align(evo_ref, correct_scale=with_scale)
        ours = metrics.ate(ref, est, align=True, with_scale=with_scale)
        np.testing.assert_allclose(ours, evo_error(evo_metrics.APE(), aligned), atol=1e-6)
        np.testing.assert_allclose(align_trajectory(est, ref, with_scale).t, aligned.positions_xyz, atol=1e-6)
    # APE rotation part and RPE (translation and rotation angle) at several deltas
    _, rot = metrics.pose_errors(est.t, est.q, ref.t, ref.q)
    np.testing.assert_allclose(
        rot, evo_error(evo_metrics.APE(evo_metrics.PoseRelation.rotation_angle_deg), evo_est), atol=1e-6
    )
    for delta, all_pairs in ((1, False), (4, False), (3, True)):
        trans, rot = metrics.rpe(ref, est, delta, all_pairs)
        kwargs = dict(delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=all_pairs)
        evo_t = evo_error(evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, **kwargs), evo_est)
        evo_r = evo_error(evo_metrics.RPE(evo_metrics.PoseRelation.rotation_angle_deg, **kwargs), evo_est)
        np.testing.assert_allclose(trans, evo_t, atol=1e-6)
        np.testing.assert_allclose(rot, evo_r, atol=1e-6)

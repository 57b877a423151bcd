"""The network's global poses fused with its odometry (vlocnetpp_core.inference.pose_fusion) on simulated drives: what
it averages out, what it keeps, when it restarts; and the localizer's two poses of a frame."""

from __future__ import annotations

import numpy as np
import pytest

from vlocnetpp_core import geometry
from vlocnetpp_core.inference.pose_fusion import OdometryFusion

# the shipped model's calibrated per-frame variances, rounded: x, y, z (m^2), rotation (rad^2)
VARIANCE = np.array([0.16, 0.19, 0.0045, 0.00023, 0.00057, 0.00032])
IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])


def _yaw(angle: float) -> np.ndarray:
    return np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])


def _drive(steps: int, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """True poses of a drive along a gentle curve: ``t (N, 3)``, ``q (N, 4)``."""
    heading = np.linspace(0.0, 1.5, steps)
    t = np.cumsum(step_m * np.stack([np.cos(heading), np.sin(heading), np.zeros(steps)], 1), 0)
    return t, np.stack([_yaw(h) for h in heading])


def _fused_errors(rng, steps: int, step_m: float, correlation: float, odometry_noise: float) -> tuple[float, float]:
    """Median position error of the frame poses and of the fused ones, the frames' errors an AR(1) series of
    ``correlation`` between consecutive frames (0.4 m per axis), the odometry off by ``odometry_noise`` of each step."""
    t, q = _drive(steps, step_m)
    err = np.zeros((steps, 3))
    for k in range(steps):
        fresh = rng.normal(0.0, 0.4, 3) * np.array([1.0, 1.0, 0.1])
        err[k] = fresh if k == 0 else correlation * err[k - 1] + np.sqrt(1 - correlation**2) * fresh
    fusion = OdometryFusion(VARIANCE)
    frame_errors, fused_errors = [], []
    for k in range(steps):
        rel_t, rel_q = geometry.relative_pose(t[k - 1], q[k - 1], t[k], q[k]) if k else (np.zeros(3), IDENTITY_Q)
        rel_t = rel_t + rng.normal(0.0, odometry_noise * step_m, 3)
        ft, _ = fusion.update(t[k] + err[k], q[k], rel_t, rel_q, continued=k > 0)
        frame_errors.append(np.linalg.norm(err[k]))
        fused_errors.append(np.linalg.norm(ft - t[k]))
    return float(np.median(frame_errors)), float(np.median(fused_errors))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fusion_averages_out_independent_errors_of_the_frames(seed):
    frame, fused = _fused_errors(np.random.default_rng(seed), 400, 1.0, correlation=0.0, odometry_noise=0.03)
    assert fused < 0.6 * frame, (frame, fused)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fusion_helps_less_but_still_with_errors_correlated_as_the_networks(seed):
    """Errors of frames 1 m apart correlated at 0.7, as the shipped network's on the campus: still lower."""
    frame, fused = _fused_errors(np.random.default_rng(seed), 400, 1.0, correlation=0.7, odometry_noise=0.03)
    assert fused < 0.95 * frame, (frame, fused)


def test_the_gain_follows_the_distance_not_the_frame_rate():
    """The same 100 m drive in 1 m and in 0.25 m steps, errors independent per metre: about as good."""
    rng = np.random.default_rng(3)
    coarse = _fused_errors(rng, 100, 1.0, correlation=0.0, odometry_noise=0.0)
    fine = _fused_errors(rng, 400, 0.25, correlation=np.exp(-0.25 / 0.3), odometry_noise=0.0)
    assert coarse[1] < 0.6 * coarse[0] and fine[1] < 0.8 * fine[0], (coarse, fine)


def test_a_first_frame_and_a_restart_give_the_frames_own_pose():
    fusion = OdometryFusion(VARIANCE)
    t0, q0 = np.array([1.0, 2.0, 0.5]), _yaw(0.3)
    np.testing.assert_array_equal(fusion.update(t0, q0, np.zeros(3), IDENTITY_Q, continued=True)[0], t0)
    moved = fusion.update(t0 + [0.5, 0.0, 0.0], q0, np.array([0.0, 0.0, 1.0]), IDENTITY_Q, continued=True)
    assert not np.allclose(moved[0], t0 + [0.5, 0.0, 0.0])  # a continued frame is blended
    t1, q1 = np.array([-4.0, 3.0, 0.1]), _yaw(-1.0)
    restarted = fusion.update(t1, q1, np.array([0.0, 0.0, 1.0]), IDENTITY_Q, continued=False)
    np.testing.assert_array_equal(restarted[0], t1)
    np.testing.assert_allclose(restarted[1], q1, atol=1e-15)


def test_standing_still_averages_the_frames_and_moving_on_lets_new_ones_in_again():
    fusion = OdometryFusion(VARIANCE)
    fusion.update(np.zeros(3), IDENTITY_Q, np.zeros(3), IDENTITY_Q, continued=False)
    for _ in range(99):  # no travel, the frames say x = 1: the mean of the 100 frames
        t, _ = fusion.update(np.array([1.0, 0, 0]), IDENTITY_Q, np.zeros(3), IDENTITY_Q, continued=True)
    assert t[0] == pytest.approx(0.99)
    for k in range(1, 21):  # 20 m along z (exact odometry), the frames now 1 m off in x: followed within a metre
        t, _ = fusion.update(np.array([2.0, 0, k]), IDENTITY_Q, np.array([0, 0, 1.0]), IDENTITY_Q, continued=True)
    assert t[0] > 1.6, t


def test_the_fused_rotation_follows_the_odometry_and_stays_a_unit_quaternion():
    fusion = OdometryFusion(VARIANCE)
    fusion.update(np.zeros(3), IDENTITY_Q, np.zeros(3), IDENTITY_Q, continued=False)
    for k in range(1, 50):  # exact odometry and exact frames of a turn: the fused rotation is the true one
        t, q = fusion.update(np.zeros(3), _yaw(0.05 * k), np.zeros(3), -_yaw(0.05), continued=True)  # -q: same turn
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12
        assert geometry.rotation_error_deg(q, _yaw(0.05 * k)) < 1e-4  # arccos of a dot product near 1


@pytest.mark.parametrize("seed", [0, 1])
def test_the_filter_learns_a_biased_odometry_and_corrects_it(seed):
    """Odometry whose steps point 3 % to one side and turn 0.2 deg/m too far, frames with independent 0.4 m errors:
    after 300 m the filter knows the bias (camera axes, per metre) and its poses are better than the frames'."""
    rng = np.random.default_rng(seed)
    t, q = _drive(400, 1.0)
    bias_t, bias_r = np.array([0.0, 0.03, 0.0]), np.array([0.0, 0.0, np.radians(0.2)])
    fusion = OdometryFusion(VARIANCE)
    frame_errors, fused_errors = [], []
    for k in range(len(t)):
        rel_t, rel_q = geometry.relative_pose(t[k - 1], q[k - 1], t[k], q[k]) if k else (np.zeros(3), IDENTITY_Q)
        travel = np.linalg.norm(rel_t)
        turn = np.r_[np.cos(bias_r[2] * travel / 2), 0.0, 0.0, np.sin(bias_r[2] * travel / 2)]
        frame_t = t[k] + rng.normal(0.0, 0.4, 3) * np.array([1.0, 1.0, 0.1])
        ft, _ = fusion.update(frame_t, q[k], rel_t + bias_t * travel, geometry.quat_mul(rel_q, turn), continued=k > 0)
        if k >= 300:
            frame_errors.append(np.linalg.norm(frame_t - t[k]))
            fused_errors.append(np.linalg.norm(ft - t[k]))
    learnt_t, learnt_r = fusion.odometry_bias
    np.testing.assert_allclose(learnt_t[:2], bias_t[:2], atol=0.01)
    np.testing.assert_allclose(learnt_r[2], bias_r[2], atol=np.radians(0.05))
    assert np.median(fused_errors) < 0.6 * np.median(frame_errors), (np.median(frame_errors), np.median(fused_errors))


def test_a_restart_forgets_the_bias():
    fusion = OdometryFusion(VARIANCE)
    fusion.update(np.zeros(3), IDENTITY_Q, np.zeros(3), IDENTITY_Q, continued=False)
    for k in range(1, 50):  # the odometry says 1.1 m a step, the frames 1 m
        fusion.update(np.array([k, 0.0, 0.0]), IDENTITY_Q, np.array([1.1, 0.0, 0.0]), IDENTITY_Q, continued=True)
    assert fusion.odometry_bias[0][0] > 0.02
    fusion.update(np.zeros(3), IDENTITY_Q, np.zeros(3), IDENTITY_Q, continued=False)
    np.testing.assert_array_equal(fusion.odometry_bias[0], np.zeros(3))


def test_bad_variances_are_refused():
    with pytest.raises(ValueError, match="6 positive variances"):
        OdometryFusion(np.zeros(6))

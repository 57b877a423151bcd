"""Camera -> base frame (vlocnetpp_core.camera.extrinsics, no ROS): poses against 4x4 matrices built with scipy,
covariances."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vlocnetpp_core.camera import extrinsics as ex
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.localizer import LocalizerResult

RNG = np.random.default_rng(7)
# a camera looking along a z-up base_link's x axis (optical: x right, y down, z forward), 0.2 m ahead, 1 m up
OPTICAL_IN_BASE = [0.2, 0.0, 1.0, 0.5, -0.5, 0.5, -0.5]


def _matrix(t: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """4x4 from scipy (independent of vlocnetpp_core.geometry)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]]).as_matrix()
    T[:3, 3] = t
    return T


def _random_pose() -> tuple[np.ndarray, np.ndarray]:
    x, y, z, w = Rotation.random(random_state=RNG.integers(1 << 30)).as_quat()
    q = np.array([w, x, y, z])
    return RNG.normal(0, 5, 3), (-q if w < 0 else q)


def _random_extrinsics() -> ex.CameraExtrinsics:
    t, q = _random_pose()
    return ex.CameraExtrinsics.from_values([*(t / 5), *q])


def _random_spd() -> np.ndarray:
    a = RNG.normal(size=(6, 6))
    return a @ a.T + 1e-3 * np.eye(6)


def _error(t: np.ndarray, q: np.ndarray, t_ref: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """(dp, dtheta) of (t, q) vs the reference, in the Localizer's convention: dp in the parent frame,
    R = R_ref Exp(dtheta) (trainer._pose_residual)."""
    dR = Rotation.from_quat([*q_ref[1:], q_ref[0]]).inv() * Rotation.from_quat([*q[1:], q[0]])
    return np.concatenate((t - t_ref, dR.as_rotvec()))


def _perturbed(t: np.ndarray, q: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t + dp, R Exp(dtheta))."""
    r = Rotation.from_quat([*q[1:], q[0]]) * Rotation.from_rotvec(delta[3:])
    x, y, z, w = r.as_quat()
    return t + delta[:3], np.array([w, x, y, z])


def test_base_pose_is_the_camera_pose_times_the_inverse_extrinsics():
    for _ in range(20):
        t_wc, q_wc = _random_pose()
        ext = _random_extrinsics()
        t_wb, q_wb = ex.base_pose(t_wc, q_wc, ext)
        expected = _matrix(t_wc, q_wc) @ np.linalg.inv(_matrix(ext.t, ext.q))
        np.testing.assert_allclose(_matrix(t_wb, q_wb), expected, atol=1e-10)
        assert q_wb[0] >= 0 and abs(np.linalg.norm(q_wb) - 1) < 1e-12


def test_odometry_of_the_base_is_conjugated_and_starts_at_identity():
    ext = _random_extrinsics()
    t0, q0 = ex.base_odometry(np.zeros(3), np.array([1.0, 0, 0, 0]), ext)
    np.testing.assert_allclose(t0, 0, atol=1e-12)
    np.testing.assert_allclose(q0, [1, 0, 0, 0], atol=1e-12)
    t_oc, q_oc = _random_pose()
    E = _matrix(ext.t, ext.q)
    np.testing.assert_allclose(
        _matrix(*ex.base_odometry(t_oc, q_oc, ext)), E @ _matrix(t_oc, q_oc) @ np.linalg.inv(E), atol=1e-10
    )


def test_the_optical_camera_of_a_forward_looking_robot():
    ext = ex.CameraExtrinsics.from_values(OPTICAL_IN_BASE)
    R = ext.matrix[:3, :3]
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # optical z (forward) = base x
    np.testing.assert_allclose(R @ [1, 0, 0], [0, -1, 0], atol=1e-12)  # optical x (right) = base -y
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, -1], atol=1e-12)  # optical y (down) = base -z
    # the camera's variance about its y axis is the base's yaw variance
    cov = np.diag([0.01, 0.02, 0.03, 0.004, 0.005, 0.006])
    base = ex.base_pose_covariance(cov, np.array([1.0, 0, 0, 0]), dataclasses.replace(ext, t=np.zeros(3)))
    np.testing.assert_allclose(np.diag(base), [0.01, 0.02, 0.03, 0.006, 0.004, 0.005], atol=1e-15)


def test_identity_extrinsics_leave_everything_unchanged():
    ext = ex.CameraExtrinsics.identity()
    assert ext.is_identity
    for _ in range(5):
        cov = _random_spd()
        _, q = _random_pose()
        np.testing.assert_allclose(ex.base_pose_covariance(cov, q, ext), cov, atol=1e-12)
        np.testing.assert_allclose(ex.base_odometry_covariance(cov, q, ext), cov, atol=1e-12)
    result = _result()
    moved = ex.to_base_frame(result, ext)
    for field in dataclasses.fields(LocalizerResult):
        a, b = getattr(result, field.name), getattr(moved, field.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_allclose(b, a, atol=1e-12, err_msg=field.name)
        else:
            assert a == b, field.name


def test_pure_rotation_extrinsics_rotate_the_rotation_block_only():
    for _ in range(5):
        _, q_e = _random_pose()
        ext = ex.CameraExtrinsics.from_values([0.0, 0.0, 0.0, *q_e])
        R_e = _matrix(ext.t, ext.q)[:3, :3]
        cov = _random_spd()
        _, q = _random_pose()
        base = ex.base_pose_covariance(cov, q, ext)
        np.testing.assert_allclose(base[:3, :3], cov[:3, :3], atol=1e-12)  # positions stay in map, no lever arm
        np.testing.assert_allclose(base[3:, 3:], R_e @ cov[3:, 3:] @ R_e.T, atol=1e-12)
        np.testing.assert_allclose(base[:3, 3:], cov[:3, 3:] @ R_e.T, atol=1e-12)


def test_covariances_stay_symmetric_positive_semidefinite():
    for _ in range(20):
        ext = _random_extrinsics()
        _, q = _random_pose()
        cov = _random_spd()
        low_rank = np.diag([1.0, 0.0, 0.0, 0.0, 0.0, 1e-3])  # singular: PSD, not PD
        for c in (cov, low_rank):
            for out in (
                ex.base_pose_covariance(c, q, ext),
                ex.base_odometry_covariance(c, q, ext),
                ex.transform_covariance(c, ext.adjoint),
            ):
                assert np.array_equal(out, out.T)
                assert np.linalg.eigvalsh(out).min() >= -1e-12 * np.abs(out).max()
                assert np.all(np.diag(out) >= 0)


def test_covariance_jacobian_matches_finite_differences_of_the_composition():
    """Perturb the camera pose by a small error in the Localizer's convention; the base's error is J times it."""
    for _ in range(5):
        ext = _random_extrinsics()
        t, q = _random_pose()
        t_b, q_b = ex.base_pose(t, q, ext)
        to, qo = _random_pose()
        to_b, qo_b = ex.base_odometry(to, qo, ext)
        eps = 1e-6
        for i in range(6):
            delta = np.zeros(6)
            delta[i] = eps
            J_pose = ex.base_pose_covariance(_unit(i), q, ext)  # J e_i e_i^T J^T: its column i squared
            got = _error(*ex.base_pose(*_perturbed(t, q, delta), ext), t_b, q_b) / eps
            np.testing.assert_allclose(np.outer(got, got), J_pose, atol=1e-5)
            J_odom = ex.base_odometry_covariance(_unit(i), qo, ext)
            got = _error(*ex.base_odometry(*_perturbed(to, qo, delta), ext), to_b, qo_b) / eps
            np.testing.assert_allclose(np.outer(got, got), J_odom, atol=1e-5)


def test_twist_of_the_base_is_the_rigid_body_velocity():
    ext = _random_extrinsics()
    R_e = ext.matrix[:3, :3]
    v_c, w_c = RNG.normal(size=3), RNG.normal(size=3)
    v_b, w_b = ex.base_twist(v_c, w_c, ext)
    np.testing.assert_allclose(w_b, R_e @ w_c, atol=1e-12)
    # base origin velocity (base axes) = camera velocity + w x (camera -> base origin), camera -> base origin = -t_e
    np.testing.assert_allclose(v_b, R_e @ v_c + np.cross(w_b, -ext.t), atol=1e-12)


def test_to_base_frame_moves_every_pose_of_a_result():
    ext = ex.CameraExtrinsics.from_values(OPTICAL_IN_BASE)
    result = _result()
    moved = ex.to_base_frame(result, ext)
    E = _matrix(ext.t, ext.q)
    np.testing.assert_allclose(_matrix(moved.t, moved.q), _matrix(result.t, result.q) @ np.linalg.inv(E), atol=1e-10)
    np.testing.assert_allclose(
        _matrix(moved.odom_t, moved.odom_q), E @ _matrix(result.odom_t, result.odom_q) @ np.linalg.inv(E), atol=1e-10
    )
    np.testing.assert_allclose(
        _matrix(moved.rel_t, moved.rel_q), E @ _matrix(result.rel_t, result.rel_q) @ np.linalg.inv(E), atol=1e-10
    )
    np.testing.assert_allclose(
        moved.pose_covariance, ex.base_pose_covariance(result.pose_covariance, result.q, ext), atol=1e-12
    )
    np.testing.assert_allclose(
        moved.odom_covariance, ex.base_odometry_covariance(result.odom_covariance, result.odom_q, ext), atol=1e-12
    )
    assert moved.mask is result.mask and moved.stamp == result.stamp and moved.reset_reason == result.reset_reason


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ([0.0, 0.0, 0.0, 1.0, 0.0, 0.0], "got 6 value"),
        ([0.0] * 8, "got 8 value"),
        ([0.0, 0.0, 0.0, 1.1, 0.0, 0.0, 0.0], "has norm 1.1, not 1 within 0.001"),
        ([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], "has norm 0"),
        ([float("nan"), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], "non-finite"),
        ("0 0 0 1 0 0 0", "must be 7 numbers"),
        ([0.0, 0.0, 0.0, True, 0.0, 0.0, 0.0], "must be 7 numbers"),
    ],
)
def test_bad_extrinsics_are_refused_with_a_clear_error(values, message):
    with pytest.raises(UserError, match=message) as err:
        ex.CameraExtrinsics.from_values(values)
    assert "camera_extrinsics" in str(err.value) and "[x, y, z, qw, qx, qy, qz]" in str(err.value)


def test_near_unit_quaternions_are_normalised_onto_w_positive():
    ext = ex.CameraExtrinsics.from_values([1, 2, 3, -0.7071, 0, 0, -0.7071])  # integers and a 4-decimal quaternion
    np.testing.assert_allclose(ext.q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)
    assert ext.values()[:3] == [1.0, 2.0, 3.0] and not ext.is_identity
    assert ex.CameraExtrinsics.from_values(np.array(ex.IDENTITY_VALUES)).is_identity


def _unit(i: int) -> np.ndarray:
    c = np.zeros((6, 6))
    c[i, i] = 1.0
    return c


def _result() -> LocalizerResult:
    """A LocalizerResult with random poses, twist and full covariances."""
    (t, q), (ot, oq), (rt, rq) = _random_pose(), _random_pose(), _random_pose()
    return LocalizerResult(
        stamp=1.5,
        t=t,
        q=q,
        rel_t=rt / 10,
        rel_q=rq,
        odom_t=ot,
        odom_q=oq,
        linear=RNG.normal(size=3),
        angular=RNG.normal(size=3),
        dt=0.05,
        pose_covariance=_random_spd(),
        odom_covariance=_random_spd(),
        twist_covariance=_random_spd(),
        mask=np.zeros((4, 5), np.uint8),
        reset_reason=None,
        seconds=0.01,
        network_t=t,
        network_q=q,
        frame_t=t,
        frame_q=q,
    )

"""Geometry core against scipy.spatial.transform.Rotation (property-based) and hand-made cases."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from vlocnetpp_core import geometry as g
from vlocnetpp_core.camera.intrinsics import Intrinsics

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
quats = arrays(np.float64, (4,), elements=finite).filter(lambda q: np.linalg.norm(q) > 0.1)
vecs = arrays(np.float64, (3,), elements=st.floats(-50, 50, allow_nan=False))
SETTINGS = settings(max_examples=60, deadline=None)


def scipy_rot(q_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(g.quat_to_ros(q_wxyz))  # scipy uses (x, y, z, w), like ROS


@SETTINGS
@given(quats)
def test_normalize_unit_and_hemisphere(q):
    n = g.quat_normalize(q)
    assert abs(np.linalg.norm(n) - 1) < 1e-12
    assert n[0] >= 0
    assert np.allclose(scipy_rot(n).as_matrix(), scipy_rot(q / np.linalg.norm(q)).as_matrix(), atol=1e-12)


@SETTINGS
@given(quats)
def test_quat_matrix_round_trip_matches_scipy(q):
    q = g.quat_normalize(q)
    R = g.quat_to_matrix(q)
    assert np.allclose(R, scipy_rot(q).as_matrix(), atol=1e-12)
    assert np.allclose(g.matrix_to_quat(R), q, atol=1e-9)


@SETTINGS
@given(quats, quats, vecs)
def test_product_inverse_rotate_match_scipy(a, b, v):
    a, b = g.quat_normalize(a), g.quat_normalize(b)
    ab = g.quat_normalize(g.quat_mul(a, b))
    assert np.allclose(scipy_rot(ab).as_matrix(), (scipy_rot(a) * scipy_rot(b)).as_matrix(), atol=1e-12)
    assert np.allclose(g.quat_rotate(a, v), scipy_rot(a).apply(v), atol=1e-9)
    ident = g.quat_normalize(g.quat_mul(a, g.quat_inverse(a)))
    assert np.allclose(ident, [1, 0, 0, 0], atol=1e-12)


@SETTINGS
@given(vecs, quats, vecs, quats)
def test_se3_compose_inverse_identities(t1, q1, t2, q2):
    q1, q2 = g.quat_normalize(q1), g.quat_normalize(q2)
    t, q = g.pose_compose(t1, q1, t2, q2)
    T = g.pose_to_matrix(t1, q1) @ g.pose_to_matrix(t2, q2)
    assert np.allclose(g.pose_to_matrix(t, q), T, atol=1e-9)
    ti, qi = g.pose_inverse(t1, q1)
    assert np.allclose(g.pose_to_matrix(ti, qi), np.linalg.inv(g.pose_to_matrix(t1, q1)), atol=1e-9)
    # T^-1 T = I
    te, qe = g.pose_compose(ti, qi, t1, q1)
    assert np.allclose(te, 0, atol=1e-9) and np.allclose(qe, [1, 0, 0, 0], atol=1e-9)
    # matrix round trip
    tm, qm = g.matrix_to_pose(T)
    assert np.allclose(tm, t, atol=1e-9) and g.rotation_error_deg(qm, q) < 1e-5


@SETTINGS
@given(vecs, quats, vecs, quats)
def test_relative_pose_recovers_the_motion(t_prev, q_prev, t_rel, q_rel):
    q_prev, q_rel = g.quat_normalize(q_prev), g.quat_normalize(q_rel)
    t_cur, q_cur = g.pose_compose(t_prev, q_prev, t_rel, q_rel)  # T_t = T_{t-1} T_rel
    tr, qr = g.relative_pose(t_prev, q_prev, t_cur, q_cur)
    assert np.allclose(tr, t_rel, atol=1e-8)
    assert g.rotation_error_deg(qr, q_rel) < 1e-5


def test_relative_pose_of_known_motion():
    # Camera 1 m forward (its own +z) and yawed: camera t-1 at origin looking along world x.
    R_wc = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)  # optical frame -> world (z up)
    q0 = g.matrix_to_quat(R_wc)
    t0 = np.array([2.0, 3.0, 1.2])
    t1 = t0 + np.array([1.0, 0, 0])  # moved 1 m along world x = camera forward
    tr, qr = g.relative_pose(t0, q0, t1, q0)
    assert np.allclose(tr, [0, 0, 1.0], atol=1e-12)  # forward along the camera's z
    assert np.allclose(qr, [1, 0, 0, 0], atol=1e-12)


def test_rotation_error_of_known_rotation():
    q0 = np.array([1.0, 0, 0, 0])
    for deg in (0.0, 1.0, 30.0, 90.0, 179.0):
        q = g.quat_from_ros(Rotation.from_euler("z", deg, degrees=True).as_quat())
        assert g.rotation_error_deg(q0, q) == pytest.approx(deg, abs=1e-6)
        assert g.rotation_error_deg(q0, -q) == pytest.approx(deg, abs=1e-6)  # sign-invariant
    assert g.translation_error(np.array([0, 0, 0.0]), np.array([3.0, 4.0, 0])) == pytest.approx(5.0)


def test_ros_quaternion_order():
    q = np.array([0.9, 0.1, 0.2, 0.3])
    assert np.array_equal(g.quat_to_ros(q), [0.1, 0.2, 0.3, 0.9])
    assert np.array_equal(g.quat_from_ros(g.quat_to_ros(q)), q)


def test_torch_batched_and_numpy_agree():
    rng = np.random.default_rng(0)
    q = g.quat_normalize(rng.normal(size=(5, 7, 4)))
    t = rng.normal(size=(5, 7, 3))
    tt, qt = g.pose_inverse(torch.from_numpy(t), torch.from_numpy(q))
    tn, qn = g.pose_inverse(t, q)
    assert isinstance(tt, torch.Tensor) and isinstance(tn, np.ndarray)
    assert np.allclose(tt.numpy(), tn) and np.allclose(qt.numpy(), qn)


def _agreement_cases() -> dict[str, tuple[np.ndarray, ...]]:
    """Inputs for every function with numpy arrays: random, with the ``w == 0`` tie-break of quat_normalize."""
    rng = np.random.default_rng(3)
    q1, q2 = rng.normal(size=(2, 64, 4))
    q1[:4, 0] = 0.0
    t1, t2 = rng.normal(size=(2, 64, 3)) * 10
    u1, u2 = g.quat_normalize(q1), g.quat_normalize(q2)
    pts = rng.normal(size=(64, 3)) * [1, 1, 5]
    K = Intrinsics(300.0, 310.0, 160.0, 90.0, 320, 180).matrix()
    return {
        "quat_normalize": (q1,),
        "quat_mul": (q1, q2),
        "quat_inverse": (q1,),
        "quat_rotate": (u1, t1),
        "quat_to_matrix": (q1,),
        "matrix_to_quat": (g.quat_to_matrix(u1),),
        "quat_to_ros": (q1,),
        "quat_from_ros": (q1,),
        "pose_to_matrix": (t1, u1),
        "matrix_to_pose": (g.pose_to_matrix(t1, u1),),
        "pose_compose": (t1, u1, t2, u2),
        "pose_inverse": (t1, u1),
        "relative_pose": (t1, u1, t2, u2),
        "translation_error": (t1, t2),
        "rotation_error_deg": (q1, q2),
        "project": (pts, K),
        "backproject": (pts[:, :2] * 100, pts[:, 2], K),
    }


def test_numpy_and_torch_run_the_same_formulas():
    """One implementation serves both: numpy inputs give float64 arrays, tensors give tensors of their dtype, and the
    numbers agree to the last bits (numpy's and torch's cross, norm and arccos round differently)."""
    cases = _agreement_cases()
    assert set(cases) == set(g.__all__) - {"pixel_grid", "warp_grid", "pool_warp_grid", "warp_features"}
    for name, args in cases.items():
        fn = getattr(g, name)
        via_numpy = fn(*args)
        via_torch = fn(*(torch.from_numpy(a) for a in args))
        via_float32 = fn(*(torch.from_numpy(a).float() for a in args))
        outputs = (o if isinstance(o, tuple) else (o,) for o in (via_numpy, via_torch, via_float32))
        for n, t, f in zip(*outputs, strict=True):
            assert isinstance(n, np.ndarray) and n.dtype == np.float64, name
            assert isinstance(t, torch.Tensor) and t.dtype == torch.float64, name
            assert np.allclose(t.numpy(), n, rtol=1e-12, atol=1e-12), name
            assert f.dtype == torch.float32, name
    single = g.rotation_error_deg(np.array([1.0, 0, 0, 0]), np.array([0.0, 0, 0, 1]))  # no batch axis
    assert isinstance(single, np.ndarray) and single.shape == () and float(single) == pytest.approx(180.0)
    assert isinstance(g.quat_normalize([0.0, 0, 0, 2]), np.ndarray)  # lists are numpy inputs


def test_importing_geometry_loads_no_torch():
    """The numpy path needs no torch: a fresh interpreter that uses it has not loaded it."""
    code = (
        "import sys, numpy as np; from vlocnetpp_core import geometry as g; "
        "g.relative_pose(np.zeros(3), np.array([1.0, 0, 0, 0]), np.ones(3), np.array([0.0, 1, 0, 0])); "
        "g.project(np.ones((2, 3)), np.eye(3)); print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_gradients_flow_through_the_tensor_path():
    """Autograd through the pose algebra: compose, invert, matrices and the errors give finite, non-zero grads
    that match finite differences."""
    rng = np.random.default_rng(5)
    t1, t2 = (torch.tensor(rng.normal(size=(3, 3)), requires_grad=True) for _ in range(2))
    q1, q2 = (torch.tensor(rng.normal(size=(3, 4)), requires_grad=True) for _ in range(2))

    def loss(t1, q1, t2, q2):
        t, q = g.pose_compose(t1, q1, t2, q2)
        ti, qi = g.pose_inverse(t, q)
        T = g.pose_to_matrix(ti, qi)
        return (
            g.rotation_error_deg(q, q2).sum()
            + g.translation_error(t, t2).sum()
            + T.sum()
            + g.matrix_to_quat(T[:, :3, :3]).sum()
        )

    loss(t1, q1, t2, q2).backward()
    for p in (t1, q1, t2, q2):
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    assert torch.autograd.gradcheck(loss, (t1, q1, t2, q2))


@SETTINGS
@given(
    arrays(np.float64, (8, 2), elements=st.floats(0, 319, allow_nan=False)),
    arrays(np.float64, (8,), elements=st.floats(0.1, 100, allow_nan=False)),
)
def test_projection_inverts_backprojection(pix, depth):
    K = Intrinsics(300.0, 310.0, 160.0, 90.0, 320, 180).matrix()
    pts = g.backproject(pix, depth, K)
    uv, z = g.project(pts, K)
    assert np.allclose(uv, pix, atol=1e-8) and np.allclose(z, depth)


def test_intrinsics_follow_resize_and_crop():
    cam = Intrinsics(700.0, 700.0, 639.5, 359.5, 1280, 720)
    X = np.array([[1.3, -0.4, 7.0]])
    uv, _ = g.project(X, cam.matrix())
    small = cam.resized(320, 180)
    uv_small, _ = g.project(X, small.matrix())
    # cv2.resize convention: u' = (u + 0.5) * s - 0.5
    assert np.allclose(uv_small, (uv + 0.5) * 0.25 - 0.5)
    crop = small.cropped(10, 20, 256, 144)
    uv_crop, _ = g.project(X, crop.matrix())
    assert np.allclose(uv_crop, uv_small - [10, 20])
    flip = small.flipped_horizontally()
    uv_flip, _ = g.project(X * [-1, 1, 1], flip.matrix())
    assert np.allclose(uv_flip[:, 0], 319 - uv_small[:, 0])
    assert Intrinsics.parse("1,2,3,4", 10, 20) == Intrinsics(1, 2, 3, 4, 10, 20)
    with pytest.raises(ValueError, match="fx,fy,cx,cy"):
        Intrinsics.parse("1,2,3", 10, 20)


def test_warp_grid_identity_motion_is_identity():
    B, H, W = 2, 12, 16
    depth = torch.rand(B, 1, H, W) * 10 + 0.5
    K = torch.tensor(Intrinsics(20.0, 20.0, 7.5, 5.5, W, H).matrix(), dtype=torch.float32).expand(B, 3, 3)
    grid, valid = g.warp_grid(depth, torch.eye(4).expand(B, 4, 4), K)
    assert valid.all()
    feat = torch.randn(B, 5, H, W)
    assert torch.allclose(g.warp_features(feat, grid, valid), feat, atol=1e-5)
    # pooled to a coarser scale: still identity
    g4, v4 = g.pool_warp_grid(grid, valid, (H // 4, W // 4))
    coarse = torch.randn(B, 5, H // 4, W // 4)
    assert torch.allclose(g.warp_features(coarse, g4, v4), coarse, atol=1e-5)


def test_warp_grid_pure_translation_shifts_by_disparity():
    H, W, f, d = 10, 20, 10.0, 5.0
    K = torch.tensor(Intrinsics(f, f, (W - 1) / 2, (H - 1) / 2, W, H).matrix(), dtype=torch.float64)[None]
    depth = torch.full((1, 1, H, W), d, dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)[None].clone()
    T[0, 0, 3] = 1.0  # camera t sits 1 m to the right of camera t-1
    grid, valid = g.warp_grid(depth, T, K)
    u_prev = (grid[..., 0] + 1) * W / 2 - 0.5
    u_cur = torch.arange(W, dtype=torch.float64).expand(1, H, W)
    shift = f * 1.0 / d
    inside = valid[:, 0] > 0
    assert torch.allclose(u_prev[inside], (u_cur + shift)[inside])
    assert not inside[0, :, -1].any() and inside[0, :, 0].all()  # right border leaves the view
    assert math.isclose(float(valid.mean()), (W - math.ceil(shift)) / W)

"""The synthetic campus: on-disk layout, determinism, class coverage and exact geometric consistency."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from vlocnetpp_core import geometry
from vlocnetpp_core.classes import NUM_CLASSES, colorize
from vlocnetpp_core.data.pfm import read_pfm
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.synth import Campus, default_intrinsics, plan_visit, render_dataset, render_frame
from vlocnetpp_core.synth.drive import MAX_LANE_OFFSET_M
from vlocnetpp_core.synth.layout import BUILDING, GRASS, LANES, ROAD, SIDEWALK, SKY
from vlocnetpp_core.synth.prims import BOX

SMALL = dict(train_loops=2, test_loops=1, frames_per_loop=5, size=(96, 54), progress=False)


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "small"
    summary = render_dataset(out, scene="campus", seed=0, **SMALL)
    assert summary["frames"] == 15 and summary["out"] == str(out)
    return out


def tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_layout_and_poses_format(small):
    W, H = SMALL["size"]
    K = json.loads((small / "intrinsics.json").read_text())
    assert set(K) == {"fx", "fy", "cx", "cy", "width", "height"} and (K["width"], K["height"]) == (W, H)
    scene = json.loads((small / "scene.json").read_text())
    assert scene["scene"] == "campus" and scene["seed"] == 0 and scene["loops"] == {"train": 2, "test": 1}
    assert scene["frames_per_loop"] == 5 and scene["size"] == [W, H] and scene["generator_version"] >= 1
    for split, loops in (("train", 2), ("test", 1)):
        lines = (small / "DeepLoc" / split / "poses.txt").read_text().splitlines()
        assert lines[0] == "# synthetic campus campus seed 0"
        assert lines[1] == "ImageName x y z qw qx qy qz"
        expected = [f"Image_{k * 10000 + i}.png" for k in range(loops) for i in range(1, 6)]
        assert [ln.split()[0] for ln in lines[2:]] == expected
        for ln in lines[2:]:
            name, *vals = ln.split(" ")
            assert len(vals) == 7
            x, y, z, *q = (float(v) for v in vals)
            assert abs(np.linalg.norm(q) - 1) < 1e-6 and q[0] >= 0
            assert -5 < x < 105 and -5 < y < 125 and 1.1 < z < 1.3  # on the campus, camera 1.2 m up
            stem = name[:-4]
            img = cv2.imread(str(small / "DeepLoc" / split / "LeftImages" / name), cv2.IMREAD_UNCHANGED)
            lab = cv2.imread(str(small / "DeepLoc" / split / "labels" / name), cv2.IMREAD_UNCHANGED)
            col = cv2.imread(str(small / "DeepLoc" / split / "labels_colorized" / name), cv2.IMREAD_UNCHANGED)
            depth = read_pfm(small / "DeepLoc_stereo" / split / "DepthImages" / f"{stem}.pfm")
            assert img.shape == (H, W, 3) and img.dtype == np.uint8
            assert lab.shape == (H, W) and lab.dtype == np.uint8 and lab.max() < NUM_CLASSES
            assert np.array_equal(col[..., ::-1], colorize(lab))
            assert depth.shape == (H, W) and depth.dtype == np.float32
            assert np.all(depth[lab == SKY] == 0) and np.all(depth[lab != SKY] > 0.05)
    for name in ("mosaic.png", "map.png"):
        assert cv2.imread(str(small / "preview" / name)) is not None


def test_same_seed_same_bytes_other_seed_other_visits(small, tmp_path):
    again = tmp_path / "again"
    render_dataset(again, scene="campus", seed=0, **SMALL)
    assert tree_bytes(again) == tree_bytes(small)
    other = tmp_path / "other"
    render_dataset(other, scene="campus", seed=1, **SMALL)
    a, b = (json.loads((d / "scene.json").read_text()) for d in (small, other))
    assert a["landmarks"] == b["landmarks"]  # the same campus
    assert [v["lighting"] for v in a["visits"]] != [v["lighting"] for v in b["visits"]]
    poses_a, poses_b = ((d / "DeepLoc/train/poses.txt").read_text().splitlines()[2:] for d in (small, other))
    assert all(pa.split()[1:] != pb.split()[1:] for pa, pb in zip(poses_a, poses_b, strict=True))


def test_campus_depends_on_the_scene_name_only():
    a, b, c = Campus("campus"), Campus("campus"), Campus("other")
    for f in ("cx", "cy", "a", "b", "z1", "label", "tx", "ty"):
        assert np.array_equal(getattr(a.prims, f), getattr(b.prims, f))
    assert all(np.array_equal(x, y) for x, y in zip(a.atlas, b.atlas, strict=True))
    assert np.array_equal(a.ground.albedo, b.ground.albedo) and np.array_equal(a.ground.labels, b.ground.labels)
    assert a.landmarks != c.landmarks and not np.array_equal(a.ground.labels, c.ground.labels)


def test_every_class_appears_in_a_default_sized_dataset(tmp_path):
    out = tmp_path / "classes"
    render_dataset(out, scene="campus", seed=0, train_loops=1, test_loops=1, frames_per_loop=12, progress=False)
    counts = np.zeros(NUM_CLASSES, np.int64)
    for p in out.glob("DeepLoc/*/labels/*.png"):
        counts += np.bincount(cv2.imread(str(p), cv2.IMREAD_UNCHANGED).ravel(), minlength=NUM_CLASSES)[:NUM_CLASSES]
    assert (counts > 0).all(), counts
    assert cv2.imread(str(next(out.glob("DeepLoc/train/LeftImages/*.png")))).shape == (180, 320, 3)


def test_existing_output_is_refused_unless_forced(small, tmp_path):
    out = tmp_path / "exists"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(UserError, match="exists already"):
        render_dataset(out, **SMALL)
    assert (out / "keep.txt").read_text() == "mine"
    render_dataset(out, force=True, **SMALL)
    assert not (out / "keep.txt").exists() and (out / "DeepLoc/train/poses.txt").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists"]  # no temporary folders left


def test_test_lane_offset_moves_the_test_visits_only():
    """``--test-lane-offset``: the visit drives that far right of its circuit's centreline; nothing else changes."""
    campus = Campus("campus")
    plain, moved = plan_visit(campus, 4, "test", 1, 60), plan_visit(campus, 4, "test", 1, 60, lane_offset=3.0)
    assert moved.pattern.lane == "offset +3.00 m" and moved.lighting == plain.lighting
    assert (moved.pattern.circuit, moved.pattern.clockwise, moved.pattern.cruise_speed) == (
        plain.pattern.circuit,
        plain.pattern.clockwise,
        plain.pattern.cruise_speed,
    )
    centreline = campus.circuits[moved.pattern.circuit].points
    distance = np.linalg.norm(moved.t[:, None, :2] - centreline[None], axis=2).min(axis=1)
    weave = moved.pattern.weave_amplitude
    assert np.all(np.abs(distance - 3.0) <= weave + 0.1), (
        distance.min(),
        distance.max(),
        weave,
    )  # + the 0.1 m vertex spacing


def test_lane_wander_drifts_across_the_road_and_changes_nothing_else():
    """``lane_wander``: the visit drifts up to that far either side of its lane, within the sidewalks'
    driving lines; its lighting, pattern and timing stay; 0 is the visit without it."""
    campus = Campus("campus")
    plain, wander = plan_visit(campus, 4, "train", 2, 250), plan_visit(campus, 4, "train", 2, 250, lane_wander=2.0)
    np.testing.assert_array_equal(plan_visit(campus, 4, "train", 2, 250, lane_wander=0.0).t, plain.t)
    assert wander.lighting == plain.lighting and wander.pattern.lane_wander == 2.0
    assert dataclasses.replace(wander.pattern, lane_wander=0.0) == plain.pattern
    np.testing.assert_array_equal(wander.times, plain.times)
    centreline = campus.circuits[plain.pattern.circuit].points
    plain_d, wander_d = (
        np.linalg.norm(v.t[:, None, :2] - centreline[None], axis=2).min(axis=1) for v in (plain, wander)
    )
    lane = abs(LANES[plain.pattern.lane])
    assert np.all(np.abs(plain_d - lane) <= plain.pattern.weave_amplitude + 0.1)
    drift = wander_d - lane
    assert drift.max() - drift.min() > 1.0, (drift.min(), drift.max())  # it really crosses the road, not just weaves
    assert np.all(wander_d <= MAX_LANE_OFFSET_M + 0.1) and np.all(
        np.abs(drift) <= 2.0 + plain.pattern.weave_amplitude + 0.1
    )


def test_lighting_presets_choose_the_visits_lighting_and_nothing_else():
    """``lighting_presets``: train visits cycle through the list (a preset named twice comes twice as often), test
    visits draw from it; the pattern and poses stay; all five presets in their order are the default's train visits."""
    campus = Campus("campus")
    presets = ("morning", "morning", "evening")
    train = [plan_visit(campus, 4, "train", k, 20, lighting_presets=presets) for k in range(6)]
    names = [v.lighting.name for v in train]
    assert sorted(names) == ["evening", "evening", "morning", "morning", "morning", "morning"]
    assert names[:3] in (list(presets), ["morning", "evening", "morning"], ["evening", "morning", "morning"])
    plain = plan_visit(campus, 4, "train", 3, 20)
    assert train[3].pattern == plain.pattern
    np.testing.assert_array_equal(train[3].t, plain.t)
    tests = {plan_visit(campus, 4, "test", k, 20, lighting_presets=("hazy", "noon")).lighting.name for k in range(8)}
    assert tests == {"hazy", "noon"}
    from vlocnetpp_core.synth.lighting import PRESETS

    for k in range(5):
        assert plan_visit(campus, 4, "train", k, 20, lighting_presets=PRESETS).lighting == (
            plan_visit(campus, 4, "train", k, 20).lighting
        )


@pytest.mark.parametrize(
    "bad",
    [
        dict(size=(8, 8)),
        dict(frames_per_loop=0),
        dict(train_loops=0, test_loops=0),
        dict(seed=-1),
        dict(scene="two\nlines"),
        dict(test_lane_offset=9.0),
        dict(test_lane_offset=float("nan")),
        dict(lane_wander=-1.0),
        dict(lane_wander=float("inf")),
        dict(lighting_presets=("dusk",)),
        dict(lighting_presets=()),
    ],
)
def test_bad_arguments_are_user_errors(tmp_path, bad):
    args = dict(SMALL, **bad)
    with pytest.raises(UserError):
        render_dataset(tmp_path / "x", **args)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- geometry


@pytest.fixture(scope="module")
def frames():
    """Consecutive frames of a test visit at 160x90, static scene (no moving objects)."""
    campus = Campus("campus")
    K = default_intrinsics(160, 90)
    visit = plan_visit(campus, 3, "test", 0, 8)
    out = [render_frame(campus, visit.t[i], visit.q[i], K, visit.lighting, ()) for i in range(8)]
    return campus, K, visit, out


def _world_points(K, t, q, depth, mask):
    v, u = np.nonzero(mask)
    z = depth[v, u].astype(np.float64)
    cam = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], 1)
    return cam @ geometry.quat_to_matrix(q).T + t


def test_depth_puts_points_on_the_surfaces_they_are_labelled(frames):
    campus, K, visit, out = frames
    P = campus.prims
    boxes = np.nonzero((P.kind == BOX) & (P.label == BUILDING))[0]
    for i, (_, lab, depth) in enumerate(out):
        ground = np.isin(lab, [ROAD, SIDEWALK, GRASS])
        pts = _world_points(K, visit.t[i], visit.q[i], depth, ground)
        assert np.abs(pts[:, 2]).max() < 2e-3  # on the plane z = 0
        pts = _world_points(K, visit.t[i], visit.q[i], depth, lab == BUILDING)
        dx, dy = pts[:, None, 0] - P.cx[boxes], pts[:, None, 1] - P.cy[boxes]
        lx, ly = dx * P.cos[boxes] + dy * P.sin[boxes], -dx * P.sin[boxes] + dy * P.cos[boxes]
        outside = np.maximum(np.abs(lx) - P.a[boxes], np.abs(ly) - P.b[boxes])  # 0 on a wall
        assert np.median(np.abs(outside).min(1)) < 1e-3 and np.quantile(np.abs(outside).min(1), 0.95) < 0.05


def _warp_errors(K, prev, cur, t0, q0, t1, q1):
    tr, qr = geometry.relative_pose(t0, q0, t1, q1)
    T = torch.from_numpy(geometry.pose_to_matrix(tr, qr)).float()[None]
    grid, valid = geometry.warp_grid(
        torch.from_numpy(cur[2])[None, None], T, torch.from_numpy(K.matrix()).float()[None]
    )
    gray = lambda img: torch.from_numpy(img.astype(np.float32).mean(-1) / 255.0)[None, None]  # noqa: E731
    warped = F.grid_sample(gray(prev[0]), grid, align_corners=False)
    m = valid[0, 0] > 0
    err = (warped - gray(cur[0])).abs()[0, 0][m].median().item()
    still = (gray(prev[0]) - gray(cur[0])).abs()[0, 0][m].median().item()
    lab = F.grid_sample(
        torch.from_numpy(prev[1].astype(np.float32))[None, None], grid, mode="nearest", align_corners=False
    )[0, 0]
    agree = float((lab[m].numpy() == cur[1][m.numpy()]).mean())
    return err, still, agree, float(m.float().mean())


def test_warping_with_depth_and_pose_reproduces_the_next_frame(frames):
    """Frame t-1 warped into frame t with depth_t, the relative pose and K matches frame t to ~1 grey level."""
    _, K, visit, out = frames
    xyzw = [1, 2, 3, 0]
    ratios = []
    for i in range(1, len(out)):
        t0, q0, t1, q1 = visit.t[i - 1], visit.q[i - 1], visit.t[i], visit.q[i]
        err, still, agree, cover = _warp_errors(K, out[i - 1], out[i], t0, q0, t1, q1)
        assert cover > 0.5 and err < 0.01 and err < 0.5 * still and agree > 0.9, (
            i,
            err,
            still,
            agree,
        )  # measured <= 0.006, >= 0.92
        bad, _, bad_agree, _ = _warp_errors(
            K, out[i - 1], out[i], t0, q0[xyzw], t1, q1[xyzw]
        )  # quaternion read in the wrong order
        assert bad > 5 * err and bad_agree < agree - 0.2, (i, err, bad, agree, bad_agree)
        ratios.append(err / still)
    assert np.median(ratios) < 0.2, ratios  # measured 0.11


def test_pitch_and_roll_are_rendered_as_pure_rotations(frames):
    """A tilted camera sees what the level camera sees, moved by the homography K R K^-1."""
    campus, K, visit, _ = frames
    yaw = math.atan2(*geometry.quat_to_matrix(visit.q[2])[[1, 0], 2])
    q_level = geometry.matrix_to_quat(
        np.array([[math.sin(yaw), 0, math.cos(yaw)], [-math.cos(yaw), 0, math.sin(yaw)], [0, -1, 0]])
    )
    tilt = geometry.quat_normalize(np.array([math.cos(0.03), math.sin(0.03), 0.0, 0.0]))  # 3.4 deg pitch
    q_tilted = geometry.quat_normalize(geometry.quat_mul(q_level, tilt))
    a = render_frame(campus, visit.t[2], q_level, K, visit.lighting)
    b = render_frame(campus, visit.t[2], q_tilted, K, visit.lighting)
    err, still, agree, _ = _warp_errors(K, a, b, visit.t[2], q_level, visit.t[2], q_tilted)
    assert err < 0.2 * still and agree > 0.95, (err, still, agree)


def test_render_frame_refuses_poses_it_cannot_render(frames):
    campus, K, visit, _ = frames
    steep = geometry.quat_normalize(
        geometry.quat_mul(visit.q[0], np.array([math.cos(0.35), math.sin(0.35), 0.0, 0.0]))
    )  # 40 deg pitch
    for t, q, words in (
        (visit.t[0], steep, "pitch/roll"),
        ([50.0, 60.0, -0.5], visit.q[0], "above the ground"),
        ([900.0, 60.0, 1.2], visit.q[0], "outside the rendered world"),
    ):
        with pytest.raises(ValueError, match=words):
            render_frame(campus, t, q, K)


def test_the_camera_never_enters_an_object():
    """Driving patterns keep the camera out of every static footprint and away from cars and pedestrians."""
    campus = Campus("campus")
    P = campus.prims
    low = P.z0 < 1.6  # crowns and sign panels above the camera do not count
    for seed in (0, 1):
        for split, loop in (("train", 0), ("train", 1), ("train", 2), ("train", 3), ("test", 0)):
            visit = plan_visit(campus, seed, split, loop, 120)
            xy = visit.t[:, :2]
            dx, dy = xy[:, None, 0] - P.cx[low], xy[:, None, 1] - P.cy[low]
            lx = np.abs(dx * P.cos[low] + dy * P.sin[low]) - P.a[low]
            ly = np.abs(-dx * P.sin[low] + dy * P.cos[low]) - P.b[low]
            box_gap = np.hypot(np.maximum(lx, 0), np.maximum(ly, 0)) + np.minimum(np.maximum(lx, ly), 0)
            gap = np.where(P.kind[low] == BOX, box_gap, np.hypot(dx, dy) - P.a[low])
            assert gap.min() > 0.5, (seed, split, loop, gap.min())
            for i in range(0, 120, 7):
                for o in visit.objects_at(i):
                    assert math.hypot(o.x - xy[i, 0], o.y - xy[i, 1]) > 1.0

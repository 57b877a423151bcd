"""The keyframe map and the refinement against it: building, the file, PnP, the refiner's checks and fallbacks,
the Localizer's refined stream, and ``vlocnetpp map build``'s refusals."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from data_fixtures import K_SMALL, PLANE_Z, trajectory, write_deeploc_split

from vlocnetpp_core import geometry
from vlocnetpp_core.cli import main
from vlocnetpp_core.data import open_dataset
from vlocnetpp_core.errors import DataError
from vlocnetpp_core.mapping.build import build_map
from vlocnetpp_core.mapping.keyframe_map import KeyframeMap
from vlocnetpp_core.mapping.pnp import solve_pnp
from vlocnetpp_core.mapping.refiner import Refiner
from vlocnetpp_core.mapping.sources import keyframe_positions
from vlocnetpp_core.mapping.stream import RefinedStream

SPACING_M = 4.0


@pytest.fixture(scope="module")
def campus(tmp_path_factory) -> Path:
    """Two training visits of the synthetic campus (one lap each, ~1.5 m between frames) at the shipped model's size."""
    from vlocnetpp_core.synth import render_dataset

    out = tmp_path_factory.mktemp("mapping") / "campus"
    render_dataset(out, seed=0, train_loops=2, test_loops=0, frames_per_loop=120, size=(320, 180), progress=False)
    return out


@pytest.fixture(scope="module")
def campus_map(campus, tmp_path_factory) -> Path:
    m = build_map([open_dataset(campus, None, "train")], spacing_m=SPACING_M, angle_deg=20.0, progress=False)
    return m.save(tmp_path_factory.mktemp("map") / "campus.map.npz")


def _between_keyframes(campus: Path) -> list:
    """Training frames that are not keyframes of the map (every other one of them): rendered views the map never saw."""
    index = open_dataset(campus, None, "train")
    frames = []
    for rng in index.sequences:
        t = np.array([index.records[i].t for i in rng])
        q = np.array([index.records[i].q for i in rng])
        keyframes = set(keyframe_positions(t, q, SPACING_M, 20.0))
        frames += [index.load(rng[p]) for p in range(1, len(rng), 2) if p not in keyframes]
    return frames


def _shifted(t: np.ndarray, q: np.ndarray, metres: float, degrees: float) -> tuple[np.ndarray, np.ndarray]:
    """The pose moved by ``metres`` along (1, 1, 0) / sqrt 2 and turned by ``degrees`` about the map's z axis."""
    half = np.radians(degrees) / 2
    turn = np.array([np.cos(half), 0.0, 0.0, np.sin(half)])
    return t + metres * np.array([1.0, 1.0, 0.0]) / np.sqrt(2), geometry.quat_normalize(geometry.quat_mul(turn, q))


def _error(t, q, frame) -> tuple[float, float]:
    return float(geometry.translation_error(t, frame.t)), float(geometry.rotation_error_deg(q, frame.q))


def test_refinement_recovers_the_pose_from_a_perturbed_prior(campus, campus_map):
    refiner = Refiner.from_file(campus_map)
    frames = _between_keyframes(campus)
    errors, statuses = [], []
    for f in frames:
        grey, K = refiner.prepare(f.image, f.intrinsics)
        result = refiner.refine(refiner.extract(grey), K, _shifted(f.t, f.q, 1.5, 5.0))
        statuses.append(result.status)
        if result.accepted:
            errors.append(_error(result.solution.t, result.solution.q, f))
    refined = np.array(errors)
    assert len(frames) >= 40 and len(refined) >= 0.9 * len(frames), statuses
    # the prior was 1.5 m / 5 deg off; the rendered depth puts the points to within millimetres
    assert np.median(refined[:, 0]) < 0.05 and np.median(refined[:, 1]) < 0.3, np.median(refined, 0)
    assert np.mean((refined[:, 0] < 0.1) & (refined[:, 1] < 1.0)) >= 0.9


def test_a_prior_far_from_the_map_or_a_blank_frame_keeps_the_network_pose_and_says_why(campus, campus_map):
    stream = RefinedStream(Refiner.from_file(campus_map))
    f = _between_keyframes(campus)[3]
    far_t, far_q = f.t + np.array([500.0, 0.0, 0.0]), f.q  # no keyframe within the search radius
    blank = np.full_like(f.image, 128)
    for image, prior, status in ((f.image, (far_t, far_q), "no_keyframes"), (blank, (f.t, f.q), "no_features")):
        job = stream.start(image, f.intrinsics)
        out = stream.finish(job, *prior, np.zeros(3), np.array([1.0, 0, 0, 0]), continued=False)
        assert (out.source, out.status, out.inliers) == ("network", status, 0)
        np.testing.assert_array_equal(out.t, prior[0])
        np.testing.assert_array_equal(out.q, prior[1])
    # a prior 20 m off, whose keyframes still hold the view: the solution is right but disagrees with the prior
    job = stream.start(f.image, f.intrinsics)
    wrong = _shifted(f.t, f.q, 20.0, 0.0)
    out = stream.finish(job, *wrong, np.zeros(3), np.array([1.0, 0, 0, 0]), continued=False)
    assert out.source == "network" and out.status in ("disagrees", "no_keyframes", "too_few_matches"), out
    np.testing.assert_array_equal(out.t, wrong[0])


def test_the_localizer_refines_the_shipped_networks_pose_and_falls_back_on_a_blank_frame(campus, campus_map):
    from vlocnetpp_core.inference.checkpoint import shipped_checkpoint
    from vlocnetpp_core.inference.localizer import Localizer

    loc = Localizer.from_checkpoint(shipped_checkpoint(), num_threads=2, map_path=campus_map)
    index = open_dataset(campus, None, "train")
    frames = [index.load(i) for i in range(12)]  # a stretch of one visit: consecutive frames, keyframes among them
    net, refined = [], []
    for k, f in enumerate(frames):
        res = loc.step(f.image, "rgb8", stamp=0.1 * k, intrinsics=f.intrinsics)
        net.append(_error(res.network_t, res.network_q, f))
        if res.source == "refined":
            assert res.refine_status == "refined" and res.inliers >= 20
            refined.append(_error(res.t, res.q, f))
    assert len(refined) >= 10, len(refined)
    assert np.median(np.array(refined)[:, 0]) < 0.1 < np.median(np.array(net)[:, 0]), (refined, net)
    res = loc.step(np.full_like(frames[0].image, 90), "rgb8", stamp=0.1 * len(frames), intrinsics=frames[0].intrinsics)
    assert (res.source, res.refine_status, res.inliers) == ("network", "no_features", 0)
    np.testing.assert_array_equal(res.t, res.network_t)


def test_begin_and_finish_in_two_threads_give_the_poses_of_step(campus, campus_map):
    """The node's two stages: the next frame's network runs while the last one is refined, with the same results."""
    import queue
    import threading

    from vlocnetpp_core.inference.checkpoint import shipped_checkpoint
    from vlocnetpp_core.inference.localizer import Localizer

    index = open_dataset(campus, None, "train")
    frames = [index.load(i) for i in range(10)]
    sequential, pipelined = (
        Localizer.from_checkpoint(shipped_checkpoint(), num_threads=1, map_path=campus_map) for _ in range(2)
    )
    expected = [sequential.step(f.image, "rgb8", 0.1 * k, intrinsics=f.intrinsics) for k, f in enumerate(frames)]
    begun, results = queue.Queue(maxsize=1), []

    def finish() -> None:
        while (step := begun.get()) is not None:
            results.append(pipelined.finish(step))

    worker = threading.Thread(target=finish)
    worker.start()
    for k, f in enumerate(frames):
        begun.put(pipelined.begin(f.image, "rgb8", 0.1 * k, intrinsics=f.intrinsics))
    begun.put(None)
    worker.join()
    assert [r.source for r in results] == [r.source for r in expected] and expected[-1].source == "refined"
    for got, want in zip(results, expected, strict=True):
        np.testing.assert_array_equal(got.t, want.t)
        np.testing.assert_array_equal(got.q, want.q)
        np.testing.assert_array_equal(got.pose_covariance, want.pose_covariance)


def test_pnp_covariance_matches_the_spread_of_the_solutions():
    """Over noisy observations of the same points, the normalised squared errors average the 6 the covariance claims."""
    rng = np.random.default_rng(0)
    K = K_SMALL.matrix()
    t_true, q_true = np.array([0.5, -0.2, 0.0]), geometry.quat_normalize(np.array([0.99, 0.05, -0.08, 0.03]))
    camera = np.c_[rng.uniform(-3, 3, (150, 2)), rng.uniform(4, 12, 150)]
    points = camera @ geometry.quat_to_matrix(q_true).T + t_true
    uv = camera[:, :2] / camera[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    d2 = []
    for _ in range(200):
        s = solve_pnp(uv + rng.normal(0, 0.5, uv.shape), points, K)
        dq = geometry.quat_mul(s.q, geometry.quat_inverse(q_true))  # map-frame rotation error, small angle
        e = np.r_[s.t - t_true, 2 * np.sign(dq[0]) * dq[1:]]
        d2.append(e @ np.linalg.solve(s.covariance, e))
    # chi-square with 6 dof: mean 6, the mean of 200 has a standard deviation of 0.24
    assert 5.0 < np.mean(d2) < 7.0, np.mean(d2)


def test_a_dataset_without_depth_is_triangulated_onto_the_surface(tmp_path):
    n = 12
    t, q = trajectory(n, yaw_deg=1.0)
    write_deeploc_split(tmp_path, "train", list(range(n)), t, q, depth=None, labels=False)
    index = open_dataset(tmp_path, "deeploc", "train", intrinsics=K_SMALL)  # the camera the fixture rendered with
    assert not index.has_depth
    m = build_map([index], spacing_m=0.3, angle_deg=20.0, progress=False)
    assert m.num_points >= 100, m.num_points
    # every fixture view looks at the plane Z = PLANE_Z, 8 m ahead, from keyframes 0.3 m apart (a tenth of a pixel of
    # keypoint error moves a point by ~0.3 m along the ray): measured |Z - PLANE_Z| median 0.06 m, 90th percentile
    # 0.12 m
    off = np.abs(m.points[:, 2] - PLANE_Z)
    assert np.median(off) < 0.15 and np.percentile(off, 90) < 0.4, (np.median(off), np.percentile(off, 90))


def test_a_scene_map_renders_only_the_keyframes_and_equals_the_map_of_the_rendered_dataset(
    campus_map, tmp_path, capsys
):
    """``--scene`` renders the keyframes of the visits ``synth`` rendered for the ``campus`` fixture (same scene, seed,
    loops, frames): the same pixels, depth and poses, so the same map, also from two worker processes."""
    out = tmp_path / "scene.map.npz"
    args = [
        "--scene",
        "campus",
        "--seed",
        "0",
        "--loops",
        "2",
        "--frames-per-loop",
        "120",
        "--spacing",
        str(SPACING_M),
        "--angle",
        "20",
    ]
    assert main(["map", "build", str(out), *args, "--workers", "2", "--no-progress"]) == 0
    assert "scene campus seed 0, 2 train visits" in KeyframeMap.load(out).source
    built, dataset = KeyframeMap.load(out), KeyframeMap.load(campus_map)
    for name in ("t", "q", "intrinsics", "image_sizes", "offsets", "uv", "points", "descriptors", "thumbnails"):
        np.testing.assert_array_equal(getattr(built, name), getattr(dataset, name), err_msg=name)
    for bad, says in (
        (["--loops", "0"], "--loops must be >= 1"),
        (["--workers", "-1"], "--workers must be >= 0"),
        (["--lane-wander", "9"], "--lane-wander must be within"),
    ):
        assert main(["map", "build", str(tmp_path / "bad.npz"), *args, *bad, "--no-progress"]) == 2, bad
        assert says in capsys.readouterr().err
    assert not (tmp_path / "bad.npz").exists()


def test_map_file_round_trip_and_bad_files(campus_map, tmp_path):
    m = KeyframeMap.load(campus_map)
    again = KeyframeMap.load(m.save(tmp_path / "again.npz"))
    for name in ("t", "q", "offsets", "points", "descriptors", "uv"):
        np.testing.assert_array_equal(getattr(again, name), getattr(m, name))
    assert again.features == m.features and len(again) == len(m) > 10
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(campus_map.read_bytes()[:5000])
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    for path, says in (
        (truncated, "not a keyframe map"),
        (other, "not a keyframe map"),
        (tmp_path / "none.npz", "no such map file"),
    ):
        with pytest.raises(DataError, match=says):
            KeyframeMap.load(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.npz", "other.npz", "truncated.npz"]


def _listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def test_map_build_refuses_bad_input_naming_it_and_leaves_nothing(campus, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "taken.npz").write_bytes(b"keep me")
    (out / "afile").write_text("a file")
    (out / "folder.npz").mkdir()
    flat = tmp_path / "flat"  # no depth and one frame a sequence: nothing to triangulate with
    write_deeploc_split(flat, "train", [0], *trajectory(1), depth=None, labels=False)
    cases = [
        ([str(out / "taken.npz")], "use --force"),
        ([str(out / "map.txt")], "ends in .npz"),
        ([str(out / "folder.npz")], "is a folder"),
        ([str(out / "afile" / "map.npz")], "is not a folder"),
        ([str(out / "m.npz"), "--split", "test"], "no images found"),
        ([str(out / "m.npz"), "--spacing", "0"], "must be positive"),
        ([str(out / "m.npz"), "--data", str(tmp_path / "missing")], "missing"),
    ]
    before = _listing(out)
    for args, says in cases:
        data = [] if "--data" in args else ["--data", str(campus)]
        assert main(["map", "build", *args, *data, "--no-progress"]) == 2, args
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err, (args, err)
    assert main(["map", "build", str(out / "m.npz"), "--data", str(flat), "--no-progress"]) == 2
    assert "no map points" in capsys.readouterr().err
    assert _listing(out) == before and (out / "taken.npz").read_bytes() == b"keep me"


def test_map_build_writes_a_map_that_map_info_reads(campus, tmp_path, capsys):
    out = tmp_path / "campus.npz"
    assert main(["map", "build", str(out), "--data", str(campus), "--spacing", "8", "--no-progress"]) == 0
    assert "wrote" in capsys.readouterr().out and os.listdir(tmp_path) == ["campus.npz"]
    assert main(["map", "info", str(out)]) == 0
    assert "keyframes" in capsys.readouterr().out

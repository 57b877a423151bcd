"""`vlocnetpp extract`: robot bags (MCAP from `convert --robot-frame`, hand-made sqlite3) back to DeepLoc-layout
datasets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import H, W, truth, write_sqlite_bag
from data_fixtures import K_SMALL, trajectory, write_deeploc_split

from vlocnetpp_core import geometry
from vlocnetpp_core.bag import extract_writer, messages
from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.extract_plan import Selection, plan_frames
from vlocnetpp_core.bag.pose_source import TfCollector
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.cli import main
from vlocnetpp_core.data import ClipDataset, open_dataset
from vlocnetpp_core.data.check import dataset_info

LOOP_A, LOOP_B = list(range(1, 7)), list(range(101, 105))  # two loops -> two sequences (10 s apart in the bag)
# T_base_link,camera: the camera 0.3 m ahead, 0.1 m right and 0.8 m up, with the optical rotation (z forward = base x, x
# right = -base y)
EXT = "0.3,-0.1,0.8,0.5,-0.5,0.5,-0.5"


def _ext() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([float(x) for x in EXT.split(",")])
    return v[:3], v[3:]


@pytest.fixture(scope="module")
def deeploc(tmp_path_factory):
    """A DeepLoc test split of two loops with labels and PFM depth (float32 metres); the ground truth per id."""
    root = tmp_path_factory.mktemp("deeploc")
    ta, qa = trajectory(len(LOOP_A))
    tb, qb = trajectory(len(LOOP_B), start=1.5)
    truth = write_deeploc_split(
        root, "test", LOOP_A + LOOP_B, np.concatenate((ta, tb)), np.concatenate((qa, qb)), depth="pfm"
    )
    return root, truth


def _robot_bag(root: Path, out: Path, compress: bool) -> Path:
    argv = [
        "convert",
        str(root),
        str(out),
        "--split",
        "test",
        "--robot-frame",
        "base_link",
        "--camera-extrinsics",
        EXT,
        "--no-labels",
        "--intrinsics",
        "80,80,47.5,35.5",
        "--no-progress",
    ]  # K_SMALL, the camera the fixture renders with
    assert main(argv + (["--compress", "png"] if compress else [])) == 0
    return out


@pytest.fixture(scope="module")
def png_bag(deeploc, tmp_path_factory) -> Path:
    return _robot_bag(deeploc[0], tmp_path_factory.mktemp("bags") / "robot.mcap", compress=True)


def _check_dataset(out: Path, truth: dict, depth: bool = True) -> None:
    """Every frame of `out` (train split) equals the source: pixels, pose within 1 mm / 0.01 deg, depth, intrinsics."""
    index = open_dataset(out, "deeploc", "train")
    assert [len(s) for s in index.sequences] == [len(LOOP_A), len(LOOP_B)]
    assert index.intrinsics == K_SMALL and index.intrinsics_source.endswith("intrinsics.json")
    for k, n in enumerate(LOOP_A + LOOP_B):
        frame, exp = index.load(k), truth[n]
        np.testing.assert_array_equal(frame.image, exp["rgb"])
        assert np.linalg.norm(frame.t - exp["t"]) < 1e-3
        assert float(geometry.rotation_error_deg(frame.q, exp["q"])) < 0.01
        if depth:
            np.testing.assert_array_equal(frame.depth, exp["depth"])
        else:
            assert frame.depth is None
    assert not (out / "DeepLoc" / "test").exists()  # no --test-ranges: everything is train


@pytest.mark.parametrize("compress", [True, False], ids=["png", "raw"])
def test_round_trip_through_tf_reproduces_the_dataset(deeploc, png_bag, tmp_path, compress, capsys):
    root, truth = deeploc
    bag = png_bag if compress else _robot_bag(root, tmp_path / "raw.mcap", compress=False)
    with BagReader(bag) as reader:
        topics = reader.topics
        statics = [m for _, _, m in reader.messages(["/tf_static"])]
        static_qos = [q for c in reader.connections if c.topic == "/tf_static" for q in c.ext.offered_qos_profiles]
    assert [q.durability.name for q in static_qos] == ["TRANSIENT_LOCAL"]  # latched, as tf2 offers it
    assert (
        topics["/tf"] == messages.TF_MESSAGE and "/ground_truth/pose" not in topics and "/camera/semantic" not in topics
    )
    assert len(statics) == 1 and statics[0].transforms[0].header.frame_id == "base_link"
    out = tmp_path / "ds"
    assert (
        main(["extract", str(bag), str(out), "--tf", "map", "base_link", "--camera-extrinsics", EXT, "--no-progress"])
        == 0
    )
    summary = capsys.readouterr().out
    assert "10 of 10 images" in summary and "train 10 frames in 2 sequences" in summary and "depth on 10" in summary
    _check_dataset(out, truth)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["ds"] + ([] if compress else ["raw.mcap"])
    )  # no temp left
    report = dataset_info(out)
    assert report["splits"]["train"]["frames"] == 10 and report["warp_consistency"] < 0.5
    assert main(["data-info", str(out)]) == 0 and "warning" not in capsys.readouterr().out
    clip = ClipDataset(open_dataset(out, None, "train"), clip_len=3)[0]  # what `train --data` reads
    assert (
        clip["image"].shape == (3, 3, K_SMALL.height, K_SMALL.width)
        and bool(clip["has_depth"])
        and not bool(clip["has_labels"])
    )
    stamps = (out / "DeepLoc/train/stamps.txt").read_text().split()
    assert (
        stamps[:2] == ["Image_1.png", "0"]
        and json.loads((out / "extract.json").read_text())["pose_source"] == "/tf map -> base_link"
    )


def test_tf_chain_to_the_camera_frame_uses_the_static_transform(deeploc, png_bag, tmp_path):
    out = tmp_path / "ds"
    assert main(["extract", str(png_bag), str(out), "--tf", "map", "camera", "--no-depth", "--no-progress"]) == 0
    _check_dataset(out, deeploc[1], depth=False)


def test_test_ranges_split_and_force(png_bag, tmp_path, capsys):
    out = tmp_path / "ds"
    out.mkdir()
    argv = ["extract", str(png_bag), str(out), "--tf", "map", "camera", "--test-ranges", "0:0.12,10:", "--no-progress"]
    assert main(argv) == 2 and "exists" in capsys.readouterr().err
    assert main(argv + ["--force"]) == 0
    assert "train 3 frames in 1 sequence, test 7 frames in 2 sequences), depth on 10" in capsys.readouterr().out
    train, test = open_dataset(out, "deeploc", "train"), open_dataset(out, "deeploc", "test")
    assert [len(s) for s in train.sequences] == [3] and [len(s) for s in test.sequences] == [3, 4]
    assert train.records[0].frame_id == test.records[0].frame_id == "Image_1" and train.has_depth and test.has_depth
    assert all(r.depth is not None for r in train.records + test.records)


# --------------------------------------------------------------------------- interpolation (a hand-made sqlite3 bag)


def test_pose_topic_at_another_rate_is_interpolated(tmp_path, capsys):
    image_s = np.round(1.0 + 0.1 * np.arange(21), 6)  # 10 Hz, 1.0 .. 3.0 s
    pose_s = 1.25 + np.arange(11) / 7  # 7 Hz, 1.25 .. 2.68 s
    pose_s = pose_s[(pose_s < 1.8) | (pose_s > 2.2)]  # a 0.43 s hole
    write_sqlite_bag(tmp_path / "bag", image_s, pose_s)
    out = tmp_path / "ds"
    argv = [
        "extract",
        str(tmp_path / "bag"),
        str(out),
        "--pose-topic",
        "/odom",
        "--camera-extrinsics",
        EXT,
        "--max-pose-gap",
        "0.3",
        "--depth-tolerance",
        "0.01",
        "--no-progress",
    ]
    assert main(argv) == 0
    summary = capsys.readouterr().out
    before, after = (image_s < pose_s[0]).sum(), (image_s > pose_s[-1]).sum()
    hole = ((image_s > pose_s[3]) & (image_s < pose_s[4])).sum()  # the only pair of samples more than 0.3 s apart
    assert (
        f"no pose: before the first sample of /odom {before}" in summary
        and f"after the last sample of /odom {after}" in summary
    )
    assert f"samples of /odom more than 0.3 s apart {hole}" in summary and (before, after, hole) == (3, 4, 6)
    index = open_dataset(out, "deeploc", "train")
    names = (out / "DeepLoc/train/stamps.txt").read_text().split()
    stamps = np.array([int(v) for v in names[1::2]]) / 1e9
    assert len(index) == len(stamps) == 21 - before - after - hole and len(index.sequences) == 1
    t_b, q_b = truth(stamps)
    t_exp, q_exp = geometry.pose_compose(t_b, q_b, *_ext())
    got_t = np.array([r.t for r in index.records])
    got_q = np.array([r.q for r in index.records])
    assert np.abs(got_t - t_exp).max() < 1e-6 and float(geometry.rotation_error_deg(got_q, q_exp).max()) < 1e-4
    for i, stamp in enumerate(stamps):
        k = int(np.argmin(np.abs(image_s - stamp)))
        frame = index.load(i)
        np.testing.assert_array_equal(frame.image, np.full((H, W, 3), 10 * k, np.uint8))  # mono8 -> grey RGB
        if k % 2:  # its depth is 30 ms away: beyond --depth-tolerance
            assert frame.depth is None
        else:  # 16UC1 kept as millimetres in a 16-bit PNG, read back as metres
            assert index.records[i].depth.endswith(".png")
            np.testing.assert_allclose(frame.depth, (1000 + 100 * k) / 1000, rtol=1e-6)
    assert index.intrinsics == Intrinsics(20.0, 20.0, 7.5, 5.5, W, H)


def test_tf_chain_goes_up_and_down_the_tree_and_interpolates():
    """gps -> camera through map: inverse(map->gps, static) * map->odom (2 Hz) * odom->base_link (10 Hz) *
    base_link->camera."""

    def motion(s, v, axis, rate):
        s = np.asarray(s, dtype=np.float64)
        ax = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        q = np.concatenate((np.cos(rate * s / 2)[:, None], np.sin(rate * s / 2)[:, None] * ax), 1)
        return s[:, None] * np.asarray(v), geometry.quat_normalize(q)

    def odom(s):  # the slow drift of map -> odom
        return motion(s, [0.05, 0.02, 0.0], [0, 0, 1], 0.05)

    def base(s):
        return motion(s, [1.0, 0.3, 0.0], [0.1, 0, 1], 0.4)

    gps = (np.array([2.0, -1.0, 0.3]), geometry.quat_normalize(np.array([0.9, 0.1, 0.0, 0.2])))
    tf = TfCollector()
    for s_list, parent, child, fn in (
        ([0.0, 0.5, 1.0, 1.5, 2.0], "map", "odom", odom),
        (np.arange(21) / 10, "odom", "base_link", base),
    ):
        t, q = fn(s_list)
        for k, s in enumerate(s_list):
            ns = messages.seconds_to_ns(s)
            tf.add(messages.tf_message([messages.transform_stamped(ns, parent, child, t[k], q[k])]), static=False)
    tf.add(
        messages.tf_message(
            [
                messages.transform_stamped(0, "base_link", "camera", *_ext()),
                messages.transform_stamped(0, "/map", "gps", *gps),
            ]
        ),
        static=True,
    )
    chain = tf.chain("gps", "camera")
    query = np.array([0.13, 0.77, 1.42, 1.999, 2.3])
    t, q, reasons = chain.at((query * 1e9).astype(np.int64), max_gap_s=0.6)
    assert reasons[:4] == [None] * 4 and reasons[4] == "no pose: after the last sample of map->odom"
    exp = geometry.pose_compose(*geometry.pose_inverse(*gps), *odom(query[:4]))
    exp = geometry.pose_compose(*exp, *base(query[:4]))
    exp = geometry.pose_compose(*exp, *_ext())
    assert np.abs(t[:4] - exp[0]).max() < 1e-9 and float(geometry.rotation_error_deg(q[:4], exp[1]).max()) < 1e-5


def test_plan_stride_min_motion_and_sequences():
    s = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 3.0, 3.1, 3.2]) * 1e9
    t = np.zeros((9, 3))
    t[:, 0] = [0, 0.1, 0.2, 0.6, 0.7, 1.5, 5, 5, 5]
    q = np.tile([1.0, 0, 0, 0], (9, 1))
    reasons = [None] * 9
    reasons[1] = "no pose"
    plan = plan_frames(s.astype(np.int64), t, q, reasons, Selection(max_gap_s=1.0, stride=1, min_motion_m=0.35))
    assert [f.ordinal for f in plan.frames] == [0, 3, 5, 6] and [f.id for f in plan.frames] == [1, 2, 3, 10001]
    assert plan.skipped == {"no pose": 1, "min motion": 4}
    plan = plan_frames(s.astype(np.int64), t, q, [None] * 9, Selection(stride=2, test_ranges=((0.25, 0.45),)))
    assert [(f.ordinal, f.split, f.sequence) for f in plan.frames] == [
        (0, "train", 0),
        (2, "train", 0),
        (3, "test", 0),
        (5, "train", 1),
        (6, "train", 2),
        (8, "train", 2),
    ]


# --------------------------------------------------------------------------- errors


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("small") / "bag"
    write_sqlite_bag(path, np.round(1.0 + 0.1 * np.arange(5), 6), 0.9 + 0.1 * np.arange(8))
    return path


@pytest.mark.parametrize(
    "flags, expected",
    [
        (["--image-topic", "/nope", "--pose-topic", "/odom"], ["--image-topic /nope", "no such topic"]),
        (["--image-topic", "/odom", "--pose-topic", "/odom"], ["/odom", "nav_msgs/msg/Odometry", "expected"]),
        (["--pose-topic", "/nope"], ["--pose-topic /nope", "no such topic"]),
        ([], ["no pose source", "/odom"]),
        (["--tf", "map", "base_link"], ["no /tf or /tf_static"]),
        (["--pose-topic", "/odom", "--camera-info-topic", "/nope"], ["/nope"]),
    ],
)
def test_bad_topics_are_named_and_leave_nothing(small_bag, tmp_path, capsys, flags, expected):
    out = tmp_path / "ds"
    assert main(["extract", str(small_bag), str(out), "--no-progress", *flags]) == 2
    err = capsys.readouterr().err
    assert all(e in err for e in expected), err
    assert "Traceback" not in err and list(tmp_path.iterdir()) == []


def test_missing_tf_frame_is_named(png_bag, tmp_path, capsys):
    assert main(["extract", str(png_bag), str(tmp_path / "ds"), "--tf", "map", "base_footprint", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "'base_footprint'" in err and "base_link" in err and list(tmp_path.iterdir()) == []


def test_unsupported_encoding_and_no_pose(tmp_path, capsys):
    write_sqlite_bag(tmp_path / "yuv", np.array([1.0, 1.1]), np.array([1.0, 1.1]), encoding="yuv422")
    assert main(["extract", str(tmp_path / "yuv"), str(tmp_path / "ds"), "--pose-topic", "/odom", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "/camera/image_raw" in err and "'yuv422'" in err
    write_sqlite_bag(tmp_path / "late", np.array([1.0, 1.1]), np.array([5.0, 5.1]))
    assert (
        main(["extract", str(tmp_path / "late"), str(tmp_path / "ds"), "--pose-topic", "/odom", "--no-progress"]) == 2
    )
    err = capsys.readouterr().err
    assert "no image of /camera/image_raw has a pose from /odom" in err and "before the first sample" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["late", "yuv"]


def test_interrupt_while_writing_leaves_nothing(png_bag, tmp_path, monkeypatch):
    calls = []
    original = extract_writer.DeepLocWriter.image

    def image(self, frame, rgb):
        calls.append(frame.id)
        if len(calls) == 3:
            raise KeyboardInterrupt
        original(self, frame, rgb)

    monkeypatch.setattr(extract_writer.DeepLocWriter, "image", image)
    assert main(["extract", str(png_bag), str(tmp_path / "ds"), "--tf", "map", "camera", "--no-progress"]) == 130
    assert len(calls) == 3 and list(tmp_path.iterdir()) == []

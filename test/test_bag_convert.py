"""`vlocnetpp convert`: datasets written to disk, converted to MCAP, read back with rosbags and with the plain mcap
reader."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import ctrl_c_interrupts
from data_fixtures import K_SMALL, trajectory, write_deeploc_split, write_sevenscenes
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from vlocnetpp_core.bag import convert as conv
from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.cli import main
from vlocnetpp_core.data import open_dataset
from vlocnetpp_core.data.sample import SEQUENCE_GAP_S
from vlocnetpp_core.inference.preprocess import FrameError
from vlocnetpp_core.outputs import temp_dir_for

REPO = Path(__file__).resolve().parents[1]
LOOP_A, LOOP_B = list(range(1, 9)), list(range(101, 106))  # two loops of one split (id gap -> two sequences)


@pytest.fixture(scope="module")
def deeploc(tmp_path_factory):
    """A DeepLoc fixture: test split of two loops (RGBA images, labels, depth PNG in mm), train split of 4 frames."""
    root = tmp_path_factory.mktemp("deeploc")
    ta, qa = trajectory(len(LOOP_A))
    tb, qb = trajectory(len(LOOP_B), start=1.5)
    truth = write_deeploc_split(root, "test", LOOP_A + LOOP_B, np.concatenate((ta, tb)), np.concatenate((qa, qb)))
    tt, qt = trajectory(4, start=20)
    write_deeploc_split(root, "train", [1, 2, 3, 4], tt, qt)
    return root, truth


def _by_topic_rosbags(path: Path) -> dict[str, list[tuple[int, object]]]:
    """Every message, decoded with rosbags' AnyReader (its own type store built from the bag's definitions)."""
    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, ns, raw in reader.messages():
            out.setdefault(conn.topic, []).append((ns, reader.deserialize(raw, conn.msgtype)))
    return out


def _by_topic_mcap(path: Path) -> dict[str, list[tuple[int, object]]]:
    """Every message, read with the plain `mcap` reader and decoded from CDR with the Jazzy type store."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            out.setdefault(channel.topic, []).append(
                (message.log_time, messages.deserialize(message.data, schema.name))
            )
    return out


def _check_frames(by_topic, index, truth, image_check) -> None:
    ids = LOOP_A + LOOP_B
    stamps = [messages.seconds_to_ns(r.stamp) for r in index.records]
    for topic in (
        conv.IMAGE_TOPIC,
        conv.CAMERA_INFO_TOPIC,
        conv.DEPTH_TOPIC,
        conv.SEMANTIC_TOPIC,
        conv.GROUND_TRUTH_TOPIC,
    ):
        assert [ns for ns, _ in by_topic[topic]] == stamps, topic
        assert [messages.stamp_ns(m) for _, m in by_topic[topic]] == stamps, topic
    for k, n in enumerate(ids):
        exp = truth[n]
        image_check(by_topic[conv.IMAGE_TOPIC][k][1], exp["rgb"])
        depth = by_topic[conv.DEPTH_TOPIC][k][1]
        assert depth.encoding == "32FC1" and depth.header.frame_id == "camera"
        np.testing.assert_allclose(messages.image_to_array(depth), exp["depth"], atol=1e-6)
        sem = by_topic[conv.SEMANTIC_TOPIC][k][1]
        assert sem.encoding == "mono8" and sem.step == sem.width
        np.testing.assert_array_equal(messages.image_to_array(sem), exp["labels"])
        info = by_topic[conv.CAMERA_INFO_TOPIC][k][1]
        assert (info.width, info.height, info.header.frame_id) == (K_SMALL.width, K_SMALL.height, "camera")
        np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3), index.intrinsics.matrix())
        np.testing.assert_allclose(np.asarray(info.p).reshape(3, 4)[:, :3], index.intrinsics.matrix())
        pose = by_topic[conv.GROUND_TRUTH_TOPIC][k][1]
        assert pose.header.frame_id == "map"
        p, o = pose.pose.position, pose.pose.orientation
        np.testing.assert_allclose([p.x, p.y, p.z], exp["t"], atol=1e-9)
        q_ros = np.array([o.x, o.y, o.z, o.w])  # ROS order (x, y, z, w); the fixture's q is (w, x, y, z)
        assert abs(abs(q_ros @ exp["q"][[1, 2, 3, 0]]) - 1.0) < 1e-9
        assert o.w >= 0


def _raw_rgb(msg, expected):
    assert msg.encoding == "rgb8" and msg.step == 3 * msg.width and msg.header.frame_id == "camera"
    np.testing.assert_array_equal(np.asarray(msg.data, np.uint8).reshape(expected.shape), expected)


def test_convert_reads_back_exactly_with_rosbags_and_mcap(deeploc, tmp_path):
    root, truth = deeploc
    out = tmp_path / "test.mcap"
    assert main(["convert", str(root), str(out), "--split", "test", "--no-progress"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["test.mcap"]  # one file, no temp left
    index = open_dataset(root, "deeploc", "test")
    assert len(index.sequences) == 2
    _check_frames(_by_topic_rosbags(out), index, truth, _raw_rgb)
    _check_frames(_by_topic_mcap(out), index, truth, _raw_rgb)
    with BagReader(out) as reader:  # also the rosbag2 Reader (bare .mcap storage) under our own wrapper
        assert reader.topics[conv.IMAGE_TOPIC] == messages.IMAGE and reader.count(conv.IMAGE_TOPIC) == len(truth)
    # the sequences are separated by the 10 s gap (longer than the node's max_gap_s)
    stamps = np.array([r.stamp for r in index.records])
    assert stamps[len(LOOP_A)] - stamps[len(LOOP_A) - 1] == pytest.approx(SEQUENCE_GAP_S)
    # the message definitions are the real Jazzy ones (what `ros2 bag` and Foxglove need)
    with open(out, "rb") as f:
        schemas = {s.name: s for s in make_reader(f).get_summary().schemas.values()}
    assert schemas[messages.IMAGE].data.decode() == messages.TYPESTORE.generate_msgdef(messages.IMAGE, ros_version=2)[0]


@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_compressed_images_decode_to_the_source(deeploc, tmp_path, fmt):
    root, truth = deeploc
    out = tmp_path / "c.mcap"
    assert main(["convert", str(root), str(out), "--compress", fmt, "--no-progress"]) == 0
    with BagReader(out) as reader:
        assert conv.IMAGE_TOPIC not in reader.topics
        msgs = [m for _, _, m in reader.messages([conv.COMPRESSED_TOPIC])]
    assert len(msgs) == len(truth)
    for msg, n in zip(msgs, LOOP_A + LOOP_B, strict=True):
        assert fmt in msg.format
        rgb = messages.compressed_to_rgb(msg)
        if fmt == "png":
            np.testing.assert_array_equal(rgb, truth[n]["rgb"])
        else:
            mse = np.mean((rgb.astype(np.float64) - truth[n]["rgb"]) ** 2)
            assert 10 * np.log10(255**2 / mse) > 30.0  # PSNR of quality-95 JPEG (4:2:0) on a busy texture


def test_split_all_rate_and_intrinsics_flags(deeploc, tmp_path):
    root, _ = deeploc
    out = tmp_path / "all.mcap"
    assert (
        main(
            [
                "convert-deeploc",
                str(root),
                str(out),
                "--split",
                "all",
                "--rate",
                "10",
                "--intrinsics",
                "50,60,40,30",
                "--no-progress",
            ]
        )
        == 0
    )
    with BagReader(out) as reader:
        stamps = np.array([ns for _, ns, _ in reader.messages([conv.GROUND_TRUTH_TOPIC], raw=True)]) / 1e9
        infos = [m for _, _, m in reader.messages([conv.CAMERA_INFO_TOPIC])]
    # train (4 frames), then the two test loops; 0.1 s apart within a sequence, 10 s between sequences
    np.testing.assert_allclose(np.diff(stamps), [0.1] * 3 + [SEQUENCE_GAP_S] + [0.1] * 7 + [SEQUENCE_GAP_S] + [0.1] * 4)
    assert messages.intrinsics_from_camera_info(infos[0]) == Intrinsics(50, 60, 40, 30, K_SMALL.width, K_SMALL.height)


def test_sevenscenes_at_30_hz(tmp_path):
    truth = write_sevenscenes(tmp_path / "scene", {1: 3, 2: 2}, train=[1], test=[2])
    out = tmp_path / "s.mcap"
    assert main(["convert", str(tmp_path / "scene"), str(out), "--split", "train", "--no-progress"]) == 0
    with BagReader(out) as reader:
        assert conv.SEMANTIC_TOPIC not in reader.topics  # 7-Scenes has no labels
        depth = [(ns, messages.image_to_array(m)) for _, ns, m in reader.messages([conv.DEPTH_TOPIC])]
        images = [messages.image_to_rgb(m) for _, _, m in reader.messages([conv.IMAGE_TOPIC])]
    assert [ns for ns, _ in depth] == [0, 33_333_333, 66_666_667]
    for k, (_, d) in enumerate(depth):
        np.testing.assert_array_equal(d, truth[f"seq-01/frame-{k:06d}"]["depth"])  # 0 and 65535 mm -> 0 (invalid)
        np.testing.assert_array_equal(images[k], truth[f"seq-01/frame-{k:06d}"]["rgb"])


# --------------------------------------------------------------------------- bad input


def _copy(root: Path, dst: Path) -> Path:
    shutil.copytree(root, dst)
    return dst


def test_missing_image_listed_in_poses_is_named(deeploc, tmp_path, capsys):
    root = _copy(deeploc[0], tmp_path / "ds")
    (root / "DeepLoc/test/LeftImages/Image_5.png").unlink()
    out = tmp_path / "out.mcap"
    assert main(["convert", str(root), str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "Image_5.png" in err and "poses.txt" in err and "Traceback" not in err
    assert not out.exists()
    assert main(["convert", str(root), str(out), "--skip-missing", "--no-progress"]) == 0
    with BagReader(out) as reader:
        assert reader.count(conv.GROUND_TRUTH_TOPIC) == len(LOOP_A + LOOP_B) - 1


def test_undecodable_image_names_the_file_and_leaves_nothing(deeploc, tmp_path, capsys):
    root = _copy(deeploc[0], tmp_path / "ds")
    bad = root / "DeepLoc/test/LeftImages/Image_103.png"  # late in the split: the bag is half written when it fails
    bad.write_bytes(bad.read_bytes()[:40])
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    assert main(["convert", str(root), str(out_dir / "out.mcap"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "decode" in err
    assert list(out_dir.iterdir()) == []


def test_existing_output_needs_force(deeploc, tmp_path, capsys):
    out = tmp_path / "out.mcap"
    out.write_bytes(b"keep me")
    assert main(["convert", str(deeploc[0]), str(out), "--no-progress"]) == 2
    assert "exists" in capsys.readouterr().err and out.read_bytes() == b"keep me"
    assert main(["convert", str(deeploc[0]), str(out), "--force", "--no-progress"]) == 0
    with BagReader(out) as reader:
        assert reader.count(conv.IMAGE_TOPIC) == len(LOOP_A + LOOP_B)
    assert main(["convert", str(deeploc[0]), str(tmp_path / "out.bag"), "--no-progress"]) == 2
    assert ".mcap" in capsys.readouterr().err


# --------------------------------------------------------------------------- streaming and interruption


def _write_long_deeploc(root: Path, n: int, size: tuple[int, int] = (160, 120)) -> None:
    """A DeepLoc test split of ``n`` frames that all show one image (written once, copied), with labels and depth."""
    K = Intrinsics(100.0, 100.0, size[0] / 2 - 0.5, size[1] / 2 - 0.5, *size)
    split = root / "DeepLoc" / "test"
    t, q = trajectory(1)
    write_deeploc_split(root, "test", [0], t, q, K=K)
    files = [
        split / "LeftImages/Image_0.png",
        split / "labels/Image_0.png",
        root / "DeepLoc_stereo/test/DepthImages/Image_0.png",
    ]
    for i in range(1, n):
        for f in files:
            shutil.copyfile(f, f.with_name(f"Image_{i}.png"))
    t, q = trajectory(n, yaw_deg=0.1)
    lines = [f"Image_{i}.png " + " ".join(f"{v:.9f}" for v in (*t[i], *q[i])) for i in range(n)]
    (split / "poses.txt").write_text("\n".join(lines) + "\n")


def _peak_bytes(root: Path, out: Path) -> tuple[int, int]:
    index = open_dataset(root, "deeploc", "test")
    frame_bytes = sum(a.nbytes for a in (lambda f: (f.image, f.depth, f.labels))(index.load(0)))
    tracemalloc.start()
    try:
        conv.convert([index], out, progress=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return peak, frame_bytes * len(index)


def test_memory_stays_flat_in_dataset_length(tmp_path):
    _write_long_deeploc(tmp_path / "short", 30)
    _write_long_deeploc(tmp_path / "long", 60)
    peak_short, data_short = _peak_bytes(tmp_path / "short", tmp_path / "short.mcap")
    peak_long, data_long = _peak_bytes(tmp_path / "long", tmp_path / "long.mcap")
    assert data_long - data_short > 4 * 2**20  # the 30 extra frames hold > 4 MiB of pixels...
    assert peak_long - peak_short < 0.2 * (data_long - data_short), (
        peak_short,
        peak_long,
    )  # ...that are never all in memory


@pytest.fixture(scope="module")
def long_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("long")
    _write_long_deeploc(root, 600)
    return root


def _start_and_stop_midway(dataset: Path, out: Path) -> subprocess.Popen:
    """Start a conversion in a subprocess and SIGSTOP it once it is writing (the temp folder exists, the output not)."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "vlocnetpp_core.cli",
            "convert",
            str(dataset),
            str(out),
            "--compress",
            "png",
            "--no-progress",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        preexec_fn=ctrl_c_interrupts,
    )
    tmp = temp_dir_for(out, proc.pid)
    while not any(tmp.rglob("*.mcap")) and proc.poll() is None:
        time.sleep(0.005)
    proc.send_signal(signal.SIGSTOP)
    assert proc.poll() is None and not out.exists(), (
        "the conversion finished before it could be interrupted: make the dataset longer"
    )
    return proc


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_interrupted_conversion_leaves_nothing(long_dataset, tmp_path, sig):
    out = tmp_path / "out.mcap"
    proc = _start_and_stop_midway(long_dataset, out)
    proc.send_signal(sig)
    proc.send_signal(signal.SIGCONT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode != 0 and b"interrupted" in err
    assert list(tmp_path.iterdir()) == []


def test_killed_conversion_leaves_only_a_temp_that_the_next_run_removes(long_dataset, tmp_path):
    out = tmp_path / "out.mcap"
    proc = _start_and_stop_midway(long_dataset, out)
    proc.kill()
    proc.wait(timeout=60)
    leftovers = list(tmp_path.iterdir())
    assert [p.name for p in leftovers] == [f".out.mcap.partial-{proc.pid}"]  # hidden, clearly temporary
    index = open_dataset(long_dataset, "deeploc", "test")
    index.records = index.records[:5]
    index.sequences = [range(5)]
    conv.convert([index], out, progress=False)
    assert [p.name for p in tmp_path.iterdir()] == ["out.mcap"]


def test_converter_cli_prints_a_summary(deeploc, tmp_path, capsys):
    out = tmp_path / "x.mcap"
    assert main(["convert", str(deeploc[0]), str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert f"{len(LOOP_A + LOOP_B)} frames" in text and "MiB" in text and conv.GROUND_TRUTH_TOPIC in text
    # and an RGBA source ends up rgb8: the alpha channel is dropped (checked against cv2's own reading)
    with BagReader(out) as reader:
        first = next(m for _, _, m in reader.messages([conv.IMAGE_TOPIC]))
    src = cv2.imread(str(deeploc[0] / "DeepLoc/test/LeftImages/Image_1.png"), cv2.IMREAD_UNCHANGED)
    assert src.shape[2] == 4
    np.testing.assert_array_equal(messages.image_to_rgb(first), cv2.cvtColor(src, cv2.COLOR_BGRA2RGB))


def test_image_messages_roundtrip_with_row_padding_and_big_endian():
    rgb = np.random.default_rng(0).integers(0, 255, (5, 7, 3), dtype=np.uint8)
    msg = messages.image(1, "camera", rgb, "rgb8")
    padded = messages.TYPESTORE.types[messages.IMAGE](
        header=msg.header,
        height=5,
        width=7,
        encoding="bgr8",
        is_bigendian=0,
        step=24,
        data=np.concatenate((rgb[..., ::-1].reshape(5, 21), np.zeros((5, 3), np.uint8)), 1).reshape(-1),
    )
    np.testing.assert_array_equal(messages.image_to_rgb(padded), rgb)
    depth = np.linspace(0, 5, 35, dtype=np.float32).reshape(5, 7)
    big = messages.TYPESTORE.types[messages.IMAGE](
        header=msg.header,
        height=5,
        width=7,
        encoding="32FC1",
        is_bigendian=1,
        step=28,
        data=depth.astype(">f4").view(np.uint8).reshape(-1),
    )
    np.testing.assert_array_equal(messages.image_to_array(big), depth)
    back = messages.deserialize(messages.serialize(messages.image(3, "c", depth, "32FC1")), messages.IMAGE)
    np.testing.assert_array_equal(messages.image_to_array(back), depth)
    truncated = messages.TYPESTORE.types[messages.IMAGE](
        header=msg.header, height=5, width=7, encoding="rgb8", is_bigendian=0, step=21, data=np.zeros(50, np.uint8)
    )
    with pytest.raises(FrameError, match="bytes"):
        messages.image_to_array(truncated)

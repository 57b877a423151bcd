"""DeepLoc and 7-Scenes readers on fixtures written to disk and read back."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from data_fixtures import K_SMALL, trajectory, write_deeploc_split, write_sevenscenes

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import DEEPLOC_DEFAULT, SEVEN_SCENES_DEFAULT, Intrinsics
from vlocnetpp_core.data import open_dataset, read_deeploc, read_sevenscenes
from vlocnetpp_core.data.pfm import write_pfm
from vlocnetpp_core.data.sample import SEQUENCE_GAP_S
from vlocnetpp_core.errors import DataError

# Two loops merged in one folder: ids 8..13 (unpadded, so "10" < "8" lexicographically) and 10001..10004.
LOOP_A = list(range(8, 14))
LOOP_B = list(range(10001, 10005))


def _two_loops(root, header, order="wxyz", depth="png"):
    ta, qa = trajectory(len(LOOP_A))
    tb, qb = trajectory(len(LOOP_B), start=2.5)
    t, q = np.concatenate((ta, tb)), np.concatenate((qa, qb))
    ids = LOOP_A + LOOP_B
    rng = np.random.default_rng(0)
    return write_deeploc_split(
        root, "train", ids, t, q, header=header, order=order, depth=depth, line_order=list(rng.permutation(len(ids)))
    )


def _same_pose(t1, q1, t2, q2):
    return np.allclose(t1, t2, atol=1e-9) and geometry.rotation_error_deg(np.asarray(q1), np.asarray(q2)) < 1e-5


@pytest.mark.parametrize(
    "header",
    [
        (),
        ("ImageName x y z qw qx qy qz",),
        ("DeepLoc train poses", "img_name x y z qw qx qy qz"),
        ("# synthetic campus", "ImageName x y z qw qx qy qz"),
    ],
    ids=["no-header", "header", "title+header", "comment+header"],
)
def test_deeploc_reads_back_exactly(tmp_path, header):
    truth = _two_loops(tmp_path, header)
    index = read_deeploc(tmp_path, "train")
    assert [r.frame_id for r in index.records] == [f"Image_{n}" for n in LOOP_A + LOOP_B]
    assert index.sequences == [range(0, len(LOOP_A)), range(len(LOOP_A), len(LOOP_A) + len(LOOP_B))]
    assert index.has_depth and index.has_labels and index.notes == []
    for i, n in enumerate(LOOP_A + LOOP_B):
        f = index.load(i)
        exp = truth[n]
        np.testing.assert_array_equal(f.image, exp["rgb"])  # RGBA on disk, alpha dropped
        np.testing.assert_array_equal(f.labels, exp["labels"])
        np.testing.assert_allclose(f.depth, exp["depth"], atol=1e-6)
        assert _same_pose(f.t, f.q, exp["t"], exp["q"])
        assert f.q[0] >= 0 and abs(np.linalg.norm(f.q) - 1) < 1e-12
        assert f.sequence == (0 if n in LOOP_A else 1)
    stamps = np.array([r.stamp for r in index.records])
    np.testing.assert_allclose(np.diff(stamps[: len(LOOP_A)]), 0.05)
    assert stamps[len(LOOP_A)] == pytest.approx(stamps[len(LOOP_A) - 1] + SEQUENCE_GAP_S)


def test_deeploc_xyzw_order_and_pfm_depth(tmp_path):
    truth = _two_loops(tmp_path, ("ImageName x y z qx qy qz qw",), order="xyzw", depth="pfm")
    index = read_deeploc(tmp_path, "train", quaternion_order="xyzw")
    for i, n in enumerate(LOOP_A + LOOP_B):
        f = index.load(i)
        assert _same_pose(f.t, f.q, truth[n]["t"], truth[n]["q"])
        np.testing.assert_array_equal(f.depth, truth[n]["depth"])
    wrong = read_deeploc(tmp_path, "train")  # the default order misreads these quaternions
    assert not _same_pose(wrong.records[1].t, wrong.records[1].q, truth[LOOP_A[1]]["t"], truth[LOOP_A[1]]["q"])


def test_deeploc_splits_on_pose_jump(tmp_path):
    t, q = trajectory(8)
    t[5:] += [30.0, 0.0, 0.0]  # contiguous ids, but the robot "teleports" 30 m
    write_deeploc_split(tmp_path, "train", list(range(1, 9)), t, q, depth=None, labels=False)
    assert read_deeploc(tmp_path, "train").sequences == [range(0, 5), range(5, 8)]
    assert read_deeploc(tmp_path, "train", max_jump_m=50.0).sequences == [range(0, 8)]
    index = read_deeploc(tmp_path, "train")
    assert not index.has_depth and not index.has_labels and index.load(0).depth is None


def test_deeploc_dir_is_deeploc_folder_with_sibling_stereo(tmp_path):
    truth = _two_loops(tmp_path, ())
    a = read_deeploc(tmp_path, "train")
    b = read_deeploc(tmp_path / "DeepLoc", "train")
    assert [r.depth for r in a.records] == [r.depth for r in b.records] and b.has_depth
    np.testing.assert_allclose(b.load(3).depth, truth[LOOP_A[3]]["depth"], atol=1e-6)


def test_deeploc_skips_unmatched_files_and_says_so(tmp_path):
    t, q = trajectory(5)
    write_deeploc_split(tmp_path, "train", [1, 2, 3, 4, 5], t, q, depth=None)
    (tmp_path / "DeepLoc/train/LeftImages/Image_5.png").unlink()
    shutil.copy(tmp_path / "DeepLoc/train/LeftImages/Image_1.png", tmp_path / "DeepLoc/train/LeftImages/Image_77.png")
    index = read_deeploc(tmp_path, "train")
    assert [r.frame_id for r in index.records] == ["Image_1", "Image_2", "Image_3", "Image_4"]
    assert any("1 poses" in n for n in index.notes) and any("1 images" in n for n in index.notes)


def test_deeploc_intrinsics_default_json_and_given(tmp_path):
    t, q = trajectory(3)
    write_deeploc_split(tmp_path, "train", [1, 2, 3], t, q, depth=None, labels=False)
    assert read_deeploc(tmp_path).intrinsics == DEEPLOC_DEFAULT.resized(96, 72)
    given = read_deeploc(tmp_path, intrinsics="81,82,40,30")
    assert given.intrinsics == Intrinsics(81, 82, 40, 30, 96, 72) and given.load(0).intrinsics == given.intrinsics
    big = Intrinsics(160, 160, 95.5, 71.5, 192, 144)
    (tmp_path / "intrinsics.json").write_text(json.dumps(big.to_dict()))
    from_json = read_deeploc(tmp_path)
    assert from_json.intrinsics == big.resized(96, 72) and from_json.intrinsics_source.endswith("intrinsics.json")
    assert read_deeploc(tmp_path / "DeepLoc").intrinsics == from_json.intrinsics


def test_sevenscenes_reads_back_exactly(tmp_path):
    truth = write_sevenscenes(tmp_path, {1: 4, 2: 3, 3: 2}, train=[1, 3], test=[2])
    train = read_sevenscenes(tmp_path, "train")
    assert [r.frame_id for r in train.records] == [f"seq-01/frame-{k:06d}" for k in range(4)] + [
        f"seq-03/frame-{k:06d}" for k in range(2)
    ]
    assert train.sequences == [range(0, 4), range(4, 6)]
    assert train.intrinsics == SEVEN_SCENES_DEFAULT.resized(96, 72)
    for i, r in enumerate(train.records):
        f = train.load(i)
        exp = truth[r.frame_id]
        np.testing.assert_array_equal(f.image, exp["rgb"])
        np.testing.assert_array_equal(f.depth, exp["depth"])
        assert f.depth[0, :5].max() == 0 and f.depth[1, :5].max() == 0  # 0 and 65535 are invalid
        assert _same_pose(f.t, f.q, exp["t"], exp["q"]) and f.sequence == exp["sequence"] and f.labels is None
    np.testing.assert_allclose(np.diff([r.stamp for r in train.records[:4]]), 1 / 30)
    test = open_dataset(tmp_path, split="test", intrinsics=K_SMALL)
    assert test.format == "7scenes" and len(test) == 3 and test.intrinsics == K_SMALL


def test_open_dataset_detects_format(tmp_path):
    t, q = trajectory(2)
    write_deeploc_split(tmp_path / "dl", "test", [1, 2], t, q, depth=None)
    write_sevenscenes(tmp_path / "7s", {1: 2}, train=[1], test=[1])
    assert open_dataset(tmp_path / "dl", split="test").format == "deeploc"
    assert open_dataset(tmp_path / "7s").format == "7scenes"
    assert open_dataset(tmp_path / "7s", format="7-Scenes").format == "7scenes"


def test_pfm_depth_invalid_values_become_zero(tmp_path):
    from vlocnetpp_core.data.imageio import read_depth

    d = np.arange(12, dtype=np.float32).reshape(3, 4) + 1
    d[0, 0], d[0, 1], d[2, 3] = np.nan, -2.0, np.inf
    write_pfm(tmp_path / "d.pfm", d)
    out = read_depth(tmp_path / "d.pfm", (3, 4))
    assert out.dtype == np.float32 and out[0, 0] == out[0, 1] == out[2, 3] == 0
    np.testing.assert_array_equal(out[1], d[1])
    (tmp_path / "t.pfm").write_bytes((tmp_path / "d.pfm").read_bytes()[:-8])
    with pytest.raises(DataError, match=r"t\.pfm: truncated PFM data"):
        read_depth(tmp_path / "t.pfm", (3, 4))

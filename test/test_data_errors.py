"""Bad dataset input gives a DataError that names the file (and line) and what was expected."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from data_fixtures import trajectory, write_deeploc_split, write_sevenscenes

from vlocnetpp_core.cli import main as cli_main
from vlocnetpp_core.data import open_dataset, read_deeploc, read_sevenscenes
from vlocnetpp_core.errors import DataError


@pytest.fixture
def deeploc(tmp_path):
    t, q = trajectory(4)
    write_deeploc_split(tmp_path, "train", [1, 2, 3, 4], t, q)
    return tmp_path


def _poses(root):
    return root / "DeepLoc/train/poses.txt"


def test_missing_folder(tmp_path):
    with pytest.raises(DataError, match="nowhere: dataset folder not found"):
        open_dataset(tmp_path / "nowhere")
    with pytest.raises(DataError, match="unknown dataset layout"):
        open_dataset(tmp_path)
    with pytest.raises(DataError, match="LeftImages"):
        read_deeploc(tmp_path)


def test_cli_reports_one_line(tmp_path, capsys):
    assert cli_main(["data-info", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "nowhere" in err and "Traceback" not in err


def test_image_that_does_not_decode(deeploc):
    (deeploc / "DeepLoc/train/LeftImages/Image_2.png").write_bytes(b"not a png at all")
    index = read_deeploc(deeploc)
    with pytest.raises(DataError, match=r"Image_2\.png: cannot decode image"):
        index.load(1)


def test_truncated_png(deeploc):
    p = deeploc / "DeepLoc/train/LeftImages/Image_3.png"
    p.write_bytes(p.read_bytes()[:-40])
    index = read_deeploc(deeploc)
    with pytest.raises(DataError, match=r"LeftImages/Image_3\.png: cannot decode image \(truncated"):
        index.load(2)


def test_pose_line_with_wrong_field_count(deeploc):
    lines = _poses(deeploc).read_text().splitlines()
    lines[3] = " ".join(lines[3].split()[:6])  # line 4: image name + 5 numbers
    _poses(deeploc).write_text("\n".join(lines))
    with pytest.raises(DataError, match=r"poses\.txt:4: expected 8 fields 'ImageName x y z qw qx qy qz', got 6"):
        read_deeploc(deeploc)


def test_pose_line_with_a_word_instead_of_a_number(deeploc):
    lines = _poses(deeploc).read_text().splitlines()
    lines[4] = lines[4].rsplit(" ", 1)[0] + " abc"
    _poses(deeploc).write_text("\n".join(lines))
    with pytest.raises(DataError, match=r"poses\.txt:5: expected 7 numbers"):
        read_deeploc(deeploc)


@pytest.mark.parametrize("quat", ["0 0 0 0", "nan 0 0 1", "1e-9 0 0 0"])
def test_non_normalisable_quaternion(deeploc, quat):
    lines = _poses(deeploc).read_text().splitlines()
    lines[2] = " ".join(lines[2].split()[:4]) + " " + quat
    _poses(deeploc).write_text("\n".join(lines))
    with pytest.raises(DataError, match=r"poses\.txt:3: .*quaternion cannot be normalised"):
        read_deeploc(deeploc)


def test_label_id_out_of_range(deeploc):
    p = deeploc / "DeepLoc/train/labels/Image_1.png"
    lab = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    lab[5, 5] = 255  # ignore is fine
    cv2.imwrite(str(p), lab)
    read_deeploc(deeploc).load(0)
    lab[6, 6] = 12
    cv2.imwrite(str(p), lab)
    with pytest.raises(DataError, match=r"labels/Image_1\.png: label id 12 outside 0\.\.9"):
        read_deeploc(deeploc).load(0)


def test_depth_of_wrong_size(deeploc):
    p = deeploc / "DeepLoc_stereo/train/DepthImages/Image_4.png"
    cv2.imwrite(str(p), np.ones((10, 20), np.uint16))
    with pytest.raises(DataError, match=r"DepthImages/Image_4\.png: depth map is 20x10, expected 96x72"):
        read_deeploc(deeploc).load(3)


def test_sevenscenes_bad_pose_and_missing_split(tmp_path):
    write_sevenscenes(tmp_path, {1: 2}, train=[1], test=[2])
    with pytest.raises(DataError, match=r"seq-02: sequence folder listed in TestSplit\.txt not found"):
        read_sevenscenes(tmp_path, "test")
    (tmp_path / "seq-01/frame-000001.pose.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(DataError, match=r"frame-000001\.pose\.txt: expected 16 finite numbers"):
        read_sevenscenes(tmp_path, "train")
    (tmp_path / "TrainSplit.txt").unlink()
    with pytest.raises(DataError, match=r"TrainSplit\.txt: split file not found"):
        read_sevenscenes(tmp_path, "train")

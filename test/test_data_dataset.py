"""ClipDataset: clips stay inside one sequence, carry the documented tensors, work with DataLoader workers."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from data_fixtures import trajectory, write_deeploc_split, write_sevenscenes

from vlocnetpp_core import geometry
from vlocnetpp_core.data import ClipDataset, make_transform, open_dataset


@pytest.fixture(scope="module")
def deeploc_index(tmp_path_factory):
    root = tmp_path_factory.mktemp("clips")
    ta, qa = trajectory(6)
    tb, qb = trajectory(4, start=1.5)
    write_deeploc_split(
        root, "train", [1, 2, 3, 4, 5, 6, 501, 502, 503, 504], np.concatenate((ta, tb)), np.concatenate((qa, qb))
    )
    return open_dataset(root)


@pytest.mark.parametrize(("clip_len", "stride", "count"), [(1, 1, 10), (3, 1, 6), (3, 2, 2), (5, 1, 2), (7, 1, 0)])
def test_clips_stay_inside_a_sequence(deeploc_index, clip_len, stride, count):
    ds = ClipDataset(deeploc_index, clip_len, stride=stride)
    assert len(ds) == count
    for i in range(len(ds)):
        idx = ds.clip_indices(i)
        assert len({deeploc_index.records[j].sequence for j in idx}) == 1
        assert np.all(np.diff(idx) == stride)


def test_clip_tensors(deeploc_index):
    ds = ClipDataset(deeploc_index, 3, make_transform(False, (64, 48)))
    s = ds[4]  # second sequence, records 6, 7, 8
    assert s["index"].tolist() == [6, 7, 8] and s["sequence"].item() == 1
    assert (
        s["image"].shape == (3, 3, 48, 64)
        and s["image"].dtype == torch.float32
        and 0 <= s["image"].min() <= s["image"].max() <= 1
    )
    assert s["depth"].shape == (3, 1, 48, 64) and s["labels"].shape == (3, 48, 64) and s["labels"].dtype == torch.int64
    assert s["has_depth"].item() and s["has_labels"].item()
    assert s["K"].shape == (3, 3, 3) and s["K"][0, 0, 2].item() == pytest.approx(
        deeploc_index.intrinsics.resized(64, 48).cx, abs=1.0
    )
    np.testing.assert_allclose(s["stamp"].numpy() - s["stamp"][0].item(), [0, 0.05, 0.1])
    assert s["rel_t"][0].abs().max() == 0 and s["rel_q"][0].tolist() == [1, 0, 0, 0]
    r = [deeploc_index.records[j] for j in (6, 7, 8)]
    for k in (1, 2):
        rt, rq = geometry.relative_pose(np.array(r[k - 1].t), np.array(r[k - 1].q), np.array(r[k].t), np.array(r[k].q))
        np.testing.assert_allclose(s["rel_t"][k].numpy(), rt, atol=1e-6)
        np.testing.assert_allclose(s["rel_q"][k].numpy(), rq, atol=1e-6)
        np.testing.assert_allclose(s["t"][k].numpy(), r[k].t, atol=1e-6)


def test_clips_without_depth_and_labels_skip_their_files(deeploc_index):
    """What stl-loc and stl-vo load: the images and poses of every clip, no depth or label files decoded."""
    full = ClipDataset(deeploc_index, 3, make_transform(False, (64, 48)))[4]
    light = ClipDataset(deeploc_index, 3, make_transform(False, (64, 48)), depth=False, labels=False)[4]
    for key in ("image", "t", "q", "rel_t", "rel_q", "K", "stamp", "index"):
        assert torch.equal(full[key], light[key]), key
    assert full["has_depth"].item() and not light["has_depth"].item() and "depth" not in light
    assert full["has_labels"].item() and not light["has_labels"].item() and "labels" not in light


@pytest.mark.parametrize("stride", [1, 2])
def test_relative_poses_of_every_clip_compose_its_frames_poses(deeploc_index, stride):
    """The relative poses computed once for all clips are those of each clip's frame pairs (T_{k-1}^{-1} T_k)."""
    ds = ClipDataset(deeploc_index, 3, stride=stride)
    assert len(ds) > 0
    for i in range(len(ds)):
        s, r = ds[i], [deeploc_index.records[j] for j in ds.clip_indices(i)]
        assert s["rel_t"][0].abs().max() == 0 and s["rel_q"][0].tolist() == [1, 0, 0, 0]
        for k in (1, 2):
            rt, rq = geometry.relative_pose(
                np.array(r[k - 1].t), np.array(r[k - 1].q), np.array(r[k].t), np.array(r[k].q)
            )
            assert np.linalg.norm(rt) > 0.01  # the frames moved
            np.testing.assert_allclose(s["rel_t"][k].numpy(), rt, atol=1e-6)
            np.testing.assert_allclose(s["rel_q"][k].numpy(), rq, atol=1e-6)


def test_mirrored_clips_carry_the_relative_poses_of_their_mirrored_frames(deeploc_index):
    """With the flip (stl-vo's training clips) half the clips are mirrored left-right; the relative poses of every
    clip are those its transformed frames' poses compose, so a mirrored clip turns the other way (yaw negated)."""
    plain = ClipDataset(deeploc_index, 3, make_transform(False, (64, 48)))
    mirrored = ClipDataset(
        deeploc_index,
        3,
        make_transform(True, (64, 48), scale=(1.0, 1.0), brightness=0, contrast=0, saturation=0, flip=True),
    )
    torch.manual_seed(0)
    seen = set()
    for i in range(len(plain)):
        p, m = plain[i], mirrored[i]
        flipped = bool(torch.equal(m["image"], p["image"].flip(-1)))
        assert flipped or torch.equal(m["image"], p["image"])
        seen.add(flipped)
        for k in (1, 2):
            rt, rq = geometry.relative_pose(
                m["t"][k - 1].double().numpy(),
                m["q"][k - 1].double().numpy(),
                m["t"][k].double().numpy(),
                m["q"][k].double().numpy(),
            )
            np.testing.assert_allclose(m["rel_t"][k].numpy(), rt, atol=1e-5)
            np.testing.assert_allclose(m["rel_q"][k].numpy(), rq, atol=1e-5)
            sign = -1.0 if flipped else 1.0  # yaw (camera y) and roll (z) change sign, pitch (x) does not
            np.testing.assert_allclose(m["rel_q"][k].numpy(), p["rel_q"][k].numpy() * [1, 1, sign, sign], atol=1e-6)
            assert abs(p["rel_q"][k][2]) > 1e-3  # the trajectory turns, so the sign is seen
    assert seen == {True, False}


def test_absent_depth_and_labels_are_filled(tmp_path):
    write_sevenscenes(tmp_path, {1: 3}, train=[1], test=[1])
    (tmp_path / "seq-01/frame-000001.depth.png").unlink()
    s = ClipDataset(open_dataset(tmp_path), 2)[0]
    assert not s["has_depth"].item() and not s["has_labels"].item()
    assert s["depth"][1].abs().max() == 0 and s["depth"][0].max() > 0
    assert (s["labels"] == 255).all()


def test_reproducible_and_picklable_for_workers(deeploc_index):
    ds = ClipDataset(deeploc_index, 2, make_transform(True, (64, 48)))
    torch.manual_seed(3)
    a = ds[0]
    torch.manual_seed(3)
    b = ds[0]
    assert torch.equal(a["image"], b["image"]) and torch.equal(a["K"], b["K"])
    copy = pickle.loads(pickle.dumps(ds))
    assert len(copy) == len(ds)
    loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2, shuffle=False)
    batches = list(loader)
    assert sum(len(x["index"]) for x in batches) == len(ds)
    assert batches[0]["image"].shape == (4, 2, 3, 48, 64)


@pytest.mark.parametrize("seg", [False, True])
def test_training_frames_cached_in_memory_give_the_clips_decoded_per_clip(deeploc_index, seg):
    """The frame cache changes speed, not data: at the network size (no zoom) every clip, its pixels, depth,
    labels, poses and intrinsics, equals the one decoded from the files, with the same augmentation draw."""
    from vlocnetpp_core.training.train_data import SeededClips, training_clips

    size = (64, 48)
    transform = make_transform(True, size, scale=(1.0, 1.0))
    logs = []
    cached = SeededClips(training_clips(deeploc_index, 3, transform, (1, 2), seg, cache_size=size, log=logs.append))
    plain = SeededClips(training_clips(deeploc_index, 3, transform, (1, 2), seg))
    assert len(logs) == 1 and "into memory" in logs[0]
    assert len(cached) == len(plain) > 0
    for i in range(len(plain)):
        a, b = cached[(i, 100 + i)], plain[(i, 100 + i)]
        assert a.keys() == b.keys()
        for key in a:
            assert torch.equal(a[key], b[key]), key
    assert bool(cached[(0, 1)]["has_labels"]) == seg

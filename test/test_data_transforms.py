"""Clip transforms: intrinsics follow every resize/crop/flip; one random draw per clip."""

from __future__ import annotations

import numpy as np
import pytest
from data_fixtures import K_SMALL, render_plane, trajectory

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.data.check import pair_warp_ratio
from vlocnetpp_core.data.sample import Frame
from vlocnetpp_core.data.transforms import (
    Compose,
    HorizontalFlip,
    RandomCrop,
    Resize,
    flip_frame,
    jitter_image,
    make_transform,
    resize_frame,
)

K0 = Intrinsics(fx=150.0, fy=140.0, cx=99.5, cy=74.5, width=200, height=150)
POINT = np.array([0.3, -0.2, 4.0])  # camera frame, metres


def _blob(u: float, v: float, w: int, h: int, sigma: float = 3.0) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))


def _marker_frame() -> Frame:
    """A frame whose image (grey) and depth both hold a blob centred on the projection of POINT."""
    u, v = geometry.project(POINT[None], K0.matrix())[0][0]
    b = _blob(u, v, K0.width, K0.height)
    img = np.repeat((b * 250).round().astype(np.uint8)[..., None], 3, axis=2)
    return Frame(img, np.array([1.0, 0, 0]), np.array([1.0, 0, 0, 0]), b.astype(np.float32), None, K0, 0.0, 0, "m")


def _centroid(weights: np.ndarray) -> np.ndarray:
    yy, xx = np.mgrid[0 : weights.shape[0], 0 : weights.shape[1]]
    return np.array([(xx * weights).sum(), (yy * weights).sum()]) / weights.sum()


def _projected(frame: Frame, point=POINT) -> np.ndarray:
    return geometry.project(point[None], frame.intrinsics.matrix())[0][0]


@pytest.mark.parametrize(
    "transform",
    [
        Resize((130, 97)),
        Resize((413, 170)),
        Compose([Resize((120, 60), (1.0, 1.15)), RandomCrop((120, 60))]),
        make_transform(False, (96, 64)),
    ],
    ids=["down", "up-anisotropic", "zoom+random-crop", "test-pipeline"],
)
def test_point_projects_onto_same_content(transform):
    for seed in range(3):
        out = transform([_marker_frame()], np.random.default_rng(seed))[0]
        assert out.image.shape[:2] == (out.intrinsics.height, out.intrinsics.width)
        np.testing.assert_allclose(_centroid(out.image[..., 0].astype(float)), _projected(out), atol=0.25)
        np.testing.assert_allclose(_centroid(out.depth), _projected(out), atol=0.6)  # nearest neighbour


def test_train_pipeline_and_flip_keep_projection():
    t = make_transform(True, (96, 64), flip=True)
    flipped = 0
    for seed in range(8):
        out = t([_marker_frame()], np.random.default_rng(seed))[0]
        assert out.image.shape == (64, 96, 3)
        is_flipped = out.t[0] == -1.0  # the flip mirrors the world x axis
        point = POINT * [-1, 1, 1] if is_flipped else POINT  # a flipped camera sees the mirrored world
        flipped += bool(is_flipped)
        np.testing.assert_allclose(_centroid(out.depth), _projected(out, point), atol=0.6)
    assert 0 < flipped < 8


def test_clip_frames_share_the_random_draw():
    t = make_transform(True, (96, 64))
    Ks = set()
    for seed in range(6):
        clip = t([_marker_frame() for _ in range(3)], np.random.default_rng(seed))
        for f in clip[1:]:
            np.testing.assert_array_equal(f.image, clip[0].image)
            np.testing.assert_array_equal(f.depth, clip[0].depth)
            assert f.intrinsics == clip[0].intrinsics
        Ks.add(clip[0].intrinsics)
    assert len(Ks) > 1  # the draw does change between clips


def test_training_without_geometric_augmentation_sees_the_test_geometry():
    """``scale=(1, 1)`` (the pose stages' default): the whole image at the input size, as at test time; only photometric
    jitter."""
    train, test = make_transform(True, (96, 64), scale=(1.0, 1.0)), make_transform(False, (96, 64))
    reference = test([_marker_frame()], np.random.default_rng(0))[0]
    images = []
    for seed in range(4):
        f = train([_marker_frame()], np.random.default_rng(seed))[0]
        assert f.intrinsics == reference.intrinsics
        np.testing.assert_array_equal(f.depth, reference.depth)
        images.append(f.image)
    assert any(not np.array_equal(im, reference.image) for im in images)  # the jitter still changes the colours


def test_jitter_scales_brightness_contrast_and_saturation():
    """Each factor alone does what its name says (to within one level of uint8): brightness scales, contrast 0 leaves
    the mean grey everywhere, saturation 0 the grey of each pixel; factors of 1 change nothing."""
    image = np.random.default_rng(0).integers(0, 256, size=(40, 60, 3), dtype=np.uint8)
    pixels = image.astype(np.float64)
    grey = pixels @ np.array([0.299, 0.587, 0.114])
    np.testing.assert_array_equal(jitter_image(image, 1.0, 1.0, 1.0), image)
    cases = [
        ((0.8, 1.0, 1.0), 0.8 * pixels),
        ((1.2, 1.0, 1.0), np.minimum(1.2 * pixels, 255)),
        ((1.0, 0.0, 1.0), np.full_like(pixels, grey.mean())),
        ((1.0, 1.0, 0.0), np.repeat(grey[..., None], 3, axis=-1)),
    ]
    for (b, c, s), want in cases:
        got = jitter_image(image, b, c, s)
        assert got.dtype == np.uint8 and got.shape == image.shape
        assert np.abs(got - want).max() <= 1.0, (b, c, s)  # rounding to uint8 in float32 arithmetic


def test_depth_and_labels_resize_never_blend():
    rng = np.random.default_rng(0)
    depth = rng.choice(np.array([0.0, 5.0, 7.0], np.float32), size=(150, 200))
    labels = rng.choice(np.array([0, 3, 255], np.uint8), size=(150, 200))
    f = Frame(np.zeros((150, 200, 3), np.uint8), np.zeros(3), np.array([1.0, 0, 0, 0]), depth, labels, K0, 0.0, 0, "x")
    for size in [(97, 61), (333, 251)]:
        out = resize_frame(f, *size)
        assert set(np.unique(out.depth)) <= {0.0, 5.0, 7.0} and set(np.unique(out.labels)) <= {0, 3, 255}
    same = resize_frame(f, 100, 75)  # exact 2x: nearest takes pixel (2i+1, 2j+1)
    np.testing.assert_array_equal(same.depth, depth[1::2, 1::2])


def test_flip_keeps_relative_pose_and_warping_consistent():
    t, q = trajectory(2)
    frames = []
    for k in range(2):
        rgb, d, lab = render_plane(t[k], q[k], K_SMALL)
        frames.append(Frame(rgb, t[k], q[k], d, lab, K_SMALL, 0.05 * k, 0, str(k)))
    a, b = (flip_frame(f) for f in frames)
    M = np.diag([-1.0, 1.0, 1.0, 1.0])
    rel = geometry.pose_to_matrix(*geometry.relative_pose(t[0], q[0], t[1], q[1]))
    rel_flipped = geometry.pose_to_matrix(*geometry.relative_pose(a.t, a.q, b.t, b.q))
    np.testing.assert_allclose(rel_flipped, M @ rel @ M, atol=1e-12)
    np.testing.assert_allclose(
        geometry.pose_to_matrix(a.t, a.q), M @ geometry.pose_to_matrix(t[0], q[0]) @ M, atol=1e-12
    )
    assert pair_warp_ratio(*frames) < 0.1 and pair_warp_ratio(a, b) < 0.1
    np.testing.assert_array_equal(flip_frame(a).image, frames[0].image)
    assert HorizontalFlip(0.0)(frames, np.random.default_rng(0)) == frames


def test_make_transform_rejects_shrinking_scale():
    with pytest.raises(ValueError, match="scale"):
        make_transform(True, (96, 64), scale=(0.8, 1.0))
